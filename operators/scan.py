"""Sensor scans: any object is a sensor; scan the evaluated scene from it, frame by frame.

``object.hybrid_raycast_sensor`` (``HybridRaycastSensor``) holds the sensor model
(``core.sensors``: rotating LiDAR, area scanner, depth camera), its physics and where
scans go; every object has one, set to a Velodyne VLP-16 without noise until the user
changes it.  The object's evaluated world matrix places the sensor each frame (its
scale is ignored: ranges stay in metres).  Use an Empty or a Camera: a mesh sensor's rays
start inside it and see it.

- ``scan(sensor_object, *, frame=None, space='WORLD')`` (re-exported as ``api.scan``):
  one frame as arrays (``ScanResult``), cast through ``query.cast`` (``api.cast``: the session cache of
  ``operators/session.py``, the structure the plan picks).
- ``scan_job``: a frame range, one file per frame (``core.pointcloud``: PLY, LAS, npz,
  PCD, KITTI .bin, each written atomically; with KITTI also ``poses.txt``, the sensor pose
  of every frame written so far), for the Scan operator (modal with progress and Esc in the
  GUI, synchronous in background and from scripts) and the CLI's ``scan`` command.
  Each frame is evaluated and cast in the main thread (Blender data cannot be read from
  a worker); the interface redraws and Esc is read between frames.

LAS classification: an object's integer custom property ``classification`` (0-255,
ASPRS classes: 2 ground, 6 building, ...) classifies every point on it; 1
('unclassified') otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from ..core import pointcloud, sensors
from . import query, session
from .jobs import BadInput, Job, JobOperator, Unwritable, writable_dir

SPACES = ("WORLD", "SENSOR")
#: the per-object custom property that sets the LAS classification of its points
CLASSIFICATION_PROPERTY = "classification"


# -- settings --------------------------------------------------------------------------------

_PRESET_ITEMS = [("CUSTOM", "Custom", "Your own settings")] + [
    (key, p.label, p.description) for key, p in sensors.PRESETS.items()]


def _apply_preset(self, _context):
    p = sensors.PRESETS.get(self.preset)
    if p is None:
        return
    self.kind = p.kind
    for name, value in p.params.items():
        setattr(self, name, value)
    if p.kind == "ROTATING":
        self.elevations = ""
    self.noise_sigma = p.noise_sigma


class HybridRaycastSensor(bpy.types.PropertyGroup):
    """``object.hybrid_raycast_sensor``: what a scan from this object shoots and writes."""

    preset: EnumProperty(name="Preset", items=_PRESET_ITEMS, default=sensors.DEFAULT_PRESET, update=_apply_preset,
                         description="Fill in a real sensor's figures (each preset's tooltip cites its source)")
    kind: EnumProperty(
        name="Type", default="ROTATING",
        items=(("ROTATING", "Rotating LiDAR", "Channels stacked in elevation, spinning about the object's Z axis; "
                                              "azimuth 0 along its X axis"),
               ("AREA", "Solid-State", "A grid over a rectangular field of view, looking along the object's X axis"),
               ("DEPTH", "Depth Camera", "One ray per pixel of this camera object (lens, sensor, shift)")))
    # rotating LiDAR
    channels: IntProperty(name="Channels", default=16, min=1, max=1024, description="Lasers stacked in elevation")
    fov_up: FloatProperty(name="FOV Up", default=15.0, min=-90.0, max=90.0, description="Elevation of the top laser (degrees)")
    fov_down: FloatProperty(name="FOV Down", default=-15.0, min=-90.0, max=90.0,
                            description="Elevation of the bottom laser (degrees)")
    elevations: StringProperty(name="Elevations", default="",
                               description="Explicit elevation of each laser, degrees, comma-separated "
                                           "(overrides channels and FOV when given)")
    azimuth_steps: IntProperty(name="Azimuth Steps", default=1800, min=1, max=1 << 16,
                               description="Firings per turn (horizontal resolution = 360 / steps)")
    rotation_rate: FloatProperty(name="Rotation Rate", default=10.0, min=0.01, max=1000.0, unit="NONE",
                                 description="Turns per second (Hz): sets each point's firing time")
    # solid state
    h_fov: FloatProperty(name="Horizontal FOV", default=70.0, min=0.01, max=360.0, description="Degrees")
    v_fov: FloatProperty(name="Vertical FOV", default=30.0, min=0.01, max=180.0, description="Degrees")
    h_steps: IntProperty(name="Columns", default=350, min=1, max=1 << 15, description="Rays across")
    v_steps: IntProperty(name="Rows", default=150, min=1, max=1 << 15, description="Rays down")
    frame_rate: FloatProperty(name="Frame Rate", default=10.0, min=0.01, max=1000.0,
                              description="Sensor frames per second (Hz): sets each point's firing time")
    # depth camera (intrinsics from the camera object)
    width: IntProperty(name="Width", default=640, min=1, max=1 << 14, description="Pixels across")
    height: IntProperty(name="Height", default=480, min=1, max=1 << 14, description="Pixels down")
    # range and physics
    range_min: FloatProperty(name="Range Min", default=0.5, min=0.0, unit="LENGTH",
                             description="Nearer returns are lost (the blind zone)")
    range_max: FloatProperty(name="Range Max", default=100.0, min=0.0, unit="LENGTH",
                             description="Farther surfaces give no return")
    noise_sigma: FloatProperty(name="Range Noise", default=0.0, min=0.0, unit="LENGTH",
                               description="Standard deviation of Gaussian range noise")
    seed: IntProperty(name="Seed", default=0, min=0, description="Noise seed: a frame's noise repeats for the same seed")
    reference_range: FloatProperty(name="Reference Range", default=10.0, min=0.001, unit="LENGTH",
                                   description="Range at which a surface facing the sensor returns intensity 1 "
                                               "(intensity ~ cos(incidence) / range^2)")
    drop_below: FloatProperty(name="Drop Below", default=0.0, min=0.0, max=1.0,
                              description="Returns weaker than this intensity are dropped")
    # output
    directory: StringProperty(name="Folder", default="//scans/", subtype="DIR_PATH",
                              description="Where the Scan button writes one file per frame")
    file_format: EnumProperty(name="Format", default="PLY", description="The point-cloud file format of each frame",
                              items=(("PLY", "PLY", "Binary PLY with the object-name table in comments"),
                                     ("LAS", "LAS", "LAS 1.4 (format 6 + extra bytes), classification from the "
                                                    "objects' 'classification' property"),
                                     ("NPZ", "NPZ", "numpy .npz arrays"),
                                     ("PCD", "PCD", "PCD 0.7, binary (the Point Cloud Library's format), the "
                                                    "object-name table in comments"),
                                     ("KITTI", "KITTI", "KITTI velodyne .bin (x, y, z, intensity as float32) "
                                                        "and the frames' sensor poses in poses.txt")))
    space: EnumProperty(name="Space", default="WORLD",
                        items=(("WORLD", "World", "Points and normals in world coordinates"),
                               ("SENSOR", "Sensor", "Points and normals in the sensor object's frame")))
    use_scene_range: BoolProperty(name="Scene Frame Range", default=True,
                                  description="Scan every frame of the scene's range")
    frame_start: IntProperty(name="Start", default=1, description="First frame to scan")
    frame_end: IntProperty(name="End", default=1, description="Last frame to scan")


def _elevations(text):
    text = text.strip()
    if not text:
        return None
    try:
        return tuple(float(x) for x in text.replace(";", ",").split(",") if x.strip())
    except ValueError:
        raise ValueError(f"elevations must be numbers separated by commas, got {text!r}") from None


def sensor_model(ob, scene=None):
    """(``core.sensors`` model, ``Returns``) of an object's settings; ValueError naming the
    setting when they make no sensor."""
    s = ob.hybrid_raycast_sensor
    common = {"range_min": s.range_min, "range_max": s.range_max}
    if s.kind == "ROTATING":
        model = sensors.RotatingLidar(channels=s.channels, fov_up=s.fov_up, fov_down=s.fov_down,
                                      elevations=_elevations(s.elevations), azimuth_steps=s.azimuth_steps,
                                      rotation_rate=s.rotation_rate, **common)
    elif s.kind == "AREA":
        model = sensors.AreaScanner(h_fov=s.h_fov, v_fov=s.v_fov, h_steps=s.h_steps, v_steps=s.v_steps,
                                    frame_rate=s.frame_rate, **common)
    else:
        cam = ob.data
        if ob.type != "CAMERA" or cam.type != "PERSP":
            raise ValueError(f"a depth-camera sensor must be a perspective camera object; '{ob.name}' is "
                             f"{'an orthographic camera' if ob.type == 'CAMERA' else 'a ' + ob.type.lower()}")
        k = sensors.camera_intrinsics(cam.lens, cam.sensor_width, cam.sensor_height, cam.sensor_fit,
                                      s.width, s.height, cam.shift_x, cam.shift_y)
        model = sensors.DepthCamera(**k, **common)
    return model, sensors.Returns(noise_sigma=s.noise_sigma, seed=s.seed, reference_range=s.reference_range,
                                  drop_below=s.drop_below)


# -- one frame ----------------------------------------------------------------------------------

@dataclass
class ScanResult:
    """One frame's returns, per point (N,) unless said otherwise.

    points: (N, 3) float64 (world or sensor frame, as ``space``); normals: (N, 3) float32
    unit geometric normals of the surfaces hit, in the same frame; range: float64 measured
    range (m, with noise); intensity: float32 in [0, 1]; ring: int32 channel / row;
    azimuth: float32 degrees; time: float64 seconds (the frame's scene time from the
    scene's first frame, plus the ray's firing time in the sweep); objects / object_names
    and object_index; instance_index into instance_matrices ((I, 4, 4) world).
    ray: int64 index of each point's ray in the frame's pattern (``sensor_model(ob)[0].pattern()``);
    sensor_matrix: (4, 4) the sensor's world pose (rotation and translation, no scale);
    rays: rays cast; frame; space.
    """

    points: np.ndarray
    normals: np.ndarray
    range: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    azimuth: np.ndarray
    time: np.ndarray
    object_index: np.ndarray
    objects: np.ndarray
    object_names: np.ndarray
    instance_index: np.ndarray
    instance_matrices: np.ndarray
    ray: np.ndarray
    sensor_matrix: np.ndarray
    rays: int
    frame: int
    space: str
    structure: str = ""
    extra: dict = field(default_factory=dict, repr=False)

    def __len__(self):
        return len(self.range)

    def fields(self) -> dict:
        """The per-point arrays ``core.pointcloud`` writes."""
        return {k: getattr(self, k) for k in pointcloud.FIELDS}


def sensor_pose(ob_eval) -> np.ndarray:
    """(4, 4) world pose of the evaluated object without its scale."""
    m = np.array(ob_eval.matrix_world, dtype=np.float64)
    r = m[:3, :3]
    norms = np.linalg.norm(r, axis=0)
    if (norms == 0).any():
        raise ValueError(f"sensor '{ob_eval.name}' has a zero scale: its axes give no direction")
    pose = np.eye(4)
    pose[:3, :3] = r / norms
    pose[:3, 3] = m[:3, 3]
    return pose


def _frame_time(scene, frame):
    fps = scene.render.fps / scene.render.fps_base
    return (frame - scene.frame_start) / fps


def scan_depsgraph(ob, depsgraph, space="WORLD", model=None, structure="auto") -> ScanResult:
    """One scan of the depsgraph's scene as it is evaluated now; ``structure`` as ``api.cast``."""
    if space not in SPACES:
        raise ValueError(f"space must be 'WORLD' or 'SENSOR', got {space!r}")
    scene = depsgraph.scene
    model, returns = model if model is not None else sensor_model(ob, scene)
    pose = sensor_pose(ob.evaluated_get(depsgraph))
    origin, rot = pose[:3, 3], pose[:3, :3]
    pat = model.pattern()
    d = pat.directions @ rot.T
    r = query.cast(origin, d, depsgraph=depsgraph, tmax=model.range_max, structure=structure)
    frame = scene.frame_current
    with np.errstate(invalid="ignore"):
        cos = np.abs(np.einsum("ij,ij->i", r.normals.astype(np.float64), d))
    keep, rng, intensity = sensors.measure(r.t, r.hit, cos, model, returns, frame=frame)
    k = np.flatnonzero(keep)
    dk = d[k]
    points = origin + rng[k, None] * dk
    normals = r.normals[k]
    if space == "SENSOR":
        points = (points - origin) @ rot
        normals = (normals.astype(np.float64) @ rot).astype(np.float32)
    return ScanResult(points=points, normals=normals, range=rng[k], intensity=intensity[k], ring=pat.ring[k],
                      azimuth=pat.azimuth[k], time=_frame_time(scene, frame) + pat.time[k],
                      object_index=r.object_index[k], objects=r.objects, object_names=r.object_names,
                      instance_index=r.instance_index[k], instance_matrices=r.instance_matrices, ray=k, sensor_matrix=pose,
                      rays=len(d), frame=frame, space=space, structure=r.structure)


def _whole(x, name):
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"{name} must be a whole number, got {type(x).__name__}")
    return int(x)


def scan(sensor_object, *, frame=None, space="WORLD", depsgraph=None, structure="auto") -> ScanResult:
    """Scan the evaluated scene from ``sensor_object`` with its ``hybrid_raycast_sensor``
    settings; the points as arrays (``ScanResult``).

    frame: scan at this frame (the scene goes back to its current frame afterwards);
    default the current one.  space: 'WORLD' or 'SENSOR' (the object's frame, no scale).
    depsgraph: an evaluated depsgraph (default the context's).
    structure: 'auto' (the session's plan), 'grid', 'bvh' or 'embree', as ``api.cast``.
    Raises TypeError/ValueError naming the argument or the setting for bad input.
    """
    if not isinstance(sensor_object, bpy.types.Object):
        raise TypeError(f"sensor_object must be a bpy.types.Object, got {type(sensor_object).__name__}")
    if space not in SPACES:
        raise ValueError(f"space must be 'WORLD' or 'SENSOR', got {space!r}")
    if depsgraph is not None:
        session.check_depsgraph(depsgraph)
    scene = depsgraph.scene if depsgraph is not None else bpy.context.scene
    model = sensor_model(sensor_object, scene)
    if frame is None:
        dg = depsgraph if depsgraph is not None else bpy.context.evaluated_depsgraph_get()
        return scan_depsgraph(sensor_object, dg, space, model, structure)
    frame = _whole(frame, "frame")
    old = (scene.frame_current, scene.frame_subframe)
    scene.frame_set(frame)
    try:
        dg = depsgraph if depsgraph is not None else session.evaluated(scene)
        return scan_depsgraph(sensor_object, dg, space, model, structure)
    finally:
        if (scene.frame_current, scene.frame_subframe) != old:
            scene.frame_set(old[0], subframe=old[1])


# -- files --------------------------------------------------------------------------------------

def classification(objects) -> np.ndarray:
    """(len(objects),) uint8 LAS class per object from its ``classification`` property (1 if unset)."""
    out = np.ones(len(objects), np.uint8)
    for i, ob in enumerate(objects):
        if ob is None or CLASSIFICATION_PROPERTY not in ob.keys():
            continue
        v = ob[CLASSIFICATION_PROPERTY]
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 255:
            raise ValueError(f"object '{ob.name}': custom property '{CLASSIFICATION_PROPERTY}' must be a whole "
                             f"number 0-255 (an ASPRS class), got {v!r}")
        out[i] = v
    return out


def write_scan(result: ScanResult, path, fmt: str) -> Path:
    fmt = fmt.lower()
    cls = None
    if fmt == "las":
        table = classification(result.objects)
        cls = table[result.object_index] if len(table) else np.ones(len(result), np.uint8)
    return pointcloud.write(path, fmt, result.fields(), list(result.object_names), cls)


def parse_frames(text: str) -> tuple[int, int]:
    """'A-B' or 'A' -> (A, B); ValueError otherwise."""
    t = str(text).strip()
    try:
        if "-" in t[1:]:
            i = t.index("-", 1)
            a, b = int(t[:i]), int(t[i + 1:])
        else:
            a = b = int(t)
    except ValueError:
        raise ValueError(f"frames must be 'START-END' or one frame, got {text!r}") from None
    if a > b:
        raise ValueError(f"frames: start {a} is after end {b}")
    return a, b


def check_frames(scene, start: int, end: int):
    if start < scene.frame_start or end > scene.frame_end:
        raise ValueError(f"frames {start}-{end} are outside the scene's frame range "
                         f"{scene.frame_start}-{scene.frame_end}")


def output_folder(directory) -> Path:
    """The absolute, writable folder for the scan files (created if missing); Unwritable otherwise."""
    text = str(directory)
    if text.startswith("//"):
        if not bpy.data.filepath:
            raise BadInput(f"the output folder {text!r} is relative to the .blend file, which is not saved; "
                           "save the file or choose an absolute folder")
        text = bpy.path.abspath(text)
    return writable_dir(text, "the output folder")


def file_name(ob, frame: int, fmt: str) -> str:
    return f"{bpy.path.clean_name(ob.name)}_{frame:05d}.{pointcloud.EXTENSIONS[fmt.lower()]}"


#: the poses file a KITTI scan writes beside its frames (KITTI odometry's layout)
POSES_NAME = "poses.txt"


def scan_job(scene, job: Job, ob, *, frames, directory, fmt, space="WORLD", view_layer=None, written=None):
    """Generator: scan ``frames`` (start, end) from ``ob`` into ``directory``, one file per
    frame; every argument is checked before the first frame.  ``written``: a list the
    finished files are appended to as they are renamed into place.  The scene returns to
    its current frame at the end, on an error and when the job is closed (Esc).

    The first frame plans (``api.cast``'s 'auto'); later frames use the structure it
    chose: a moving scene is extracted again every frame, and planning again would time
    the grid on sample rays each frame for the same answer."""
    fmt = str(fmt).lower()
    if fmt not in pointcloud.FORMATS:
        raise BadInput(f"bad arguments: format must be one of {', '.join(pointcloud.FORMATS)}, got {fmt!r}")
    if space not in SPACES:
        raise BadInput(f"bad arguments: space must be 'WORLD' or 'SENSOR', got {space!r}")
    try:
        model = sensor_model(ob, scene)
        start, end = frames
        check_frames(scene, start, end)
    except (TypeError, ValueError) as e:
        raise BadInput(f"sensor '{ob.name}': {e}") from None
    folder = output_folder(directory)
    written = written if written is not None else []
    old = (scene.frame_current, scene.frame_subframe)
    count = end - start + 1
    rays = points = 0
    structure = "auto"
    poses = []
    try:
        for i, frame in enumerate(range(start, end + 1)):
            job.progress(i / count, f"frame {frame} ({i + 1} of {count})")
            yield job.fraction, job.text
            job.check()
            scene.frame_set(frame)
            dg = session.evaluated(scene, view_layer)
            result = scan_depsgraph(ob, dg, space, model, structure)
            structure = result.structure
            try:
                written.append(write_scan(result, folder / file_name(ob, frame, fmt), fmt))
                if fmt == "kitti":  # rewritten whole after each frame: it always matches the frames written
                    poses.append(result.sensor_matrix)
                    pointcloud.write_poses(folder / POSES_NAME, poses)
            except OSError as e:
                raise Unwritable(f"unwritable path: {folder}: {e.strerror or e}") from None
            except ValueError as e:
                raise BadInput(str(e)) from None
            rays += result.rays
            points += len(result)
    finally:
        if (scene.frame_current, scene.frame_subframe) != old:
            scene.frame_set(old[0], subframe=old[1])
    return {"files": list(written), "frames": count, "rays": rays, "points": points, "folder": folder,
            "structure": structure}


# -- the operator -------------------------------------------------------------------------------

class HYBRID_RAYCAST_OT_scan(JobOperator, bpy.types.Operator):
    """Scan the scene from the active object with its sensor settings: one point-cloud file per frame"""

    bl_idname = "hybrid_raycast.scan"
    bl_label = "Scan"
    bl_options = {"REGISTER"}
    job_label = "Hybrid RT scan"

    @classmethod
    def poll(cls, context):
        return context.active_object is not None

    def start(self, context, job):
        ob = context.active_object
        s = ob.hybrid_raycast_sensor
        scene = context.scene
        frames = (scene.frame_start, scene.frame_end) if s.use_scene_range else (s.frame_start, s.frame_end)
        if frames[0] > frames[1]:
            raise BadInput(f"frames: start {frames[0]} is after end {frames[1]}")
        self._written = []
        return scan_job(scene, job, ob, frames=frames, directory=s.directory, fmt=s.file_format,
                        space=s.space, view_layer=context.view_layer, written=self._written)

    def finish(self, context, result):
        return [("INFO", f"scanned {result['frames']} frames, {result['rays']:,} rays, {result['points']:,} points "
                         f"into {result['folder']}")]

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._stop(context)
            self.report({"WARNING"}, f"scan cancelled: {len(self._written)} finished frames written, complete, "
                                     f"no partial file")
            return {"CANCELLED"}
        return super().modal(context, event)


classes = (HybridRaycastSensor, HYBRID_RAYCAST_OT_scan)


def register_properties():
    bpy.types.Object.hybrid_raycast_sensor = bpy.props.PointerProperty(type=HybridRaycastSensor)


def unregister_properties():
    if hasattr(bpy.types.Object, "hybrid_raycast_sensor"):
        del bpy.types.Object.hybrid_raycast_sensor


# -- the command line ---------------------------------------------------------------------------

def scan_command(scene, args, out_dir, stdout) -> dict:
    """``-c hybrid_raycast scan --sensor NAME [--frames A-B] --output DIR [--format ...]``:
    the JSON document of the run (the CLI prints or writes it)."""
    if not args.sensor:
        raise BadInput("bad arguments: scan needs --sensor NAME (the object to scan from)")
    if out_dir is None:
        raise BadInput("bad arguments: scan needs --output DIR (one file per frame goes there)")
    ob = scene.objects.get(args.sensor)
    if ob is None:
        raise BadInput(f"bad arguments: --sensor {args.sensor!r}: no object of that name in scene '{scene.name}'")
    try:
        frames = parse_frames(args.frames) if args.frames else (scene.frame_start, scene.frame_end)
    except ValueError as e:
        raise BadInput(f"bad arguments: --frames: {e}") from None
    s = ob.hybrid_raycast_sensor
    fmt = args.format or s.file_format.lower()
    space = (args.space or s.space).upper()
    from .jobs import run_sync

    result = run_sync(scan_job(scene, Job(), ob, frames=frames, directory=str(out_dir), fmt=fmt, space=space))
    print(f"hybrid_raycast scan: {result['frames']} frames, {result['rays']:,} rays, {result['points']:,} points "
          f"-> {result['folder']}", file=stdout, flush=True)
    return {"command": "scan", "sensor": ob.name, "frames": list(frames), "format": fmt, "space": space,
            "rays": result["rays"], "points": result["points"], "files": [str(p) for p in result["files"]]}
