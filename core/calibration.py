"""Calibration: measure and fit the paper's two constants per structure, save and load them.

Hapala, Karlik and Havran (2011), section 3: over s representative scenes, build the
hierarchical structure and shoot M rays in each scene i, then

    c_B = (1/s) sum_i T_B(i) / (N(i) log2 N(i))      (build constant)
    c_R = (1/s) sum_i T_R(i) / (M(i) log2 N(i))      (per-ray constant)

so that a new scene of N triangles is estimated at T_B ~ c_B N log2 N and
t ~ c_R log2 N per ray (``model='paper'``).  The default, ``model='affine'``, adds a fixed
cost to each, T_B ~ a_B + c_B N log2 N and t ~ a_R + c_R log2 N (least squares on
relative residuals): per-call overheads that N log2 N cannot carry inflate the paper's
ratios on small scenes, so its constants overestimate large ones (docs/report/report.md,
issue 4, compares the two on held-out scenes).

This module fits the same form for every candidate ('bvh', 'embree'), keeps each scene's own values, and takes the spread across scenes as the
constants' interval: ``low``/``high`` are the 10th/90th percentiles of the per-scene
values (numpy's linear interpolation; with few scenes that is close to min/max), widened
if needed so that low <= mean <= high.  The grid is not fitted (the plan measures it on
the scene itself, as the paper does) but its per-scene build and ray times are recorded
beside the others for the report.

A calibration is only valid where it was measured: the file records the format, the
package, numpy and Python versions and a machine fingerprint (OS, architecture, CPU
name, core count).  ``load`` refuses anything else with a ``CalibrationError`` whose
message is one line; ``load_or_default`` never raises and falls back on the shipped
defaults (``default_calibration.json``, labelled ``source='shipped defaults'``) or on a
fresh calibration when asked.

Timings: ``time.perf_counter`` around one build and one trace per scene and structure,
each batch traced as ``trace`` runs it (``time_trace``).  The default 131,072 rays per
scene fill both threads of every structure, so the per-ray constants are a large
workload's.  The grid is also timed on samples of K = 1,024 to 65,536 rays: a plan's
K-ray sample pays the grid's fixed per-batch cost over few rays, and the per-scene ratio
(large-workload time / sample time) corrects it (``Calibration.grid_sample_ratio``).
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import sys
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .accel import Accel
from .factory import build
from .mesh import TriangleMesh

#: bump when the JSON layout or the meaning of a field changes
CALIBRATION_FORMAT = 2
#: the constants shipped with the package, measured by ``calibrate()`` on the default set
DEFAULT_PATH = Path(__file__).with_name("default_calibration.json")
#: the model fitted by ``fit``; see MODELS
DEFAULT_MODEL = "affine"
DEFAULT_SPREAD = (10.0, 90.0)
#: rays per scene for each calibration scale.  The default is two chunks of the BVH
#: (2 x 65,536 rays), so that the measured time per ray is a large workload's, spread
#: over the structure's threads like one
RAYS_PER_SCENE = {"tiny": 2000, "quick": 20000, "default": 1 << 17}
#: sample sizes K at which calibration times the grid on each scene, to correct a plan's
#: K-ray sample for the fixed per-batch cost of lockstep traversal (see grid_sample_ratio)
SAMPLE_LADDER = (1024, 2048, 4096, 8192, 16384, 32768, 65536)
#: the least number of rays the grid's large-workload time per ray is measured on when
#: samples are timed (whatever the scale's rays per scene)
GRID_LARGE_RAYS = 1 << 17


class CalibrationError(Exception):
    """A calibration that cannot be used here; ``str(error)`` is a one-line reason."""


# -- what was measured ---------------------------------------------------------------------

def nlog2n(n: int) -> float:
    """N log2 N with log2 taken of max(N, 2): one triangle still costs something."""
    n = max(int(n), 1)
    return n * math.log2(max(n, 2))


def log2n(n: int) -> float:
    return math.log2(max(int(n), 2))


@dataclass
class Measurement:
    """One structure on one scene: build time and the time of ``rays`` rays, in seconds."""

    build_time: float
    trace_time: float
    rays: int
    threads: int = 1

    @property
    def per_ray(self) -> float:
        return self.trace_time / max(self.rays, 1)


@dataclass
class SceneRecord:
    """One calibration scene: its size and one Measurement per structure."""

    name: str
    triangles: int
    rays: int
    kinds: dict[str, Measurement] = field(default_factory=dict)
    #: the grid's time per ray on a batch of K rays, {K: seconds}: what a plan's sample costs
    grid_samples: dict[int, float] = field(default_factory=dict)

    def grid_sample_ratio(self, k: int) -> float | None:
        """Large-workload grid time per ray over the K-ray sample's, or None if not measured."""
        g, s = self.kinds.get("grid"), self.grid_samples.get(k)
        return g.per_ray / s if g is not None and s else None

    def c_B(self, kind: str) -> float:
        """This scene's build constant T_B / (N log2 N)."""
        return self.kinds[kind].build_time / nlog2n(self.triangles)

    def c_R(self, kind: str) -> float:
        """This scene's ray constant T_R / (M log2 N)."""
        m = self.kinds[kind]
        return m.trace_time / (max(m.rays, 1) * log2n(self.triangles))


@dataclass
class KindFit:
    """The fitted constants of one structure, with their interval over the scenes."""

    c_B: float
    c_R: float
    c_B_low: float
    c_B_high: float
    c_R_low: float
    c_R_high: float
    scenes: int
    #: parameters of models beyond the paper's two constants (empty for 'paper')
    extra: dict = field(default_factory=dict)


@dataclass
class Estimate:
    """Estimated build time and per-ray time (seconds) of one structure for N triangles."""

    kind: str
    build: float
    build_low: float
    build_high: float
    per_ray: float
    per_ray_low: float
    per_ray_high: float


# -- the model (the hook for refinements) ------------------------------------------------------

def _spread(values, spread) -> tuple[float, float, float]:
    v = np.asarray(values, np.float64)
    mean = float(v.mean())
    lo, hi = (float(x) for x in np.percentile(v, spread))
    return mean, min(lo, mean), max(hi, mean)


def _fit_paper(records: list[SceneRecord], kind: str, spread) -> KindFit:
    """The paper's two constants: plain means of the per-scene ratios (section 3)."""
    have = [r for r in records if kind in r.kinds]
    cb, cb_lo, cb_hi = _spread([r.c_B(kind) for r in have], spread)
    cr, cr_lo, cr_hi = _spread([r.c_R(kind) for r in have], spread)
    return KindFit(cb, cr, cb_lo, cb_hi, cr_lo, cr_hi, len(have))


def _estimate_paper(fit: KindFit, kind: str, n: int) -> Estimate:
    """T_B ~ c_B N log2 N, t ~ c_R log2 N (section 3)."""
    a, b = nlog2n(n), log2n(n)
    return Estimate(kind, fit.c_B * a, fit.c_B_low * a, fit.c_B_high * a, fit.c_R * b, fit.c_R_low * b, fit.c_R_high * b)


def _affine_lsq(x, y) -> tuple[float, float]:
    """(a, c) >= 0 minimising sum ((a + c x_i) / y_i - 1)^2: least squares on relative
    residuals, so a 500-triangle scene weighs as much as a 1M one; a < 0 falls back on a = 0."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ok = (y > 0) & np.isfinite(y) & (x > 0)
    x, y = x[ok], y[ok]
    if x.size < 3:  # too few scenes to tell a fixed cost from a slope: the paper's mean ratio
        return 0.0, float(np.mean(y / x)) if x.size else 0.0
    (a, c), *_ = np.linalg.lstsq(np.stack([1 / y, x / y], axis=1), np.ones_like(y), rcond=None)
    if not (a >= 0 and c > 0):
        a, c = 0.0, float(np.sum(x / y) / np.sum((x / y) ** 2))
    return float(a), float(c)


def _fit_affine(records: list[SceneRecord], kind: str, spread) -> KindFit:
    """T_B ~ a_B + c_B N log2 N and t ~ a_R + c_R log2 N: the paper's terms plus a fixed
    cost each (per-call overheads that N log2 N cannot carry inflate the ratio on small
    scenes).  The interval scales the slopes by the spread of measured / fitted over the scenes."""
    have = [r for r in records if kind in r.kinds]
    xb, yb = [nlog2n(r.triangles) for r in have], [r.kinds[kind].build_time for r in have]
    xr, yr = [log2n(r.triangles) for r in have], [r.kinds[kind].per_ray for r in have]
    ab, cb = _affine_lsq(xb, yb)
    ar, cr = _affine_lsq(xr, yr)

    def spread_of(x, y, a, c):
        q = [yi / (a + c * xi) for xi, yi in zip(x, y) if a + c * xi > 0]
        if not q:
            return [1.0, 1.0]
        lo, hi = (float(v) for v in np.percentile(q, spread))
        return [min(lo, 1.0), max(hi, 1.0)]

    qb, qr = spread_of(xb, yb, ab, cb), spread_of(xr, yr, ar, cr)
    return KindFit(cb, cr, cb * qb[0], cb * qb[1], cr * qr[0], cr * qr[1], len(have), extra={"a_B": ab, "a_R": ar})


def _estimate_affine(fit: KindFit, kind: str, n: int) -> Estimate:
    """a + c x with the interval on the slope; with no fixed terms (a = 0) this is 'paper'."""
    x, y = nlog2n(n), log2n(n)
    a_b, a_r = fit.extra.get("a_B", 0.0), fit.extra.get("a_R", 0.0)
    return Estimate(kind, a_b + fit.c_B * x, a_b + fit.c_B_low * x, a_b + fit.c_B_high * x,
                    a_r + fit.c_R * y, a_r + fit.c_R_low * y, a_r + fit.c_R_high * y)


#: model name -> (fit per kind, estimate).  A refinement keeps its parameters in
#: KindFit.extra.  'affine' (issue 4, item 5) is the default: it cuts the leave-one-out
#: break-even error on the calibration scenes and the build / per-ray errors on the real
#: meshes (docs/report/report.md has both models side by side).
MODELS = {"paper": (_fit_paper, _estimate_paper), "affine": (_fit_affine, _estimate_affine)}


def fit(records: list[SceneRecord], kinds, *, model: str = DEFAULT_MODEL, spread=DEFAULT_SPREAD) -> dict[str, KindFit]:
    """Fit ``model`` for each kind measured in at least one record."""
    if model not in MODELS:
        raise ValueError(f"unknown calibration model {model!r}; expected one of {', '.join(MODELS)}")
    fit_one = MODELS[model][0]
    return {k: fit_one(records, k, tuple(spread)) for k in kinds if any(k in r.kinds for r in records)}


# -- where it was measured ---------------------------------------------------------------------

def package_version() -> str:
    """The extension's version from blender_manifest.toml at the package root."""
    try:
        text = (Path(__file__).resolve().parents[1] / "blender_manifest.toml").read_text(encoding="utf-8")
    except OSError:
        return "unknown"
    m = re.search(r'^version\s*=\s*"([^"]*)"', text, re.M)
    return m.group(1) if m else "unknown"


def _cpu_name() -> str:
    name = platform.processor()
    if not name and sys.platform.startswith("linux"):
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
                for line in f:
                    if line.startswith("model name"):
                        return line.split(":", 1)[1].strip()
        except OSError:
            pass
    return name or "unknown"


def machine_fingerprint() -> dict:
    return {"system": platform.system(), "machine": platform.machine(), "processor": _cpu_name(), "cpus": os.cpu_count()}


def current_version() -> dict:
    """What a calibration depends on besides the scenes: compared field by field on load."""
    return {
        "format": CALIBRATION_FORMAT,
        "package": package_version(),
        "numpy": np.__version__,
        "python": f"{sys.version_info[0]}.{sys.version_info[1]}",
        "machine": machine_fingerprint(),
    }


def _first_difference(there: dict, here: dict, prefix: str = "") -> str | None:
    for key in sorted(set(there) | set(here)):
        a, b = there.get(key), here.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            d = _first_difference(a, b, f"{prefix}{key}.")
            if d:
                return d
        elif a != b:
            return f"{prefix}{key} {a!r} in the file, {b!r} here"
    return None


# -- the calibration -------------------------------------------------------------------------

@dataclass
class Calibration:
    """Fitted constants per structure, the per-scene data behind them, and where they hold.

    ``source`` says where the numbers come from: 'measured' (``calibrate`` here),
    'shipped defaults' (the package's file, measured on another machine), or anything a
    caller sets (tests build one by hand).
    """

    fits: dict[str, KindFit]
    scenes: list[SceneRecord] = field(default_factory=list)
    model: str = DEFAULT_MODEL
    spread: tuple = DEFAULT_SPREAD
    rays_per_scene: int = 0
    scale: str = ""
    threads: int | None = None
    duration_s: float = 0.0
    created: str = ""
    source: str = "measured"
    version: dict = field(default_factory=current_version)
    notes: list[str] = field(default_factory=list)

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(self.fits)

    def estimate(self, kind: str, n: int) -> Estimate:
        """Build and per-ray time of ``kind`` for an N-triangle scene, with the interval."""
        if kind not in self.fits:
            raise KeyError(f"no calibration constants for {kind!r} (calibrated: {', '.join(self.fits) or 'none'})")
        return MODELS[self.model][1](self.fits[kind], kind, n)

    def grid_sample_ratio(self, k: int) -> tuple[float, float, float]:
        """(median, low, high) of the per-scene ratio large-workload grid time per ray /
        time per ray on a K-ray sample, interpolated in log2 K between the measured sample
        sizes (clamped at the ends); low/high are the calibration's spread percentiles.

        A plan multiplies its sample's time per ray by it: a small batch pays the lockstep
        traversal's fixed per-step cost over few rays, so it overstates a large workload's
        time per ray (measured 1.2-1.5x at K = 16,384, over 3x at K = 1,024).  (1, 1, 1)
        when the calibration holds no grid samples.
        """
        ladder = sorted({kk for r in self.scenes for kk in r.grid_samples})
        if not ladder:
            return 1.0, 1.0, 1.0
        per_k = []
        for kk in ladder:
            q = [x for x in (r.grid_sample_ratio(kk) for r in self.scenes) if x is not None and math.isfinite(x) and x > 0]
            med = float(np.median(q))
            lo, hi = (float(v) for v in np.percentile(q, self.spread))
            per_k.append((min(lo, med), med, max(hi, med)))
        x = np.log2(np.asarray(ladder, np.float64))
        xk = math.log2(max(int(k), 1))
        lo, med, hi = (float(np.interp(xk, x, [p[i] for p in per_k])) for i in range(3))
        return med, lo, hi

    def describe(self) -> str:
        """One line per structure: the constants and their interval, in ns."""
        lines = [f"calibration ({self.source}, {self.model} model, {len(self.scenes)} scenes, {self.created or 'undated'})"]
        for k, f in self.fits.items():
            lines.append(
                f"  {k:7s} c_B {f.c_B * 1e9:8.2f} ns [{f.c_B_low * 1e9:.2f}, {f.c_B_high * 1e9:.2f}]"
                f"   c_R {f.c_R * 1e9:8.2f} ns [{f.c_R_low * 1e9:.2f}, {f.c_R_high * 1e9:.2f}]   ({f.scenes} scenes)"
            )
        return "\n".join(lines)

    # -- JSON ---------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = asdict(self)
        d["spread"] = list(self.spread)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_dict(cls, d: dict, *, check_version: bool = True) -> "Calibration":
        """Rebuild from ``to_dict``; raises CalibrationError naming what is wrong."""
        if not isinstance(d, dict):
            raise CalibrationError(f"expected a JSON object, found {type(d).__name__}")
        version = d.get("version")
        if not isinstance(version, dict) or "format" not in version:
            raise CalibrationError("no version information (not a calibration file?)")
        if version.get("format") != CALIBRATION_FORMAT:
            raise CalibrationError(f"calibration format {version.get('format')!r}, this package reads format {CALIBRATION_FORMAT}")
        if check_version:
            diff = _first_difference(version, current_version())
            if diff:
                raise CalibrationError(f"made for another setup: {diff}")
        try:
            fits = {str(k): KindFit(**v) for k, v in d["fits"].items()}
            scenes = [
                SceneRecord(s["name"], int(s["triangles"]), int(s["rays"]), {k: Measurement(**m) for k, m in s["kinds"].items()},
                            {int(k): float(v) for k, v in s.get("grid_samples", {}).items()})
                for s in d.get("scenes", [])
            ]
            model = str(d.get("model", DEFAULT_MODEL))
            cal = cls(
                fits=fits, scenes=scenes, model=model, spread=tuple(d.get("spread", DEFAULT_SPREAD)),
                rays_per_scene=int(d.get("rays_per_scene", 0)), scale=str(d.get("scale", "")),
                threads=d.get("threads"), duration_s=float(d.get("duration_s", 0.0)), created=str(d.get("created", "")),
                source=str(d.get("source", "measured")), version=version, notes=[str(x) for x in d.get("notes", [])],
            )
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise CalibrationError(f"malformed calibration data ({type(e).__name__}: {e})") from None
        if model not in MODELS:
            raise CalibrationError(f"unknown model {model!r} (this package knows {', '.join(MODELS)})")
        if not fits:
            raise CalibrationError("no fitted constants in the file")
        for k, f in fits.items():
            vals = (f.c_B, f.c_R, f.c_B_low, f.c_B_high, f.c_R_low, f.c_R_high)
            if not all(isinstance(x, (int, float)) and math.isfinite(x) and x >= 0 for x in vals):
                raise CalibrationError(f"constants of {k!r} are not finite non-negative numbers: {vals}")
            if not (f.c_B_low <= f.c_B <= f.c_B_high and f.c_R_low <= f.c_R <= f.c_R_high):
                raise CalibrationError(f"interval of {k!r} does not contain its constants")
        return cal

    @classmethod
    def from_json(cls, text: str, *, check_version: bool = True) -> "Calibration":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise CalibrationError(f"not valid JSON ({e.msg} at line {e.lineno})") from None
        return cls.from_dict(d, check_version=check_version)

    def save(self, path) -> Path:
        """Write JSON to ``path`` (atomically: a temporary file, then a rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(self.to_json(), encoding="utf-8")
        os.replace(tmp, path)
        return path


def load(path, *, check_version: bool = True) -> Calibration:
    """Read a calibration saved by ``Calibration.save``.

    Raises CalibrationError (one-line reason) when the file is missing, unreadable, not
    JSON, malformed, or made with another format, package, numpy, Python or machine.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibrationError(f"no calibration file at {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CalibrationError(f"cannot read {path}: {getattr(e, 'strerror', None) or e}") from None
    try:
        return Calibration.from_json(text, check_version=check_version)
    except CalibrationError as e:
        raise CalibrationError(f"{path.name}: {e}") from None


#: last resort when the shipped file itself is unreadable (a broken install): the shipped
#: defaults' (c_B, c_R) rounded, with a factor-3 interval, labelled as such
_BUILTIN = {"bvh": (4.5e-7, 6e-7), "embree": (1.8e-7, 9e-8)}


def _builtin_fallback(reason: str) -> Calibration:
    fits = {k: KindFit(b, r, b / 3, b * 3, r / 3, r * 3, 0) for k, (b, r) in _BUILTIN.items()}
    return Calibration(fits, source="built-in fallback", notes=[f"shipped defaults unusable: {reason}"])


def load_default() -> Calibration:
    """The shipped defaults (any machine, same format), labelled ``source='shipped defaults'``."""
    try:
        cal = load(DEFAULT_PATH, check_version=False)
    except CalibrationError as e:
        return _builtin_fallback(str(e))
    cal.source = "shipped defaults"
    return cal


def load_or_default(path, *, recalibrate: bool = False, progress=None, **calibrate_kw) -> tuple[Calibration, str]:
    """A usable calibration and a one-line message saying where it came from; never raises.

    Loads ``path`` when it holds a calibration made here.  Otherwise (missing, corrupt,
    foreign) it either recalibrates (``recalibrate=True``; the result is saved to
    ``path``, with ``progress`` and ``calibrate_kw`` passed to ``calibrate``) or returns
    the shipped defaults.  ``path=None`` means the shipped defaults.
    """
    if path is None:
        cal = load_default()
        return cal, f"using {cal.source} (no calibration file given)"
    try:
        cal = load(path)
        return cal, f"loaded calibration from {path} (measured {cal.created or 'undated'}, {len(cal.scenes)} scenes)"
    except CalibrationError as e:
        reason = str(e)
    except Exception as e:  # never crash on a bad file
        reason = f"{path}: unexpected {type(e).__name__}: {e}"
    if recalibrate:
        try:
            cal = calibrate(progress=progress, **calibrate_kw)
        except Exception as e:
            cal = load_default()
            return cal, f"{reason}; recalibration failed ({type(e).__name__}: {e}); using {cal.source}"
        try:
            cal.save(path)
            where = f"saved to {path}"
        except OSError as e:
            where = f"could not save to {path}: {e.strerror or e}"
        return cal, f"{reason}; recalibrated in {cal.duration_s:.0f} s, {where}"
    cal = load_default()
    return cal, f"{reason}; using {cal.source} (run calibrate to measure this machine)"


# -- measuring ---------------------------------------------------------------------------------

def time_trace(accel: Accel, origins, directions, tmin=0.0, tmax=np.inf):
    """Trace and time a batch as a caller would: (Hits, seconds).

    The batch runs exactly as ``accel.trace`` runs it (its chunks, its threads).  Splitting
    a small batch over the threads does not make it cost what a large workload does: with
    a few thousand rays per thread the numpy calls of the two threads contend for the GIL
    and the time per ray doubled (measured on the real meshes at K = 16,384).  A plan
    corrects its small sample with ``Calibration.grid_sample_ratio`` instead.
    """
    t0 = time.perf_counter()
    hits = accel.trace(origins, directions, tmin, tmax)
    return hits, time.perf_counter() - t0


def measure(mesh: TriangleMesh, kind: str, origins, directions, *, threads=None, config=None) -> Measurement:
    """Build ``kind`` over ``mesh`` and trace the rays through it: one Measurement."""
    cfg = dict(config or {})
    if threads is not None:
        cfg.setdefault("threads", threads)
    accel = build(mesh, kind, **cfg)
    _, dt = time_trace(accel, origins, directions)
    return Measurement(float(accel.build_time), float(dt), int(len(origins)), int(accel.threads))


def available_kinds(kinds) -> tuple[tuple[str, ...], list[str]]:
    """The kinds that can be built here, and a note for each one that cannot."""
    from .embree import embree_available

    keep, notes = [], []
    for k in kinds:
        if k == "embree" and not embree_available():
            notes.append("embree skipped: embreex is not installed")
        else:
            keep.append(k)
    return tuple(keep), notes


def _prepare(mesh: TriangleMesh):
    """Compute the mesh's cached arrays before timing, so no structure pays for them."""
    mesh.tri_vertices
    mesh.valid


def warm_up(kinds, *, threads=None, configs=None):
    """Build and trace each kind once on a tiny scene, untimed: the first build of a kind
    in a process pays one-off costs (Embree starts its threads, ~10 ms measured here)."""
    from .rays import uniform_rays
    from .scenes import sphere

    warm = sphere(80)
    _prepare(warm)
    o, d = uniform_rays(warm, 64, seed=0)
    for kind in kinds:
        measure(warm, kind, o, d, threads=threads, config=(configs or {}).get(kind))


@dataclass
class BreakEven:
    """Measured break-even of each hierarchical structure against the grid on one scene.

    ``R_C[k] = T_B^k / (t_G - t_k)`` with measured times (inf where t_G <= t_k), the same
    formula as the estimate (the grid's build is sunk), so the two compare directly.
    """

    triangles: int
    rays: int
    measurements: dict[str, Measurement]
    R_C: dict[str, float]


def measure_break_even(mesh: TriangleMesh, rays, kinds=("grid", "bvh"), *, threads=None, configs=None, seed=0) -> BreakEven:
    """Really build every structure in ``kinds`` (which must include 'grid') and trace
    ``rays`` through each: the true break-even R_C of the paper's evaluation.

    rays: (origins, directions), or a count of the paper's uniform random rays.
    configs: optional {kind: config dict} passed to ``build``.
    """
    from .rays import uniform_rays

    if "grid" not in kinds:
        raise ValueError("measure_break_even needs 'grid' among the kinds (the break-even is against the grid)")
    if isinstance(rays, (int, np.integer)):
        origins, directions = uniform_rays(mesh, int(rays), seed=seed)
    else:
        origins, directions = rays
    _prepare(mesh)
    warm_up(kinds, threads=threads, configs=configs)
    meas = {k: measure(mesh, k, origins, directions, threads=threads, config=(configs or {}).get(k)) for k in kinds}
    g = meas["grid"].per_ray
    rc = {}
    for k, m in meas.items():
        if k != "grid":
            rc[k] = m.build_time / (g - m.per_ray) if g > m.per_ray else math.inf
    return BreakEven(mesh.triangle_count, len(origins), meas, rc)


def _measure_grid(mesh, origins, directions, ladder, threads, config, seed):
    """The grid's Measurement on the calibration rays, and its time per ray on fresh
    uniform samples of each size in ``ladder`` (what a plan's K-sample costs per ray).

    Each sample is traced as ``plan`` traces it: first thing through a grid just built.
    A grid's first traces can cost more than later ones (freshly allocated memory is
    faulted in; measured up to 2x on 800k triangles), and a sample timed after the large
    batch would miss that."""
    from .rays import uniform_rays

    samples = {}
    for k in ladder:
        o, d = uniform_rays(mesh, int(k), seed=seed + int(k))
        samples[int(k)] = measure(mesh, "grid", o, d, threads=threads, config=config).per_ray
    if ladder and len(origins) < GRID_LARGE_RAYS:
        # the ratio needs a large workload's time per ray: the 'tiny' and 'quick' scales'
        # few rays per scene would themselves be a small batch (a ratio of 2 measured)
        origins, directions = uniform_rays(mesh, GRID_LARGE_RAYS, seed=seed)
    return measure(mesh, "grid", origins, directions, threads=threads, config=config), samples


def _size_hint(factory) -> float:
    """Expected work of a scene for the progress fraction: N log2 N of its size."""
    if isinstance(factory, TriangleMesh):
        return nlog2n(factory.triangle_count)
    args = getattr(factory, "args", ())
    n = args[0] if args and isinstance(args[0], (int, np.integer)) else 10000
    return nlog2n(n)


def calibrate(
    scenes=None,
    kinds=("bvh", "embree"),
    *,
    scale: str = "default",
    rays_per_scene: int | None = None,
    progress=None,
    threads: int | None = None,
    grid: bool = True,
    configs: dict | None = None,
    model: str = DEFAULT_MODEL,
    spread=DEFAULT_SPREAD,
    seed: int = 0,
    sample_ladder=SAMPLE_LADDER,
) -> Calibration:
    """Measure every structure in ``kinds`` on each scene and fit the model.

    scenes: (name, factory-or-TriangleMesh) pairs; default ``scenes.calibration_set(scale)``.
    rays_per_scene: M, the paper's uniform random rays per scene (default by scale).
    progress: ``callback(fraction in [0, 1], message)``, called before each structure.
    threads: passed to every structure (None: each structure's default).
    grid: also measure the grid per scene: its time per ray on the calibration rays and on
    samples of each size in ``sample_ladder``, which give ``Calibration.grid_sample_ratio``
    (the grid's constants are not fitted: a plan measures the grid on its own scene).
    configs: optional {kind: config dict} passed to ``build``.
    """
    from . import scenes as scene_lib
    from .rays import uniform_rays

    t_start = time.perf_counter()
    if scenes is None:
        scenes = scene_lib.calibration_set(scale)
    else:
        scale = "custom"
    scenes = list(scenes)
    if not scenes:
        raise ValueError("calibrate needs at least one scene")
    m_rays = int(rays_per_scene or RAYS_PER_SCENE.get(scale, RAYS_PER_SCENE["default"]))
    if m_rays < 1:
        raise ValueError(f"rays_per_scene must be at least 1, got {m_rays}")
    fitted, notes = available_kinds(kinds)
    if not fitted:
        raise ValueError(f"none of the structures {tuple(kinds)} can be built here: {'; '.join(notes)}")
    measured = (("grid",) if grid and "grid" not in fitted else ()) + fitted
    weights = np.array([_size_hint(f) for _, f in scenes])
    done = np.concatenate([[0.0], np.cumsum(weights)]) / weights.sum()

    def report(i, j, msg):
        if progress is not None:
            progress(float(done[i] + (done[i + 1] - done[i]) * j / len(measured)), msg)

    warm_up(measured, threads=threads, configs=configs)

    records = []
    for i, (name, factory) in enumerate(scenes):
        report(i, 0, f"scene {i + 1}/{len(scenes)}: generating {name}")
        mesh = factory if isinstance(factory, TriangleMesh) else factory()
        _prepare(mesh)
        origins, directions = uniform_rays(mesh, m_rays, seed=seed + i)
        rec = SceneRecord(name, mesh.triangle_count, m_rays)
        for j, kind in enumerate(measured):
            report(i, j, f"scene {i + 1}/{len(scenes)}: {name} ({mesh.triangle_count:,} triangles), {kind}")
            if kind == "grid":
                rec.kinds[kind], rec.grid_samples = _measure_grid(mesh, origins, directions, sample_ladder, threads,
                                                                  (configs or {}).get(kind), seed + 7919 * (i + 1))
            else:
                rec.kinds[kind] = measure(mesh, kind, origins, directions, threads=threads, config=(configs or {}).get(kind))
        records.append(rec)
        del mesh
    fits = fit(records, fitted, model=model, spread=spread)
    duration = time.perf_counter() - t_start
    if progress is not None:
        progress(1.0, f"calibrated {', '.join(fits)} on {len(records)} scenes in {duration:.1f} s")
    return Calibration(
        fits=fits, scenes=records, model=model, spread=tuple(spread), rays_per_scene=m_rays, scale=scale,
        threads=threads, duration_s=duration, created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        source="measured", notes=notes,
    )
