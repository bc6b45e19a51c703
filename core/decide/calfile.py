"""The calibration file: fitted constants, the scenes behind them, where they hold, and
the policy for loading one.

A calibration is only valid where it was measured: the file records the format, the
package, numpy and Python versions and a machine fingerprint (OS, architecture, CPU
name, core count).  ``load`` refuses anything else with a ``CalibrationError`` whose
message is one line; ``load_or_default`` never raises and falls back on the shipped
defaults (``default_calibration.json``, labelled ``source='shipped defaults'``) or on a
fresh calibration when asked.
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from .cost import (DEFAULT_MODEL, DEFAULT_SPREAD, MODELS, Cost, CountFit, KindFit, Measurement, SceneRecord,
                   Prior, describe_fit, fit, fit_counts, grid_estimate, grid_laws, prior)
from .cost import COUNT_FALLBACK, COUNT_TERMS, surface_spread
from .points import PointModel

#: bump when the JSON layout or the meaning of a field changes.  3: constants
#: stated at a reference size (the 'power' model's x_ref_B / x_ref_R, a count model's refs)
#: and the 'terms' build model; a file of format 2 has neither field and reads with its old
#: meaning (reference 1 or 0), so it still loads.  A 'terms' fit's ``form_B`` names its build
#: form ('log-quadratic'); a fit without it is a sum of ``terms_B`` (``cost.BUILD_FORMS``),
#: so files written before the log-quadratic form estimate as they did
CALIBRATION_FORMAT = 3
READABLE_FORMATS = (2, 3)
#: the constants shipped with the package, measured by ``calibrate()`` on the default set
DEFAULT_PATH = Path(__file__).resolve().parents[1] / "default_calibration.json"


class CalibrationError(Exception):
    """A calibration that cannot be used here; ``str(error)`` is a one-line reason."""


# -- where it was measured ---------------------------------------------------------------------

def package_version() -> str:
    """The extension's version from blender_manifest.toml at the package root."""
    try:
        text = (Path(__file__).resolve().parents[2] / "blender_manifest.toml").read_text(encoding="utf-8")
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
    #: per-ray time models on the grid sample's work counts, {'grid' | kind: CountFit}
    #: (``cost.fit_counts``); empty in files made before them: the plan then times its sample
    counts: dict = field(default_factory=dict)
    #: the point queries' decision (``points.PointModel.to_dict``); empty in files made before
    #: it and in calibrations run without it: ``point_model`` then takes the shipped one's
    points: dict = field(default_factory=dict)
    #: (the scenes list, the spread, ``cost.grid_laws`` of them): the grid's laws, fitted on first use
    _grid_laws: tuple | None = field(default=None, repr=False, compare=False)
    #: (the scenes list, the spread, (log2 K, [(low, median, high)]) per measured sample size or
    #: None): what ``grid_sample_ratio`` interpolates, made on first use
    _ratio_table: tuple | None = field(default=None, repr=False, compare=False)
    #: (the points dict, the ``PointModel`` it gives): ``point_model``'s, made on first use (a
    #: calibration without its own reads the shipped file once, not at every query)
    _point_model: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(self.fits)

    def estimate(self, kind: str, n: int) -> Cost:
        """Build and per-ray time of ``kind`` for an N-triangle scene, with the interval."""
        if kind not in self.fits:
            raise KeyError(f"no calibration constants for {kind!r} (calibrated: {', '.join(self.fits) or 'none'})")
        return MODELS[self.model][1](self.fits[kind], kind, n)

    def grid_estimate(self, n: int) -> Cost | None:
        """The grid's build and time per ray for an N-triangle mesh from the calibration
        scenes alone (``cost.grid_estimate``), None when they measured no grid."""
        if not self._cached(self._grid_laws):
            self._grid_laws = (self.scenes, self.spread, grid_laws(self.scenes, self.spread))
        return grid_estimate(self.scenes, n, self.spread, laws=self._grid_laws[2] or ())

    def _cached(self, entry) -> bool:
        """Whether a cache entry (scenes, spread, ...) was made from this calibration's
        scenes and spread (``replace`` copies the entry with the fields)."""
        return entry is not None and entry[0] is self.scenes and entry[1] == self.spread

    def grid_sample_ratio(self, k: int) -> tuple[float, float, float]:
        """(median, low, high) of the per-scene ratio large-workload grid time per ray /
        time per ray on a K-ray sample, interpolated in log2 K between the measured sample
        sizes (clamped at the ends); low/high are the calibration's spread percentiles.

        A plan multiplies its sample's time per ray by it: a small batch pays the lockstep
        traversal's fixed per-step cost over few rays, so it overstates a large workload's
        time per ray, the more so the smaller K.  (1, 1, 1)
        when the calibration holds no grid samples.
        """
        if not self._cached(self._ratio_table):  # the percentiles over the scenes: once
            ladder = sorted({kk for r in self.scenes for kk in r.grid_samples})
            per_k = []
            for kk in ladder:
                q = [x for x in (r.grid_sample_ratio(kk) for r in self.scenes)
                     if x is not None and math.isfinite(x) and x > 0]
                med = float(np.median(q))
                lo, hi = (float(v) for v in np.percentile(q, self.spread))
                per_k.append((min(lo, med), med, max(hi, med)))
            table = (np.log2(np.asarray(ladder, np.float64)), per_k) if ladder else None
            self._ratio_table = (self.scenes, self.spread, table)
        if self._ratio_table[2] is None:
            return 1.0, 1.0, 1.0
        x, per_k = self._ratio_table[2]
        xk = math.log2(max(int(k), 1))
        lo, med, hi = (float(np.interp(xk, x, [p[i] for p in per_k])) for i in range(3))
        return med, lo, hi

    def uses_term(self, name: str) -> bool:
        """Whether any count model weighs the work count ``name`` (e.g. 'refs')."""
        return any(name in f.terms for f in self.counts.values())

    def count_per_ray(self, kind: str, n: int, work: dict, surface: bool = False):
        """(point, low, high) time per ray of ``kind`` ('grid' or a structure) on an
        N-triangle scene whose grid sample counted ``work``; None without a count model.
        surface: the scene is a surface mesh, whose interval is the spread over the
        calibration's surfaces (``CountFit.spread_for``)."""
        f = self.counts.get(kind)
        if f is None or not work:
            return None
        t = f.predict(n, work)
        lo, hi = f.spread_for(surface)
        return t, t * lo, t * hi

    def prior(self, n: int, kinds) -> Prior:
        """What the calibration alone says about an N-triangle scene against ``kinds`` (the
        break-even's floor, ``cost.prior``)."""
        return prior(self.scenes, n, [k for k in kinds if k != "grid"])

    def break_even_floor(self, n: int, kinds) -> float:
        """A lower bound on the break-even of an N-triangle scene against ``kinds``; 0: none."""
        return self.prior(n, kinds).floor

    def describe(self) -> str:
        """One line per structure: its build and per-ray model with the constants that
        define it (times at the reference size N_REF, in ms / ns) and their interval."""
        lines = [f"calibration ({self.source}, {self.model} model, {len(self.scenes)} scenes, {self.created or 'undated'})"]
        for k, f in self.fits.items():
            lines.append(f"  {k:7s} {describe_fit(f, self.model)}   ({f.scenes} scenes)")
        for k, f in self.counts.items():
            surf = f", surfaces [{f.surface_low:.2f}, {f.surface_high:.2f}]x" if f.surface_low is not None else ""
            lines.append(f"  {k:7s} per ray = {f.formula()}   [{f.low:.2f}, {f.high:.2f}]x{surf}   ({f.scenes} scenes)")
        return "\n".join(lines)

    # -- JSON ---------------------------------------------------------------------------
    def point_model(self) -> PointModel | None:
        """The point queries' decision constants: this calibration's, else the shipped
        defaults' (None when neither has them)."""
        if self._point_model is None or self._point_model[0] is not self.points:
            points = self.points or (None if self.source == "shipped defaults" else load_default().points)
            self._point_model = (self.points, PointModel.from_dict(points) if points else None)
        return self._point_model[1]

    def refitted(self, model: str = DEFAULT_MODEL) -> "Calibration":
        """The same records fitted again with ``model`` and the current count models (no new
        timing): an older file's constants become what this package states and predicts.
        A file made before count models keeps none."""
        kinds = tuple(self.fits)
        counts = fit_counts(self.scenes, ("grid",) + kinds, self.spread) if self.counts else {}
        return replace(self, fits=fit(self.scenes, kinds, model=model, spread=self.spread), model=model, counts=counts)

    def to_dict(self) -> dict:
        d = asdict(replace(self, _grid_laws=None, _ratio_table=None, _point_model=None))  # the caches hold the scenes again
        for cache in ("_grid_laws", "_ratio_table", "_point_model"):
            d.pop(cache)
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
        if version.get("format") not in READABLE_FORMATS:
            raise CalibrationError(f"calibration format {version.get('format')!r}, this package reads formats "
                                   f"{', '.join(map(str, READABLE_FORMATS))}")
        if check_version:  # a readable older format is no other setup
            diff = _first_difference(dict(version, format=CALIBRATION_FORMAT), current_version())
            if diff:
                raise CalibrationError(f"made for another setup: {diff}")
        try:
            fits = {str(k): KindFit(**v) for k, v in d["fits"].items()}
            scenes = [
                SceneRecord(s["name"], int(s["triangles"]), int(s["rays"]), {k: Measurement(**m) for k, m in s["kinds"].items()},
                            {int(k): float(v) for k, v in s.get("grid_samples", {}).items()},
                            {str(k): float(v) for k, v in s.get("work", {}).items() if v is not None},
                            {str(k): [Measurement(**m) for m in v] for k, v in s.get("passes", {}).items()})
                for s in d.get("scenes", [])
            ]
            model = str(d.get("model", DEFAULT_MODEL))
            cal = cls(
                fits=fits, scenes=scenes, model=model, spread=tuple(d.get("spread", DEFAULT_SPREAD)),
                rays_per_scene=int(d.get("rays_per_scene", 0)), scale=str(d.get("scale", "")),
                threads=d.get("threads"), duration_s=float(d.get("duration_s", 0.0)), created=str(d.get("created", "")),
                source=str(d.get("source", "measured")), version=version, notes=[str(x) for x in d.get("notes", [])],
                counts={str(k): CountFit(tuple(v["terms"]), tuple(float(c) for c in v["coef"]), float(v["low"]),
                                         float(v["high"]), int(v.get("scenes", 0)), str(v.get("form", "linear")),
                                         tuple(float(r) for r in v.get("refs", ())),
                                         *(None if v.get(b) is None else float(v[b])
                                           for b in ("surface_low", "surface_high")))
                        for k, v in d.get("counts", {}).items()},
                points=dict(d.get("points") or {}),
            )
            if cal.points:
                PointModel.from_dict(cal.points)  # malformed constants fail here, not in a query
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise CalibrationError(f"malformed calibration data ({type(e).__name__}: {e})") from None
        if model not in MODELS:
            raise CalibrationError(f"unknown model {model!r} (this package knows {', '.join(MODELS)})")
        stale = [k for k, f in cal.counts.items() if f.terms not in (COUNT_TERMS.get(k, f.terms), COUNT_FALLBACK.get(k))]
        new = fit_counts(cal.scenes, tuple(stale), cal.spread) if stale else {}
        if new:
            # count models of another package version, fitted again on the file's own records
            # (no new timing) where they hold the counts this package's terms weigh
            cal.counts.update(new)
            cal.notes.append(f"count models of {', '.join(sorted(new))} refitted on the file's records with this "
                             f"package's terms")
        for k, f in cal.counts.items():
            if f.surface_low is None and k not in new:  # a file made before the surfaces' spread
                f.surface_low, f.surface_high = surface_spread(f, cal.scenes, k, cal.spread)
        if not fits:
            raise CalibrationError("no fitted constants in the file")
        for k, f in fits.items():
            vals = (f.c_B, f.c_R, f.c_B_low, f.c_B_high, f.c_R_low, f.c_R_high)
            if not all(isinstance(x, (int, float)) and math.isfinite(x) and x >= 0 for x in vals):
                raise CalibrationError(f"constants of {k!r} are not finite non-negative numbers: {vals}")
            if not (f.c_B_low <= f.c_B <= f.c_B_high and f.c_R_low <= f.c_R <= f.c_R_high):
                raise CalibrationError(f"interval of {k!r} does not contain its constants")
            _check_build_form(k, f.extra)
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
        with atomic_path(path) as tmp:
            Path(tmp).write_text(self.to_json(), encoding="utf-8")
        return path


def _check_build_form(kind: str, extra: dict) -> None:
    """A 'terms' fit's build form is one this package estimates, with its coefficients."""
    form = extra.get("form_B")
    if form is None:
        return
    if form != "log-quadratic":
        raise CalibrationError(f"unknown build form {form!r} of {kind!r} (this package knows 'log-quadratic' "
                               "and the sum of terms_B)")
    coef, n_min, n_max = extra.get("coef_B"), extra.get("n_min"), extra.get("n_max")
    if not (isinstance(coef, list) and len(coef) == 3
            and all(isinstance(c, (int, float)) and math.isfinite(c) for c in coef)):
        raise CalibrationError(f"the log-quadratic build of {kind!r} needs three finite coefficients, found {coef!r}")
    if not (isinstance(n_min, int) and isinstance(n_max, int) and 0 < n_min <= n_max):
        raise CalibrationError(f"the log-quadratic build of {kind!r} needs its fitted sizes 0 < n_min <= n_max, "
                               f"found {n_min!r}, {n_max!r}")


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


def load_or_default(path) -> tuple[Calibration, str]:
    """A usable calibration and a one-line message saying where it came from; never raises.

    Loads ``path`` when it holds a calibration made here; otherwise (missing, corrupt,
    foreign) returns the shipped defaults, and the message says why.  ``path=None`` means
    the shipped defaults.  Measuring this machine is ``measurements.calibrate`` (the
    Calibrate operator, the CLI's ``calibrate``), never a side effect of loading.
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
    cal = load_default()
    return cal, f"{reason}; using {cal.source} (run calibrate to measure this machine)"


