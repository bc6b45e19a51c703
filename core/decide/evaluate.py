"""The evaluation: the paper's protocol on evaluated scenes, its measuring and its tables.

Hapala, Karlik and Havran (2011), section 4: on each evaluated scene the true break-even
R_C is measured by really building and running both structures, and compared with the
estimate R_est by the relative error ``100 (R_est - R_C) / R_C``; the paper reports the
sum of the errors and the sum of their absolute values, and the median speedup of the
hybrid over always-grid and always-HDS across ray counts.

Two parts.  The measuring of the truths and of the plan's estimate: ``measure_truths``
(and ``truth_jobs``, its jobs for a calibration's passes), ``measure_scene``,
``sweep_scene`` and ``timed_build`` build and trace structures and run ``core.plan``, so
they time things (``truth.measure_break_evens`` does the truths' measuring).
Everything else is arithmetic on the measured (and estimated) numbers as plain floats,
``SceneResult`` and calibration records, with no timing, so the tables are testable on
synthetic timings: the errors, the strategies' totals, the model comparison and its
decision, the summary of an evaluation (``summarise``), the repeatability of plans and
of calibrations.  ``scripts/report.py`` holds the command's arguments, the Markdown and
the plots.

Totals for a ray count R are extrapolated from the measured build times and per-ray
times, ``T_B + R t``, as the paper does: a per-ray time measured on a large batch stands for
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
import statistics
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..factory import build
from ..plan import plan, sample_pays
from ..rays import uniform_rays
from .calfile import Calibration
from .cost import DEFAULT_MODEL, DEFAULT_SPREAD, MODELS, Cost, KindFit, affine_lsq, SceneRecord, break_even, log2n, nlog2n
from .measurements import ONE_THREAD, time_trace
from .truth import break_even_jobs, measure_break_evens
from .rule import REUSES_SAMPLES, choose, settle_bound, unsampled
from .work import DEFAULT_SAMPLES, sample_count

#: the ray counts of the speedup tables: 1e3 to 1e8, four points a decade
RAY_COUNTS = np.logspace(3, 8, 21)
#: "the two structures differ" when the dearer costs more than this fraction over the cheaper
DIFFER = 0.10
#: ray count at which the estimate's own cost is quoted
COST_AT = 1e6


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
    #: {kind: the calibration's ceiling on the break-even against it} (``Calibration.prior``)
    #: and {kind: its estimate for N alone}: above the ceiling of the kind estimated cheapest,
    #: the plan builds no grid and takes that kind (``Plan.grid_built``)
    ceiling: dict = field(default_factory=dict)
    prior_estimated: dict = field(default_factory=dict)
    #: {K: the plan's figures with K samples}, for the smaller samples a plan takes for fewer
    #: expected rays (``work.sample_count``): 'grid_per_ray', 'estimated' ({kind: Cost}),
    #: 'estimate_time' and 'reuse_estimate_time', as the fields of the same names for ``samples``
    at_samples: dict = field(default_factory=dict)
    #: for more rays than ``floor`` and at most these, the plan takes no sample (it would cost
    #: more than SAMPLE_COST_SHARE of the rays' trace: ``plan.sample_pays``) and decides on the
    #: calibration's estimates for N (``prior_estimated``, ``rule.unsampled``); 0: never
    unsampled_below: float = 0.0
    #: whether the mesh is a surface (``TriangleMesh.is_surface``): the plan may then settle
    #: for a structure within ``rule.SETTLE_SLACK`` of the grid without a sample
    surface: bool = False

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
        d["grid"] = Cost.from_dict(d["grid"], "grid")
        d["measured"] = {k: Cost.from_dict(v, k) for k, v in d["measured"].items()}
        d["estimated"] = {k: Cost.from_dict(v, k) for k, v in d["estimated"].items()}
        d["prior_estimated"] = {k: Cost.from_dict(v, k) for k, v in d.get("prior_estimated", {}).items()}
        d["at_samples"] = {int(k): dict(v, estimated={kk: Cost.from_dict(c, kk) for kk, c in v["estimated"].items()})
                           for k, v in d.get("at_samples", {}).items()}
        return cls(**d)

    def at(self, k: int) -> tuple:
        """(grid time per ray, {kind: estimated Cost}, estimate time, reuse estimate time) of
        the plan with ``k`` samples: ``at_samples``' figures, or this result's own for its K."""
        a = self.at_samples.get(int(k))
        if a is None:
            return (self.grid_estimate_per_ray, self.estimated, self.estimate_time,
                    self.estimate_time if self.reuse_estimate_time is None else self.reuse_estimate_time)
        return a["grid_per_ray"], a["estimated"], a["estimate_time"], a["reuse_estimate_time"]

    def samples_for(self, rays) -> np.ndarray:
        """(R,) the samples the plan takes for each ray count (``work.sample_count``)."""
        r = np.atleast_1d(np.asarray(rays, np.float64))
        if not self.samples:  # a plan that took no sample
            return np.zeros(len(r), np.int64)
        return np.array([sample_count(self.samples, x) for x in r], np.int64)


# -- break-even and its error -------------------------------------------------------------------

def true_break_even(s: SceneResult, kind: str = "bvh") -> float:
    """R_C: measured build and per-ray times of both structures."""
    return break_even(s.measured[kind].build_time, s.grid.per_ray, s.measured[kind].per_ray)


def estimated_break_even(s: SceneResult, kind: str = "bvh") -> float:
    """R_est: the grid's estimated time per ray (as the plan corrected it) against the
    calibration's estimate of H."""
    return break_even(s.estimated[kind].build_time, s.grid_estimate_per_ray, s.estimated[kind].per_ray)


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

def _by_samples(s: SceneResult, rays, kinds, reuse: bool) -> np.ndarray:
    """``rule.choose`` for each ray count on the estimates of the plan with the samples it
    takes for that count (``SceneResult.at``); ``reuse``: those samples are of the workload."""
    r = np.atleast_1d(np.asarray(rays, np.float64))
    ks = s.samples_for(r)
    out = np.empty(len(r), dtype=object)
    for k in np.unique(ks).tolist():
        sel = ks == k
        g, estimated, _, _ = s.at(k)
        est = {kk: estimated[kk] for kk in kinds if kk in estimated}
        out[sel] = choose(r[sel], g, est, answered=k if reuse else 0, floor=s.floor)
    u = unsampled_rays(s, r)
    if u.any():
        grid = s.prior_estimated.get("grid")
        est = {kk: s.prior_estimated[kk] for kk in kinds if kk in s.prior_estimated}
        out[u] = choose(r[u], *unsampled(grid, est), floor=s.floor) if grid is not None and est else "grid"
    return out


def unsampled_rays(s: SceneResult, rays) -> np.ndarray:
    """(R,) bool: the ray counts the plan decides for without a sample, on the calibration's
    estimates for N (above the floor, at most ``SceneResult.unsampled_below``)."""
    r = np.atleast_1d(np.asarray(rays, np.float64))
    return (r <= s.unsampled_below) & (r > s.floor)


def hybrid_choice(s: SceneResult, rays, kinds=("bvh",)) -> np.ndarray:
    """The plan's decision for each ray count (array of names), K samples apart from the
    workload: ``rule.choose`` on the estimated costs of the plan with the samples it takes
    for that count."""
    return _by_samples(s, rays, kinds, False)


def online_switch(s: SceneResult, kind: str = "bvh", batch: int = 1 << 15) -> float:
    """Rays the grid traces before the online mode switches to ``kind`` (inf: never).

    The switch comes at the first batch boundary where the grid's accumulated trace time
    ``b t_G`` reaches H's estimated build time, and only if H's estimated per-ray time is
    below the grid's (``plan.trace_online``).
    """
    est = s.estimated.get(kind)
    t_g = s.grid.per_ray
    if est is None or not math.isfinite(est.build_time) or est.per_ray >= t_g or t_g <= 0:
        return math.inf
    batches = max(1, math.ceil(est.build_time / (t_g * batch) - 1e-12))
    return float(batches * batch)


def chosen_cost(s: SceneResult, choice, rays) -> np.ndarray:
    """True time of the chosen structures on ``rays`` rays, the grid's build excluded (it
    is sunk): ``R t_G`` where the choice is the grid, ``T_B^H + R t_H`` where it is H."""
    r = np.asarray(rays, np.float64)
    out = r * s.grid.per_ray
    for k, c in s.measured.items():
        out = np.where(choice == k, c.total_time(r), out)
    return out


def settled_without_grid(s: SceneResult, rays, kinds=("bvh",)) -> tuple[np.ndarray, np.ndarray]:
    """(settled (R,) bool, pick (R,) names): where the plan builds no grid (the rays above
    the calibration's ceiling against the kind its estimate for N alone makes cheapest or,
    on a surface, above the rays from which that kind comes within ``rule.SETTLE_SLACK`` of
    the grid: ``rule.settle_bound``, ``plan._settled_without_grid``) and the kind it takes there."""
    r = np.atleast_1d(np.asarray(rays, np.float64))
    est = {k: s.prior_estimated[k] for k in kinds if k in s.prior_estimated and k in s.measured}
    if not est:
        return np.zeros(len(r), bool), np.full(len(r), "grid", dtype=object)
    names = sorted(est)
    totals = np.stack([est[k].build_time + r * est[k].per_ray for k in names])
    pick = np.asarray(names, dtype=object)[np.argmin(totals, axis=0)]
    grid = s.prior_estimated.get("grid")
    bounds = {k: settle_bound(grid, est[k], s.ceiling.get(k), surface=s.surface) for k in names}
    return r >= np.array([bounds[k] for k in pick], np.float64), pick


def hybrid_reuse_choice(s: SceneResult, rays, kinds=("bvh",)) -> np.ndarray:
    """The plan's decision when its K samples are K of the workload's R rays:
    ``rule.choose`` with ``answered=K``, K the samples it takes for R."""
    return _by_samples(s, rays, kinds, True)


def hybrid_totals(s: SceneResult, rays, kinds=("bvh",)) -> dict[str, np.ndarray]:
    """The two hybrids' totals (see the module docstring) and the plan's choices.

    hybrid: K uniform samples apart from the workload, ``T_B^G + e + C(R)``; at most
    ``s.floor`` rays (the calibration's floor on R*) are planned without a sample, ``T_B^G + R t_G``;
    hybrid_reuse: the samples are K of the R rays and the decision weighs the rays left
    (``hybrid_reuse_choice``): ``T_B^G + e' + C(R - K)`` where the choice keeps the
    sample's answers (grid, numpy BVH), ``T_B^G + e' + C(R)`` otherwise; when R <= K the
    grid answers all while planning, ``T_B^G + R t_G``.  C is the true cost of the choice
    (its build included, the grid's sunk) and e' the estimate's cost with workload samples;
    K, e, e' and the estimates behind each choice are the plan's with the samples it takes
    for R (``work.sample_count``, ``SceneResult.at``).
    Where the calibration alone settles the plan (``settled_without_grid``), both are the
    settled kind's true total, with no grid and no estimate; where a sample would cost too
    much (``unsampled_rays``), ``T_B^G + C(R)`` with the choice made on the calibration's
    estimates for N.
    """
    r = np.atleast_1d(np.asarray(rays, np.float64))
    kinds = [k for k in kinds if k in s.measured]
    choice = hybrid_choice(s, r, kinds)
    reuse = hybrid_reuse_choice(s, r, kinds)
    ks = s.samples_for(r)
    k = ks.astype(np.float64)
    u = unsampled_rays(s, r)  # no sample: no estimate to pay for, no workload rays answered
    e = np.where(u, 0.0, [s.at(x)[2] for x in ks.tolist()])
    e_reuse = np.where(u, 0.0, [s.at(x)[3] for x in ks.tolist()])
    k = np.where(u, 0.0, k)
    rest = np.where(np.isin(reuse, REUSES_SAMPLES), np.maximum(r - k, 0.0), r)
    below = r <= s.floor  # the plan keeps the grid without sampling: no estimate to pay for
    settled, pick = settled_without_grid(s, r, kinds)
    alone = chosen_cost(s, pick, r)  # no grid: the pick's build and rays only
    hybrid = np.where(below, s.grid.total_time(r), s.grid.build_time + e + chosen_cost(s, choice, r))
    hybrid_reuse = np.where(((r <= k) & ~u) | below, s.grid.total_time(r),
                            s.grid.build_time + e_reuse + chosen_cost(s, reuse, rest))
    return {
        "hybrid": np.where(settled, alone, hybrid),
        "hybrid_reuse": np.where(settled, alone, hybrid_reuse),
        "choice": np.where(settled, pick, choice).astype(object),
        "choice_reuse": np.where(settled, pick, reuse).astype(object),
        "settled": settled,
    }


def strategy_totals(s: SceneResult, rays=RAY_COUNTS, kinds=("bvh",), online_kind: str = "bvh",
                    batch: int = 1 << 15) -> dict[str, np.ndarray]:
    """Total time of each strategy for each ray count (see the module docstring)."""
    r = np.atleast_1d(np.asarray(rays, np.float64))
    kinds = [k for k in kinds if k in s.measured]
    out = {"grid": s.grid.total_time(r)}
    for k in kinds:
        out[k] = s.measured[k].total_time(r)
    out.update(hybrid_totals(s, r, kinds))
    if online_kind in s.measured:
        sw = online_switch(s, online_kind, batch)
        h = s.measured[online_kind]
        out["online"] = np.where(r <= sw, s.grid.total_time(r), s.grid.build_time + sw * s.grid.per_ray + h.build_time + (r - np.minimum(r, sw)) * h.per_ray)
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
        g = s.grid.total_time(r) if not sunk_grid else r * s.grid.per_ray
        h = s.measured[kind].total_time(r)
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
        return 100.0 * s.estimate_time / float(s.grid.total_time(rays))
    t = hybrid_totals(s, [rays], kinds)
    net = t["hybrid_reuse"][0] - s.grid.build_time - chosen_cost(s, t["choice"], [rays])[0]
    return 100.0 * float(net) / float(s.grid.total_time(rays))


def interval_coverage(scenes) -> dict:
    """How often the plan's break-even interval against the numpy BVH (``Plan`` break_even_low
    / high, the calibration's spread) holds the measured R_C, and how often its upper end is
    'never' (a cover that says little)."""
    held, open_top, n = 0, 0, 0
    for s in scenes:
        lo, hi = s.extra.get("break_even_low"), s.extra.get("break_even_high")
        if lo is None and hi is None:
            continue
        lo = math.inf if lo is None else float(lo)
        hi = math.inf if hi is None else float(hi)
        rc = true_break_even(s)
        n += 1
        held += int(lo <= rc <= hi)
        open_top += int(not math.isfinite(hi))
    return {"scenes": n, "held": held, "percent": 100.0 * held / n if n else math.nan, "never_above": open_top}


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

    return {"build": rel(e.build_time, m.build_time), "per_ray": rel(e.per_ray, m.per_ray),
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


# -- the compared models ----------------------------------------------------------------------

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


def _estimate_paper(fit: KindFit, kind: str, n: int) -> Cost:
    """T_B ~ c_B N log2 N, t ~ c_R log2 N (section 3)."""
    a, b = nlog2n(n), log2n(n)
    return Cost(kind, fit.c_B * a, fit.c_B_low * a, fit.c_B_high * a, fit.c_R * b, fit.c_R_low * b, fit.c_R_high * b)



def _fit_affine(records: list[SceneRecord], kind: str, spread) -> KindFit:
    """T_B ~ a_B + c_B N log2 N and t ~ a_R + c_R log2 N: the paper's terms plus a fixed
    cost each (per-call overheads that N log2 N cannot carry inflate the ratio on small
    scenes).  The interval scales the slopes by the spread of measured / fitted over the scenes."""
    have = [r for r in records if kind in r.kinds]
    xb, yb = [nlog2n(r.triangles) for r in have], [r.kinds[kind].build_time for r in have]
    xr, yr = [log2n(r.triangles) for r in have], [r.kinds[kind].per_ray for r in have]
    ab, cb = affine_lsq(xb, yb)
    ar, cr = affine_lsq(xr, yr)

    def spread_of(x, y, a, c):
        q = [yi / (a + c * xi) for xi, yi in zip(x, y) if a + c * xi > 0]
        if not q:
            return [1.0, 1.0]
        lo, hi = (float(v) for v in np.percentile(q, spread))
        return [min(lo, 1.0), max(hi, 1.0)]

    qb, qr = spread_of(xb, yb, ab, cb), spread_of(xr, yr, ar, cr)
    return KindFit(cb, cr, cb * qb[0], cb * qb[1], cr * qr[0], cr * qr[1], len(have), extra={"a_B": ab, "a_R": ar})


def _estimate_affine(fit: KindFit, kind: str, n: int) -> Cost:
    """a + c x with the interval on the slope; with no fixed terms (a = 0) this is 'paper'."""
    x, y = nlog2n(n), log2n(n)
    a_b, a_r = fit.extra.get("a_B", 0.0), fit.extra.get("a_R", 0.0)
    return Cost(kind, a_b + fit.c_B * x, a_b + fit.c_B_low * x, a_b + fit.c_B_high * x,
                a_r + fit.c_R * y, a_r + fit.c_R_low * y, a_r + fit.c_R_high * y)



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


#: the models the evaluation compares the shipped ones (``cost.MODELS``) with, in the same
#: (fit, estimate) form: the paper's two constants, their medians, and the paper's terms
#: plus a fixed cost each.  A compared model moves into ``cost.MODELS`` only when the report
#: shows it helps on held-out scenes; a calibration file never names one
COMPARED_MODELS = {
    "paper": (_fit_paper, _estimate_paper),
    "median": (_fit_median, _estimate_paper),
    "affine": (_fit_affine, _estimate_affine),
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
    if model in COMPARED_MODELS:
        return COMPARED_MODELS[model]
    raise ValueError(f"unknown model {model!r}; expected one of {', '.join(list(MODELS) + list(COMPARED_MODELS))}")


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
        r_est = break_even(e.build_time, g.per_ray, e.per_ray)
        out.append({"name": rec.name, "triangles": rec.triangles, "R_C": r_c, "R_est": r_est,
                    "error": relative_error(r_est, r_c),
                    "build_error": 100.0 * (e.build_time - h.build_time) / h.build_time if h.build_time > 0 else math.nan,
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
        est[k] = Cost.point(k, e.build_time, s.estimated[k].per_ray if keep_per_ray and k in s.estimated else e.per_ray)
    return replace(s, estimated=est, extra=dict(s.extra))


# -- count models: held-out break-even errors ------------------------------------------------------

def _ratio_of(records, k: int) -> float:
    """Median large-workload / K-sample grid time per ray over ``records`` (as the
    calibration's ``grid_sample_ratio``), 1 when none was measured."""
    return Calibration({}, scenes=list(records)).grid_sample_ratio(k)[0] if records else 1.0


def held_out_errors(train, test, kind: str = "bvh", grid: str = "counts", hds: str = "counts", terms_of=None,
                    model: str = DEFAULT_MODEL, samples: int = DEFAULT_SAMPLES, forms_of=None) -> list[dict]:
    """Fit on ``train`` (SceneRecords), estimate each of ``test`` and compare its break-even
    with the one measured in its own record.

    grid: 'counts' (the count model on the record's work) or 'sample' (its K-sample time
    times the training scenes' ratio, the estimator before the count models); hds: 'counts' or
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
        r_c, r_est = break_even(h.build_time, g.per_ray, h.per_ray), break_even(e.build_time, t_g, t_h)
        rel = (lambda a, b: 100.0 * (a - b) / b if b > 0 else math.nan)
        out.append({"name": rec.name, "triangles": rec.triangles, "R_C": r_c, "R_est": r_est,
                    "error": relative_error(r_est, r_c), "grid_error": rel(t_g, g.per_ray),
                    "per_ray_error": rel(t_h, h.per_ray), "build_error": rel(e.build_time, h.build_time)})
    return out


def leave_one_out(records, **kw) -> list[dict]:
    """``held_out_errors`` with each record left out of the fit in turn."""
    out = []
    for i, rec in enumerate(records):
        out += held_out_errors([r for j, r in enumerate(records) if j != i], [rec], **kw)
    return out


# -- measuring an evaluated scene: the truths and the plan's estimate (these time things) --------

#: the grid estimates compared: the plan's own (the count model on the sample's work counts;
#: K-sample time x the calibration's ratio for a calibration without one), the K-sample time
#: x the ratio, and the paper's uncorrected time / K
GRID_ESTIMATES = ("plan", "sample x ratio", "uncorrected")


def timed_build(mesh, kind: str, repeats: int, **config):
    """Build ``repeats`` times; the last structure and the median build time."""
    times, acc = [], None
    for _ in range(max(1, repeats)):
        acc = None  # the previous structure goes before the next is built
        acc = build(mesh, kind, **config)
        times.append(acc.build_time)
    return acc, float(statistics.median(times))


def truth_jobs(meshes, kinds, passes: int, *, rays: int, seed: int = 0, progress=None):
    """``measure_truths``' jobs (``break_even_jobs``), to run in a calibration's ``passes``."""
    return break_even_jobs([(mesh, rays) for mesh in meshes], ("grid",) + tuple(kinds), seed=seed, passes=passes,
                           progress=progress)


def measure_truths(meshes, kinds, *, rays: int, repeats: int = 1, quiet: float | None = None, seed: int = 0,
                   progress=None):
    """One BreakEven per mesh (grid and each of ``kinds`` on ``rays`` uniform rays), measured
    in ``repeats`` passes over all the scenes (``measure_break_evens``), as the calibration
    measures its own, so that a slow minute of the machine falls on every scene alike and
    not on the few measured in it.  quiet: ``measure_break_evens``' share of the CPU others
    may take before a round is retaken (None: never)."""
    return measure_break_evens([(mesh, rays) for mesh in meshes], ("grid",) + tuple(kinds), repeats=repeats,
                               quiet=quiet, seed=seed, progress=progress)


def measure_scene(name, group, mesh, cal: Calibration, kinds, be=None, *, rays: int, samples: int = DEFAULT_SAMPLES,
                  seed: int = 0, plan_repeats: int = 1, repeats: int = 1, quiet: float | None = None, progress=None):
    """The plan's estimate against the true costs ``be`` (``measure_truths`` with ``rays``
    and ``seed``; measured here, in ``repeats`` passes, when None): one SceneResult (+ the
    rays, the grid and the structures).

    The plan runs as the add-on runs it, with K = ``samples``: once with K uniform samples
    (its decision and estimates are the SceneResult's), and once given the workload's rays,
    for what the estimate costs when its samples are K of them (``reuse_estimate_time``);
    ``plan_repeats - 1`` more times with other sample rays, for the estimate's
    repeatability."""
    n = mesh.triangle_count
    if be is None:
        be = measure_truths([mesh], kinds, rays=rays, repeats=repeats, quiet=quiet, seed=seed, progress=progress)[0]
    o, d = uniform_rays(mesh, rays, seed=seed)  # the rays the truths traced
    grid, structs = be.structures["grid"], {k: be.structures[k] for k in kinds}
    g_build, g_time = be.measurements["grid"].build_time, be.measurements["grid"].trace_time
    measured = {k: Cost.point(k, be.measurements[k].build_time, be.measurements[k].per_ray, measured=True) for k in kinds}
    rc_halves = be.R_C_repeats
    candidates = ("grid",) + tuple(kinds)
    # prior=False: the estimate is what is evaluated, so it is always made (the floor and the
    # ceiling are priced apart, from the SceneResult's own)
    p = plan(mesh, COST_AT, cal, samples=samples, kinds=candidates, seed=seed + 1, prior=False)
    pw = plan(mesh, COST_AT, cal, rays=(o, d), samples=samples, grid=p.grid, kinds=candidates, seed=seed + 2)
    est = {k: Cost.point(k, c.build_time, c.per_ray) for k, c in p.candidates.items() if k != "grid"}
    ratio, lo, hi = cal.grid_sample_ratio(p.samples)
    # the same plan again with other sample rays: how far the estimate moves between runs
    again = [plan(mesh, COST_AT, cal, samples=samples, grid=p.grid, kinds=candidates, seed=seed + 10 + r)
             for r in range(plan_repeats - 1)]
    # the plans with the fewer samples a plan takes for fewer rays, each as the add-on runs it
    at_samples = {}
    for kk in sorted({sample_count(samples, x) for x in RAY_COUNTS} - {p.samples}):
        q = plan(mesh, COST_AT, cal, samples=kk, grid=p.grid, kinds=candidates, seed=seed + 1, prior=False)
        qw = plan(mesh, COST_AT, cal, rays=(o, d), samples=kk, grid=p.grid, kinds=candidates, seed=seed + 2)
        at_samples[kk] = {"grid_per_ray": q.grid_per_ray, "estimate_time": q.estimate_time,
                          "reuse_estimate_time": qw.estimate_time,
                          "estimated": {k: Cost.point(k, c.build_time, c.per_ray) for k, c in q.candidates.items()
                                        if k != "grid"}}
    s = SceneResult(
        name, n, len(o), Cost.point("grid", g_build, g_time / len(o), measured=True), measured, est, p.grid_per_ray, p.estimate_time,
        p.samples, group, grid_sample_per_ray=p.grid_sample_per_ray, reuse_estimate_time=pw.estimate_time,
        # the hybrid the evaluation runs decides between the grid and the numpy BVH: its floor
        floor=cal.break_even_floor(n, ("bvh",)),
        ceiling=dict(cal.prior(n, kinds).ceiling), at_samples=at_samples,
        prior_estimated={**{k: cal.estimate(k, n) for k in kinds if k in cal.fits},
                         **({"grid": g} if (g := cal.grid_estimate(n)) is not None else {})},
        unsampled_below=max([float(x) for x in RAY_COUNTS if not sample_pays(cal, samples, x)], default=0.0),
        surface=mesh.is_surface(),
        extra={"plan_grid_build": p.grid_build_time, "grid_resolution": [int(x) for x in getattr(grid, "res", [])],
               "plan_break_even": {k: c.break_even for k, c in p.candidates.items() if k != "grid"},
               "break_even_low": p.candidates["bvh"].break_even_low, "break_even_high": p.candidates["bvh"].break_even_high,
               "grid_sample_ratio": [p.grid_sample_ratio, lo, hi], "R_C_repeats": rc_halves,
               "R_C_repeatability": {k: be.repeatability(k) for k in kinds},
               "work": p.work, "plan_repeats": {k: [q.candidates[k].break_even for q in [p] + again] for k in kinds},
               "previous_estimate": {"grid_per_ray": p.grid_sample_per_ray * ratio,
                                     **{k: cal.estimate(k, n).per_ray for k in kinds}},
               "reuse_plan": {"workload_samples": pw.workload_samples, "break_even": pw.candidates["bvh"].break_even,
                              "grid_per_ray": pw.grid_per_ray, "estimate_time": pw.estimate_time},
               "threads": {"grid": grid.threads, **{k: a.threads for k, a in structs.items()}},
               "build_parallelism": {k: [m.build_parallelism for m in be.runs[k]] for k in kinds},
               "measurement_notes": be.notes},
    )
    return s, (o, d), grid, structs


def sweep_scene(s: SceneResult, mesh, rays, cal: Calibration, bvh, *, sweep_rays: int, densities, ks, repeats: int = 1,
                log=None):
    """Speed against error on one scene: for every (grid density, K in ``ks``, repeat), the
    plan's grid estimate, the K-sample time x the calibration's ratio and the uncorrected
    one, against the grid's true time per ray on the first ``sweep_rays`` of ``rays`` (one
    trace per density, outside any interleaved passes); and at density 2 the raw time per
    ray of the grid and of ``bvh`` (a built structure) on K rays.  (rows, batch_rows);
    log(text) is told of each density."""
    o, d = rays[0][:sweep_rays], rays[1][:sweep_rays]
    h = s.measured["bvh"]
    rows, batch_rows = [], []
    for density in densities:
        grid, g_build = timed_build(mesh, "grid", 3, density=density)
        _, g_time = time_trace(grid, o, d)
        t_g = g_time / len(o)
        r_c = break_even(h.build_time, t_g, h.per_ray)
        total = g_build + COST_AT * t_g
        for k in ks:
            for r in range(repeats):
                p = plan(mesh, COST_AT, cal, samples=k, grid=grid, kinds=("grid", "bvh"), seed=1000 * r + k)
                e = p.candidates["bvh"]
                row = {"scene": s.name, "triangles": s.triangles, "density": density, "K": k, "repeat": r,
                       "grid_build": g_build, "grid_per_ray": t_g, "R_C": r_c, "ratio": p.grid_sample_ratio,
                       "measured_ratio": t_g / p.grid_sample_per_ray if p.grid_sample_per_ray > 0 else math.nan}
                row["calibration_ratio"] = cal.grid_sample_ratio(p.samples)[0]
                per = {"plan": p.grid_per_ray, "sample x ratio": p.grid_sample_per_ray * row["calibration_ratio"],
                       "uncorrected": p.grid_sample_per_ray}
                for name, per_ray in per.items():
                    r_est = break_even(e.build_time, per_ray, e.per_ray)
                    row[name] = {"per_ray": per_ray, "R_est": r_est, "error": relative_error(r_est, r_c),
                                 "cost": p.estimate_time, "cost_pct": 100 * p.estimate_time / total}
                rows.append(row)
                if density == 2.0 and r == 0:
                    so, sd = uniform_rays(mesh, k, seed=2000 * r + k + 7)
                    _, tb = time_trace(bvh, so, sd)
                    batch_rows.append({"scene": s.name, "K": k, "grid": p.grid_sample_per_ray, "bvh": tb / k})
        if log is not None:
            log(f"  sweep {s.name}: density {density:g}, grid {t_g * 1e6:.2f} us/ray, R_C {r_c:,.0f}")
        del grid
    batch_rows.append({"scene": s.name, "K": s.rays, "grid": s.grid.per_ray, "bvh": h.per_ray})
    return rows, batch_rows


# -- the grid's estimators ------------------------------------------------------------------------

def grid_sample_ratios(cal: Calibration, ks) -> dict:
    """The grid's small-batch ratio as the calibration holds it (large-workload time per ray
    / time per ray on K sample rays, measured on the calibration scenes, never the
    evaluated ones): per scene at each measured K, and interpolated at every K in ``ks``."""
    ladder = sorted({k for r in cal.scenes for k in r.grid_samples})
    rows = [{"scene": r.name, "triangles": r.triangles, "true": r.kinds["grid"].per_ray,
             "sample": dict(r.grid_samples), "ratio": {k: r.grid_sample_ratio(k) for k in ladder}}
            for r in cal.scenes if "grid" in r.kinds]
    ratios = {}
    for k in ks:
        med, lo, hi = cal.grid_sample_ratio(k)
        ratios[k] = {"median": med, "low": lo, "high": hi, "measured": k in ladder}
    return {"scale": cal.scale, "rays": cal.rays_per_scene, "ladder": ladder, "spread": list(cal.spread),
            "ratios": ratios, "scenes": rows}


def grid_estimators(s: SceneResult) -> dict[str, SceneResult]:
    """The evaluated grid estimators for one scene: name (``GRID_ESTIMATES``) -> SceneResult
    with that estimate.

    'plan' is the SceneResult as measured (the plan's own estimate: the count model when
    the calibration holds one); 'sample x ratio' the estimator without the count models
    (the K-sample time x the calibration's ratio, a + c log2 N per ray for the structures);
    'uncorrected' the raw K-sample time (the paper's time / K), never corrected again."""
    prev = s.extra.get("previous_estimate") or {}
    before = replace(with_grid_estimate(s, prev.get("grid_per_ray", s.grid_estimate_per_ray)), estimated={
        k: Cost.point(k, c.build_time, prev.get(k, c.per_ray)) for k, c in s.estimated.items()})
    return {"plan": s, "sample x ratio": before, "uncorrected": with_grid_estimate(s, s.grid_sample_per_ray)}


# -- the report's text ------------------------------------------------------------------------------

def fnum(x, digits=0, pct=False) -> str:
    """A number for the report's text: pct False plain, True a signed percentage, None a bare
    percentage; None and NaN are 'n/a', an infinite count 'never'."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        if pct is not False:
            return "inf%" if x > 0 else "-inf%"
        return "never" if x > 0 else "-inf"
    if pct is None:  # a bare percentage, no sign
        return f"{x:,.{digits}f}%"
    s = f"{x:+,.{digits}f}" if pct else f"{x:,.{digits}f}"
    return s + ("%" if pct else "")


def median_finite(values) -> float:
    """Median of the finite values (NaN when there are none; None is left out)."""
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def median_abs(values) -> float:
    """Median of the finite absolute values (NaN when there are none)."""
    return median_finite([abs(x) for x in values if x is not None])


# -- the models compared on the evaluated scenes ---------------------------------------------------

def model_comparison(scenes, cal: Calibration) -> dict:
    """Held-out break-even error of each calibration model (``MODELS`` and
    ``COMPARED_MODELS``) with each grid estimate (``GRID_ESTIMATES``): leave-one-out on the
    calibration scenes, and the evaluated ``scenes`` re-estimated from all of them."""
    out = {}
    names = list(dict.fromkeys(list(MODELS) + list(COMPARED_MODELS)))
    for m in names:
        loo = loo_break_even_errors(cal.scenes, "bvh", m)
        held = [reestimate(s, cal.scenes, m, keep_per_ray=bool(cal.counts)) for s in scenes]
        comps = [error_components(s) for s in held]
        entry = {
            "loo": error_summary([x["error"] for x in loo]), "loo_scenes": loo,
            "loo_never": never_agreement([(x["R_est"], x["R_C"]) for x in loo]),
            "loo_build_mabs": median_abs([x["build_error"] for x in loo]),
            "loo_per_ray_mabs": median_abs([x["per_ray_error"] for x in loo]),
            "held_out_build_mabs": median_abs([c["build"] for c in comps]),
            "held_out_per_ray_mabs": median_abs([c["per_ray"] for c in comps]),
            "grid": {},
        }
        for est_name in GRID_ESTIMATES:
            variant = [grid_estimators(s)[est_name] for s in held]
            errs = [relative_error(estimated_break_even(s), true_break_even(s)) for s in variant]
            sp = speedup_summary(variant)
            entry["grid"][est_name] = {
                "held_out": error_summary(errs), "errors": {s.name: e for s, e in zip(variant, errs)},
                "never": never_agreement([(estimated_break_even(s), true_break_even(s)) for s in variant]),
                "picks": pick_accuracy(variant),
                "hybrid_over_oracle": sp.get("hybrid_over_oracle", {}).get("median", math.nan),
                "hybrid_reuse_over_oracle": sp.get("hybrid_reuse_over_oracle", {}).get("median", math.nan),
            }
        out[m] = entry
    return out


def decide_model(models, current: str, default: str) -> tuple[str, str]:
    """(model, text): under the plan's own grid estimate, the model with the lowest held-out
    break-even error on the evaluated meshes among those that do not worsen the paper's
    leave-one-out error on the calibration scenes (the paper's model when none beats it).
    models: ``model_comparison``'s; current: the model the evaluated calibration is fitted
    with; default: the package's."""
    def err(m, g="plan"):
        return models[m]["grid"][g]["held_out"]["median_abs"]

    def loo(m):
        return models[m]["loo"]["median_abs"]

    lines = ["Median absolute break-even error with the plan's grid estimate (the count model on the sample's "
             "work counts), evaluated meshes / leave-one-out on the calibration scenes: "
             + ", ".join(f"{m} {fnum(err(m), 1, None)} / {fnum(loo(m), 1, None)}" for m in models) + "."]
    lines.append("With the uncorrected sample (time / K, the paper's method) instead, on the evaluated meshes: "
                 + ", ".join(f"{m} {fnum(err(m, 'uncorrected'), 1, None)}" for m in models) + ".")
    ok = [m for m in models if m != "paper" and math.isfinite(err(m)) and err(m) < err("paper")
          and loo(m) <= loo("paper")]
    best = min(ok, key=err) if ok else "paper"
    if ok:
        lines.append(f"Lowest held-out error without a worse leave-one-out error than the paper's: **{best}**.")
    else:
        lines.append("No model cuts the paper's error on the evaluated meshes without a worse leave-one-out error: "
                     "**paper**.")
    where = f"the calibration used here is fitted with '{current}'" + ("" if current == default else
                                                                       f" (the package default is '{default}')")
    lines.append(f"`core.decide.DEFAULT_MODEL` is '{default}'; {where}; "
                 + ("the evaluation agrees with the default." if best == default else
                    f"the evaluation favours '{best}' over it."))
    return best, " ".join(lines)


# -- speed against error: the sweep's tables and the defaults ---------------------------------------

def sweep_table(rows, estimator: str) -> list[dict]:
    """Median |error| and median cost per (density, K) over the sweep scenes and repeats
    (``sweep_scene``'s rows) for one of ``GRID_ESTIMATES``, with the calibration's ratio at
    K and the ratio the sweep measured (true / sample)."""
    cells = {}
    for r in rows:
        cells.setdefault((r["density"], r["K"]), []).append(r)
    out = []
    for (dens, k), rs in sorted(cells.items()):
        errs = [r[estimator]["error"] for r in rs]
        fin = [x for x in errs if x is not None and math.isfinite(x)]
        out.append({"density": dens, "K": k, "median_abs_error": float(np.median(np.abs(fin))) if fin else math.nan,
                    "median_error": float(np.median(fin)) if fin else math.nan, "undefined": len(rs) - len(fin),
                    "median_cost_pct": float(np.median([r[estimator]["cost_pct"] for r in rs])),
                    "max_cost_pct": float(np.max([r[estimator]["cost_pct"] for r in rs])), "cases": len(rs),
                    "ratio": float(np.median([r["ratio"] for r in rs])),
                    "measured_ratio": median_finite([r["measured_ratio"] for r in rs])})
    return out


def choose_defaults(table, goal_cost=5.0):
    """The cheapest (density, K) whose worst-scene cost stays under the goal and whose error is
    within 2 points of the best such; returns (row, reason)."""
    ok = [r for r in table if r["max_cost_pct"] < goal_cost and math.isfinite(r["median_abs_error"])]
    if not ok:
        return None, "no configuration keeps the estimate's cost under the goal on every sweep scene"
    best = min(r["median_abs_error"] for r in ok)
    near = [r for r in ok if r["median_abs_error"] <= best + 2.0]
    pick = min(near, key=lambda r: r["median_cost_pct"])
    return pick, (f"lowest median |error| among configurations whose cost stays under {goal_cost:g}% of the "
                  f"grid-only total at 1e6 rays on every sweep scene is {fnum(best, 1)}%; the cheapest within 2 points "
                  f"of it is density {pick['density']:g}, K = {pick['K']:,}")


def sweep_summary(rows, batch_rows, scene_order, model: str) -> dict:
    """The sweep's part of the report from ``sweep_scene``'s rows and batch rows: its scenes
    (in the order of ``scene_order``, names), a table per grid estimator, the defaults each
    recommends, and the text comparing them with the plan's (``DEFAULT_SAMPLES`` at density
    2); model: the calibration's build model, for the text."""
    tables = {est: sweep_table(rows, est) for est in GRID_ESTIMATES}
    picks = {est: choose_defaults(t) for est, t in tables.items()}
    pick = picks["plan"][0]
    text = (f"With the plan's estimate ({model} build model, the count model's time per ray): "
            f"{picks['plan'][1]}. With the uncorrected sample instead: {picks['uncorrected'][1]}. "
            f"The plan's default is K = {DEFAULT_SAMPLES:,} at density 2 (`core.plan.DEFAULT_SAMPLES`)")
    if pick is not None:
        here = {(r["density"], r["K"]): r for r in tables["plan"]}.get((2.0, DEFAULT_SAMPLES))
        text += ("; " + (f"it gives {fnum(here['median_abs_error'], 1, None)} at {fnum(here['median_cost_pct'], 2, None)} "
                         f"median cost" if here else "it is not in this sweep")
                 + (f"; the sweep recommends density {pick['density']:g}, K = {pick['K']:,}." if
                    (pick["density"], pick["K"]) != (2.0, DEFAULT_SAMPLES) else "; the sweep agrees with it."))
    else:
        text += "."
    order = list(scene_order)
    return {"scenes": sorted({r["scene"] for r in rows}, key=order.index), "rows": rows, "tables": tables,
            "batch": batch_rows, "choice": {"picks": {est: p for est, (p, _) in picks.items()}, "text": text}}


# -- repeatability: of the plan, of the calibration -----------------------------------------------

def plan_repeatability(scenes, kind: str = "bvh") -> dict:
    """max / min of each scene's break-evens over the repeated plan() runs (one calibration)."""
    r = []
    for s in scenes:
        v = [x for x in s.extra.get("plan_repeats", {}).get(kind, []) if x is not None and math.isfinite(x)]
        if len(v) >= 2:
            r.append(max(v) / min(v))
    return {"median": median_finite(r), "max": max(r, default=math.nan), "within_1_2": sum(x <= 1.2 for x in r),
            "scenes": len(r), "runs": max((len(s.extra.get("plan_repeats", {}).get(kind, [])) for s in scenes), default=0)}


def calibration_repeatability(cal: Calibration, cal2: Calibration, scenes) -> dict:
    """How two calibrations in a row differ: each constant's relative difference
    |a - b| / mean, as the model states them (``constants_apart``: builds at
    ``cost.BUILD_ANCHORS``, per-ray times at ``cost.COUNT_ANCHORS``) and as the file stores
    the coefficients, and (what a plan uses) the per-ray times they predict on the
    evaluated scenes' own work counts and the break-evens they give."""
    rel = relative_difference
    consts = constants_apart(cal, cal2)
    preds, bes = {}, []
    for s in scenes:
        w = s.extra.get("work")
        for k in cal.counts:
            a, b = cal.count_per_ray(k, s.triangles, w or {}), cal2.count_per_ray(k, s.triangles, w or {})
            if a and b:
                preds.setdefault(k, []).append(rel(a[0], b[0]))
        if w and "grid" in cal.counts and "bvh" in cal.counts:
            r = [break_even(c.estimate("bvh", s.triangles).build_time, c.count_per_ray("grid", s.triangles, w)[0],
                            c.count_per_ray("bvh", s.triangles, w)[0]) for c in (cal, cal2)]
            if all(math.isfinite(x) for x in r):
                bes.append(max(r) / min(r))
    coefs = constants_apart(cal, cal2, stated=False)
    return {"constants": consts, "large_builds": large_builds(cal, cal2), "max_constant": max(consts.values(), default=math.nan),
            "median_constant": median_finite(list(consts.values())),
            "coefficients": coefs, "max_coefficient": max(coefs.values(), default=math.nan),
            "median_coefficient": median_finite(list(coefs.values())),
            "per_ray": {k: {"median": median_finite(v), "max": max(v)} for k, v in preds.items()},
            "break_even_ratio": {"median": median_finite(bes), "max": max(bes, default=math.nan), "scenes": len(bes)}}


#: the calibration scenes whose builds the two-calibrations table lists (the large builds
#: the build constants at 262,144 and 1,048,576 triangles come from)
LARGE_BUILD = 262_144


def large_builds(cal: Calibration, cal2: Calibration) -> list[dict]:
    """Each structure's build on the calibration scenes of at least ``LARGE_BUILD``
    triangles in both calibrations: median time, page faults and system seconds (None
    where a file does not have them), so the report can say how much of a build
    constant's difference is the kernel's."""
    second = {r.name: r for r in cal2.scenes}
    rows = []
    for r in cal.scenes:
        r2 = second.get(r.name)
        if r2 is None or r.triangles < LARGE_BUILD:
            continue
        for k, m in r.kinds.items():
            m2 = r2.kinds.get(k)
            if m2 is not None:
                rows.append({"scene": r.name, "triangles": r.triangles, "kind": k,
                             "build": [m.build_time, m2.build_time], "faults": [m.build_faults, m2.build_faults],
                             "system": [m.build_system, m2.build_system]})
    return rows


def calibration_parallelism(cal, kind: str) -> list:
    """The calibration's builds of ``kind``: each pass's threads busy where the file keeps its
    passes (``SceneRecord.passes``), else each scene's median build over its median CPU time."""
    return [m.build_parallelism for r in cal.scenes
            for m in (r.passes.get(kind) or ([r.kinds[kind]] if kind in r.kinds else []))]


def parallelism_summary(values) -> dict:
    """Builds' CPU seconds per second (``Measurement.build_parallelism``): their median, how
    many there are and the share that kept about one thread busy (below ONE_THREAD)."""
    v = [float(x) for x in values if x is not None and math.isfinite(x)]
    return {"builds": len(v), "median": float(np.median(v)) if v else math.nan,
            "one_thread_share": sum(x < ONE_THREAD for x in v) / len(v) if v else math.nan}


# -- count models on the calibration scenes --------------------------------------------------------

#: count models compared by held-out error: (grid estimate, structure's per ray, grid terms,
#: structure terms, grid form, structure form); forms as ``cost.CountFit.form``
COUNT_VARIANTS = [
    ("sample x ratio", "affine log2n", None, None, "linear", "linear"),
    ("counts: cells", "affine log2n", ("1", "cells"), None, "linear", "linear"),
    ("counts: cells, refs", "affine log2n", ("1", "cells", "refs"), None, "linear", "linear"),
    ("sample x ratio", "counts: log2n", None, ("1", "log2n"), "linear", "linear"),
    ("counts: cells", "counts: log2n", ("1", "cells"), ("1", "log2n"), "linear", "linear"),
    ("counts: steps, candidates", "counts: log2n", ("1", "steps", "candidates"), ("1", "log2n"), "linear", "linear"),
    ("counts: steps, candidates, tests", "counts: log2n", ("1", "steps", "candidates", "tests"), ("1", "log2n"),
     "linear", "linear"),
    ("counts: cells", "counts: log2n, hit, length", ("1", "cells"), ("1", "log2n", "hit_log2n", "length_log2n"), "linear", "linear"),
    ("counts: cells", "counts: log2n, cells, refs", ("1", "cells"), ("1", "log2n", "cells", "refs"), "linear", "linear"),
    ("counts: cells, refs", "counts: log2n, cells, refs", ("1", "cells", "refs"), ("1", "log2n", "cells", "refs"), "linear", "linear"),
    ("log counts: cells", "counts: log2n, cells, refs", ("1", "cells"), ("1", "log2n", "cells", "refs"), "log", "linear"),
    ("log counts: cells", "log counts: log2n, refs", ("1", "cells"), ("1", "log2n", "refs"), "log", "log"),
    ("log counts: cells", "log counts: log2n", ("1", "cells"), ("1", "log2n"), "log", "log"),
]


def count_comparison(cal: Calibration, kind: str = "bvh", samples: int = DEFAULT_SAMPLES) -> list[dict]:
    """Leave-one-out over the calibration scenes of each count-model variant
    (``COUNT_VARIANTS``): the held-out break-even error and the per-ray errors of the grid
    and of ``kind``."""
    rows = []
    for gname, hname, gt, ht, gf, hf in COUNT_VARIANTS:
        kw = dict(kind=kind, grid="sample" if gt is None else "counts", hds="affine" if ht is None else "counts",
                  terms_of={"grid": gt or ("1", "cells", "refs"), kind: ht or ("1", "log2n")},
                  forms_of={"grid": gf, kind: hf}, samples=samples, model=cal.model)
        loo = leave_one_out([r for r in cal.scenes if r.work], **kw)
        rows.append({"grid": gname, "per_ray": hname, "loo": median_abs([x["error"] for x in loo]),
                     "grid_error": median_abs([x["grid_error"] for x in loo]),
                     "per_ray_error": median_abs([x["per_ray_error"] for x in loo]),
                     "undefined": sum(not math.isfinite(x["error"]) for x in loo), "scenes": len(loo)})
    return rows


# -- the evaluation's summary -----------------------------------------------------------------------

def calls_of_1000(scenes, kind: str = "bvh") -> dict:
    """A workload arriving as calls of 1,000 rays (a script calling ``api.cast`` in a loop):
    the ski-rental rule counting the grid time of all calls so far (``online`` with
    batches of 1,000) against the oracle, and a plan per call that forgets the calls before
    it (1,000 rays never pay for a build: the grid every time)."""
    on, per_call = [], []
    for s in scenes:
        t = strategy_totals(s, RAY_COUNTS, (kind,), kind, batch=1000)
        on += list(t["online"] / t["oracle"])
        per_call += list(t["grid"] / t["oracle"])
    return {"online_over_oracle": {"median": median_finite(on), "max": max(on, default=math.nan)},
            "per_call_over_oracle": {"median": median_finite(per_call), "max": max(per_call, default=math.nan)}}


def summarise(scenes, kinds) -> dict:
    """The tables of the evaluation, for ``scenes`` (SceneResults) as estimated: errors
    (overall, by group, on the scenes whose R_C is repeatable), speedups over
    ``RAY_COUNTS``, picks, the estimate's cost, repeatability, and with Embree among
    ``kinds`` its own errors and builds."""
    errs = [relative_error(estimated_break_even(s), true_break_even(s)) for s in scenes]
    by_group = {}
    for g in sorted({s.group for s in scenes}):
        by_group[g] = error_summary([e for s, e in zip(scenes, errs) if s.group == g])
    rows, wasted = [], 0
    for r in RAY_COUNTS:
        per = [strategy_totals(s, [r], ("bvh",)) for s in scenes]
        wasted += sum(int(r <= s.samples_for([r])[0] and t["choice_reuse"][0] != "grid") for s, t in zip(scenes, per))
        rows.append({"R": float(r),
                     "grid": median_finite([t["grid"][0] / t["hybrid"][0] for t in per]),
                     "bvh": median_finite([t["bvh"][0] / t["hybrid"][0] for t in per]),
                     "hybrid_oracle": median_finite([t["hybrid"][0] / t["oracle"][0] for t in per]),
                     "reuse_oracle": median_finite([t["hybrid_reuse"][0] / t["oracle"][0] for t in per]),
                     "online_oracle": median_finite([t["online"][0] / t["oracle"][0] for t in per]),
                     "bvh_share": float(np.mean([t["choice"][0] == "bvh" for t in per])) if per else math.nan})
    costs = [estimate_cost_percent(s) for s in scenes]
    reuse_costs = [estimate_cost_percent(s, reuse=True) for s in scenes]
    imax = int(np.argmax(costs)) if costs else 0
    spreads, steady = [], []
    for s, e in zip(scenes, errs):
        spread = s.extra.get("R_C_repeatability", {}).get("bvh", math.nan)
        if spread is not None and math.isfinite(spread):
            spreads.append(spread)
            if spread <= 25:
                steady.append(e)
    out = {
        "errors": error_summary(errs), "errors_by_group": by_group,
        "never": never_agreement([(estimated_break_even(s), true_break_even(s)) for s in scenes]),
        "median_per_ray": median_per_ray(scenes, ("grid",) + tuple(kinds)),
        "speedups": speedup_summary(scenes, RAY_COUNTS, ("bvh",)),
        "picks": pick_accuracy(scenes), "picks_total": pick_accuracy(scenes, sunk_grid=False),
        "interval_coverage": interval_coverage(scenes),
        "by_ray_count": rows, "wasted_builds": {"cases": wasted, "of": len(scenes) * len(RAY_COUNTS)},
        "rc_repeatability": ({"median": float(np.median(spreads)), "max": float(np.max(spreads)), "scenes": len(spreads)}
                             if spreads else None),
        "errors_repeatable": error_summary(steady),
        "plan_repeatability": {k: plan_repeatability(scenes, k) for k in kinds},
        "calls_1000": calls_of_1000(scenes),
        "evaluated_ratio": sample_ratio([s.grid.per_ray for s in scenes], [s.grid_sample_per_ray for s in scenes]),
        "estimate_cost": {"median": median_finite(costs), "max": costs[imax] if costs else math.nan,
                          "max_scene": scenes[imax].name if scenes else "-",
                          "reuse_median": median_finite(reuse_costs), "reuse_max": max(reuse_costs, default=math.nan),
                          "per_scene": {s.name: c for s, c in zip(scenes, costs)},
                          "reuse_per_scene": {s.name: c for s, c in zip(scenes, reuse_costs)}},
    }
    if "embree" in kinds:
        em = []
        for s in scenes:
            rc = true_break_even(s, "embree")
            re_ = estimated_break_even(s, "embree")
            par = [x for x in s.extra.get("build_parallelism", {}).get("embree", []) if x is not None]
            em.append({"name": s.name, "triangles": s.triangles, "build": s.measured["embree"].build_time,
                       "build_est": s.estimated["embree"].build_time,
                       "build_error": error_components(s, "embree")["build"],
                       "per_ray": s.measured["embree"].per_ray, "R_C": rc, "R_est": re_, "error": relative_error(re_, rc),
                       "parallelism": par})
        out["embree"] = {"scenes": em, "errors": error_summary([x["error"] for x in em]),
                         "speedups": speedup_summary(scenes, RAY_COUNTS, ("bvh", "embree")),
                         "parallelism": parallelism_summary([x for r in em for x in r["parallelism"]])}
    return out


def scene_rows(scenes) -> list[dict]:
    """Each SceneResult as a dict with its R_C, R_est, error and error components."""
    return [dict(s.to_dict(), R_C=true_break_even(s), R_est=estimated_break_even(s),
                 error=relative_error(estimated_break_even(s), true_break_even(s)),
                 components=error_components(s)) for s in scenes]


__all__ = [
    "COMPARED_MODELS", "COST_AT", "COUNT_VARIANTS", "DIFFER", "GRID_ESTIMATES", "LARGE_BUILD", "MODEL_DOCS",
    "RAY_COUNTS", "REUSES_SAMPLES", "SceneResult",
    "break_even", "calibration_parallelism", "calibration_repeatability", "calls_of_1000", "choose_defaults",
    "chosen_cost", "constants_apart", "count_comparison", "decide_model", "error_components", "error_summary",
    "estimate_cost_percent", "estimated_break_even", "fit_model", "fnum", "grid_estimators", "grid_sample_ratios",
    "held_out_errors", "hybrid_choice", "interval_coverage", "unsampled_rays", "hybrid_reuse_choice", "hybrid_totals", "large_builds", "leave_one_out",
    "log2n", "loo_break_even_errors", "measure_scene", "measure_truths", "median_abs", "median_finite",
    "median_per_ray", "model_comparison", "model_functions", "never_agreement", "nlog2n", "online_switch",
    "parallelism_summary", "pick_accuracy", "plan_repeatability", "reestimate", "relative_difference",
    "relative_error", "sample_ratio", "scene_rows", "speedup_summary", "strategy_totals", "summarise",
    "sweep_scene", "sweep_summary", "sweep_table", "timed_build", "true_break_even", "truth_jobs",
    "with_grid_estimate",
]
