"""The cost model: what a structure costs, as numbers, and the break-even they imply.

Hapala, Karlik and Havran (2011), section 3: over s representative scenes, build the
hierarchical structure and shoot M rays in each scene i, then

    c_B = (1/s) sum_i T_B(i) / (N(i) log2 N(i))      (build constant)
    c_R = (1/s) sum_i T_R(i) / (M(i) log2 N(i))      (per-ray constant)

so that a new scene of N triangles is estimated at T_B ~ c_B N log2 N and
t ~ c_R log2 N per ray.  The shipped models refine that form (the paper's own, and the
others the evaluation compares, are ``evaluate.COMPARED_MODELS``).  ``model='power'`` fits
T_B ~ c_B (N log2 N / X_REF)^p_B and t ~ c_R (log2 N / L_REF)^p_R by least squares on log
times (an affine a + c x where the scenes' sizes are too close for an exponent).
``model='terms'`` (the default) writes the numpy BVH's build as a sum of nonnegative costs
in N, a + d (log2 N - 10) + b n + c n (log2 N - 16) with n = N / N_REF, which follows its
U-shaped build per triangle from 500 to 1M triangles, and Embree's as a quadratic in
log-log, ln T_B = a + b u + c u^2 with u = ln(N / N_REF) (``BUILD_FORMS``); it keeps the
power model for the time per ray and for any structure without a build form.  The interval
of each constant is the spread across the calibration scenes (``low``/``high``: 10th/90th
percentiles of the per-scene values).  Per-ray times of a plan come from the sample's work
counts where the calibration has count models (``fit_counts``).

The break-even (section 3, step 4): the grid is built already, so H pays for itself
after R* = T_B^H / (t_G - t_H) rays when t_G > t_H, never otherwise.  ``break_even`` is
the one place that formula is written.  ``prior`` bounds R* from below with the
calibration alone, so a plan for fewer rays need not sample at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

DEFAULT_MODEL = "terms"
DEFAULT_SPREAD = (10.0, 90.0)

#: the scene size every fitted constant is stated at: a constant is a time at N_REF
#: triangles, or a slope there, so that two calibrations agree on it even where they trade
#: an intercept against a slope far from the data (a + b log2 N's a is the time at N = 1,
#: which two calibrations in a row put far apart; BENCHMARKS.md, "Calibration and plan
#: repeatability")
N_REF = 65_536
L_REF = 16.0  # log2 N_REF
X_REF = float(N_REF * 16)  # N_REF log2 N_REF


def break_even(build: float, t_grid: float, t_hds: float) -> float:
    """R* = T_B^H / (t_G - t_H): rays after which H (build ``build``, ``t_hds`` per ray)
    beats an already built grid (``t_grid`` per ray); inf when the grid is at least as
    fast per ray."""
    return build / (t_grid - t_hds) if t_grid > t_hds else math.inf


# -- what was measured ---------------------------------------------------------------------

def nlog2n(n: int) -> float:
    """N log2 N with log2 taken of max(N, 2): one triangle still costs something."""
    n = max(int(n), 1)
    return n * math.log2(max(n, 2))


def log2n(n: int) -> float:
    return math.log2(max(int(n), 2))



@dataclass
class Measurement:
    """One structure on one scene: build time and the time of ``rays`` rays, in seconds.

    build_faults, build_system: the page faults the process took during the build and its
    system CPU seconds then (None where the OS does not say, and in older files): the
    kernel's part of a build's time, which moves with the machine's state.
    build_cpu: the process's CPU seconds during the build, user and system, all its threads
    (None as above): over build_time, how many threads the build kept busy
    (``build_parallelism``)."""

    build_time: float
    trace_time: float
    rays: int
    threads: int = 1
    build_faults: int | None = None
    build_system: float | None = None
    build_cpu: float | None = None

    @property
    def per_ray(self) -> float:
        return self.trace_time / max(self.rays, 1)

    @property
    def build_parallelism(self) -> float | None:
        """CPU seconds per second of the build (1.0: one thread busy throughout; 2.0: two),
        None where the CPU time was not measured or the build took no time."""
        if self.build_cpu is None or not self.build_time > 0:
            return None
        return self.build_cpu / self.build_time


@dataclass
class SceneRecord:
    """One calibration scene: its size and one Measurement per structure (the median of its
    passes, ``measurements.median_measurement``)."""

    name: str
    triangles: int
    rays: int
    kinds: dict[str, Measurement] = field(default_factory=dict)
    #: the grid's time per ray on a batch of K rays, {K: seconds}: what a plan's sample costs
    grid_samples: dict[int, float] = field(default_factory=dict)
    #: the grid's per-ray work counts on K uniform sample rays (``work.Work`` as a dict)
    work: dict = field(default_factory=dict)
    #: every pass's Measurement of each structure, in pass order ({} in older files): the
    #: state of each build (``Measurement.build_parallelism``), not only the medians in kinds
    passes: dict[str, list[Measurement]] = field(default_factory=dict)

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
    #: parameters of models beyond the paper's two constants (empty for the paper's own)
    extra: dict = field(default_factory=dict)


@dataclass
class Cost:
    """One structure's cost in seconds: its build time and time per ray, each with an
    interval [low, high], whether they were measured (the plan's grid, an evaluation's
    truth) or estimated (``Calibration.estimate``), and, once a plan has weighed it against
    the grid, its break-even: the rays after which it beats the (already built) grid, inf
    when it never does, None for the grid itself or before any plan.  The one cost type of
    the decision: the estimate, the plan's candidates, the rule's inputs and the
    evaluation's truths are all Costs."""

    kind: str
    build_time: float
    build_low: float
    build_high: float
    per_ray: float
    per_ray_low: float
    per_ray_high: float
    measured: bool = False
    break_even: float | None = None
    break_even_low: float | None = None
    break_even_high: float | None = None

    @classmethod
    def point(cls, kind: str, build_time: float, per_ray: float, *, measured: bool = False) -> "Cost":
        """A cost known as two figures, with no interval (low = high = the figure)."""
        return cls(kind, float(build_time), float(build_time), float(build_time), float(per_ray), float(per_ray),
                   float(per_ray), measured)

    def total_time(self, rays, bound: str = "point", include_build: bool = True):
        """T_build + R t_ray with the point, 'low' or 'high' figures (R may be an array)."""
        b, t = {"point": (self.build_time, self.per_ray), "low": (self.build_low, self.per_ray_low),
                "high": (self.build_high, self.per_ray_high)}[bound]
        return (b if include_build else 0.0) + np.asarray(rays, np.float64) * t

    def to_dict(self) -> dict:
        """Every field; a break-even that is infinite (never) or unknown as None (JSON has no
        infinity; null in a break-even means 'never')."""
        d = dict(self.__dict__)
        for k in ("break_even", "break_even_low", "break_even_high"):
            d[k] = float(d[k]) if d[k] is not None and math.isfinite(d[k]) else None
        return d

    @classmethod
    def from_dict(cls, d: dict, kind: str = "") -> "Cost":
        """The inverse of ``to_dict``; also reads a point cost written as {'build', 'per_ray'}
        (the evaluation's files before its costs carried intervals)."""
        if "build_time" not in d:
            return cls.point(d.get("kind", kind), d["build"], d["per_ray"], measured=bool(d.get("measured", False)))
        return cls(**d)


# -- the model (the hook for refinements) ------------------------------------------------------

def affine_lsq(x, y) -> tuple[float, float]:
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


def _spans(x, min_ratio: float) -> bool:
    """Whether the positive x span a ratio of at least ``min_ratio`` (and are not all equal)."""
    x = np.asarray([v for v in x if v > 0], np.float64)
    return x.size >= 3 and float(np.ptp(np.log(x))) >= math.log(min_ratio) and np.ptp(x) > 0


def _loglog_fit(x, y) -> tuple[float, float]:
    """(c, p) of y ~ c x^p by least squares on log y (every residual is a relative one, and
    there is no sign constraint that could drop or keep a term between two calibrations);
    fewer than 3 points, or a flat x, fall back on the paper's mean ratio (p = 1)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ok = (y > 0) & np.isfinite(y) & (x > 0)
    x, y = x[ok], y[ok]
    if x.size < 3 or np.ptp(np.log(x)) == 0:
        return (float(np.mean(y / x)) if x.size else 0.0), 1.0
    p, a = np.polyfit(np.log(x), np.log(y), 1)
    return float(np.exp(a)), float(p)


#: the spread of x a power law's exponent needs: a decade of N log2 N for builds, 1.5 for
#: per-ray times in log2 N (about 1k to 30k triangles).  Narrower calibration sets get the
#: affine fit (p = 1): over the 'tiny' set's 500-1,000 triangles a fitted exponent says
#: little about larger scenes (p_B came out near 0, a build that hardly grows with N, and so
#: far too low a break-even beyond the set)
POWER_MIN_RATIO = {"build": 10.0, "per_ray": 1.5}


def _power_or_affine(x, y, min_ratio: float, x_ref: float) -> tuple[float, float, float]:
    """(a, c, p) of y ~ a + c (x / x_ref)^p: the log-space power law (a = 0) where x spans
    ``min_ratio``, else the affine least squares (p = 1)."""
    if _spans(x, min_ratio):
        c, p = _loglog_fit(x, y)
        return 0.0, c * x_ref ** p, p
    a, c = affine_lsq(x, y)
    return a, c * x_ref, 1.0


def _ratio_spread(x, y, f, spread) -> list[float]:
    """(low, high) percentiles of measured / fitted over the scenes, bracketing 1."""
    q = [yi / f(xi) for xi, yi in zip(x, y) if f(xi) > 0 and yi > 0]
    if not q:
        return [1.0, 1.0]
    lo, hi = (float(v) for v in np.percentile(q, spread))
    return [min(lo, 1.0), max(hi, 1.0)]


def _fit_power(records: list[SceneRecord], kind: str, spread) -> KindFit:
    """T_B ~ c_B (N log2 N / X_REF)^p_B and t ~ c_R (log2 N / L_REF)^p_R, fitted in log
    space: c_B is the build time and c_R the time per ray of an N_REF-triangle scene (65,536),
    p_B and p_R the exponents.  A power law bends where the affine model needs a fixed term,
    and with no constraint to switch on or off its constants move smoothly with the timings
    (the affine fit's build constants jump between two calibrations in a row where its
    fixed term is dropped in one and kept in the next); stating c at
    N_REF instead of at x = 1 keeps it within the data, where the exponent cannot trade
    against it.  Where the calibration scenes' sizes are too close to measure an exponent
    (``POWER_MIN_RATIO``) it is the affine model a + c (x / x_ref).  The interval scales c by
    the spread of measured / fitted over the scenes."""
    have = [r for r in records if kind in r.kinds]
    xb, yb = [nlog2n(r.triangles) for r in have], [r.kinds[kind].build_time for r in have]
    xr, yr = [log2n(r.triangles) for r in have], [r.kinds[kind].per_ray for r in have]
    ab, cb, pb = _power_or_affine(xb, yb, POWER_MIN_RATIO["build"], X_REF)
    ar, cr, pr = _power_or_affine(xr, yr, POWER_MIN_RATIO["per_ray"], L_REF)
    qb = _ratio_spread(xb, yb, lambda x: ab + cb * (x / X_REF) ** pb, spread)
    qr = _ratio_spread(xr, yr, lambda x: ar + cr * (x / L_REF) ** pr, spread)
    return KindFit(cb, cr, cb * qb[0], cb * qb[1], cr * qr[0], cr * qr[1], len(have),
                   extra={"p_B": pb, "p_R": pr, "a_B": ab, "a_R": ar, "x_ref_B": X_REF, "x_ref_R": L_REF})


def _estimate_power(fit: KindFit, kind: str, n: int) -> Cost:
    """a + c (x / x_ref)^p with the interval on c (a = 0 where the exponent was fitted).
    x_ref is 1 in files of format 2 (c was the factor of x^p then)."""
    e = fit.extra
    xb = (nlog2n(n) / e.get("x_ref_B", 1.0)) ** e.get("p_B", 1.0)
    yr = (log2n(n) / e.get("x_ref_R", 1.0)) ** e.get("p_R", 1.0)
    a_b, a_r = e.get("a_B", 0.0), e.get("a_R", 0.0)
    return Cost(kind, a_b + fit.c_B * xb, a_b + fit.c_B_low * xb, a_b + fit.c_B_high * xb,
                a_r + fit.c_R * yr, a_r + fit.c_R_low * yr, a_r + fit.c_R_high * yr)


# -- the 'terms' model: a build that is a sum of costs in N ------------------------------------

#: where the build's fixed cost is stated: a 1,024-triangle scene, among the small
#: calibration scenes whose builds it dominates (stated at N_REF instead, far from the
#: scenes that measure it, it moves several times as much between two calibrations in a row)
L_FIXED = 10.0


def build_terms(n: float) -> dict[str, float]:
    """The build model's regressors for an N-triangle scene: the fixed cost ('1'); the
    per-level cost ('log2n-10': one Python/numpy round per level of the tree, log2 N - 10
    levels beyond a 1,024-triangle scene's); the per-triangle cost ('n': N / N_REF) and its
    growth with the depth ('n(log2n-16)': (N / N_REF)(log2 N - 16), the N log2 N of the paper
    with its N part moved into 'n')."""
    lg = math.log2(max(float(n), 2.0))
    r = float(n) / N_REF
    return {"1": 1.0, "log2n-10": lg - L_FIXED, "n": r, "n(log2n-16)": r * (lg - L_REF)}


#: the build terms of the 'sum' form (``build_terms``), chosen by leave-one-out on the
#: calibration scenes and on held-out meshes.  The numpy BVH's build per triangle is
#: U-shaped in N: high on small scenes (a fixed and a per-level cost), lowest in between,
#: higher again on large ones, where its arrays leave the cache.  All four terms are needed
#: to follow it: with them the held-out build error is far below the power law's, and
#: dropping either 'log2n-10' or 'n(log2n-16)' raises it markedly (BENCHMARKS.md, "Studies")
_FULL_TERMS = ("1", "log2n-10", "n", "n(log2n-16)")
BUILD_TERMS = {"bvh": _FULL_TERMS}

#: the form of each structure's build in the 'terms' model: 'sum', the nonnegative sum of
#: its ``BUILD_TERMS``; 'log-quadratic', ln T_B = a + b u + c u^2 with u = ln(N / N_REF)
#: (``_fit_log_quadratic``).  A structure in neither table gets the power model.  Embree's
#: build is log-quadratic: on the held-out meshes the four-term sum runs low where the
#: log-quadratic is nearly unbiased and closer, and the log-quadratic has the lower
#: leave-one-out build and break-even errors too.  On the numpy BVH it is not clearly better,
#: so that stays a sum (BENCHMARKS.md, "Studies")
BUILD_FORMS = {"bvh": "sum", "embree": "log-quadratic"}


#: the spread of N the terms need (the largest calibration scene over the smallest): the
#: fixed cost shows below ~5k triangles and the per-triangle cost's growth above ~100k, so
#: a set that does not reach both ('tiny': 500-1k, 'quick': 1k-60k) gets the power model,
#: which extrapolates more gently
TERMS_MIN_RATIO = 100.0


def _terms_value(names, coef, n: float) -> float:
    t = build_terms(n)
    return float(sum(c * t[k] for k, c in zip(names, coef)))


def _log_quadratic_value(coef, n_min: float, n_max: float, n: float) -> float:
    """exp(a + b u + c u^2), u = ln(N / N_REF), made non-decreasing in N: the parabola is
    followed only on [p, q], the part of the fitted range ln(n_min / N_REF) .. ln(n_max /
    N_REF) where it rises; below p the build is the one at p (below the smallest scene,
    as 'sum' does, and below a minimum the data put inside the range); above q it goes on
    as a power law with the parabola's slope at q (>= 0), so a quadratic fitted up to 1M
    triangles cannot turn down (or up ever faster) on a 100M-triangle scene."""
    a, b, c = (float(v) for v in coef)
    lo, hi = math.log(n_min / N_REF), math.log(n_max / N_REF)
    top = -b / (2 * c) if c else (math.inf if b >= 0 else -math.inf)  # where the slope b + 2cu is 0
    if c > 0:  # slope rising: the parabola rises from its vertex on
        p, q = min(max(lo, top), hi), hi
    else:  # slope falling (or constant): it rises up to its vertex
        p, q = lo, max(min(hi, top), lo)
    u = math.log(max(float(n), 1.0) / N_REF)
    uc = min(max(u, p), q)
    return math.exp(a + b * uc + c * uc * uc + max(b + 2 * c * q, 0.0) * max(u - q, 0.0))


def _fit_log_quadratic(have: list[SceneRecord], kind: str, spread, power: KindFit) -> KindFit:
    """``have``: the scenes with a measured build of ``kind`` (``_fit_terms`` chose them).
    ln T_B ~ a + b u + c u^2, u = ln(N / N_REF), by least squares on ln T_B (every
    residual a relative one; no sign constraint, so no term is dropped in one calibration
    and kept in the next).  Centred at N_REF: exp(a) is the build of an N_REF-triangle
    scene (c_B), b the build's exponent there (d ln T_B / d ln N), 2c how that exponent
    grows per e-fold of N.  Embree's build per triangle falls from a fixed-cost regime at
    500 triangles towards a slowly growing per-triangle cost at 1M: a curve in log-log
    that a quadratic follows.  The estimate is ``_log_quadratic_value`` (monotone); the
    interval scales it by the spread of measured / fitted over the scenes."""
    ns = [r.triangles for r in have]
    y = np.array([r.kinds[kind].build_time for r in have])
    u = np.log(np.asarray(ns, np.float64) / N_REF)
    c, b, a = np.polyfit(u, np.log(y), 2)
    coef = [float(a), float(b), float(c)]
    n_min, n_max = min(ns), max(ns)
    f = lambda n: _log_quadratic_value(coef, n_min, n_max, n)  # noqa: E731
    cb = f(N_REF)
    qb = _ratio_spread(ns, y, f, spread)
    extra = {k: v for k, v in power.extra.items() if k.endswith("_R")}
    extra.update({"form_B": "log-quadratic", "coef_B": coef, "n_min": int(n_min), "n_max": int(n_max)})
    return KindFit(cb, power.c_R, cb * qb[0], cb * qb[1], power.c_R_low, power.c_R_high, len(have), extra=extra)


def _fit_terms(records: list[SceneRecord], kind: str, spread) -> KindFit:
    """T_B ~ sum_j b_j term_j(N) over ``BUILD_TERMS[kind]`` (the power model for a kind not
    named there), b_j >= 0 by least squares on relative residuals (``nonneg_relative_lsq``).
    Each b_j is a time in seconds: '1', the fixed and per-level cost of a 1,024-triangle
    build; 'log2n-10', what one doubling of N adds to that; 'n', the per-triangle part of an
    N_REF-triangle build (65,536); 'n(log2n-16)', what one doubling adds to that part per
    N_REF triangles.  c_B is the fitted build of an N_REF-triangle scene.  Scenes smaller
    than the smallest calibration scene (n_min) are estimated as that scene: below it the
    per-level term is not measured and could make a build negative.  The time per ray is the
    power model's, c_R (log2 N / L_REF)^p_R.  The interval scales the build by the spread
    of measured / fitted over the scenes.  With fewer scenes than terms + 1, or sizes spanning
    less than TERMS_MIN_RATIO, it is the power model."""
    power = _fit_power(records, kind, spread)
    form = BUILD_FORMS.get(kind, "sum")
    if form not in ("sum", "log-quadratic"):  # before any fallback, so a typo never passes as the power model
        raise ValueError(f"unknown build form {form!r} for {kind!r}; expected 'sum' or 'log-quadratic'")
    names = ("1", "u", "u^2") if form == "log-quadratic" else BUILD_TERMS.get(kind)
    have = [r for r in records if kind in r.kinds and r.kinds[kind].build_time > 0]
    ns = [r.triangles for r in have]
    if names is None or len(have) < len(names) + 1 or not _spans(ns, TERMS_MIN_RATIO):
        return power  # not a terms structure, or too few scenes or sizes to weigh its terms
    if form == "log-quadratic":
        return _fit_log_quadratic(have, kind, spread, power)
    y = np.array([r.kinds[kind].build_time for r in have])
    x = np.array([[build_terms(n)[k] for k in names] for n in ns])
    b = nonneg_relative_lsq(x, y)
    n_min = min(ns)
    f = lambda n: _terms_value(names, b, max(n, n_min))  # noqa: E731
    cb = f(N_REF)
    qb = _ratio_spread(ns, y, f, spread)
    extra = {k: v for k, v in power.extra.items() if k.endswith("_R")}
    extra.update({"terms_B": list(names), "coef_B": [float(v) for v in b], "n_min": int(n_min)})
    return KindFit(cb, power.c_R, cb * qb[0], cb * qb[1], power.c_R_low, power.c_R_high, len(have), extra=extra)


def _estimate_terms(fit: KindFit, kind: str, n: int) -> Cost:
    """sum_j b_j term_j(max(N, n_min)), the interval as the ratio of c_B's; the power model's
    per-ray time (and build, for a structure fitted without terms)."""
    e = fit.extra
    if "coef_B" not in e:
        return _estimate_power(fit, kind, n)
    if e.get("form_B") == "log-quadratic":
        build = _log_quadratic_value(e["coef_B"], e["n_min"], e["n_max"], n)
    else:
        build = _terms_value(e["terms_B"], e["coef_B"], max(int(n), int(e.get("n_min", 1))))
    lo, hi = (fit.c_B_low / fit.c_B, fit.c_B_high / fit.c_B) if fit.c_B > 0 else (1.0, 1.0)
    p = _estimate_power(fit, kind, n)
    return Cost(kind, build, build * lo, build * hi, p.per_ray, p.per_ray_low, p.per_ray_high)


#: the shipped calibration models, name -> (fit per kind, estimate); a model keeps its
#: parameters beyond the two constants in KindFit.extra.  'terms' is the default, 'power'
#: its per-ray model and its fallback for a set of scenes too narrow to weigh the terms.  The
#: models the evaluation compares them with (the paper's own two constants, 'affine',
#: 'median') are ``evaluate.COMPARED_MODELS``
MODELS = {"power": (_fit_power, _estimate_power), "terms": (_fit_terms, _estimate_terms)}


#: the scene sizes a 'terms' build is stated at: its time at each, four sizes for
#: its four coefficients (the terms at these sizes form an invertible matrix, so the four
#: times are the model), all within the calibration set's 500 to 1M triangles.  The
#: coefficients themselves are not constants two calibrations can agree on: over that range
#: the four regressors are nearly collinear, so the fit trades one against another (two
#: calibrations in a row put 'log2n-10' far apart, and the nonnegative fit drops a term in
#: one and keeps it in the next) while the builds they predict stay close
BUILD_ANCHORS = (1_024, 16_384, 262_144, 1_048_576)


def fit_constants(f: KindFit, model: str, *, per_ray: bool = True) -> dict[str, float]:
    """Each constant a model fitted, by what it means (what two calibrations should agree
    on): times in seconds, exponents bare.  'terms' states its build at ``BUILD_ANCHORS``,
    'power' its times at N_REF (format 3; a format-2 'power' file's c is the factor of
    x^p).  per_ray=False: the build's constants alone (a calibration with count models
    takes each structure's time per ray from those, ``CountFit.constants``)."""
    e = f.extra
    if model == "terms" and "coef_B" in e:
        out = {f"build at {n:,}": _estimate_terms(f, "", n).build_time for n in BUILD_ANCHORS}
        ray = {"per ray at N_REF": f.c_R, "p_R": e.get("p_R", 1.0)}
    elif model in ("power", "terms"):
        out = {"build at N_REF" if "x_ref_B" in e else "c_B": f.c_B, "p_B": e.get("p_B", 1.0)}
        ray = {"per ray at N_REF" if "x_ref_R" in e else "c_R": f.c_R, "p_R": e.get("p_R", 1.0)}
        out.update({"a_B": e["a_B"]} if e.get("a_B") else {})
        ray.update({"a_R": e["a_R"]} if e.get("a_R") else {})
    else:
        out, ray = {"c_B": f.c_B}, {"c_R": f.c_R}
        out.update({"a_B": e["a_B"]} if "a_B" in e else {})
        ray.update({"a_R": e["a_R"]} if "a_R" in e else {})
    return {**out, **ray} if per_ray else out


def fit_coefficients(f: KindFit, model: str) -> dict[str, float]:
    """The build's raw coefficients as the file stores them ('terms': one per term of
    ``BUILD_TERMS``, in seconds), for a report that shows how far the fit trades them."""
    e = f.extra
    if model == "terms" and e.get("form_B") == "log-quadratic":
        a, b, c = e["coef_B"]
        return {"build at N_REF": math.exp(a), "build exponent at N_REF": b, "build curvature": c}
    if model == "terms" and "coef_B" in e:
        return {f"build {t}": c for t, c in zip(e["terms_B"], e["coef_B"])}
    return fit_constants(f, model, per_ray=False)


def describe_fit(f: KindFit, model: str) -> str:
    """One structure's fitted model as a reader writes it (ms for builds, ns per ray)."""
    e = f.extra
    per_ray = (f"per ray {f.c_R * 1e9:.2f} ns [{f.c_R_low * 1e9:.2f}, {f.c_R_high * 1e9:.2f}]"
               + (f" x (log2 N / {e['x_ref_R']:g})^{e.get('p_R', 1.0):.3f}" if "x_ref_R" in e else
                  f" x (log2 N)^{e['p_R']:.3f}" if "p_R" in e else " x log2 N")
               + (f" + {e['a_R'] * 1e9:.2f} ns" if e.get("a_R") else ""))
    if model == "terms" and e.get("form_B") == "log-quadratic":
        a, b, c = e["coef_B"]
        return (f"build {math.exp(a) * 1e3:.1f} ms [{f.c_B_low * 1e3:.1f}, {f.c_B_high * 1e3:.1f}] x "
                f"(N / {N_REF:,})^({b:.3f} + {c:.4f} u), u = ln(N / {N_REF:,}) "
                f"(N >= {e['n_min']:,}; above {e['n_max']:,} the exponent there)   {per_ray}")
    if model == "terms" and "coef_B" in e:
        names = {"1": "", "log2n-10": " x (log2 N - 10)", "n": " x n", "n(log2n-16)": " x n (log2 N - 16)"}
        build = " + ".join(f"{c * 1e3:.3g} ms{names.get(t, ' x ' + t)}" for t, c in zip(e["terms_B"], e["coef_B"]))
        return (f"build {build} (n = N / {N_REF:,}, N >= {e.get('n_min', 1):,}): {f.c_B * 1e3:.1f} ms at N = {N_REF:,} "
                f"[{f.c_B_low * 1e3:.1f}, {f.c_B_high * 1e3:.1f}]   {per_ray}")
    if "x_ref_B" in e:
        build = (f"build {f.c_B * 1e3:.1f} ms [{f.c_B_low * 1e3:.1f}, {f.c_B_high * 1e3:.1f}] x "
                 f"(N log2 N / {e['x_ref_B']:,.0f})^{e.get('p_B', 1.0):.3f}")
    else:
        build = (f"build c_B {f.c_B * 1e9:.2f} ns [{f.c_B_low * 1e9:.2f}, {f.c_B_high * 1e9:.2f}] x "
                 + (f"(N log2 N)^{e['p_B']:.3f}" if "p_B" in e else "N log2 N"))
    return build + (f" + {e['a_B'] * 1e3:.2f} ms" if e.get("a_B") else "") + "   " + per_ray


def fit(records: list[SceneRecord], kinds, *, model: str = DEFAULT_MODEL, spread=DEFAULT_SPREAD) -> dict[str, KindFit]:
    """Fit ``model`` for each kind measured in at least one record."""
    if model not in MODELS:
        raise ValueError(f"unknown calibration model {model!r}; expected one of {', '.join(MODELS)}")
    fit_one = MODELS[model][0]
    return {k: fit_one(records, k, tuple(spread)) for k in kinds if any(k in r.kinds for r in records)}



# -- per-ray times from the grid sample's work counts --------------------------------------------

#: log2 of the scene size (16,384 triangles) above which each further level of Embree's tree
#: costs a ray that hits measurably more: below it Embree's time per ray hardly grows with N
#: (its tree stays in the cache), above it it grows by a constant factor per level for each
#: ray that hits (``hit_above_16k``); of the thresholds 12 to 16 this one had the lowest
#: leave-one-out error (BENCHMARKS.md, "Measurement protocol and model terms")
L_CACHED = 14.0


def terms(triangles: int, work: dict) -> dict[str, float]:
    """The named quantities a count model may weigh, for one scene: its size and the grid
    sample's per-ray means (``work.Work``; the traversal's own counts only where the file
    recorded them).  hit_above_16k: the hit fraction times the levels beyond a 16,384-triangle
    scene's, hit x max(log2 N - L_CACHED, 0): how much deeper than in a small scene the rays
    that hit descend."""
    lg = log2n(triangles)
    # a count the sample did not take (refs when no model weighs them) is absent, so a
    # model that needs it fails by name instead of reading a zero
    w = {k: float(v) for k in ("cells", "refs", "hit", "length", "steps", "candidates", "tests")
         if (v := work.get(k)) is not None}
    out = {"1": 1.0, "log2n": lg, **w}
    for k in ("hit", "length"):
        if k in w:
            out[f"{k}_log2n"] = w[k] * lg
    if "hit" in w:
        out["hit_above_16k"] = w["hit"] * max(lg - L_CACHED, 0.0)
    return out


def nonneg_relative_lsq(x, y) -> np.ndarray:
    """Coefficients b >= 0 minimising sum ((x b)_i / y_i - 1)^2 (relative residuals, so a
    small scene weighs as much as a large one): least squares, dropping the most negative
    term and refitting until none is negative."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    keep = list(range(x.shape[1]))
    b = np.zeros(x.shape[1])
    while keep:
        a = x[:, keep] / y[:, None]
        sol, *_ = np.linalg.lstsq(a, np.ones(len(y)), rcond=None)
        if (sol >= 0).all():
            b[keep] = sol
            return b
        keep.pop(int(np.argmin(sol)))
    return b


def _log_columns(x: np.ndarray, names) -> np.ndarray:
    """The log form's regressors: 1 for the term '1' (the intercept), log(1 + term) else
    (every count is >= 0; 1 + keeps a zero hit fraction finite)."""
    return np.stack([np.ones(len(x)) if k == "1" else np.log1p(np.maximum(x[:, j], 0.0))
                     for j, k in enumerate(names)], axis=1)


#: where each count model's constant is stated: a count model's '1' coefficient is its time
#: per ray at these counts, not at zero counts far outside the data, where it trades against
#: the slopes (stated at zero, the BVH's moved far between two calibrations in a row).
#: log2n: an N_REF-triangle scene; cells: 15 cells a ray (1 + cells = 16, near the
#: calibration scenes' median); steps and candidates: 8 lockstep steps and 20 candidate
#: pairs a ray (near the calibration scenes' medians).  A term not named here is stated at 0
COUNT_REFERENCE = {"log2n": L_REF, "cells": 15.0, "steps": 8.0, "candidates": 20.0}

#: the counts a one-count linear model is stated at (``CountFit.constants``): its time per
#: ray at two counts the calibration scenes span (their sample rays step through 4.6 to 54
#: cells; they have 2^9 to 2^20 triangles).  Two times are the model, as intercept and slope
#: are, but each is measured by the scenes near it, where a slope is the difference of two
#: noisy ends (between two calibrations in a row the grid's slope moves more than either of
#: its times at the two anchors).  Embree's hit_above_16k: a scene of at most 16k
#: triangles (or rays that all miss), and 40% of the rays hitting a 2M-triangle scene.
#: A linear model of several counts is stated, alike, by its times at as many points of
#: their space as it has coefficients, keyed by the tuple of its counts: the grid's steps and
#: candidates at three corners of what the calibration scenes span (4-22 steps, 8-38
#: candidates a ray): few of both (small scenes), many steps and few candidates (cities,
#: scatter), many of both (large closed meshes, terrain).  The numpy BVH's hit fraction and
#: steps likewise (hits 0.01-0.84 a ray, 4-11 steps where half of them hit): few hits
#: (slivers, scatter), many hits in few steps (small spheres, cities), many hits in many
#: (large closed meshes and soups)
COUNT_ANCHORS = {"cells": (5.0, 40.0), "log2n": (10.0, 20.0), "hit_above_16k": (0.0, 2.5),
                 ("steps", "candidates"): ((5.0, 10.0), (10.0, 13.0), (10.0, 35.0)),
                 ("hit", "steps"): ((0.1, 10.0), (0.6, 5.0), (0.6, 10.0))}


def _anchor_points(slopes: tuple) -> list[dict] | None:
    """The points ({count: value}) a linear model of the counts ``slopes`` is stated at, or
    None where COUNT_ANCHORS has none for them."""
    if len(slopes) == 1 and slopes[0] in COUNT_ANCHORS:
        return [{slopes[0]: float(x)} for x in COUNT_ANCHORS[slopes[0]]]
    if len(slopes) > 1 and tuple(slopes) in COUNT_ANCHORS:
        return [dict(zip(slopes, map(float, p))) for p in COUNT_ANCHORS[tuple(slopes)]]
    return None


@dataclass
class CountFit:
    """time per ray from the named ``terms`` (seconds), with the spread of measured / fitted
    over the calibration scenes as (low, high) multipliers, stated at the reference counts
    ``refs`` (one per term; r_j = 0 for '1'):

    form 'linear': coef['1'] + sum_j coef[j] (term_j - r_j), coef['1'] being the time per ray
                   at the reference and the slopes >= 0 (``nonneg_relative_lsq``, with each
                   term's own cost >= 0);
    form 'log':    exp(coef['1']) prod_j ((1 + term_j) / (1 + r_j))^coef[j]: exp(coef['1'])
                   is the time per ray at the reference, a power law fitted by least squares
                   on log time (no sign constraint, so no term is dropped in one calibration
                   and kept in the next);
    form 'exp':    exp(coef['1'] + sum_j coef[j] (term_j - r_j)): exp(coef['1']) is the time
                   per ray at the reference and coef[j] the e-folds per unit of term j, by
                   least squares on log time (no sign constraint).
    ``refs`` empty (files of format 2): every r_j = 0."""

    terms: tuple
    coef: tuple
    low: float = 1.0
    high: float = 1.0
    scenes: int = 0
    form: str = "linear"
    refs: tuple = ()
    #: the spread of measured / fitted over the calibration scenes that are surfaces
    #: (``scenes.is_surface_scene``), as (low, high) multipliers; None in older files or with
    #: fewer than 3 such scenes.  A surface mesh's interval reads these (``surface_spread``):
    #: the soups' trees trace far slower than any count predicts and widen the whole spread
    surface_low: float | None = None
    surface_high: float | None = None

    def spread_for(self, surface: bool) -> tuple[float, float]:
        """(low, high): the surfaces' spread for a surface mesh where the fit holds one, else
        the spread over every scene."""
        if surface and self.surface_low is not None and self.surface_high is not None:
            return self.surface_low, self.surface_high
        return self.low, self.high

    def _refs(self) -> tuple:
        return tuple(self.refs) if self.refs else tuple(0.0 for _ in self.terms)

    @property
    def weighed(self) -> tuple:
        """The counts the model weighs: its terms but the constant '1'."""
        return tuple(k for k in self.terms if k != "1")

    def predict(self, triangles: int, work: dict) -> float:
        t = terms(triangles, work)
        missing = [k for k in self.terms if k not in t]
        if missing:
            raise ValueError(f"the grid sample's work counts lack {', '.join(missing)}, which this count model weighs")
        refs = self._refs()
        if self.form == "log":
            x = np.array([[t[k] for k in self.terms]], np.float64)
            r = np.array([[0.0 if k == "1" else v for k, v in zip(self.terms, refs)]], np.float64)
            cols = _log_columns(x, self.terms)[0] - np.where(np.array(self.terms) == "1", 0.0, np.log1p(r[0]))
            return float(np.exp(cols @ np.asarray(self.coef, np.float64)))
        return self._at({k: t[k] for k in self.weighed})

    def _at(self, counts: dict) -> float:
        """A 'linear' or 'exp' model's time per ray at ``counts`` ({term: value}, every
        weighed term)."""
        s = sum(c * (counts[k] - r) if k != "1" else c for k, c, r in zip(self.terms, self.coef, self._refs()))
        return float(math.exp(s) if self.form == "exp" else s)

    def constants(self) -> dict[str, float]:
        """Each fitted constant by what it means.  A 'linear' or 'exp' model of counts named
        in ``COUNT_ANCHORS``: its time per ray (s) at the anchor points, one per coefficient,
        which are the model; any other: the time per ray at the reference (s) and each
        term's slope (linear, s a unit), exponent (log) or e-folds per unit (exp)."""
        slopes = self.weighed
        points = _anchor_points(slopes) if self.form in ("linear", "exp") and "1" in self.terms else None
        if points is None:
            return self.coefficients()
        return {"at " + ", ".join(f"{k} = {v:g}" for k, v in p.items()): self._at(p) for p in points}

    def coefficients(self) -> dict[str, float]:
        """The coefficients as stored: the time per ray at the reference (s) and each
        term's slope (linear, s a unit) or exponent (log)."""
        out = {}
        for k, c, r in zip(self.terms, self.coef, self._refs()):
            if k == "1":
                out["at ref" if self.refs else "1"] = math.exp(c) if self.form in ("log", "exp") else c
            else:
                out[{"log": "p ", "exp": "e-folds per "}.get(self.form, "x ") + k] = c
        return out

    def formula(self) -> str:
        """The model as a reader writes it, in ns: '2.10 ns + 0.10 ns x (log2n - 16)',
        '919.00 ns x ((1 + cells) / 16)^0.624' or '89.67 ns x exp(0.346 x hit_above_16k)'."""
        refs = self._refs()
        if self.form == "exp":
            scale = math.exp(self.coef[self.terms.index("1")]) * 1e9
            return f"{scale:.2f} ns x exp(" + " + ".join(
                f"{c:.3f} x ({t} - {r:g})" if r else f"{c:.3f} x {t}"
                for t, c, r in zip(self.terms, self.coef, refs) if t != "1") + ")"
        if self.form == "log":
            scale = math.exp(self.coef[self.terms.index("1")]) * 1e9
            return f"{scale:.2f} ns" + "".join(
                f" x ((1 + {t}) / {1 + r:g})^{c:.3f}" if r else f" x (1 + {t})^{c:.3f}"
                for t, c, r in zip(self.terms, self.coef, refs) if t != "1")
        return " + ".join(f"{c * 1e9:.2f} ns" if t == "1" and self.refs else
                          f"{c * 1e9:.2f} ns x ({t} - {r:g})" if r else f"{c * 1e9:.2f} ns x {t}"
                          for t, c, r in zip(self.terms, self.coef, refs))

    @classmethod
    def fit(cls, rows, names, spread=DEFAULT_SPREAD, form: str = "linear", reference=None) -> "CountFit":
        """rows: (triangles, work dict, measured time per ray) per scene.  ``reference``:
        {term: count} where the constants are stated (default ``COUNT_REFERENCE``; {} states
        them at zero counts, as format 2 did).  The fit itself is the uncentred one, so the
        reference changes the constants, never the predictions."""
        if form not in ("linear", "log", "exp"):
            raise ValueError(f"unknown count-model form {form!r}; expected 'linear', 'log' or 'exp'")
        if form in ("log", "exp") and "1" not in names:
            raise ValueError(f"a {form!r} count model needs the term '1' (its scale)")
        reference = COUNT_REFERENCE if reference is None else reference
        refs = tuple(0.0 if k == "1" else float(reference.get(k, 0.0)) for k in names) if "1" in names else ()
        refs = refs if any(refs) else ()
        rows = [r for r in rows if r[2] > 0 and math.isfinite(r[2])]
        if not rows:
            return cls(tuple(names), tuple(0.0 for _ in names), form=form, refs=refs)
        x = np.array([[terms(n, w)[k] for k in names] for n, w, _ in rows])
        y = np.array([t for _, _, t in rows])
        if form == "log":
            b, *_ = np.linalg.lstsq(_log_columns(x, names), np.log(y), rcond=None)
            shift = sum(c * math.log1p(r) for c, r, k in zip(b, refs, names) if k != "1")
        elif form == "exp":
            b, *_ = np.linalg.lstsq(x, np.log(y), rcond=None)  # the column of '1' is ones
            shift = sum(c * r for c, r, k in zip(b, refs, names) if k != "1")
        else:
            b = nonneg_relative_lsq(x, y)
            shift = sum(c * r for c, r, k in zip(b, refs, names) if k != "1")
        b = [float(v) for v in b]
        if refs:
            b[list(names).index("1")] += float(shift)
        f = cls(tuple(names), tuple(b), scenes=len(rows), form=form, refs=refs)
        q = [t / p for (n, w, t) in rows if (p := f.predict(n, w)) > 0]
        if q:
            lo, hi = (float(v) for v in np.percentile(q, spread))
            f.low, f.high = min(lo, 1.0), max(hi, 1.0)
        return f


#: the terms of each count model (``terms``): the grid's time per ray from what its traversal
#: did for the sample rays, lockstep steps and candidate (ray, reference) pairs
#: (``UniformGrid.traversal_work``); the numpy BVH's and Embree's from log2 N alone.
#: The 3D-DDA's cells along each ray (a + b cells, the fallback) misread the grid's work:
#: the grid jumps over empty space, so on closed meshes it takes far fewer steps than there
#: are cells, while the calibration's soups and slivers take about one a cell and test more
#: triangles; so a cells model runs high on held-out meshes, where a model of steps and
#: candidates follows them closely and has the lower leave-one-out error too (BENCHMARKS.md,
#: "Studies").
#: Adding the kernel's tests lowers leave-one-out further but not the held-out break-evens.
#: The grid sample's cells and references in the BVH's model lowered the error on the
#: calibration scenes but not on held-out meshes, and made two calibrations in a row predict
#: per-ray times far apart (the nonnegative fit trades log2 N against references).
#: Embree's is exp(a + b hit_above_16k): a + b log2 N, fitted on relative residuals, runs low
#: on the held-out meshes and lowest on the largest ones (their hit rays descend a tree that
#: has left the cache, where the calibration's low stadium-500k and scatter scenes and high
#: soups pull the slope flat); exp(a + b hit_above_16k) follows the held-out meshes closely
#: and has the lower leave-one-out error, over calibrations and reports' truths alike.
#: The numpy BVH's is a + b hit + c steps: a ray that hits descends to the leaves and a
#: ray that misses leaves the tree near its root, so its time follows the sample's hit
#: fraction; the grid's lockstep steps (an empty stretch jumped over is one) count the
#: stretches of occupied space the ray passes, whose boxes the tree opens too.  a + b log2 N
#: sees neither.  The grid's candidates in place of its steps say how full its cells are,
#: which a tree's leaves bound whatever the mesh: on flat and thin meshes, whose rays pass
#: few stretches, that model put the tree's time per ray far high (BENCHMARKS.md, "The new
#: evaluation set: tuning and final halves").
COUNT_TERMS = {
    "grid": ("1", "steps", "candidates"),
    "bvh": ("1", "hit", "steps"),
    "embree": ("1", "hit_above_16k"),
}

#: the terms a count model falls back on when the records lack its counts (files made before
#: the grid counted its traversal): their work has the cells, not the steps
COUNT_FALLBACK = {"grid": ("1", "cells")}


#: the form of each count model (``CountFit.form``): nonnegative sums, a + b steps + c
#: candidates for the grid and a + b log2 N for the numpy BVH; Embree's exp(a + b
#: hit_above_16k) (``COUNT_TERMS``).  With the calibration tracing large batches, a sum
#: follows the held-out meshes' grid time per ray more closely than a power law in
#: (1 + cells) does (leave-one-out on the calibration scenes is about even) and its
#: break-even against the numpy BVH has a smaller error and no bias left; a power law in
#: log2 N extrapolated worse and moved more between calibrations for the structures
COUNT_FORMS = {"grid": "linear", "bvh": "linear", "embree": "exp"}


def fit_counts(records, kinds, spread=DEFAULT_SPREAD, terms_of=None, forms_of=None, reference=None) -> dict[str, CountFit]:
    """A CountFit per kind ('grid' and the structures) over the records with work counts,
    its constants stated at ``reference`` (``CountFit.fit``).  A kind whose default terms
    (``COUNT_TERMS``, not ``terms_of``) fewer than 3 records can give is fitted on its
    ``COUNT_FALLBACK`` terms; none at all leaves the kind out."""
    chosen = set(terms_of or {})
    terms_of = dict(COUNT_TERMS, **(terms_of or {}))
    forms_of = dict(COUNT_FORMS, **(forms_of or {}))
    out = {}
    for k in kinds:
        if k not in terms_of:
            continue
        for names in (terms_of[k], None if k in chosen else COUNT_FALLBACK.get(k)):
            usable = counted(records, k, names) if names else []
            if len(usable) >= 3:
                f = CountFit.fit([(r.triangles, r.work, r.kinds[k].per_ray) for r in usable], names, spread,
                                 forms_of.get(k, "linear"), reference)
                f.surface_low, f.surface_high = surface_spread(f, usable, k, spread)
                out[k] = f
                break
    return out


def counted(records, kind: str, names) -> list[SceneRecord]:
    """The records that measured ``kind`` and hold every count the terms ``names`` weigh."""
    return [r for r in records if r.work and kind in r.kinds and all(t in terms(r.triangles, r.work) for t in names)]


def surface_spread(f: CountFit, records, kind: str, spread=DEFAULT_SPREAD) -> tuple[float | None, float | None]:
    """(low, high): the ``spread`` percentiles of measured / ``f``'s prediction over the
    records whose scenes are surfaces (``scenes.is_surface_scene``), as ``CountFit.fit``
    states its own; (None, None) with fewer than 3 of them."""
    from ..scenes import is_surface_scene

    q = [r.kinds[kind].per_ray / p for r in counted(records, kind, f.terms)
         if is_surface_scene(r.name) and r.kinds[kind].per_ray > 0 and (p := f.predict(r.triangles, r.work)) > 0]
    if len(q) < 3:
        return None, None
    lo, hi = (float(v) for v in np.percentile(q, spread))
    return min(lo, 1.0), max(hi, 1.0)


# -- a prior bound on the break-even, before any sample ------------------------------------------

#: the floor's safety factor: a bound from extremes of ~20 scenes' timings, halved because
#: timings on a shared machine move between runs by more than those extremes allow for (and
#: the scene is not among them)
FLOOR_MARGIN = 0.5
#: the ceiling's safety factor, the floor's mirror: a bound from the extremes, doubled
CEILING_MARGIN = 2.0


def _power_envelope(x, y, side: str) -> tuple[float, float]:
    """(c, p) with y_i >= c x_i^p for all i (side 'low') or <= (side 'high'): the log-space
    power law through the points, shifted to their lowest / highest ratio; with x spanning
    less than a decade, p = 1 (an exponent from close sizes would not extrapolate)."""
    c, p = _loglog_fit(x, y) if _spans(x, 10.0) else (float(np.mean(np.asarray(y) / np.asarray(x))), 1.0)
    q = [yi / (c * xi ** p) for xi, yi in zip(x, y) if yi > 0 and xi > 0]
    if not q or c <= 0:
        return 0.0, 1.0
    return c * (min(q) if side == "low" else max(q)), p


@dataclass
class Prior:
    """What the calibration alone says about an N-triangle scene, before any sample.

    floor: a lower bound on the break-even against every candidate (0: none);
    grid_per_ray: the slowest grid time per ray the calibration scenes imply;
    per_ray: {kind: grid_per_ray less the largest gain per ray any calibration scene showed},
    figures under which each candidate's break-even is at least ``floor / FLOOR_MARGIN``;
    ceiling: {kind: an upper bound on the rays from which building it beats building the grid},
    for the candidates that beat the grid per ray on every calibration scene (absent: none);
    gain_low: {kind: the least gain per ray t_G - t_H}, the figure the ceiling divides by."""

    floor: float = 0.0
    grid_per_ray: float = 0.0
    per_ray: dict = field(default_factory=dict)
    ceiling: dict = field(default_factory=dict)
    gain_low: dict = field(default_factory=dict)


def _ceiling(x, y, n: float) -> float:
    """The high power-law envelope of (x, y) at n; 0 with fewer than 3 points."""
    if len(x) < 3:
        return 0.0
    c, p = _power_envelope(x, y, "high")
    return c * float(n) ** p


def prior(records: list[SceneRecord], n: int, kinds) -> Prior:
    """Bounds on R* = T_B^H / (t_G - t_H) from the calibration scenes alone.

    Floor: R*_H >= T_B,low(N) / g_high(N), the lowest build and the largest gain per ray g =
    t_G - t_H any calibration scene showed, as power laws (in N log2 N and N) through the
    extremes; g is also bounded by the grid's slowest time per ray (t_H >= 0).  The floor is
    FLOOR_MARGIN times the least of these over the candidates: below it the grid wins
    without a sample, so a plan for so few rays need not pay for one.  No floor without 3
    scenes measuring the grid and each candidate.

    Ceiling, the mirror, before anything is built (the grid's build not yet sunk): building H
    beats building the grid from R_0 = (T_B^H - T_B^G) / (t_G - t_H) rays on (0 where H builds
    faster).  Both builds grow about linearly in N and the gain per ray slowly, so R_0 / N is
    bounded by its largest value on the calibration scenes; the ceiling is CEILING_MARGIN
    times that, times N, for a candidate that beat the grid per ray on every one of at least 3
    calibration scenes (Embree, about ten times the grid's speed): above it H wins whatever a
    sample would say, so a plan for so many rays builds neither the grid nor a sample."""
    grid = [r for r in records if "grid" in r.kinds and r.triangles > 0]
    t_g = _ceiling([r.triangles for r in grid], [r.kinds["grid"].per_ray for r in grid], n) if n > 0 else 0.0
    if not t_g > 0 or not kinds:
        return Prior(0.0, t_g)
    bounds, per_ray, ceiling, gain_low = [], {}, {}, {}
    for k in kinds:
        have = [r for r in grid if k in r.kinds]
        if len(have) < 3:
            bounds.append(0.0)  # a candidate the calibration cannot bound: no floor
            continue
        x_build = [nlog2n(r.triangles) for r in have]
        cb, pb = _power_envelope(x_build, [r.kinds[k].build_time for r in have], "low")
        every = [(r.triangles, r.kinds["grid"].per_ray - r.kinds[k].per_ray) for r in have]
        gain = [(x, y) for x, y in every if y > 0]
        g = min(t_g, _ceiling([x for x, _ in gain], [y for _, y in gain], n)) if len(gain) >= 3 else t_g
        if not g > 0:
            g = t_g
        bounds.append(cb * nlog2n(n) ** pb / g)
        per_ray[k] = max(t_g - g, 0.0)
        if len(gain) == len(every):  # H faster per ray on every scene: a least gain exists
            cg, pg = _power_envelope([x for x, _ in gain], [y for _, y in gain], "low")
            gain_low[k] = cg * float(n) ** pg
            r0 = [max(r.kinds[k].build_time - r.kinds["grid"].build_time, 0.0) / y / r.triangles
                  for r, (_, y) in zip(have, every)]
            ceiling[k] = CEILING_MARGIN * max(r0) * float(n)
    return Prior(FLOOR_MARGIN * min(bounds), t_g, per_ray, ceiling, gain_low)


def grid_laws(records: list[SceneRecord], spread=DEFAULT_SPREAD) -> tuple | None:
    """The grid's build and time per ray as power laws in N through the calibration scenes
    that measured it (least squares on log times), each (c, p, low, high) with y ~ c N^p and
    [low, high] the scenes' spread around it as factors; None with fewer than 3 such scenes."""
    have = [r for r in records if "grid" in r.kinds and r.triangles > 0]
    if len(have) < 3:
        return None
    x = [r.triangles for r in have]
    laws = []
    for y in ([r.kinds["grid"].build_time for r in have], [r.kinds["grid"].per_ray for r in have]):
        c, p = _loglog_fit(x, y)
        laws.append((c, p, *_ratio_spread(x, y, lambda v, c=c, p=p: c * float(v) ** p, spread)))
    return tuple(laws)


def grid_estimate(records: list[SceneRecord], n: int, spread=DEFAULT_SPREAD, laws=None) -> Cost | None:
    """The grid's build and time per ray for an N-triangle mesh from the calibration scenes
    alone, before any sample (``grid_laws``, or ``laws`` made by it already); None without
    them.  What the persistent scene weighs per mesh, where a sample per mesh would cost
    more than the choice it informs."""
    laws = grid_laws(records, spread) if laws is None else laws
    if not laws or n <= 0:
        return None
    figures = []
    for c, p, lo, hi in laws:
        y = c * float(n) ** p
        figures += [y, y * lo, y * hi]
    return Cost("grid", *figures)
