"""Pure-numpy core of Hybrid Ray Cast: meshes, the shared kernel and the structures.

Never imports bpy or mathutils, so everything here runs and is tested without Blender.
embreex (optional) is imported only when an 'embree' structure is built, dask only when
a ``core.distributed`` function is called.
"""

from .accel import Accel
from .factory import KINDS, build
from .embree import embree_available
from .hits import Hits
from .intersect import prepare_rays
from .mesh import TriangleMesh
from .twolevel import InstanceHits, Split, Swept, TwoLevel
from .objio import load_obj
from .meshio import InstancedScene, SceneFile, SceneFileError, load_mesh, read_scene, save_mesh, save_scene
from .rays import camera_rays, hemisphere_rays, quasi_uniform_rays, uniform_rays
from . import decide
from .decide import Calibration, CalibrationError, calibrate, load_or_default, measure_break_even, measure_break_evens
from .plan import Plan, plan, ski_rental, trace_online
from .multihit import all_hits
from .scenes import calibration_set
from . import distributed  # noqa: E402  (core.distributed; imports dask only when called)

__all__ = [
    "KINDS",
    "Accel",
    "Hits",
    "TriangleMesh",
    "TwoLevel",
    "Split",
    "Swept",
    "InstanceHits",
    "all_hits",
    "build",
    "Calibration",
    "CalibrationError",
    "Plan",
    "calibrate",
    "calibration_set",
    "load_or_default",
    "measure_break_even",
    "measure_break_evens",
    "plan",
    "ski_rental",
    "trace_online",
    "camera_rays",
    "embree_available",
    "hemisphere_rays",
    "load_obj",
    "load_mesh",
    "read_scene",
    "save_mesh",
    "save_scene",
    "InstancedScene",
    "SceneFile",
    "SceneFileError",
    "distributed",
    "prepare_rays",
    "quasi_uniform_rays",
    "uniform_rays",
]
