"""HYBRID_RAYCAST_OT_calibrate: measure this machine's constants and store them.

Where the calibration lives (``calibration_path``), first match wins:
1. ``CALIBRATION_PATH`` of this module, when set (tests inject a temporary file here);
2. the environment variable ``HYBRID_RAYCAST_CALIBRATION``;
3. installed as an extension (``bl_ext.<repo>.hybrid_raycast``): the extension's user
   directory, ``bpy.utils.extension_path_user(package)/calibration.json``, which
   survives upgrades;
4. otherwise (the package loaded from a checkout, as ``make demo`` does): Blender's user
   config folder, ``<config>/hybrid_raycast/calibration.json``.
A missing, corrupt or foreign file is never an error: ``core.load_or_default`` falls
back on the shipped defaults and says why; the operators report that as a warning.
"""

from __future__ import annotations

import os
from pathlib import Path

import bpy

from .. import core
from ..settings import CALIBRATION_SCALES
from .jobs import BadInput, Job, JobOperator, Unwritable

#: set to a path to override where the calibration is read and written (tests)
CALIBRATION_PATH = None
ENV = "HYBRID_RAYCAST_CALIBRATION"
FILENAME = "calibration.json"
#: the add-on's root package: bl_ext.<repo>.hybrid_raycast when installed
PACKAGE = __package__.rpartition(".")[0]


def calibration_path() -> Path:
    if CALIBRATION_PATH is not None:
        return Path(CALIBRATION_PATH)
    env = os.environ.get(ENV)
    if env:
        return Path(env)
    if PACKAGE.startswith("bl_ext."):
        try:
            return Path(bpy.utils.extension_path_user(PACKAGE, path="", create=True)) / FILENAME
        except (ValueError, RuntimeError, OSError):
            pass
    return Path(bpy.utils.user_resource("CONFIG", path="hybrid_raycast", create=False)) / FILENAME


def load_calibration():
    """(Calibration, one-line message, path): never raises."""
    path = calibration_path()
    cal, message = core.load_or_default(path)
    return cal, message, path


def calibration_job(job: Job, *, scale: str = "default", path=None):
    """Generator: calibrate the candidates that can be built here, save, return the result."""
    if scale not in core.decide.RAYS_PER_SCENE:
        raise BadInput(f"unknown calibration scale {scale!r}; expected one of {', '.join(core.decide.RAYS_PER_SCENE)}")
    path = Path(path) if path is not None else calibration_path()
    _check_writable(path)
    kinds = ("bvh", "embree") if core.embree.embree_available() else ("bvh",)
    yield 0.0, f"calibrating {', '.join(kinds)} ({scale})"
    cal = yield from job.call(core.calibrate, kinds=kinds, scale=scale, progress=job.progress)
    try:
        cal.save(path)
    except OSError as e:
        raise Unwritable(f"unwritable path: cannot save the calibration to {path}: {e.strerror or e}") from None
    return {"calibration": cal, "path": path, "kinds": kinds}


def _check_writable(path: Path):
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise Unwritable(f"unwritable path: cannot create {path.parent}: {e.strerror or e}") from None
    if not os.access(path.parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise Unwritable(f"unwritable path: {path} cannot be written")


def apply_calibration(scene, result) -> list[tuple[str, str]]:
    cal = result["calibration"]
    msgs = [("INFO", f"calibrated {', '.join(cal.fits)} in {cal.duration_s:.1f} s; saved to {result['path']}")]
    if "embree" not in result["kinds"]:
        msgs.insert(0, ("WARNING", "embreex cannot be imported here: calibrated the BVH only"))
    # other programs kept the CPU busy through the retakes: the constants may be slow
    msgs += [("WARNING", n) for n in cal.notes if n.endswith(core.decide.load_watch.BUSY_ADVICE)]
    if scene is not None and getattr(scene, "hybrid_raycast", None) is not None and scene.hybrid_raycast.has_results:
        msgs.append(("INFO", "run Analyze again to decide with the new constants"))
    return msgs


#: the operator's scales: the scene setting's, or one of the calibration scales
SCALE_ITEMS = (("SCENE", "Scene Setting", "Use scene.hybrid_raycast.calibration_scale"),) + CALIBRATION_SCALES


class HYBRID_RAYCAST_OT_calibrate(JobOperator, bpy.types.Operator):
    """Measure this machine's build and per-ray constants on procedural scenes and save them in the extension's user folder"""

    bl_idname = "hybrid_raycast.calibrate"
    bl_label = "Calibrate"
    bl_options = {"REGISTER"}
    job_label = "Hybrid RT calibration"

    scale: bpy.props.EnumProperty(
        name="Scale",
        description="How many procedural scenes and rays to measure (default: the scene setting)",
        items=SCALE_ITEMS,
        default="SCENE",
    )

    def start(self, context, job):
        scale = context.scene.hybrid_raycast.calibration_scale if self.scale == "SCENE" else self.scale
        return calibration_job(job, scale=scale)

    def finish(self, context, result):
        return apply_calibration(context.scene, result)
