"""The evaluation: the paper's tables, computed from measurements; pure arithmetic, no timing.

Hapala, Karlik and Havran (2011), section 4: on each evaluated scene the true break-even
R_C is measured by really building and running both structures, and compared with the
estimate R_est by the relative error ``100 (R_est - R_C) / R_C``; the paper reports the
sum of the errors and the sum of their absolute values, and the median speedup of the
hybrid over always-grid and always-HDS across ray counts.  Everything here takes the
measured (and estimated) numbers as plain floats, so the tables are testable on
synthetic timings; ``measurements.measure_break_even`` does the measuring.

Totals for a ray count R are extrapolated from the measured build times and per-ray
times, ``T_B + R t``, as the paper does: a per-ray time measured on 2M rays stands for
every larger workload with the same ray distribution.

Strategies compared per (scene, R), all in seconds:

- always-grid  ``T_B^G + R t_G``;
- always-H     ``T_B^H + R t_H`` for each hierarchical structure H (no grid built);
- hybrid       ``T_B^G + e + (R t_G  if R <= R_est  else  T_B^H + R t_H)``: the sidebar's
  Analyze, K uniform sample rays apart from the workload.  It builds the grid, pays the
  estimate e (tracing the K samples, plus arithmetic), then follows its estimated decision
  at the *true* cost of the structure it chose;
- hybrid_reuse the same plan given the workload's own rays (``api.cast``, the Trace
  operator): the K samples are K of the R rays and their answers are kept, so the chosen
  structure traces only the R - K others (Embree, which does not answer bit for bit like
  the grid, retraces all R).  The estimate then costs its arithmetic plus the difference
  between the grid's sample time and what those K rays cost with the chosen structure.
  The decision weighs the rays left (``hybrid_reuse_choice``), so when R <= K the grid,
  which answered the whole workload while planning, is kept;
- online       the ski-rental rule of ``plan.trace_online``: the grid traces in batches
  until its accumulated trace time reaches H's *estimated* build time, then H is built
  and traces the rest, at true costs; switching happens on batch boundaries and only
  when H's estimated per-ray time is below the grid's;
- oracle       ``min`` over always-grid and every always-H: the best fixed choice.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .cost import DEFAULT_MODEL, DEFAULT_SPREAD, MODELS, KindFit, SceneRecord, break_even, log2n, nlog2n
from .rule import REUSES_SAMPLES, choose
from .work import DEFAULT_SAMPLES

#: the ray counts of the speedup tables: 1e3 to 1e8, four points a decade
RAY_COUNTS = np.logspace(3, 8, 21)
#: "the two structures differ" when the dearer costs more than this fraction over the cheaper
DIFFER = 0.10
#: ray count at which the estimate's own cost is quoted
COST_AT = 1e6


@dataclass
class Cost:
    """A structure's build time and time per ray (seconds)."""

    build: float
    per_ray: float

    def total(self, rays):
        return self.build + np.asarray(rays, np.float64) * self.per_ray


@dataclass
class SceneResult:
    """What was measured and estimated on one evaluated scene.

    grid / measured: true costs (the grid and each hierarchical structure, built and run
    on ``rays`` rays); estimated: the plan's estimates for the hierarchical structures;
    grid_estimate_per_ray: the grid's time per ray the estimate used, i.e. ``Plan.grid_per_ray``
    (the K-sample time times the calibration's small-batch ratio); grid_sample_per_ray:
    the raw K-sample time per ray (``Plan.grid_sample_per_ray``; None when unknown);
    estimate_time: the estimate's own cost beyond the grid build with K uniform samples;
    reuse_estimate_time: the same when the samples are drawn from the workload (None: as
    estimate_time).
    """

    name: str
    triangles: int
    rays: int
    grid: Cost
    measured: dict[str, Cost]
    estimated: dict[str, Cost]
    grid_estimate_per_ray: float
    estimate_time: float
    samples: int = 0
    group: str = ""
    grid_sample_per_ray: float | None = None
    reuse_estimate_time: float | None = None
    extra: dict = field(default_factory=dict)
    #: the calibration's floor on the break-even (``Plan.break_even_floor``): for at most
    #: this many rays the plan keeps the grid without sampling (0: no floor)
    floor: float = 0.0

    @property
    def grid_sample_ratio(self) -> float | None:
        """The correction the estimate applied to the raw sample (None when unknown)."""
        if not self.grid_sample_per_ray:
            return None
        return self.grid_estimate_per_ray / self.grid_sample_per_ray

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SceneResult":
        d = dict(d)
        d["grid"] = Cost(**d["grid"])
        d["measured"] = {k: Cost(**v) for k, v in d["measured"].items()}
        d["estimated"] = {k: Cost(**v) for k, v in d["estimated"].items()}
        return cls(**d)


# -- break-even and its error -------------------------------------------------------------------

def true_break_even(s: SceneResult, kind: str = "bvh") -> float:
    """R_C: measured build and per-ray times of both structures."""
    return break_even(s.measured[kind].build, s.grid.per_ray, s.measured[kind].per_ray)


def estimated_break_even(s: SceneResult, kind: str = "bvh") -> float:
    """R_est: the grid's estimated time per ray (as the plan corrected it) against the
    calibration's estimate of H."""
    return break_even(s.estimated[kind].build, s.grid_estimate_per_ray, s.estimated[kind].per_ray)


def relative_error(r_est: float, r_c: float) -> float:
    """``100 (R_est - R_C) / R_C`` in percent (the paper's measure).

    Undefined (NaN) when either is infinite: with R_C infinite the measure has no scale,
    and an infinite estimate of a finite R_C is an unbounded error.  ``never_agreement``
    counts those cases apart; ``error_summary`` leaves them out of the sums.
    """
    if math.isinf(r_c) or math.isinf(r_est) or r_c <= 0:
        return math.nan
    return 100.0 * (r_est - r_c) / r_c


def relative_difference(a: float, b: float) -> float:
    """``100 |a - b| / mean(|a|, |b|)`` in percent: how far apart two measurements of one
    quantity are, neither taken as the reference (0 when both are 0)."""
    m = (abs(a) + abs(b)) / 2
    return 100.0 * abs(a - b) / m if m > 0 else 0.0


def constants_apart(a, b, *, stated: bool = True) -> dict[str, float]:
    """Each constant two calibrations fitted and its ``relative_difference``: as the model
    states it (``cost.fit_constants``, ``CountFit.constants``: times at anchor sizes and
    counts, exponents), or with stated=False as the file stores the coefficients
    (``cost.fit_coefficients``, ``CountFit.coefficients``).  A structure whose time per ray
    comes from a count model is compared on that model's constants, not on the per-ray
    fit no estimate reads.  Constants of fits that differ in model, terms, form or
    reference are not comparable and left out."""
    from .cost import fit_coefficients, fit_constants

    out = {}
    if a.model == b.model:
        for k, f in a.fits.items():
            if k in b.fits:
                if stated:
                    per_ray = not (k in a.counts and k in b.counts)
                    ca, cb = (fit_constants(x, a.model, per_ray=per_ray) for x in (f, b.fits[k]))
                else:
                    ca, cb = (fit_coefficients(x, a.model) for x in (f, b.fits[k]))
                out.update({f"{k} {n}": relative_difference(v, cb[n]) for n, v in ca.items() if n in cb})
    for k, f in a.counts.items():
        g = b.counts.get(k)
        if g is not None and (g.terms, g.form, g.refs) == (f.terms, f.form, f.refs):
            ca, cb = (f.constants(), g.constants()) if stated else (f.coefficients(), g.coefficients())
            out.update({f"{k} per ray {n}": relative_difference(v, cb[n]) for n, v in ca.items()})
    return out


def never_agreement(pairs) -> dict:
    """Over (R_est, R_C) pairs: how often both say 'never' (the grid always wins), and how
    often only one of them does (an unbounded error the sums leave out)."""
    both = only_est = only_true = 0
    for r_est, r_c in pairs:
        a, b = math.isinf(r_est), math.isinf(r_c)
        both += a and b
        only_est += a and not b
        only_true += b and not a
    return {"both_never": both, "only_estimate_never": only_est, "only_measured_never": only_true}


def error_summary(errors) -> dict:
    """The paper's sums plus robust figures, over the finite errors (in percent).

    ``undefined`` counts the scenes where R_C or R_est is infinite (see ``never_agreement``).
    """
    e = np.asarray([x for x in errors], np.float64)
    fin = e[np.isfinite(e)]
    a = np.abs(fin)
    out = {"scenes": int(e.size), "defined": int(fin.size), "undefined": int(e.size - fin.size)}
    if fin.size == 0:
        out.update(sum=math.nan, sum_abs=math.nan, mean=math.nan, mean_abs=math.nan, median=math.nan,
                   median_abs=math.nan, max_abs=math.nan, within_10=0, within_25=0)
        return out
    out.update(
        sum=float(fin.sum()), sum_abs=float(a.sum()), mean=float(fin.mean()), mean_abs=float(a.mean()),
        median=float(np.median(fin)), median_abs=float(np.median(a)), max_abs=float(a.max()),
        within_10=int((a <= 10).sum()), within_25=int((a <= 25).sum()),
    )
    return out


# -- strategies over ray counts ----------------------------------------------------------------

def hybrid_choice(s: SceneResult, rays, kinds=("bvh",)) -> np.ndarray:
    """The plan's decision for each ray count (array of names), K samples apart from the
    workload: ``rule.choose`` on the estimated costs."""
    est = {k: (s.estimated[k].build, s.estimated[k].per_ray) for k in kinds if k in s.estimated}
    return choose(rays, s.grid_estimate_per_ray, est, floor=s.floor)


def online_switch(s: SceneResult, kind: str = "bvh", batch: int = 1 << 15) -> float:
    """Rays the grid traces before the online mode switches to ``kind`` (inf: never).

    The switch comes at the first batch boundary where the grid's accumulated trace time
    ``b t_G`` reaches H's estimated build time, and only if H's estimated per-ray time is
    below the grid's (``plan.trace_online``).
    """
    est = s.estimated.get(kind)
    t_g = s.grid.per_ray
    if est is None or not math.isfinite(est.build) or est.per_ray >= t_g or t_g <= 0:
        return math.inf
    batches = max(1, math.ceil(est.build / (t_g * batch) - 1e-12))
    return float(batches * batch)


def chosen_cost(s: SceneResult, choice, rays) -> np.ndarray:
    """True time of the chosen structures on ``rays`` rays, the grid's build excluded (it
    is sunk): ``R t_G`` where the choice is the grid, ``T_B^H + R t_H`` where it is H."""
    r = np.asarray(rays, np.float64)
    out = r * s.grid.per_ray
    for k, c in s.measured.items():
        out = np.where(choice == k, c.total(r), out)
    return out


def hybrid_reuse_choice(s: SceneResult, rays, kinds=("bvh",)) -> np.ndarray:
    """The plan's decision when its K samples are K of the workload's R rays:
    ``rule.choose`` with ``answered=K``."""
    est = {k: (s.estimated[k].build, s.estimated[k].per_ray) for k in kinds if k in s.estimated}
    return choose(rays, s.grid_estimate_per_ray, est, answered=s.samples, floor=s.floor)


def hybrid_totals(s: SceneResult, rays, kinds=("bvh",)) -> dict[str, np.ndarray]:
    """The two hybrids' totals (see the module docstring) and the plan's choices.

    hybrid: K uniform samples apart from the workload, ``T_B^G + e + C(R)``; at most
    ``s.floor`` rays (the calibration's floor on R*) are planned without a sample, ``T_B^G + R t_G``;
    hybrid_reuse: the samples are K of the R rays and the decision weighs the rays left
    (``hybrid_reuse_choice``): ``T_B^G + e' + C(R - K)`` where the choice keeps the
    sample's answers (grid, numpy BVH), ``T_B^G + e' + C(R)`` otherwise; when R <= K the
    grid answers all while planning, ``T_B^G + R t_G``.  C is the true cost of the choice
    (its build included, the grid's sunk) and e' the estimate's cost with workload samples.
    """
    r = np.atleast_1d(np.asarray(rays, np.float64))
    kinds = [k for k in kinds if k in s.measured]
    choice = hybrid_choice(s, r, kinds)
    reuse = hybrid_reuse_choice(s, r, kinds)
    k = float(s.samples)
    e_reuse = s.estimate_time if s.reuse_estimate_time is None else s.reuse_estimate_time
    rest = np.where(np.isin(reuse, REUSES_SAMPLES), np.maximum(r - k, 0.0), r)
    below = r <= s.floor  # the plan keeps the grid without sampling: no estimate to pay for
    return {
        "hybrid": np.where(below, s.grid.total(r), s.grid.build + s.estimate_time + chosen_cost(s, choice, r)),
        "hybrid_reuse": np.where((r <= k) | below, s.grid.total(r), s.grid.build + e_reuse + chosen_cost(s, reuse, rest)),
        "choice": choice,
        "choice_reuse": reuse,
    }


def strategy_totals(s: SceneResult, rays=RAY_COUNTS, kinds=("bvh",), online_kind: str = "bvh",
                    batch: int = 1 << 15) -> dict[str, np.ndarray]:
    """Total time of each strategy for each ray count (see the module docstring)."""
    r = np.atleast_1d(np.asarray(rays, np.float64))
    kinds = [k for k in kinds if k in s.measured]
    out = {"grid": s.grid.total(r)}
    for k in kinds:
        out[k] = s.measured[k].total(r)
    out.update(hybrid_totals(s, r, kinds))
    if online_kind in s.measured:
        sw = online_switch(s, online_kind, batch)
        h = s.measured[online_kind]
        out["online"] = np.where(r <= sw, s.grid.total(r), s.grid.build + sw * s.grid.per_ray + h.build + (r - np.minimum(r, sw)) * h.per_ray)
    out["oracle"] = np.min(np.stack([out["grid"]] + [out[k] for k in kinds]), axis=0)
    return out


def pick_accuracy(scenes, rays=RAY_COUNTS, kind: str = "bvh", differ: float = DIFFER, sunk_grid: bool = True) -> dict:
    """How often the hybrid picks the faster of the grid and ``kind``, over the (scene, R)
    cases where the dearer costs more than ``differ`` over the cheaper.

    sunk_grid=True compares what the hybrid actually decides between once its grid is
    built: ``R t_G`` against ``T_B^H + R t_H``.  False compares the fixed strategies'
    totals (the grid's build included).
    """
    considered = correct = 0
    wrong = []
    for s in scenes:
        if kind not in s.measured:
            continue
        r = np.atleast_1d(np.asarray(rays, np.float64))
        g = s.grid.total(r) if not sunk_grid else r * s.grid.per_ray
        h = s.measured[kind].total(r)
        lo, hi = np.minimum(g, h), np.maximum(g, h)
        clear = hi > (1 + differ) * lo
        faster = np.where(g <= h, "grid", kind)
        picked = hybrid_choice(s, r, (kind,))
        ok = picked == faster
        considered += int(clear.sum())
        correct += int((ok & clear).sum())
        wrong += [(s.name, float(x)) for x in r[clear & ~ok]]
    return {"considered": considered, "correct": correct,
            "percent": 100.0 * correct / considered if considered else math.nan, "wrong": wrong}


def speedup_summary(scenes, rays=RAY_COUNTS, kinds=("bvh",), online_kind: str = "bvh", batch: int = 1 << 15) -> dict:
    """Medians over every (scene, R) case of the time ratios between strategies.

    speedup_vs_X = T_X / T_hybrid (above 1: the hybrid is faster); hybrid_over_oracle =
    T_hybrid / T_oracle (1 is perfect); the reuse_* and hybrid_reuse_* figures likewise for
    the hybrid with samples from the workload; online_over_oracle likewise.
    """
    ratios: dict[str, list] = {}

    def add(key, values):
        ratios.setdefault(key, []).extend(np.asarray(values, np.float64).tolist())

    for s in scenes:
        t = strategy_totals(s, rays, kinds, online_kind, batch)
        add("speedup_vs_grid", t["grid"] / t["hybrid"])
        for k in kinds:
            if k in t:
                add(f"speedup_vs_{k}", t[k] / t["hybrid"])
        for k in ["grid"] + list(kinds):
            if k in t:
                add(f"reuse_speedup_vs_{k}", t[k] / t["hybrid_reuse"])
        add("hybrid_over_oracle", t["hybrid"] / t["oracle"])
        add("hybrid_reuse_over_oracle", t["hybrid_reuse"] / t["oracle"])
        if "online" in t:
            add("online_over_oracle", t["online"] / t["oracle"])
            add("online_over_hybrid", t["online"] / t["hybrid"])
    out = {}
    for k, v in ratios.items():
        a = np.asarray(v)
        out[k] = {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max()),
                  "p90": float(np.percentile(a, 90)), "cases": int(a.size)}
    return out


def estimate_cost_percent(s: SceneResult, rays: float = COST_AT, reuse: bool = False, kinds=("bvh",)) -> float:
    """The estimate's own cost as a percentage of the grid-only total for ``rays`` rays.

    reuse=False: the K uniform samples apart from the workload (``estimate_time``).
    reuse=True: the net cost when the samples come from the workload, the hybrid's total
    less the grid's build and what the chosen structure costs on all ``rays`` rays."""
    if not reuse:
        return 100.0 * s.estimate_time / float(s.grid.total(rays))
    t = hybrid_totals(s, [rays], kinds)
    net = t["hybrid_reuse"][0] - s.grid.build - chosen_cost(s, t["choice"], [rays])[0]
    return 100.0 * float(net) / float(s.grid.total(rays))


def median_per_ray(scenes, kinds=("grid", "bvh")) -> dict:
    """Median over the scenes of each structure's measured time per ray (seconds)."""
    out = {}
    for k in kinds:
        v = [s.grid.per_ray if k == "grid" else s.measured[k].per_ray for s in scenes if k == "grid" or k in s.measured]
        out[k] = float(np.median(v)) if v else math.nan
    return out


def error_components(s: SceneResult, kind: str = "bvh") -> dict:
    """Where an estimate's error comes from, each as ``100 (estimate - truth) / truth``:
    H's build, H's time per ray, and the grid's estimated time per ray (the plan's
    corrected figure); grid_sample: the raw K-sample time's (NaN when unknown)."""
    m, e = s.measured[kind], s.estimated[kind]

    def rel(a, b):
        return 100.0 * (a - b) / b if b > 0 else math.nan

    return {"build": rel(e.build, m.build), "per_ray": rel(e.per_ray, m.per_ray),
            "grid_per_ray": rel(s.grid_estimate_per_ray, s.grid.per_ray),
            "grid_sample": rel(s.grid_sample_per_ray, s.grid.per_ray) if s.grid_sample_per_ray else math.nan}


# -- the grid's estimate ---------------------------------------------------------------------------

def with_grid_estimate(s: SceneResult, per_ray: float, estimate_time: float | None = None) -> SceneResult:
    """``s`` with another estimate of the grid's time per ray (and of the estimate's cost),
    used as it is: e.g. ``with_grid_estimate(s, s.grid_sample_per_ray)`` is the paper's
    uncorrected time / K."""
    return replace(s, estimated=dict(s.estimated), grid_estimate_per_ray=float(per_ray), extra=dict(s.extra),
                   estimate_time=s.estimate_time if estimate_time is None else float(estimate_time))


def sample_ratio(true_per_ray, sample_per_ray) -> dict:
    """How the grid's time per ray on K sample rays relates to a large workload's, over
    scenes: the median of ``true / sample`` and its spread (10th / 90th percentiles).  The
    calibration's ``grid_sample_ratio`` is this on its own scenes; on the evaluated
    scenes it tells whether that correction carries over."""
    ok = [(t, x) for t, x in zip(true_per_ray, sample_per_ray) if t and x and math.isfinite(t) and math.isfinite(x)]
    if not ok:
        return {"median": math.nan, "p10": math.nan, "p90": math.nan, "scenes": 0}
    r = np.asarray([t / x for t, x in ok], np.float64)
    return {"median": float(np.median(r)), "p10": float(np.percentile(r, 10)), "p90": float(np.percentile(r, 90)),
            "scenes": int(r.size)}


# -- calibration model candidates (item 5) -------------------------------------------------------

def _fit_median(records: list[SceneRecord], kind: str, spread) -> KindFit:
    """The paper's form with the median of the per-scene ratios instead of their mean (robust
    to one pathological calibration scene)."""
    have = [r for r in records if kind in r.kinds]
    b = np.array([r.c_B(kind) for r in have])
    t = np.array([r.c_R(kind) for r in have])
    cb, cr = float(np.median(b)), float(np.median(t))
    blo, bhi = (float(x) for x in np.percentile(b, spread))
    tlo, thi = (float(x) for x in np.percentile(t, spread))
    return KindFit(cb, cr, min(blo, cb), max(bhi, cb), min(tlo, cr), max(thi, cr), len(have))


#: refinements evaluated by the report beside calibration.MODELS (same (fit, estimate) form);
#: one moves into calibration.MODELS only when the report shows it helps on held-out scenes
#: ('affine' did: see calibration.MODELS)
CANDIDATE_MODELS = {
    "median": (_fit_median, MODELS["paper"][1]),
}
MODEL_DOCS = {
    "paper": "c_B = mean T_B/(N log2 N), c_R = mean T_R/(M log2 N) (section 3)",
    "median": "the same ratios' medians",
    "affine": "T_B = a_B + c_B N log2 N, t = a_R + c_R log2 N, least squares on relative residuals",
    "power": "T_B = c_B (N log2 N / 2^20)^p_B, t = c_R (log2 N / 16)^p_R, least squares on log times "
             "(c_B, c_R: a 65,536-triangle scene's)",
    "terms": "T_B = a + d (log2 N - 10) + b n + c n (log2 N - 16), n = N / 65,536, coefficients >= 0 by least "
             "squares on relative residuals; t as 'power'",
}


def model_functions(model: str):
    """(fit one kind, estimate) of a calibration model or a candidate."""
    if model in MODELS:
        return MODELS[model]
    if model in CANDIDATE_MODELS:
        return CANDIDATE_MODELS[model]
    raise ValueError(f"unknown model {model!r}; expected one of {', '.join(list(MODELS) + list(CANDIDATE_MODELS))}")


def fit_model(records: list[SceneRecord], kinds, model: str, spread=DEFAULT_SPREAD) -> dict[str, KindFit]:
    fit_one = model_functions(model)[0]
    return {k: fit_one(records, k, tuple(spread)) for k in kinds if any(k in r.kinds for r in records)}


# -- model choice: leave-one-out on the calibration scenes --------------------------------------

def loo_break_even_errors(records: list[SceneRecord], kind: str = "bvh", model: str = "paper") -> list[dict]:
    """Leave each calibration scene out in turn, fit ``model`` on the others, and estimate
    the left-out scene's break-even against its own measured grid: the held-out error of
    the calibration model alone (the grid time is exact here, so only the model errs)."""
    est_fn = model_functions(model)[1]
    out = []
    have = [r for r in records if kind in r.kinds and "grid" in r.kinds]
    for i, rec in enumerate(have):
        rest = [r for j, r in enumerate(have) if j != i]
        if not rest:
            continue
        f = fit_model(rest, (kind,), model)[kind]
        e = est_fn(f, kind, rec.triangles)
        g, h = rec.kinds["grid"], rec.kinds[kind]
        r_c = break_even(h.build_time, g.per_ray, h.per_ray)
        r_est = break_even(e.build, g.per_ray, e.per_ray)
        out.append({"name": rec.name, "triangles": rec.triangles, "R_C": r_c, "R_est": r_est,
                    "error": relative_error(r_est, r_c),
                    "build_error": 100.0 * (e.build - h.build_time) / h.build_time if h.build_time > 0 else math.nan,
                    "per_ray_error": 100.0 * (e.per_ray - h.per_ray) / h.per_ray if h.per_ray > 0 else math.nan})
    return out


def reestimate(s: SceneResult, records: list[SceneRecord], model: str, kinds=("bvh",), keep_per_ray: bool = False) -> SceneResult:
    """``s`` with its estimates recomputed from ``records`` under another calibration model
    (the grid's estimate is kept as it is: only the model changes).  keep_per_ray: change
    only the build estimate (when the per-ray times came from the count models)."""
    est_fn = model_functions(model)[1]
    est = dict(s.estimated)
    for k, f in fit_model(records, kinds, model).items():
        e = est_fn(f, k, s.triangles)
        est[k] = Cost(e.build, s.estimated[k].per_ray if keep_per_ray and k in s.estimated else e.per_ray)
    return replace(s, estimated=est, extra=dict(s.extra))


__all__ = [
    "CANDIDATE_MODELS", "COST_AT", "DIFFER", "MODEL_DOCS", "RAY_COUNTS", "REUSES_SAMPLES", "Cost", "SceneResult",
    "break_even", "chosen_cost", "error_components", "error_summary", "estimate_cost_percent", "estimated_break_even",
    "fit_model", "hybrid_choice", "hybrid_reuse_choice", "hybrid_totals", "log2n", "loo_break_even_errors", "median_per_ray", "model_functions",
    "never_agreement", "nlog2n", "online_switch", "pick_accuracy", "reestimate", "relative_error", "sample_ratio",
    "speedup_summary", "strategy_totals", "true_break_even", "with_grid_estimate",
]


# -- count models: held-out break-even errors (issue 14) ------------------------------------------

def _ratio_of(records, k: int) -> float:
    """Median large-workload / K-sample grid time per ray over ``records`` (as the
    calibration's ``grid_sample_ratio``), 1 when none was measured."""
    from .calfile import Calibration

    return Calibration({}, scenes=list(records)).grid_sample_ratio(k)[0] if records else 1.0


def held_out_errors(train, test, kind: str = "bvh", grid: str = "counts", hds: str = "counts", terms_of=None,
                    model: str = DEFAULT_MODEL, samples: int = DEFAULT_SAMPLES, forms_of=None) -> list[dict]:
    """Fit on ``train`` (SceneRecords), estimate each of ``test`` and compare its break-even
    with the one measured in its own record.

    grid: 'counts' (the count model on the record's work) or 'sample' (its K-sample time
    times the training scenes' ratio, the estimator before issue 14); hds: 'counts' or
    'affine' (a + c log2 N) for the structure's time per ray.  Its build is always the
    calibration model's (``model``)."""
    from .cost import fit_counts

    fits = model_functions(model)[0]
    est_fn = model_functions(model)[1]
    f = fits([r for r in train if kind in r.kinds], kind, DEFAULT_SPREAD)
    counts = fit_counts(train, ("grid", kind), terms_of=terms_of, forms_of=forms_of)
    ratio = _ratio_of(train, samples)
    out = []
    for rec in test:
        if kind not in rec.kinds or "grid" not in rec.kinds:
            continue
        e = est_fn(f, kind, rec.triangles)
        if grid == "counts":
            t_g = counts["grid"].predict(rec.triangles, rec.work)
        else:
            t_g = rec.grid_samples.get(samples, math.nan) * ratio
        t_h = counts[kind].predict(rec.triangles, rec.work) if hds == "counts" else e.per_ray
        g, h = rec.kinds["grid"], rec.kinds[kind]
        r_c, r_est = break_even(h.build_time, g.per_ray, h.per_ray), break_even(e.build, t_g, t_h)
        rel = (lambda a, b: 100.0 * (a - b) / b if b > 0 else math.nan)
        out.append({"name": rec.name, "triangles": rec.triangles, "R_C": r_c, "R_est": r_est,
                    "error": relative_error(r_est, r_c), "grid_error": rel(t_g, g.per_ray),
                    "per_ray_error": rel(t_h, h.per_ray), "build_error": rel(e.build, h.build_time)})
    return out


def leave_one_out(records, **kw) -> list[dict]:
    """``held_out_errors`` with each record left out of the fit in turn."""
    out = []
    for i, rec in enumerate(records):
        out += held_out_errors([r for j, r in enumerate(records) if j != i], [rec], **kw)
    return out
