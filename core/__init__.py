"""Pure-numpy core of Hybrid Ray Cast: meshes, the shared kernel and the structures.

Never imports bpy or mathutils, so everything here runs and is tested without Blender.
"""

from .accel import KINDS, Accel, build
from .hits import Hits
from .intersect import prepare_rays
from .mesh import TriangleMesh

__all__ = ["KINDS", "Accel", "Hits", "TriangleMesh", "build", "prepare_rays"]
