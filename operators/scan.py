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

One frame (``scan_frame``): the pattern's beams, each a cone of ``beam_samples`` sub-rays
(``core.returns.beam_directions``), traced through ``query.cast`` with the hit's material
(``operators.materials``: reflectivity, glass passing light on, mirrors reflecting it up to
``max_bounces``); every surface met is an echo, and ``core.returns.measure_returns`` turns
the echoes into the returns the mode reports, with noise, atmosphere, rain/fog returns and
dropout.  SWEEP motion cuts the beams into blocks of firing times (``core.motion``).

Classification: an object's integer custom property ``classification`` (0-255, ASPRS
classes: 2 ground, 6 building, ...) classifies every point on it; 1 ('unclassified')
otherwise, 7 ('low point (noise)') for a rain or fog return.  Every format carries it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from ..core import motion, pointcloud, returns, sensors, twolevel
from . import query, session
from .jobs import BadInput, Job, JobOperator, Unwritable, writable_dir

SPACES = ("WORLD", "SENSOR")
#: the per-object custom property that sets the LAS classification of its points
CLASSIFICATION_PROPERTY = "classification"
#: the ASPRS class of a rain or fog return: 7, 'low point (noise)' (LAS 1.4 R15, table 17)
NOISE_CLASS = 7


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
    # time within a sweep
    motion: EnumProperty(
        name="Motion", default="FRAME",
        items=(("FRAME", "Frame", "Every ray sees the scene and the sensor as they are at the frame"),
               ("SWEEP", "Sweep", "Each block of firings sees the scene at its own time within the sweep "
                                  "(1 / rotation rate), every ray from the sensor's pose at its firing time: "
                                  "moving objects and the sensor's own motion skew the scan as a real one")))
    sweep_tolerance: FloatProperty(name="Max Skew", default=0.01, min=1e-5, max=100.0, unit="LENGTH",
                                   description="Sweep blocks are fine enough that no scene point moves more than "
                                               "this within one block (half of it from the block's time)")
    sweep_blocks: IntProperty(name="Blocks", default=0, min=0, max=4096,
                              description="A fixed number of sweep blocks (0: as many as Max Skew needs, at most 256)")
    # returns
    returns: EnumProperty(
        name="Returns", default="STRONGEST",
        items=(("STRONGEST", "Strongest", "One return per beam: the strongest echo"),
               ("FIRST", "First", "One return per beam: the nearest echo"),
               ("LAST", "Last", "One return per beam: the farthest echo"),
               ("DUAL", "Dual", "Up to two returns per beam: the strongest and the last")))
    beam_divergence: FloatProperty(name="Beam Divergence", default=0.0, min=0.0, max=100.0, precision=3,
                                   description="Full cone angle of one beam (milliradians): its footprint can "
                                               "split over an edge into several returns")
    beam_samples: IntProperty(name="Beam Samples", default=1, min=1, max=64,
                              description="Sub-rays traced over each beam's cone (1: the beam's axis only)")
    range_resolution: FloatProperty(name="Range Resolution", default=0.1, min=0.001, max=100.0, unit="LENGTH",
                                    description="Echoes of one beam closer than this merge into one return")
    use_materials: BoolProperty(name="Materials", default=True,
                                description="Reflectivity from the hit material (Principled BSDF base colour, or "
                                            "a 'hybrid_raycast_reflectivity' property on the material or object); "
                                            "transmissive surfaces pass light on, mirror-like ones reflect it")
    max_bounces: IntProperty(name="Mirror Bounces", default=0, min=0, max=8,
                             description="Reflections off mirror-like surfaces (metallic, smooth) followed per ray")
    # weather and dropout
    use_atmosphere: BoolProperty(name="Atmosphere", default=False,
                                 description="Attenuate intensity by exp(-2 alpha range), alpha = 3.912 / visibility")
    visibility: FloatProperty(name="Visibility", default=1000.0, min=0.01, soft_max=50000.0, unit="LENGTH",
                              description="Meteorological visibility (fog: under 1 km)")
    false_return_rate: FloatProperty(name="Rain/Fog Returns", default=0.0, min=0.0, max=1.0, subtype="FACTOR",
                                     description="Share of beams, per frame, that return from a rain drop or fog "
                                                 "near the sensor instead")
    false_return_range: FloatProperty(name="Clutter Range", default=5.0, min=0.01, max=1000.0, unit="LENGTH",
                                      description="Rain and fog returns fall between Range Min and this range")
    false_return_intensity: FloatProperty(name="Clutter Intensity", default=0.05, min=0.0, max=1.0, subtype="FACTOR",
                                          description="Intensity of a rain or fog return")
    dropoff_general_rate: FloatProperty(name="Dropout", default=0.0, min=0.0, max=1.0, subtype="FACTOR",
                                        description="Share of points lost at random (CARLA's dropoff_general_rate)")
    dropoff_intensity_limit: FloatProperty(name="Dropout Intensity Limit", default=1.0, min=0.0, max=1.0,
                                           subtype="FACTOR",
                                           description="Points above this intensity are never lost to the "
                                                       "intensity rule (CARLA's dropoff_intensity_limit)")
    dropoff_zero_intensity: FloatProperty(name="Dropout at Zero Intensity", default=0.0, min=0.0, max=1.0,
                                          subtype="FACTOR",
                                          description="Chance to lose a point of zero intensity, falling linearly to "
                                                      "0 at the limit (CARLA's dropoff_zero_intensity)")
    # output
    directory: StringProperty(name="Folder", default="//scans/", subtype="DIR_PATH",
                              description="Where the Scan button writes one file per frame")
    file_format: EnumProperty(name="Format", default="PLY", description="The point-cloud file format of each frame",
                              items=(("PLY", "PLY", "Binary PLY with the object-name table in comments"),
                                     ("LAS", "LAS", "LAS 1.4 (format 6 + extra bytes), return numbers, "
                                                    "classification from the objects' 'classification' property"),
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
    return model, sensors.Returns(
        noise_sigma=s.noise_sigma, seed=s.seed, reference_range=s.reference_range, drop_below=s.drop_below,
        mode=s.returns, beam_divergence=s.beam_divergence, beam_samples=s.beam_samples,
        range_resolution=s.range_resolution, visibility=s.visibility if s.use_atmosphere else float("inf"),
        false_return_rate=s.false_return_rate, false_return_range=s.false_return_range,
        false_return_intensity=s.false_return_intensity, dropoff_general_rate=s.dropoff_general_rate,
        dropoff_intensity_limit=s.dropoff_intensity_limit, dropoff_zero_intensity=s.dropoff_zero_intensity,
        max_bounces=s.max_bounces)


@dataclass
class SensorSettings:
    """Everything one scan from an object needs, checked: the model of its rays, what a
    return is (``core.sensors.Returns``), time within the sweep (``core.motion.Sweep``) and
    whether the materials hit set reflectivity, transmission and mirrors."""

    model: object
    returns: sensors.Returns
    sweep: motion.Sweep
    materials: bool = True


def sensor_settings(ob, scene=None) -> SensorSettings:
    """The object's ``hybrid_raycast_sensor`` as ``SensorSettings``; ValueError naming the
    setting when they make no sensor."""
    model, returns = sensor_model(ob, scene)
    s = ob.hybrid_raycast_sensor
    sweep = motion.Sweep(motion=s.motion, tolerance=s.sweep_tolerance, blocks=s.sweep_blocks)
    if returns.false_return_rate > 0 and returns.false_return_range < model.range_min:
        raise ValueError(f"false_return_range (Clutter Range, {returns.false_return_range:g} m) must not be below "
                         f"range_min ({model.range_min:g} m) while rain/fog returns are on")
    return SensorSettings(model, returns, sweep, bool(s.use_materials))


def _settings(value, ob, scene) -> SensorSettings:
    if value is None:
        return sensor_settings(ob, scene)
    if isinstance(value, SensorSettings):
        return value
    model, returns = value  # the (model, Returns) pair of ``sensor_model``
    return SensorSettings(model, returns, motion.Sweep(), False)


# -- one frame ----------------------------------------------------------------------------------

@dataclass
class ScanResult:
    """One frame's returns, per point (N,) unless said otherwise.

    points: (N, 3) float64 (world or sensor frame, as ``space``; with SWEEP motion a point
    in the sensor frame is in the sensor's pose at its own firing time); normals: (N, 3)
    float32 unit geometric normals of the surfaces hit, in the same frame (NaN for a
    weather return); range: float64 measured range (m, with noise); intensity: float32 in
    [0, 1]; cos_incidence: float32 |cos| of the angle between beam and surface normal;
    ring: int32 channel / row; azimuth: float32 degrees; time: float64 seconds (the frame's
    scene time from the scene's first frame, plus the ray's firing time in the sweep);
    return_index: uint8, 1-based rank by range among the returns of its beam, and
    return_count: uint8 how many its beam reported (``returns`` mode DUAL gives up to 2);
    objects / object_names and object_index (-1 for a rain or fog return);
    instance_index into instance_matrices ((I, 4, 4) world; with SWEEP motion each block's
    instances, at its time); materials / material_names and material_index (-1: none);
    classification: uint8 ASPRS class (the object's ``classification`` property, 1 when
    unset, 7 'low point (noise)' for a rain or fog return).
    ray: int64 index of each point's beam in the frame's pattern (``sensor_model(ob)[0].pattern()``);
    sensor_matrix: (4, 4) the sensor's world pose at the start of the sweep (rotation and
    translation, no scale); rays: rays cast (sub-rays of every beam, and the rays that
    went on through glass or off mirrors); frame; space; blocks: the sweep's blocks (1 for FRAME);
    extra['rigid_blocks']: blocks whose instant was read as the placements' matrices only (a
    sweep in which a few placements only move reads their matrices at each block's instant,
    extracts nothing more, and traces every ray at once); 0 when each block was traced anew.
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
    cos_incidence: np.ndarray | None = None
    return_index: np.ndarray | None = None
    return_count: np.ndarray | None = None
    material_index: np.ndarray | None = None
    materials: np.ndarray | None = None
    material_names: np.ndarray | None = None
    classification: np.ndarray | None = None
    blocks: int = 1
    extra: dict = field(default_factory=dict, repr=False)

    def __len__(self):
        return len(self.range)

    def fields(self) -> dict:
        """The per-point arrays ``core.pointcloud`` writes."""
        return {k: getattr(self, k) for k in pointcloud.FIELDS}

    @property
    def point_object_names(self) -> np.ndarray:
        """(N,) object array: each point's object name, '' for a rain or fog return (an index
        of -1 would pick the table's last name)."""
        return _names_of(self.object_names, self.object_index)

    @property
    def point_material_names(self) -> np.ndarray:
        """(N,) object array: each point's material name, '' where it hit no material."""
        return _names_of(self.material_names, self.material_index)


def _names_of(table, index) -> np.ndarray:
    if table is None or index is None:
        return np.full(0 if index is None else len(index), "", object)
    padded = np.empty(len(table) + 1, object)
    padded[:-1] = list(table)
    padded[-1] = ""
    return padded[np.where(np.asarray(index) >= 0, index, len(table))]


def sensor_pose(ob_eval) -> np.ndarray:
    """(4, 4) world pose of the evaluated object without its scale."""
    pose = np.array(ob_eval.matrix_world, dtype=np.float64)
    r = pose[:3, :3]
    norms = np.sqrt((r * r).sum(axis=0))  # as np.linalg.norm(axis=0), in fewer calls: a sweep reads one a block
    if not norms.all():
        raise ValueError(f"sensor '{ob_eval.name}' has a zero scale: its axes give no direction")
    r /= norms
    pose[3] = (0.0, 0.0, 0.0, 1.0)
    return pose


def _frame_time(scene, frame):
    fps = scene.render.fps / scene.render.fps_base
    return (frame - scene.frame_start) / fps


def sweep_duration(model) -> float:
    """Seconds one sweep (one frame of the sensor) lasts: a turn, a solid-state frame, 0 for a
    depth camera (every pixel at once)."""
    rate = getattr(model, "rotation_rate", None) or getattr(model, "frame_rate", None)
    return 1.0 / rate if rate else 0.0


#: how far past a surface a ray that goes on through it starts (metres, plus this share of
#: the distance travelled): beyond the float32 rounding of a hit point, short of any real gap
PASS_EPSILON = 1e-4
PASS_RELATIVE = 1e-6
#: surfaces one sub-ray goes on through (glass), at most
MAX_PASSES = 3
#: the share of a mirror's reflectivity it returns diffusely to the sensor; the rest goes on
#: along the reflected ray (this add-on's approximation, not a measured BRDF)
MIRROR_DIFFUSE = 0.05


@dataclass
class _Echoes:
    """Every surface the sub-rays met, in one evaluated state of the scene (one block)."""

    ray: np.ndarray            # (E,) sub-ray index (global: beam * samples + sample)
    range: np.ndarray          # (E,) path length from the sensor
    cos: np.ndarray            # (E,) |cos incidence| at the surface
    reflectivity: np.ndarray   # (E,) diffuse reflectivity sent back
    factor: np.ndarray         # (E,) share of the sub-ray's power reaching the surface
    normals: np.ndarray        # (E, 3) float32 world normals
    object_names: list         # the block's object table (names), objects, instance matrices, materials
    objects: list
    object_index: np.ndarray
    instance_index: np.ndarray
    instance_matrices: np.ndarray
    material_index: np.ndarray
    materials: list
    rays: int
    structure: str


def _cast_echoes(dg, ray_ids, origins, dirs, settings: SensorSettings, structure, budget, session_=None,
                 slot=None):
    """Trace sub-rays ``dirs`` (unit) from ``origins`` in ``dg``: the first surface of each,
    then on through transmissive surfaces (up to ``MAX_PASSES``) and off mirror-like ones
    (up to ``returns.max_bounces``), all rays of one generation in one cast.  ``budget``:
    the rays the structures serve (a frame's, over every block of a sweep); ``session_``: the
    session to trace with instead of the depsgraph's (``session.swept``, with ``slot`` each
    ray's instant: a rigid sweep)."""
    model, phys = settings.model, settings.returns
    cols = {k: [] for k in ("ray", "range", "cos", "reflectivity", "factor", "normals", "object_index",
                            "instance_index", "material_index")}
    idx, o, d = ray_ids, origins, dirs
    offset = factor = passes = bounces = None  # the first generation: 0, 1, 0, 0 for every ray
    tables = None
    rays = 0
    used = structure
    op = None
    while len(idx):
        first = offset is None
        r = query.cast(o, d, depsgraph=dg, tmin=0.0 if first else tmin,
                       tmax=model.range_max if first else model.range_max - offset,
                       structure=used, expected_rays=max(1, budget), session_=session_, slot_=slot, points_=False,
                       hits_=True, **({"materials": True} if settings.materials else {}))
        rays += len(idx)
        used = r.structure
        if tables is None:
            tables = r
            if settings.materials:
                from .materials import optics

                op = optics(list(r.materials), list(r.objects))
        h = np.flatnonzero(r.hit)
        if not len(h):
            break
        t = np.take(r.t, h).astype(np.float64)
        n = r.normals  # the hits' rows (hits_)
        # the hits' sub-ray directions in float32, one dtype with the normals; the dot product as
        # a product with ones (a reduction over rows of 3 costs several times more)
        dh = d[0:1].astype(np.float32) if len(d) == 1 else np.take(d, h, axis=0).astype(np.float32)
        cos = np.abs((n * dh) @ np.ones(3, np.float32)).astype(np.float64)
        if op is not None:
            refl, trans, mirror = op.per_hit(r.material_index, r.object_index)
            refl, trans = np.asarray(refl, np.float64), np.asarray(trans, np.float64)
            mirror = np.asarray(mirror, bool) & ((bounces[h] if not first else 0) < phys.max_bounces)
        else:
            refl, trans, mirror = np.ones(len(h)), np.zeros(len(h)), np.zeros(len(h), bool)
        dist = t if first else offset[h] + t
        fh = np.ones(len(h)) if first else factor[h]
        cols["ray"].append(idx[h])
        cols["range"].append(dist)
        cols["cos"].append(cos)
        cols["reflectivity"].append(np.where(mirror, refl * MIRROR_DIFFUSE, refl * (1.0 - trans)))
        cols["factor"].append(fh)
        cols["normals"].append(n)
        cols["object_index"].append(r.object_index)
        cols["instance_index"].append(r.instance_index)
        cols["material_index"].append(r.material_index if r.material_index is not None
                                      else np.full(len(h), -1, np.int32))
        # the next generation: on through glass, off mirrors
        on = (~mirror) & (trans > 0) & ((passes[h] if not first else 0) < MAX_PASSES)
        nf = fh * np.where(mirror, refl * (1.0 - MIRROR_DIFFUSE), trans)
        g = np.flatnonzero((on | mirror) & (nf > 0) & (model.range_max - dist > PASS_EPSILON + PASS_RELATIVE * dist))
        if not len(g):
            break
        hg, mg = h[g], mirror[g]
        nd = d[hg].copy()
        if mg.any():
            ng = n[g][mg].astype(np.float64)
            rd = nd[mg] - 2.0 * np.einsum("ij,ij->i", nd[mg], ng)[:, None] * ng
            nd[mg] = rd / np.linalg.norm(rd, axis=1, keepdims=True)
        o = (o[hg] if len(o) == len(d) else o[0]) + t[g, None] * d[hg]  # one origin row: a sensor at one pose
        d = nd
        passes = (np.zeros(len(g), np.int32) if first else passes[hg]) + on[g]
        bounces = (np.zeros(len(g), np.int32) if first else bounces[hg]) + mg
        idx, offset, factor = idx[hg], dist[g], nf[g]
        slot = None if slot is None else slot[hg]
        tmin = PASS_EPSILON + PASS_RELATIVE * offset
    cat = {k: (v[0] if len(v) == 1 else np.concatenate(v) if v else None) for k, v in cols.items()}
    if cat["ray"] is None:
        cat = {"ray": np.zeros(0, np.int64), "range": np.zeros(0), "cos": np.zeros(0), "reflectivity": np.zeros(0),
               "factor": np.zeros(0), "normals": np.zeros((0, 3), np.float32),
               "object_index": np.zeros(0, np.int32), "instance_index": np.zeros(0, np.int32),
               "material_index": np.zeros(0, np.int32)}
    return _Echoes(ray=cat["ray"].astype(np.int64), range=cat["range"], cos=np.clip(cat["cos"], 0.0, 1.0),
                   reflectivity=np.clip(cat["reflectivity"], 0.0, 1.0), factor=np.clip(cat["factor"], 0.0, 1.0),
                   normals=cat["normals"], object_names=list(tables.object_names), objects=list(tables.objects),
                   object_index=cat["object_index"], instance_index=cat["instance_index"],
                   instance_matrices=tables.instance_matrices, material_index=cat["material_index"],
                   materials=list(tables.materials) if tables.materials is not None else [], rays=rays,
                   structure=used)


#: (model, divergence, samples) -> (Pattern, sub-ray directions, weights) of the last few sensors
_PATTERNS: dict = {}


def _pattern(model, phys):
    """The model's pattern and its beams' sub-rays, made once per sensor setting (a scan of
    many frames shoots the same rays in the sensor frame every frame)."""
    key = (repr(model), phys.beam_divergence, phys.beam_samples)
    hit = _PATTERNS.get(key)
    if hit is None:
        pat = model.pattern()
        sub, weights = returns.beam_directions(pat.directions, phys.beam_divergence, phys.beam_samples)
        times, at = np.unique(pat.time, return_inverse=True)  # the channels of a step fire together
        for a in (pat.directions, pat.ring, pat.azimuth, pat.time, sub, weights, times, at):
            a.flags.writeable = False
        if len(_PATTERNS) >= 4:
            _PATTERNS.pop(next(iter(_PATTERNS)))
        hit = _PATTERNS[key] = (pat, sub, weights, (times, at))
    return hit


def _beam_poses(pose_times, poses, firing, members=None):
    """The sensor's pose at each beam's firing time (``motion.interpolate_poses``),
    interpolated once per distinct time: (rotations (T, 3, 3), origins (T, 3), each beam's
    time (B,) in 0..T-1); ``firing`` = (distinct times, each beam's one); ``members``: only
    these beams."""
    times, at = firing
    if members is not None:
        used, at = np.unique(at[members], return_inverse=True)
        times = times[used]
    p = motion.interpolate_poses(pose_times, np.stack(poses), times)
    return np.ascontiguousarray(p[:, :3, :3]), np.ascontiguousarray(p[:, :3, 3]), at


def _sub_rays(rot, origin, at, rows, samples):
    """(origins, directions) world of beams fired from poses (``rot`` (T, 3, 3), ``origin``
    (T, 3) per distinct time, ``at`` (B,) each beam's): each beam's ``samples`` consecutive
    sensor-frame sub-ray directions of ``rows`` (B * samples, 3).  A spinning sensor fires
    its channels together, time after time: then one product per time over its group of
    rows, instead of a rotation gathered and applied per beam."""
    t, b = len(rot), len(at)
    group = b // t if t and b % t == 0 else 0
    if group and np.array_equal(at, np.repeat(np.arange(t), group)):
        d = np.matmul(rows.reshape(t, group * samples, 3), rot.transpose(0, 2, 1)).reshape(-1, 3)
        return np.repeat(origin, group * samples, axis=0), d
    # np.take of contiguous rows: a fancy index of the strided views gathers several times slower
    r = np.take(rot, at, axis=0)
    d = np.einsum("bij,bsj->bsi", r, rows.reshape(b, samples, 3)).reshape(-1, 3)
    return np.repeat(np.take(origin, at, axis=0), samples, axis=0), d


def _merge(blocks: list[_Echoes]):
    """One table of objects, instances and materials over the blocks of a sweep (by name:
    each block is its own extraction), and every echo re-indexed into it."""
    if len(blocks) == 1:
        b = blocks[0]
        return b, b.objects, b.object_names, b.instance_matrices, b.materials
    names, objects, where = [], [], {}
    mats, mat_where = [], {}
    inst, cols = [], {k: [] for k in ("ray", "range", "cos", "reflectivity", "factor", "normals", "object_index",
                                      "instance_index", "material_index")}
    base = 0
    for b in blocks:
        remap = np.empty(len(b.object_names) + 1, np.int32)
        for i, (nm, ob) in enumerate(zip(b.object_names, b.objects)):
            if nm not in where:
                where[nm] = len(names)
                names.append(nm)
                objects.append(ob)
            remap[i] = where[nm]
        remap[-1] = -1
        mremap = np.empty(len(b.materials) + 1, np.int32)
        for i, m in enumerate(b.materials):
            key = m.name if m is not None else ""
            if key not in mat_where:
                mat_where[key] = len(mats)
                mats.append(m)
            mremap[i] = mat_where[key]
        mremap[-1] = -1
        for k in cols:
            cols[k].append(getattr(b, k))
        cols["object_index"][-1] = remap[b.object_index]
        cols["material_index"][-1] = mremap[b.material_index]
        cols["instance_index"][-1] = np.where(b.instance_index >= 0, b.instance_index + base, -1).astype(np.int32)
        inst.append(b.instance_matrices)
        base += len(b.instance_matrices)
    merged = _Echoes(**{k: np.concatenate(v) for k, v in cols.items()}, object_names=names, objects=objects,
                     instance_matrices=np.concatenate(inst) if inst else np.zeros((0, 4, 4)), materials=mats,
                     rays=sum(b.rays for b in blocks), structure=blocks[-1].structure)
    return merged, objects, names, merged.instance_matrices, mats


def _evaluate_at(scene, view_layer, frame: int, seconds: float):
    """The scene evaluated ``seconds`` after the start of ``frame``."""
    fps = scene.render.fps / scene.render.fps_base
    f = frame + seconds * fps
    whole = int(np.floor(f))
    sub = float(f - whole)
    # already there (the sweep's start is the frame itself): no evaluation again, whose
    # worker threads would then still be spinning beside the trace
    if (scene.frame_current, scene.frame_subframe) != (whole, sub):
        scene.frame_set(whole, subframe=sub)
    return session.evaluated(scene, view_layer)


def _session(dg, settings: SensorSettings):
    """The session of the scene as evaluated now (meshes kept across calls), with what the
    scan reads of it, or None."""
    try:
        return session.get(dg, strict=False, attributes=("material",) if settings.materials else ())
    except (session.NoGeometry, session.InvalidGeometry):
        return None


def _along(origins, directions, rows, dist, one: bool) -> np.ndarray:
    """(P, 3) float64 ``origins[rows] + dist * directions[rows]`` (``one``: one origin row
    for all), column by column into a C-ordered result: numpy's broadcasts over rows of 3
    cost several times more than these passes over columns, and the sums are the same."""
    out = np.empty((len(rows), 3))
    for c in range(3):
        o = origins[0, c] if one else origins[:, c][rows]
        np.add(o, dist * directions[:, c][rows], out=out[:, c])
    return out


def _instants(scene, vl, frame, plan, start, ob, pose_times, poses):
    """Evaluate each block's instant once, reading the sensor's pose (into ``pose_times``,
    ``poses``) and the placements' matrices of the layout ``start``: (K, I, 4, 4), or None
    when some instant's instance walk differs from the start's (extract block by block)."""
    mats = []
    for _members, at in plan:
        dgb = _evaluate_at(scene, vl, frame, at)
        m = start.read_matrices(dgb)
        if m is None:
            return None
        mats.append(m)
        if at not in pose_times:
            i = int(np.searchsorted(pose_times, at))
            pose_times.insert(i, at)
            poses.insert(i, sensor_pose(ob.evaluated_get(dgb)))
    return np.stack(mats)


def scan_frame(ob, scene, *, view_layer=None, depsgraph=None, space="WORLD", settings=None,
               structure="auto") -> ScanResult:
    """One frame's scan from ``ob`` of the scene as evaluated now (its current frame).

    FRAME motion: every ray against the scene and the sensor pose of the frame.  SWEEP: the
    rays are cut into blocks of consecutive firing times (``core.motion``); each block sees
    the scene evaluated at its middle time, every ray from the sensor pose at its own firing
    time (interpolated between evaluated poses).  Where the same meshes only move over the
    sweep (fewer than ``twolevel.PAIRS_FROM`` placements of them), each block's instant is
    read as the placements' matrices and every ray is traced at once, the movers placed at
    its block's instant (``session.swept``, ``core.Swept``); otherwise each block is
    extracted and traced in turn.  The scene is left at a
    time within the sweep: callers restore the frame.  ``structure`` as ``api.cast``; the
    first block's choice serves the later ones.
    """
    if space not in SPACES:
        raise ValueError(f"space must be 'WORLD' or 'SENSOR', got {space!r}")
    settings = _settings(settings, ob, scene)
    model, phys, sweep = settings.model, settings.returns, settings.sweep
    vl = view_layer if view_layer is not None else (depsgraph.view_layer if depsgraph is not None else None)
    frame = scene.frame_current
    pat, sub, weights, firing = _pattern(model, phys)
    n_beams = len(pat)
    samples = len(weights)
    duration = sweep_duration(model)
    dg = depsgraph if depsgraph is not None else session.evaluated(scene, vl)
    pose0 = sensor_pose(ob.evaluated_get(dg))
    pose_times, poses = [0.0], [pose0]
    rigid = None  # (the sweep start's session, (I,) placements that stay put) when only placements move
    if sweep.motion == "FRAME" or duration <= 0:
        plan = [(np.arange(n_beams), None)]  # None: the depsgraph as it is
    else:
        body0 = session.fingerprint(dg)[1]
        dg_end = _evaluate_at(scene, vl, frame, duration)
        pose_times.append(duration)
        poses.append(sensor_pose(ob.evaluated_get(dg_end)))
        cap = min(sweep.max_blocks, len(firing[0]))
        if session.fingerprint(dg_end)[1] == body0:
            # nothing with triangles changed (a sensor that brings none is not in the body):
            # one block, every ray from its own pose
            n_blocks = 1
        else:
            end = _session(dg_end, settings)
            end = end.layout if end is not None else None
            start_s = _session(_evaluate_at(scene, vl, frame, 0.0), settings)
            start = start_s.layout if start_s is not None else None
            if start is not None and end is not None and start.rigid_to(end) \
                    and (start.matrices != end.matrices).any(axis=(1, 2)).sum() < twolevel.PAIRS_FROM:
                # the same meshes throughout, a few of them only moved: every block reads the
                # placements' matrices at its instant, and one trace places the movers at each
                # ray's instant (core.Swept)
                rigid = (start_s, (start.matrices == end.matrices).all(axis=(1, 2)))
            if sweep.blocks:
                n_blocks = min(sweep.blocks, cap)
            else:
                # inf when the topology changed within the sweep: as many blocks as allowed
                disp = start.displacement(end) if start is not None and end is not None else np.inf
                n_blocks = motion.blocks_for(disp, sweep.tolerance, cap)
        if n_blocks == 1:
            plan = [(np.arange(n_beams), 0.0)]
        else:
            block_of, mids = motion.sweep_blocks(pat.time, duration, n_blocks)
            # each block's beams in increasing order: one stable sort, not a pass per block
            members = np.split(np.argsort(block_of, kind="stable"),
                               np.cumsum(np.bincount(block_of, minlength=n_blocks))[:-1])
            plan = [(m, float(at)) for m, at in zip(members, mids) if len(m)]
    echoes = []
    used = structure
    instants = None
    if rigid is not None and len(plan) > 1:
        instants = _instants(scene, vl, frame, plan, rigid[0].layout, ob, pose_times, poses)
    # one pose for every beam: FRAME, or a sensor that stands still at every instant evaluated
    # (a block by block sweep evaluates its blocks' instants as it goes: it interpolates)
    one_pose = all(np.array_equal(p, pose0) for p in poses) and \
        (instants is not None or all(at is None or at in pose_times for _, at in plan))
    # each beam's sensor rotation, where a sensor-frame result needs it
    beam_rot = np.empty((n_beams, 3, 3)) if space == "SENSOR" and not one_pose else None
    # every sub-ray's world origin (one row for one pose) and direction, as traced
    world_o = pose0[None, :3, 3] if one_pose else np.empty((n_beams * samples, 3))
    # np.dot: matmul of (M, 3) by a strided 3 x 3 view takes a slow path (several times np.dot's time)
    world_d = np.dot(sub, pose0[:3, :3].T) if one_pose else np.empty((n_beams * samples, 3))
    if instants is not None:
        # a rigid sweep: every ray in one trace, the movers placed at the ray's block's instant
        slot = np.empty(n_beams, np.int32)
        for k, (members, _at) in enumerate(plan):
            slot[members] = k
        if not one_pose:
            rot, org, at_ = _beam_poses(pose_times, poses, firing)
            world_o, world_d = _sub_rays(rot, org, at_, sub, samples)
            if beam_rot is not None:
                beam_rot = np.take(rot, at_, axis=0)
        swept = session.swept(rigid[0], rigid[0].layout, instants, rigid[1])
        echoes.append(_cast_echoes(dg, np.arange(n_beams * samples), world_o, world_d, settings, used,
                                   n_beams * samples, swept, slot=np.repeat(slot, samples)))
        rigid[0].adopt(swept)
        used = echoes[-1].structure
    for members, at in plan if instants is None else ():
        dgb = dg
        if at is not None:
            dgb = _evaluate_at(scene, vl, frame, at)
            if at not in pose_times:
                i = int(np.searchsorted(pose_times, at))
                pose_times.insert(i, at)
                poses.insert(i, sensor_pose(ob.evaluated_get(dgb)))
        whole = len(members) == n_beams  # every beam in this block (FRAME, or one block)
        ids = np.arange(n_beams * samples) if whole else \
            (members[:, None] * samples + np.arange(samples)[None, :]).reshape(-1)
        if one_pose:
            o, d = world_o, (world_d if whole else world_d[ids])
        else:
            # every beam from the sensor's pose at its own firing time (motion.interpolate_poses)
            rot, org, at_ = _beam_poses(pose_times, poses, firing, None if whole else members)
            o, d = _sub_rays(rot, org, at_, sub if whole else sub[ids], samples)
            if whole:
                world_o, world_d = o, d
            else:
                world_o[ids], world_d[ids] = o, d
            if beam_rot is not None:
                beam_rot[members] = np.take(rot, at_, axis=0)
        e = _cast_echoes(dgb, ids, o, d, settings, used, n_beams * samples)
        used = e.structure
        echoes.append(e)
    merged, objects, names, inst_m, mats = _merge(echoes)
    meas = returns.measure_returns(merged.ray, merged.range, merged.cos, merged.reflectivity, merged.factor,
                                   beams=n_beams, samples=samples, weights=weights, sensor=model, returns=phys,
                                   frame=frame)
    beam, echo = meas.beam, meas.echo
    real = echo >= 0
    every = bool(real.all())  # no rain or fog return: gather directly
    er = echo if every else np.where(real, echo, 0)
    if every:
        sub_of = merged.ray[er]
    else:
        sub_of = np.where(real, merged.ray[er] if len(merged.ray) else 0, beam * samples)
    points = _along(world_o, world_d, sub_of, meas.range, one_pose)
    if every and len(er) == len(merged.ray) and np.array_equal(er, np.arange(len(er))):
        # every echo reported once, in order: the echoes' own arrays
        normals, obj, inst = merged.normals, merged.object_index, merged.instance_index
        mat, cos = merged.material_index, merged.cos.astype(np.float32)
    elif every:
        normals, obj, inst = merged.normals[er], merged.object_index[er], merged.instance_index[er]
        mat, cos = merged.material_index[er], merged.cos[er].astype(np.float32)
    else:
        nan3 = np.full((len(beam), 3), np.nan, np.float32)
        normals = np.where(real[:, None], merged.normals[er] if len(merged.normals) else nan3, nan3)
        obj = np.where(real, merged.object_index[er] if len(merged.object_index) else -1, -1)
        inst = np.where(real, merged.instance_index[er] if len(merged.instance_index) else -1, -1)
        mat = np.where(real, merged.material_index[er] if len(merged.material_index) else -1, -1)
        cos = np.where(real, merged.cos[er] if len(merged.cos) else np.nan, np.nan).astype(np.float32)
    normals, obj = normals.astype(np.float32, copy=False), obj.astype(np.int32, copy=False)
    inst, mat = inst.astype(np.int32, copy=False), mat.astype(np.int32, copy=False)
    table = classification(objects)
    cls = np.where(obj >= 0, table[np.maximum(obj, 0)] if len(table) else 1, NOISE_CLASS).astype(np.uint8)
    if space == "SENSOR" and one_pose:
        points = np.dot(points - world_o[0], pose0[:3, :3])
        normals = np.dot(normals.astype(np.float64), pose0[:3, :3]).astype(np.float32)
    elif space == "SENSOR":
        rot = beam_rot[beam]
        points = np.einsum("mji,mj->mi", rot, points - np.take(world_o, sub_of, axis=0))
        normals = np.einsum("mji,mj->mi", rot, normals.astype(np.float64)).astype(np.float32)
    obj_arr, name_arr = np.empty(len(objects), object), np.empty(len(names), object)
    obj_arr[:], name_arr[:] = objects, names
    mat_arr, mat_names = np.empty(len(mats), object), np.empty(len(mats), object)
    mat_arr[:] = mats
    mat_names[:] = [m.name if m is not None else "" for m in mats]
    return ScanResult(points=points, normals=normals, range=meas.range, intensity=meas.intensity,
                      ring=pat.ring[beam], azimuth=pat.azimuth[beam], time=_frame_time(scene, frame) + pat.time[beam],
                      object_index=obj, objects=obj_arr, object_names=name_arr, instance_index=inst,
                      instance_matrices=inst_m, ray=beam.astype(np.int64), sensor_matrix=pose0,
                      rays=merged.rays, frame=frame, space=space, structure=used, cos_incidence=cos,
                      return_index=meas.return_index, return_count=meas.return_count, material_index=mat,
                      materials=mat_arr, material_names=mat_names, classification=cls, blocks=len(plan),
                      extra={"rigid_blocks": len(plan) if instants is not None else 0})


def scan_depsgraph(ob, depsgraph, space="WORLD", model=None, structure="auto") -> ScanResult:
    """One scan of the depsgraph's scene as it is evaluated now; ``structure`` as ``api.cast``.
    ``model``: a ``SensorSettings`` or a ``sensor_model`` pair (default the object's settings)."""
    return scan_frame(ob, depsgraph.scene, depsgraph=depsgraph, space=space, settings=model, structure=structure)


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
    With SWEEP motion the scene is evaluated at times within the sweep and put back.
    Raises TypeError/ValueError naming the argument or the setting for bad input.
    """
    if not isinstance(sensor_object, bpy.types.Object):
        raise TypeError(f"sensor_object must be a bpy.types.Object, got {type(sensor_object).__name__}")
    if space not in SPACES:
        raise ValueError(f"space must be 'WORLD' or 'SENSOR', got {space!r}")
    if depsgraph is not None:
        session.check_depsgraph(depsgraph)
    scene = depsgraph.scene if depsgraph is not None else bpy.context.scene
    settings = sensor_settings(sensor_object, scene)
    if frame is None and settings.sweep.motion == "FRAME":
        dg = depsgraph if depsgraph is not None else bpy.context.evaluated_depsgraph_get()
        return scan_frame(sensor_object, scene, depsgraph=dg, space=space, settings=settings, structure=structure)
    frame = scene.frame_current if frame is None else _whole(frame, "frame")
    old = (scene.frame_current, scene.frame_subframe)
    view_layer = depsgraph.view_layer if depsgraph is not None else None
    try:
        if (scene.frame_current, scene.frame_subframe) != (frame, 0.0):
            scene.frame_set(frame)
        dg = depsgraph if depsgraph is not None and settings.sweep.motion == "FRAME" else \
            session.evaluated(scene, view_layer)
        return scan_frame(sensor_object, scene, view_layer=view_layer, depsgraph=dg, space=space,
                          settings=settings, structure=structure)
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
    f = result.fields()
    if f.get("classification") is None:  # a ScanResult made without one: the objects' property
        table = classification(result.objects)
        f["classification"] = table[result.object_index] if len(table) else np.ones(len(result), np.uint8)
    names = () if result.material_names is None else [str(x) for x in result.material_names]
    return pointcloud.write(path, fmt.lower(), f, list(result.object_names), material_names=names)


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

    The first frame plans (``api.cast``'s 'auto'); later frames inherit its decision (a
    session of the same scene does not plan again), and after a change each part of the
    scene picks its structure for the frames still to come (``session.expecting``): the
    still soup and each moved mesh's bottom level for the rest of the job, a deforming mesh
    for its one frame.  ``structures``: how the last frame was traced, per part
    (``Session.describe``)."""
    fmt = str(fmt).lower()
    if fmt not in pointcloud.FORMATS:
        raise BadInput(f"bad arguments: format must be one of {', '.join(pointcloud.FORMATS)}, got {fmt!r}")
    if space not in SPACES:
        raise BadInput(f"bad arguments: space must be 'WORLD' or 'SENSOR', got {space!r}")
    try:
        settings = sensor_settings(ob, scene)
        start, end = frames
        check_frames(scene, start, end)
    except (TypeError, ValueError) as e:
        raise BadInput(f"sensor '{ob.name}': {e}") from None
    folder = output_folder(directory)
    written = written if written is not None else []
    old = (scene.frame_current, scene.frame_subframe)
    count = end - start + 1
    rays = points = 0
    structure, structures = "auto", None
    poses = []
    try:
        for i, frame in enumerate(range(start, end + 1)):
            job.progress(i / count, f"frame {frame} ({i + 1} of {count})")
            yield job.fraction, job.text
            job.check()
            scene.frame_set(frame)
            dg = session.evaluated(scene, view_layer)
            try:
                with session.expecting(count - i):
                    result = scan_frame(ob, scene, view_layer=view_layer, depsgraph=dg, space=space,
                                        settings=settings)
            except ValueError as e:  # what only a frame shows: a material's bad reflectivity, a zero scale
                raise BadInput(f"sensor '{ob.name}', frame {frame}: {e}") from None
            structure = result.structure
            structures = session.described(dg)
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
            "structure": structure, "structures": structures}


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
    """``-c hybrid_raycast scan --sensor NAME [--frames A-B] --output DIR [--format ...]
    [--motion ...] [--returns ...] [--beam-samples N] [--beam-divergence MRAD]``: the JSON
    document of the run (the CLI prints or writes it).  The last four override the sensor's
    settings for this run only: they are set on the object and put back afterwards."""
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

    # --motion, --returns, --beam-samples, --beam-divergence (checked by the parser): set on the
    # sensor for this run only, the old values put back afterwards, also on an error
    given = {"motion": getattr(args, "motion", None), "returns": getattr(args, "returns", None),
             "beam_samples": getattr(args, "beam_samples", None),
             "beam_divergence": getattr(args, "beam_divergence", None)}
    given = {k: (v.upper() if isinstance(v, str) else v) for k, v in given.items() if v is not None}
    old = {k: getattr(s, k) for k in given}
    try:
        for k, v in given.items():
            setattr(s, k, v)
        used = {"motion": s.motion, "returns": s.returns, "beam_samples": s.beam_samples,
                "beam_divergence": round(float(s.beam_divergence), 6)}
        result = run_sync(scan_job(scene, Job(), ob, frames=frames, directory=str(out_dir), fmt=fmt, space=space))
    finally:
        for k, v in old.items():
            setattr(s, k, v)
    print(f"hybrid_raycast scan: {result['frames']} frames, {result['rays']:,} rays, {result['points']:,} points "
          f"({used['motion']}, {used['returns']} returns) -> {result['folder']}", file=stdout, flush=True)
    return {"command": "scan", "sensor": ob.name, "frames": list(frames), "format": fmt, "space": space, **used,
            "rays": result["rays"], "points": result["points"], "files": [str(p) for p in result["files"]],
            "structure": result["structure"], "structures": result["structures"]}
