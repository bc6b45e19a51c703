"""Sensor models for synthetic scans: the rays of one frame, and what a return looks like.

Three models give the rays of one frame in the *sensor frame* (``pattern()`` -> ``Pattern``):

- ``RotatingLidar``: ``channels`` lasers stacked in elevation (evenly over ``fov_down`` ..
  ``fov_up``, or an explicit ``elevations`` list), fired at ``azimuth_steps`` evenly spaced
  azimuths per turn, turning at ``rotation_rate`` Hz.  Axes: the spin axis is +Z, azimuth
  0 is +X and grows towards +Y (counter-clockwise seen from above).
- ``AreaScanner`` (solid-state): a ``h_steps`` x ``v_steps`` grid over ``h_fov`` x ``v_fov``
  degrees, looking along +X with +Z up, one frame every 1 / ``frame_rate`` s, rows scanned
  top to bottom.
- ``DepthCamera``: a pinhole from intrinsics in pixels (``fx``, ``fy``, ``cx``, ``cy``,
  ``width``, ``height``), in Blender's camera convention: looking along -Z, +X right, +Y up,
  pixel rows counted downwards; one ray through each pixel centre, all at time 0.

Every ray has a ``ring`` (the laser channel / the row), an ``azimuth`` in degrees in
[0, 360) (the firing angle of a rotating LiDAR, else atan2(y, x) of the direction) and a
``time`` in seconds from the start of the frame (the firing time within the sweep).

The pattern is in the sensor frame and has no motion: a scan with FRAME motion casts every
ray against the scene of the frame, and ``time`` says when each ray would have fired; a
SWEEP scan (``operators/scan.py`` with ``core.motion``) casts each block of firing times
against the scene at its own time, from the sensor's pose at each ray's time.

``Returns`` turns hits into measurements (``measure``): the range limits (a hit nearer than
``range_min`` is a blind-zone miss, not a see-through), Gaussian range noise with
``noise_sigma`` metres drawn from ``numpy.random.default_rng((seed, frame))`` so a frame
repeats exactly and frames differ, an intensity from the lidar equation for a Lambertian
target (received power ~ cos(incidence) / range^2, scaled to 1 for a perpendicular target at
``reference_range`` and clipped to [0, 1]), and returns with intensity below
``drop_below`` dropped.  ``core.returns.measure_returns`` is the same measurement for beams
with a footprint (divergence, several echoes per beam, materials, weather, dropout); with one
thin ray per beam and its other settings at their defaults it gives what ``measure`` gives.

``PRESETS``: a few real sensors, each with the document its figures come from.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

__all__ = ["Pattern", "RotatingLidar", "AreaScanner", "DepthCamera", "Returns", "RETURN_MODES", "Preset",
           "PRESETS", "measure", "camera_intrinsics"]

#: which returns of a beam are reported: the strongest, the nearest, the farthest, or the
#: strongest and the farthest ('DUAL', as dual-return LiDARs do); ``core.returns`` applies them
RETURN_MODES = ("STRONGEST", "FIRST", "LAST", "DUAL")


@dataclass
class Pattern:
    """The rays of one frame in the sensor frame.

    directions: (N, 3) float64 unit vectors; ring: (N,) int32; azimuth: (N,) float32 degrees
    in [0, 360); time: (N,) float64 seconds from the start of the frame.
    """

    directions: np.ndarray
    ring: np.ndarray
    azimuth: np.ndarray
    time: np.ndarray

    def __len__(self):
        return len(self.directions)


def _count(value, name):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float, np.floating)):
        raise TypeError(f"{name} must be a positive whole number, got {type(value).__name__}")
    if not np.isfinite(value) or value < 1 or int(value) != value:
        raise ValueError(f"{name} must be a positive whole number, got {value!r}")
    return int(value)


def _number(value, name, *, low=None, high=None, positive=False):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float, np.floating)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    value = float(value)
    if not np.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if positive and not value > 0:
        raise ValueError(f"{name} must be greater than 0, got {value!r}")
    if low is not None and value < low:
        raise ValueError(f"{name} must be at least {low}, got {value!r}")
    if high is not None and value > high:
        raise ValueError(f"{name} must be at most {high}, got {value!r}")
    return value


def _ranges(self):
    self.range_min = _number(self.range_min, "range_min", low=0.0)
    self.range_max = _number(self.range_max, "range_max", positive=True)
    if self.range_min >= self.range_max:
        raise ValueError(f"range_min ({self.range_min:g}) must be below range_max ({self.range_max:g})")


def _azimuth_deg(d):
    return (np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0).astype(np.float32)


def _fan(elevation, azimuth, *, azimuth_major):
    """Unit directions (N, 3) float64 for every pair of ``elevation`` x ``azimuth`` angles
    (radians; azimuth 0 is +X growing towards +Y, elevation up towards +Z), and each ray's
    ring (N,) int32, the index of its elevation.  Order: azimuth-major (every elevation of
    one azimuth, then the next) or elevation-major (one row of azimuths per elevation)."""
    ce, se = np.cos(elevation), np.sin(elevation)
    d = np.empty((len(elevation), len(azimuth), 3))
    d[..., 0] = ce[:, None] * np.cos(azimuth)[None, :]
    d[..., 1] = ce[:, None] * np.sin(azimuth)[None, :]
    d[..., 2] = se[:, None]
    ring = np.broadcast_to(np.arange(len(elevation), dtype=np.int32)[:, None], d.shape[:2])
    if azimuth_major:
        d, ring = d.transpose(1, 0, 2), ring.T
    return d.reshape(-1, 3), ring.reshape(-1).copy()


@dataclass
class RotatingLidar:
    """A spinning multi-beam LiDAR (module doc).  Angles in degrees, ranges in metres."""

    channels: int = 16
    fov_up: float = 15.0
    fov_down: float = -15.0
    #: explicit elevation of each channel (degrees); overrides channels / fov_up / fov_down
    elevations: tuple | None = None
    azimuth_steps: int = 1800
    rotation_rate: float = 10.0
    range_min: float = 0.5
    range_max: float = 100.0

    def __post_init__(self):
        if self.elevations is not None:
            e = np.asarray(self.elevations, dtype=np.float64).ravel()
            if e.size == 0:
                raise ValueError("elevations must list at least one angle")
            if not np.isfinite(e).all() or (np.abs(e) > 90).any():
                raise ValueError("elevations must be finite angles between -90 and 90 degrees")
            self.elevations = tuple(float(x) for x in e)
            self.channels = len(e)
        else:
            self.channels = _count(self.channels, "channels")
            self.fov_up = _number(self.fov_up, "fov_up", low=-90.0, high=90.0)
            self.fov_down = _number(self.fov_down, "fov_down", low=-90.0, high=90.0)
            if self.fov_down > self.fov_up:
                raise ValueError(f"fov_down ({self.fov_down:g}) must not be above fov_up ({self.fov_up:g})")
        self.azimuth_steps = _count(self.azimuth_steps, "azimuth_steps")
        self.rotation_rate = _number(self.rotation_rate, "rotation_rate", positive=True)
        _ranges(self)

    def elevation_angles(self) -> np.ndarray:
        """(channels,) degrees, ring 0 first (lowest for an evenly spaced fan)."""
        if self.elevations is not None:
            return np.asarray(self.elevations, dtype=np.float64)
        if self.channels == 1:
            return np.array([(self.fov_up + self.fov_down) / 2.0])
        return np.linspace(self.fov_down, self.fov_up, self.channels)

    def pattern(self) -> Pattern:
        n_az = self.azimuth_steps
        az = np.arange(n_az) * (2.0 * np.pi / n_az)
        # azimuth-major order: all channels of one firing, then the next azimuth
        d, ring = _fan(np.radians(self.elevation_angles()), az, azimuth_major=True)
        shape = (n_az, self.channels)
        azimuth = np.broadcast_to(np.degrees(az).astype(np.float32)[:, None], shape)
        t = np.broadcast_to((np.arange(n_az) / (n_az * self.rotation_rate))[:, None], shape)
        return Pattern(d, ring, azimuth.reshape(-1).copy(), t.reshape(-1).copy())


@dataclass
class AreaScanner:
    """A solid-state scanner: a grid over a rectangular field of view (module doc)."""

    h_fov: float = 70.0
    v_fov: float = 30.0
    h_steps: int = 350
    v_steps: int = 150
    frame_rate: float = 10.0
    range_min: float = 0.5
    range_max: float = 100.0

    def __post_init__(self):
        self.h_fov = _number(self.h_fov, "h_fov", high=360.0, positive=True)
        self.v_fov = _number(self.v_fov, "v_fov", high=180.0, positive=True)
        self.h_steps = _count(self.h_steps, "h_steps")
        self.v_steps = _count(self.v_steps, "v_steps")
        self.frame_rate = _number(self.frame_rate, "frame_rate", positive=True)
        _ranges(self)

    def pattern(self) -> Pattern:
        def centres(fov, n):  # cell centres, symmetric about 0
            return np.radians((np.arange(n) + 0.5) / n * fov - fov / 2.0)

        az = centres(self.h_fov, self.h_steps)[::-1]        # left (+Y) to right
        el = centres(self.v_fov, self.v_steps)[::-1]        # top to bottom
        d, ring = _fan(el, az, azimuth_major=False)         # rows of azimuths, top row first
        n = len(d)
        return Pattern(d, ring, _azimuth_deg(d), np.arange(n) / (n * self.frame_rate))


@dataclass
class DepthCamera:
    """A pinhole depth camera from intrinsics in pixels (module doc)."""

    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 320.0
    cy: float = 240.0
    range_min: float = 0.1
    range_max: float = 100.0

    def __post_init__(self):
        self.width = _count(self.width, "width")
        self.height = _count(self.height, "height")
        self.fx = _number(self.fx, "fx", positive=True)
        self.fy = _number(self.fy, "fy", positive=True)
        self.cx = _number(self.cx, "cx")
        self.cy = _number(self.cy, "cy")
        _ranges(self)

    def pattern(self) -> Pattern:
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        d = np.empty((self.height, self.width, 3))
        d[..., 0] = ((u - self.cx) / self.fx)[None, :]
        d[..., 1] = (-(v - self.cy) / self.fy)[:, None]
        d[..., 2] = -1.0
        d = d.reshape(-1, 3)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        ring = np.repeat(np.arange(self.height, dtype=np.int32), self.width)
        return Pattern(d, ring, _azimuth_deg(d), np.zeros(len(d)))


def camera_intrinsics(lens_mm, sensor_width_mm, sensor_height_mm, sensor_fit, width, height,
                      shift_x=0.0, shift_y=0.0) -> dict:
    """Pinhole intrinsics (pixels) of a Blender perspective camera rendered at width x height
    (square pixels): Blender fits the sensor to the larger side ('AUTO'), or to the side
    ``sensor_fit`` names; shifts are in units of the larger side (``bpy.types.Camera``)."""
    width, height = _count(width, "width"), _count(height, "height")
    if sensor_fit == "AUTO":
        horizontal = width >= height
        size = sensor_width_mm
    elif sensor_fit == "HORIZONTAL":
        horizontal, size = True, sensor_width_mm
    elif sensor_fit == "VERTICAL":
        horizontal, size = False, sensor_height_mm
    else:
        raise ValueError(f"sensor_fit must be 'AUTO', 'HORIZONTAL' or 'VERTICAL', got {sensor_fit!r}")
    f = lens_mm / size * (width if horizontal else height)
    big = max(width, height)
    return {"width": width, "height": height, "fx": f, "fy": f,
            "cx": width / 2.0 - shift_x * big, "cy": height / 2.0 + shift_y * big}


@dataclass
class Returns:
    """What turns a hit into a measurement (module doc).  The fields after ``drop_below``
    are used by ``core.returns.measure_returns`` only (beam divergence, multiple returns,
    weather, dropout; that module's doc has the physics); ``measure`` ignores them."""

    noise_sigma: float = 0.0
    seed: int = 0
    reference_range: float = 10.0
    drop_below: float = 0.0
    #: which returns of a beam are reported, one of ``RETURN_MODES``
    mode: str = "STRONGEST"
    #: full cone angle of a beam, milliradians (0: a thin ray)
    beam_divergence: float = 0.0
    #: sub-rays cast per beam over its cone
    beam_samples: int = 1
    #: metres: echoes of one beam closer than this merge into one return
    range_resolution: float = 0.1
    #: meteorological visibility, metres (inf: clear air); extinction 3.912 / visibility
    visibility: float = float("inf")
    #: per beam and frame, the probability of a false return (rain, fog) near the sensor
    false_return_rate: float = 0.0
    #: metres: false returns fall between range_min and this (at most range_max)
    false_return_range: float = 5.0
    false_return_intensity: float = 0.05
    #: CARLA's dropout: every return dropped with dropoff_general_rate; one with intensity
    #: I <= dropoff_intensity_limit also with dropoff_zero_intensity * (1 - I / limit)
    dropoff_general_rate: float = 0.0
    dropoff_intensity_limit: float = 1.0
    dropoff_zero_intensity: float = 0.0
    #: mirror reflections the caller follows (0: a mirror is an ordinary surface)
    max_bounces: int = 0

    def __post_init__(self):
        self.noise_sigma = _number(self.noise_sigma, "noise_sigma", low=0.0)
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative whole number, got {self.seed!r}")
        self.seed = int(self.seed)
        self.reference_range = _number(self.reference_range, "reference_range", positive=True)
        self.drop_below = _number(self.drop_below, "drop_below", low=0.0, high=1.0)
        if not isinstance(self.mode, str):
            raise TypeError(f"returns mode must be a string, one of {', '.join(RETURN_MODES)}; "
                            f"got {type(self.mode).__name__}")
        if self.mode not in RETURN_MODES:
            raise ValueError(f"returns mode must be one of {', '.join(RETURN_MODES)}, got {self.mode!r}")
        self.beam_divergence = _number(self.beam_divergence, "beam_divergence", low=0.0)
        self.beam_samples = _count(self.beam_samples, "beam_samples")
        self.range_resolution = _number(self.range_resolution, "range_resolution", positive=True)
        v = self.visibility
        if isinstance(v, bool) or not isinstance(v, (int, np.integer, float, np.floating)):
            raise TypeError(f"visibility must be a number, got {type(v).__name__}")
        if not float(v) > 0:  # also rejects nan; inf is clear air
            raise ValueError(f"visibility must be greater than 0 (inf for clear air), got {v!r}")
        self.visibility = float(v)
        self.false_return_rate = _number(self.false_return_rate, "false_return_rate", low=0.0, high=1.0)
        self.false_return_range = _number(self.false_return_range, "false_return_range", positive=True)
        self.false_return_intensity = _number(self.false_return_intensity, "false_return_intensity",
                                              low=0.0, high=1.0)
        for name in ("dropoff_general_rate", "dropoff_intensity_limit", "dropoff_zero_intensity"):
            setattr(self, name, _number(getattr(self, name), name, low=0.0, high=1.0))
        b = self.max_bounces
        if isinstance(b, bool) or not isinstance(b, (int, np.integer, float, np.floating)):
            raise TypeError(f"max_bounces must be a whole number, got {type(b).__name__}")
        if not np.isfinite(b) or b < 0 or int(b) != b:
            raise ValueError(f"max_bounces must be a whole number of at least 0, got {b!r}")
        self.max_bounces = int(b)


def measure(t, hit, cos_incidence, sensor, returns: Returns, frame: int = 0):
    """Measurements of one frame from the true hits.

    t: (N,) true range along unit directions (inf on a miss); hit: (N,) bool;
    cos_incidence: (N,) |cos| of the angle between ray and surface normal.
    Returns (keep (N,) bool, range (N,) float64 with noise, intensity (N,) float32):
    keep is True for returns within [range_min, range_max] (true range) whose intensity
    reaches ``drop_below``; range and intensity are meaningful where keep is True.
    """
    t = np.asarray(t, dtype=np.float64)
    keep = np.asarray(hit, bool) & (t >= sensor.range_min) & (t <= sensor.range_max)
    r = np.where(keep, t, np.nan)
    if returns.noise_sigma > 0:
        rng = np.random.default_rng((returns.seed, int(frame) & 0xFFFFFFFF))
        r = r + rng.normal(0.0, returns.noise_sigma, len(r))
        keep &= r > 0  # a noisy range cannot put the point behind the sensor
    with np.errstate(invalid="ignore", divide="ignore"):
        falloff = np.minimum(1.0, (returns.reference_range / np.where(keep, t, 1.0)) ** 2)
        intensity = np.clip(np.abs(cos_incidence) * falloff, 0.0, 1.0)
    intensity = np.where(keep, intensity, 0.0).astype(np.float32)
    if returns.drop_below > 0:
        keep &= intensity >= returns.drop_below
    return keep, r, intensity


# -- presets ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Preset:
    """A real sensor: ``kind`` ('ROTATING' or 'AREA'), its model's parameters, the range
    noise its document states (1 sigma, metres), and where every figure comes from."""

    label: str
    kind: str
    params: dict
    noise_sigma: float
    description: str
    returns: dict = field(default_factory=dict)

    def sensor(self):
        return (RotatingLidar if self.kind == "ROTATING" else AreaScanner)(**self.params)


PRESETS = {
    "VLP16": Preset(
        "Velodyne VLP-16", "ROTATING",
        {"channels": 16, "fov_up": 15.0, "fov_down": -15.0, "azimuth_steps": 1800, "rotation_rate": 10.0,
         "range_min": 0.5, "range_max": 100.0},
        0.0,
        "16 lasers at -15 to +15 deg in 2 deg steps, 300-1200 RPM, 0.2 deg azimuth at 600 RPM (10 Hz): "
        "VLP-16 User Manual 63-9243 Rev. D, sections 8.3 and 9.2. Range 100 m as the VLP-16 datasheet "
        "states it; range_min 0.5 m and noise 0 are this add-on's choices, not Velodyne's"),
    "OS1_64": Preset(
        "Ouster OS1-64", "ROTATING",
        {"channels": 64, "fov_up": 16.6, "fov_down": -16.6, "azimuth_steps": 2048, "rotation_rate": 10.0,
         "range_min": 0.8, "range_max": 120.0},
        0.015,
        "64 beams over +16.6 to -16.6 deg, 2048 (or 1024, 512) columns, 10-20 Hz, range 0.8-120 m "
        "(80 % Lambertian target), repeatability 1.5 cm 1 sigma at high SNR: Ouster OS1 datasheet "
        "(High Resolution Imaging LIDAR, 64/16-channel figures); beams are evenly spread here"),
    "LIVOX_HAP": Preset(
        "Livox HAP", "AREA",
        {"h_fov": 120.0, "v_fov": 25.0, "h_steps": 600, "v_steps": 75, "frame_rate": 10.0,
         "range_min": 0.5, "range_max": 150.0},
        0.02,
        "120 x 25 deg field of view, 452,000 points/s at 10 Hz, 0.5 m blind zone, 150 m at 10 % "
        "reflectivity, random range error < 2 cm 1 sigma at 20 m: Livox HAP User Manual, table 1.2.1. "
        "Livox scans a non-grid pattern; here a uniform 600 x 75 grid gives the same field of view and "
        "45,000 points per frame (about the stated point rate at 10 Hz)"),
    "LIVOX_AVIA_LINE": Preset(
        "Livox Avia (repetitive line mode)", "AREA",
        {"h_fov": 70.4, "v_fov": 4.5, "h_steps": 704, "v_steps": 6, "frame_rate": 10.0,
         "range_min": 1.0, "range_max": 100.0},
        0.0,
        "70.4 x 4.5 deg field of view in the repetitive scanning mode (the Avia as the GreenValley "
        "LiAir X3 User Guide, section 2.3.1, describes it); the 704 x 6 grid, the 1-100 m range and "
        "zero noise are this add-on's choices, not Livox figures"),
    "PANDAR_XT16": Preset(
        "Hesai PandarXT-16", "ROTATING",
        {"channels": 16, "fov_up": 15.0, "fov_down": -15.0, "azimuth_steps": 2000, "rotation_rate": 10.0,
         "range_min": 0.05, "range_max": 120.0},
        0.0,
        "16 channels at +15 to -15 deg in 2 deg steps (design values), instrument range 120 m: PandarXT-16 "
        "User Manual, Appendix I (Channel Distribution); 600 RPM (10 Hz) default spin rate: section 4.2.2. "
        "The 0.18 deg azimuth step (2,000 a turn, taken at 10 Hz) and the 0.05 m minimum range are TIER IV's "
        "nebula driver's figures (class PandarXT16: peak_resolution_mdeg, min_range), not found in the manual "
        "pages searched; no range accuracy was found, so noise is 0. Ring 0 is the lowest beam (Hesai's channel 16)"),
    "RS_LIDAR_16": Preset(
        "RoboSense RS-LiDAR-16", "ROTATING",
        {"channels": 16, "fov_up": 15.0, "fov_down": -15.0, "azimuth_steps": 1800, "rotation_rate": 10.0,
         "range_min": 0.4, "range_max": 150.0},
        0.0,
        "16 channels, 8 pitched down and 8 up (RS-LiDAR-16 User Manual, appendix B.7); range 150 m (its revision "
        "history, rev. 3.3). The manual gives no design angles: the sample calibration file of RoboSense's "
        "ros_rslidar driver (rslidar_pointcloud/data/angle.csv) has them within 0.04 deg of -15 to +15 deg in "
        "2 deg steps, so they are spread evenly here. 1,800 azimuth steps at 600 RPM: rs_driver's guide "
        "doc/howto/19_about_splitting_frame.md, section 19.2.1 (a firing round every 55.5 us, 0.2 deg); "
        "range_min 0.4 m is rs_driver's RS16 decoder minimum (decoder_RS16.hpp); no range accuracy was found, "
        "so noise is 0"),
}
#: the sensor an object has until the user changes it: a common rotating LiDAR, no noise
DEFAULT_PRESET = "VLP16"


def sensor_fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in fields(cls))
