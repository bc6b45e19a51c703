"""The hybrid decision: grid or a hierarchical structure, for this scene and ray budget.

Hapala, Karlik and Havran (2011), section 3 ("application"), as this module runs it:
  1. build the uniform grid, timed (T_B^G);
  2. trace K representative rays through it and take their work counts
     (``decide.work.grid_work``: the cells each ray crosses, whether it hits, and the
     grid traversal's own lockstep steps and candidate pairs);
  3. estimate from those counts, with the calibration's count models
     (``Calibration.count_per_ray``), the grid's time per ray t_G and each hierarchical
     structure H's t_H, and H's build T_B^H from the calibration's fitted build model
     (``Calibration.estimate``; by default 'terms': a sum of costs in N for the numpy BVH,
     a quadratic in log-log for Embree, ``decide.cost``).  A structure without a count
     model takes t_H from the fitted model too;
  4. the grid is built already (a sunk cost), so H pays for itself after
     R*_H = T_B^H / (t_G - t_H) rays when t_G > t_H, never otherwise (R* = inf);
  5. keep the grid for R <= R*, else build and use H.
A calibration without count models (files made before them) falls back on the sample's
time: t_G is the K rays' measured time per ray times the calibration's small-batch ratio
(a K-ray batch pays the lockstep traversal's fixed per-step cost over few rays, see
``Calibration.grid_sample_ratio``), and each H's T_B^H and t_H come from the fitted model
alone (the paper's T_B^H ~ c_B N log2 N and t_H ~ c_R log2 N, as ``decide.cost`` refines them).
With several candidates (numpy BVH, Embree) the grid stays cheapest exactly while
R <= min_H R*_H, and beyond that the candidate with the least T_B^H + R t_H wins.  The
calibration's spread gives each R* an interval: R*_low uses the low constants (cheap
build, fast rays) and the high end of the grid's time per ray, R*_high the opposite, so
R*_low <= R* <= R*_high.

When the workload's own rays are given, the K sample rays are drawn from them and their
answers kept: ``Plan.trace`` on those same arrays traces only the other rays (with the
grid or the numpy BVH, which agree bit for bit; Embree retraces everything), and the
decision weighs only the rays left.  A workload of at most K rays is therefore answered
whole while planning, and the plan keeps the grid: nothing is left to build for.

K is the ``samples`` asked for, cut to SAMPLE_SHARE of the expected rays (never below
SAMPLE_MIN, ``work.sample_count``).  Before any sample, the calibration alone bounds R*
from below (``Calibration.prior``: the lowest build over the largest gain per ray of any
calibration scene, halved): for fewer expected rays the grid wins whatever a sample would
say, so the plan takes none.  Above that floor, a sample that would cost more than
SAMPLE_COST_SHARE of the workload's own grid trace (``sample_pays``) is not taken either:
the calibration's estimates for N decide (``rule.unsampled``), leaning to the grid.

Online mode (``trace_online``), which needs no ray count: trace with the grid in batches
and switch to H once the grid's accumulated trace time reaches H's estimated build
time, the ski-rental rule (Karlin et al. 1988), which is never worse than about twice
the best fixed choice in hindsight.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from .accel import Accel
from .factory import available_kinds, build, unavailable_reason
from .decide.calfile import Calibration, load_default
from .decide.cost import Cost, break_even
from .decide.measurements import time_trace
from .decide.rule import REUSES_SAMPLES, SETTLE_SLACK, choose, settle_bound, unsampled
from .decide.work import SAMPLE_COST_SHARE, DEFAULT_SAMPLES, grid_work, sample_count, traversal_counts
from .hits import Hits
from .mesh import TriangleMesh

#: default rays per batch in the online mode
DEFAULT_BATCH = 1 << 15


#: ``Plan.no_sample``'s words
NO_SAMPLE_FLOOR = "too few rays for any structure to pay back its build"
NO_SAMPLE_DEAR = (f"a sample would cost more than {SAMPLE_COST_SHARE:.0%} of the rays' trace: the calibration's "
                  f"estimates decided")


def _check_expected(expected_rays) -> float:
    try:
        r = float(expected_rays)
    except (TypeError, ValueError):
        raise ValueError(f"expected_rays must be a number of rays, got {expected_rays!r}") from None
    if not r > 0 or not math.isfinite(r):
        raise ValueError(f"expected_rays must be a positive finite number of rays, got {expected_rays!r}")
    return r


def _json_float(x):
    """inf (and NaN) as None: JSON has no infinity; null in a break-even means 'never'."""
    return float(x) if x is not None and math.isfinite(x) else None


@dataclass
class Plan:
    """Everything the decision used and decided.  Times in seconds.

    decision: 'GRID', 'BVH' or 'EMBREE'.
    break_even: the ray count up to which the grid is cheapest (min over the candidates
    of their R*), with its interval and the candidate that attains it; inf when no
    candidate ever beats the grid.
    estimate_time: what the estimate itself cost beyond the grid build: tracing the K
    sample rays plus the arithmetic.  plan_time: the whole ``plan()`` call (grid build,
    samples, arithmetic).
    """

    triangles: int
    expected_rays: float
    samples: int
    grid_build_time: float
    grid_per_ray: float
    candidates: dict[str, Cost]
    break_even: float
    break_even_low: float
    break_even_high: float
    break_even_kind: str | None
    decision: str
    certain: bool
    #: the grid's time per ray on the K samples, and the small-batch ratio applied to it
    #: (with count models, the ratio of their estimate to the sample's time)
    grid_sample_per_ray: float = 0.0
    grid_sample_ratio: float = 1.0
    #: the grid sample's per-ray work counts (``decide.work.Work`` as a dict) when the
    #: calibration's count model made the estimate, else None
    work: dict | None = None
    #: the counts the grid's count model weighed (its terms but '1', e.g. ('steps',
    #: 'candidates')) when it made the estimate, else (): which of ``work`` a reader quotes
    grid_terms: tuple = ()
    #: sample rays that came from the workload and whose answers the plan keeps
    workload_samples: int = 0
    #: the calibration's lower bound on the break-even (0: none); a plan for fewer rays
    #: keeps the grid without sampling (``Calibration.prior``)
    break_even_floor: float = 0.0
    #: False when the calibration alone settled the plan for a hierarchical structure
    #: (the expected rays above ``break_even_ceiling``): no grid built, no sample traced,
    #: and the grid's figures are the calibration's bound, not a measurement
    grid_built: bool = True
    #: the rays from which the calibration alone settled the plan (inf: the plan measured the
    #: grid): its upper bound on the break-even against the structure it settled for, or,
    #: where ``settled_slack`` > 0, the rays from which building that structure at once costs
    #: at most that share more than building the grid (``rule.regret_bound``)
    break_even_ceiling: float = math.inf
    #: 0, or ``rule.SETTLE_SLACK`` when the plan settled for a structure that may lose to the
    #: grid by at most that share of the grid's total (a surface mesh; no bound on the
    #: break-even above the floor)
    settled_slack: float = 0.0
    #: words when the break-even is ill-conditioned (``conditioning``), else ''
    ill_conditioned: str = ""
    #: why a plan that built the grid traced no sample ('' when it did): NO_SAMPLE_FLOOR or NO_SAMPLE_DEAR
    no_sample: str = ""
    estimate_time: float = 0.0
    plan_time: float = 0.0
    grid_reused: bool = False
    calibration_source: str = ""
    notes: list[str] = field(default_factory=list)
    #: candidates asked for but left out, {kind: one-line reason} (embreex missing, no
    #: calibration constants); the candidates that exist are the keys of ``candidates``
    unavailable: dict = field(default_factory=dict)
    #: what ``trace`` did: kind, build_time (0 for a reused grid), trace_time, rays
    executed: list[dict] = field(default_factory=list)
    # not serialised: the objects the plan traces with
    grid: Accel | None = field(default=None, repr=False)
    mesh: TriangleMesh | None = field(default=None, repr=False)
    configs: dict = field(default_factory=dict, repr=False)
    structure: Accel | None = field(default=None, repr=False)
    #: (origins, directions, sample indices, their Hits) when the samples came from the workload
    sample: tuple | None = field(default=None, repr=False)

    @property
    def chosen(self) -> str:
        return self.decision.lower()

    def total_time(self, kind: str, rays, bound: str = "point", include_grid_build: bool = False):
        """Predicted time to shoot ``rays`` rays with ``kind``: R t_G for the grid (its build
        is sunk unless ``include_grid_build``), T_B + R t for the others."""
        c = self.candidates[kind]
        if kind == "grid":
            return c.total_time(rays, bound, include_build=include_grid_build)
        return c.total_time(rays, bound)

    def to_dict(self) -> dict:
        """JSON-able figures.  Infinite break-evens are written as null ("never")."""
        return {
            "triangles": self.triangles, "expected_rays": self.expected_rays, "samples": self.samples,
            "grid_build_time": self.grid_build_time, "grid_per_ray": self.grid_per_ray,
            "candidates": {k: c.to_dict() for k, c in self.candidates.items()},
            "break_even": _json_float(self.break_even), "break_even_low": _json_float(self.break_even_low),
            "break_even_high": _json_float(self.break_even_high), "break_even_kind": self.break_even_kind,
            "decision": self.decision, "certain": self.certain, "grid_sample_per_ray": self.grid_sample_per_ray,
            "grid_sample_ratio": self.grid_sample_ratio, "workload_samples": self.workload_samples, "work": self.work,
            "grid_terms": list(self.grid_terms), "break_even_floor": self.break_even_floor,
            "grid_built": self.grid_built, "break_even_ceiling": _json_float(self.break_even_ceiling),
            "settled_slack": self.settled_slack,
            "ill_conditioned": self.ill_conditioned, "no_sample": self.no_sample,
            "estimate_time": self.estimate_time,
            "plan_time": self.plan_time, "grid_reused": self.grid_reused,
            "calibration_source": self.calibration_source, "notes": list(self.notes),
            "unavailable": dict(self.unavailable),
            "executed": [dict(e) for e in self.executed],
        }

    def summary(self) -> str:
        """One line for a status bar or a log."""
        def num(x):
            return "inf" if not math.isfinite(x) else f"{x:,.0f}"

        head = f"{self.decision} for {self.expected_rays:,.0f} rays on {self.triangles:,} triangles; "
        if not self.grid_built and self.settled_slack > 0:
            return head + (f"no grid built: on the calibration alone building {self.chosen} costs at most "
                           f"{self.settled_slack:.0%} more than building the grid from {num(self.break_even_ceiling)} rays")
        if not self.grid_built:
            return head + (f"no grid built: on the calibration alone {self.chosen} beats building the grid "
                           + (f"from at most {num(self.break_even_ceiling)} rays" if self.break_even_ceiling > 0
                              else "for any number of rays"))
        if not math.isfinite(self.break_even):
            return head + "the grid is always cheapest" + (f" (up to {num(self.break_even_low)} at the low end)"
                                                            if math.isfinite(self.break_even_low) else "")
        return (head + f"the grid is cheapest up to {num(self.break_even)} rays "
                f"[{num(self.break_even_low)}, {num(self.break_even_high)}] (vs {self.break_even_kind})")

    # -- shooting the workload --------------------------------------------------------------
    def accel(self) -> Accel:
        """The chosen structure: the plan's grid when it wins, else built now (once)."""
        if self.decision == "GRID":
            if self.grid is None:
                raise RuntimeError("this plan holds no grid (made from timings only); use plan() to trace")
            return self.grid
        if self.structure is None:
            if self.mesh is None:
                raise RuntimeError("this plan holds no mesh (made from timings only); use plan() to trace")
            self.structure = build(self.mesh, self.chosen, **self.configs.get(self.chosen, {}))
            self.executed.append({"kind": self.chosen, "build_time": self.structure.build_time, "trace_time": 0.0, "rays": 0})
        return self.structure

    def reusable_samples(self, origins, directions):
        """(indices, Hits) of the sample rays already answered, when ``origins`` and
        ``directions`` are the very arrays the plan sampled and the chosen structure
        answers bit for bit like the grid (grid, numpy BVH); else None."""
        if self.sample is None or self.chosen not in REUSES_SAMPLES:
            return None
        so, sd, idx, hits = self.sample
        if origins is not so or directions is not sd:
            return None
        return idx, hits

    def split(self, origins, directions, tmin=0.0, tmax=np.inf):
        """(rest, (origins, directions, tmin, tmax) of the rays still to trace).

        ``rest`` indexes the workload rays the plan has not answered yet, or is None when
        none of its sample can be reused (then the rays come back as given)."""
        reuse = self.reusable_samples(origins, directions)
        if reuse is None:
            return None, (origins, directions, tmin, tmax)
        m = len(origins)
        keep = np.ones(m, bool)
        keep[reuse[0]] = False
        rest = np.flatnonzero(keep)
        o, d = np.asarray(origins), np.asarray(directions)
        return rest, (o[rest], d[rest], _pick(tmin, rest, m), _pick(tmax, rest, m))

    def merge(self, m: int, rest, part):
        """The whole workload's answers from ``part`` (the answers for ``split``'s ``rest``)
        and the kept sample: Hits for Hits, a boolean array for ``occluded`` answers."""
        if rest is None:
            return part
        idx, done = self.sample[2], self.sample[3]
        if isinstance(part, Hits):
            out = Hits.empty(m)
            for name in ("t", "triangle", "u", "v"):
                getattr(out, name)[idx] = getattr(done, name)
                getattr(out, name)[rest] = getattr(part, name)
            return out
        out = np.zeros(m, bool)
        out[idx] = done.hit  # a nearest hit within [tmin, tmax] is exactly an occluder
        out[rest] = np.asarray(part, bool)
        return out

    def trace(self, origins, directions, tmin=0.0, tmax=np.inf) -> Hits:
        """Shoot the workload with the chosen structure (building a BVH only when chosen).

        Given the arrays ``plan()`` sampled, the sample rays keep their answers and only
        the others are traced."""
        acc = self.accel()
        t0 = time.perf_counter()
        rest, rays = self.split(origins, directions, tmin, tmax)
        m = len(origins)
        traced = m if rest is None else len(rest)
        part = acc.trace(*rays) if traced or rest is None else Hits.empty(0)
        hits = self.merge(m, rest, part)
        self.executed.append({"kind": acc.kind, "build_time": 0.0, "trace_time": time.perf_counter() - t0,
                              "rays": traced, "reused": m - traced})
        return hits


def _pick(x, sel, m):
    """A per-ray bound's entries at ``sel``; a scalar as it is."""
    x = np.asarray(x)
    return x[sel] if x.ndim == 1 and len(x) == m else x


def plan_from_timings(
    triangles: int,
    expected_rays,
    calibration: Calibration,
    grid_build_time: float,
    grid_per_ray: float,
    *,
    grid_per_ray_low: float | None = None,
    grid_per_ray_high: float | None = None,
    kinds=("grid", "bvh", "embree"),
    samples: int = 0,
    answered: int = 0,
    per_ray: dict | None = None,
    unavailable: dict | None = None,
    notes=(),
    floor: float = 0.0,
) -> Plan:
    """The plan's arithmetic alone, from a measured grid and the calibration.

    Pure: no structure is built or traced, so tests can check the break-even on known
    numbers.  ``kinds`` other than 'grid' are candidates; those the calibration has no
    constants for are skipped with a note.  grid_per_ray_low/high: the interval of the
    grid's time per ray (default: the point value).  answered: rays of the workload the
    grid's samples have answered already; the decision then weighs what is left to trace,
    R - answered rays for the grid and the structures in REUSES_SAMPLES, R for the others
    (the break-even figures still count a workload's rays from zero).  per_ray:
    {kind: (point, low, high)} time per ray of a candidate from elsewhere (the count
    model) instead of the calibration's estimate for N.  floor: the calibration's lower
    bound on the break-even (``Calibration.prior``); at most this many rays keep the grid.
    """
    r = _check_expected(expected_rays)
    notes = list(notes)
    unavailable = dict(unavailable or {})
    n = int(triangles)
    g_lo = grid_per_ray if grid_per_ray_low is None else min(grid_per_ray_low, grid_per_ray)
    g_hi = grid_per_ray if grid_per_ray_high is None else max(grid_per_ray_high, grid_per_ray)
    cands = {"grid": Cost("grid", grid_build_time, grid_build_time, grid_build_time, grid_per_ray, g_lo, g_hi,
                          measured=True)}
    for kind in kinds:
        if kind == "grid":
            continue
        if kind not in calibration.fits:
            why = f"no calibration constants for it (calibrated: {', '.join(calibration.fits) or 'none'})"
            unavailable[kind] = why
            notes.append(f"{kind} skipped: {why}")
            continue
        e = calibration.estimate(kind, n)
        if per_ray and kind in per_ray:
            e.per_ray, e.per_ray_low, e.per_ray_high = per_ray[kind]
        cands[kind] = replace(
            e, measured=False, break_even=break_even(e.build_time, grid_per_ray, e.per_ray),
            # the low end: cheap build, fast rays, a slow grid; the high end: the opposite
            break_even_low=break_even(e.build_low, g_hi, e.per_ray_low),
            break_even_high=break_even(e.build_high, g_lo, e.per_ray_high),
        )
    hds = [c for k, c in cands.items() if k != "grid"]
    if n == 0:
        notes.append("empty scene: nothing to accelerate, the grid (empty) answers every ray")
        hds = []
    if hds:
        first = min(hds, key=lambda c: (c.break_even, c.kind))
        be, be_kind = first.break_even, (first.kind if math.isfinite(first.break_even) else None)
        be_low = min(c.break_even_low for c in hds)
        be_high = min(c.break_even_high for c in hds)
    else:
        be, be_low, be_high, be_kind = math.inf, math.inf, math.inf, None
    answered = max(0, int(answered))
    if answered and r <= answered:
        notes.append(f"all {r:,.0f} rays were answered by the grid while planning")
    decision = str(choose(r, grid_per_ray, {c.kind: c for c in hds}, answered, floor)[0])
    certain = not (be_low <= r <= be_high)
    if not certain:
        notes.append(f"{r:,.0f} expected rays lie inside the break-even interval: the choice is uncertain")
    words = conditioning(grid_per_ray, cands[be_kind].per_ray, be_kind) if be_kind is not None else ""
    if words:
        notes.append(words)
    return Plan(
        triangles=n, expected_rays=r, samples=int(samples), grid_build_time=float(grid_build_time),
        grid_per_ray=float(grid_per_ray), candidates=cands, break_even=be, break_even_low=be_low,
        break_even_high=be_high, break_even_kind=be_kind, decision=decision.upper(), certain=certain,
        calibration_source=calibration.source, notes=notes, unavailable=unavailable,
        break_even_floor=float(floor), ill_conditioned=words,
    )


#: the grid's time per ray over the candidate's below which the break-even is ill-conditioned
#: (R* = T_B / (t_G - t_H) moves by t_G / (t_G - t_H) times a relative error in t_G: 3x at 1.5)
ILL_CONDITIONED = 1.5


def conditioning(grid_per_ray: float, per_ray: float, kind: str) -> str:
    """Words for an ill-conditioned break-even against ``kind`` (the grid at most
    ``ILL_CONDITIONED`` times slower per ray), else ''."""
    if not (per_ray > 0 and grid_per_ray > per_ray):
        return ""
    ratio = grid_per_ray / per_ray
    if ratio >= ILL_CONDITIONED:
        return ""
    moves = 10.0 * ratio / (ratio - 1.0)
    return (f"ill-conditioned: the grid is only {ratio:.2f}x slower per ray than {kind}, so a 10% error in either "
            f"time moves the break-even by about {moves:.0f}%; near it both cost about the same")


def _sample_rays(mesh, rays, k, seed):
    """K representative rays: the user's rays, one from each of K equal blocks of them, else
    the paper's uniform ones, quasi-random (``rays.quasi_uniform_rays``); either way the
    counts' mean moves less between seeds than on independent rays.

    Returns (origins, directions, tmin, tmax, what, indices into the workload or None)."""
    from .rays import quasi_uniform_rays

    rng = np.random.default_rng(seed)
    if rays is not None and len(rays[0]) == 0:
        rays = None  # an empty workload says nothing about the grid: sample uniformly
    if rays is None:
        o, d = quasi_uniform_rays(mesh, k, seed=rng)
        return o, d, 0.0, np.inf, "uniform, quasi-random", None
    rays = tuple(rays)
    if len(rays) not in (2, 4):
        raise ValueError("rays must be (origins, directions) or (origins, directions, tmin, tmax)")
    o, d = np.asarray(rays[0]), np.asarray(rays[1])
    tmin, tmax = (rays[2], rays[3]) if len(rays) == 4 else (0.0, np.inf)
    m = len(o)
    if k < m:
        # one ray at random from each of K equal blocks of the workload: each ray is drawn
        # with probability about K / M, as in a random subset, and a workload in an order (a
        # camera's rows, a scanner's sweep) is covered evenly, so the counts' mean moves less
        # between seeds (on camera rays, much less than on a random subset: BENCHMARKS.md,
        # "Calibration and plan repeatability")
        edges = (np.arange(k + 1, dtype=np.int64) * m) // k
        idx = edges[:-1] + (rng.random(k) * np.diff(edges)).astype(np.int64)
        return o[idx], d[idx], _pick(tmin, idx, m), _pick(tmax, idx, m), "the given rays, one from each of K blocks", idx
    return o, d, tmin, tmax, "the given rays (all of them)", np.arange(m)


def plan(
    mesh: TriangleMesh,
    expected_rays,
    calibration: Calibration | None = None,
    *,
    rays=None,
    samples: int = DEFAULT_SAMPLES,
    grid: Accel | None = None,
    kinds=("grid", "bvh", "embree"),
    grid_config: dict | None = None,
    configs: dict | None = None,
    seed: int = 0,
    prior: bool = True,
) -> Plan:
    """Build (or reuse) the grid, time K sample rays through it, and decide.

    calibration: from ``decide.load_or_default``; None uses the shipped defaults.
    rays: the workload's own rays, (origins, directions[, tmin, tmax]); K of them are
    sampled, one from each of K equal blocks.  Without it K uniform rays (the paper's
    distribution, quasi-random) are used.
    grid: an already built grid over ``mesh`` to reuse (its build time is reported).
    grid_config / configs: build options for the grid / {kind: options} for the others.
    prior: skip the sample when ``expected_rays`` is below the calibration's floor on the
    break-even (``Calibration.prior``): the grid wins there whatever the sample says; and
    build neither the grid nor a sample when they are above its ceiling against the
    candidate estimated cheapest (``Plan.grid_built`` False): that candidate wins there.
    """
    t0 = time.perf_counter()
    _check_expected(expected_rays)
    if "grid" not in kinds:
        raise ValueError(f"plan() measures the grid and decides against it: kinds must include 'grid', got {tuple(kinds)}")
    notes = []
    if calibration is None:
        calibration = load_default()
        notes.append(f"no calibration given: using {calibration.source}")
    unavailable = {k: why for k in kinds if (why := unavailable_reason(k))}
    kinds, skipped = available_kinds(kinds)
    notes += skipped
    k = sample_count(samples, _check_expected(expected_rays))
    if grid is not None and getattr(grid, "mesh", None) is not mesh:
        raise ValueError("the grid passed to plan() was built over another mesh")
    cands = [kk for kk in kinds if kk != "grid" and kk in calibration.fits]
    pri = calibration.prior(mesh.triangle_count, cands) if prior and mesh.triangle_count and cands else None
    floor = pri.floor if pri is not None else 0.0
    if grid is None and pri is not None:
        settled = _settled_without_grid(mesh, expected_rays, calibration, pri, cands, kinds, unavailable, notes)
        if settled is not None:
            settled.plan_time = settled.estimate_time = time.perf_counter() - t0
            settled.mesh, settled.configs = mesh, dict(configs or {})
            return settled
    mesh.prepare()
    if grid is None:
        grid = build(mesh, "grid", **(grid_config or {}))
        reused = False
    else:
        reused = True
    t1 = time.perf_counter()
    sample, idx, grid_fig = None, None, None
    per_ray = {}
    if floor and _check_expected(expected_rays) <= floor:
        # too few rays for any structure to pay back its build on this calibration's
        # evidence: the grid wins without a sample, and the sample's cost is saved.  The
        # figures are the prior's (slowest grid, largest gain), under which the one rule
        # below picks the grid too
        k, what, t_sample = 0, "none", pri.grid_per_ray
        per_ray = {kk: (t, t, t) for kk, t in pri.per_ray.items()}
        notes.append(f"{float(expected_rays):,.0f} expected rays are below the calibration's floor on the break-even "
                     f"({floor:,.0f}): the grid wins without sampling; its time per ray and the gains are the "
                     f"calibration's extremes")
    elif prior and mesh.triangle_count and cands and not sample_pays(calibration, samples, expected_rays) \
            and (gq := calibration.grid_estimate(mesh.triangle_count)) is not None:
        # the sample would cost more than SAMPLE_COST_SHARE of the workload's own grid trace:
        # the calibration's estimates for N decide, leaning to the grid already built
        g_fig, costs = unsampled(gq, {kk: calibration.estimate(kk, mesh.triangle_count) for kk in cands})
        k, what, t_sample = 0, "none", g_fig
        grid_fig = (g_fig, gq.per_ray_low, gq.per_ray_high)
        per_ray = {kk: (c.per_ray, calibration.estimate(kk, mesh.triangle_count).per_ray_low, c.per_ray)
                   for kk, c in costs.items()}
        notes.append(f"a sample for {float(expected_rays):,.0f} rays would cost more than "
                     f"{SAMPLE_COST_SHARE:.0%} of their trace: decided on the calibration's estimates for "
                     f"{mesh.triangle_count:,} triangles (the grid's time per ray at its low end, the candidates' "
                     f"at their high end)")
    elif mesh.triangle_count:
        o, d, tmin, tmax, what, idx = _sample_rays(mesh, rays, k, seed)
        counted = getattr(grid, "traversal_work", None)
        before = counted() if counted else None
        sample, dt = time_trace(grid, o, d, tmin, tmax)
        traversal = traversal_counts(before, counted()) if counted else None
        k = len(o)
        t_sample = dt / max(k, 1)
    else:
        k, t_sample, what = 0, 0.0, "none"
    ratio, ratio_lo, ratio_hi = calibration.grid_sample_ratio(k) if k else (1.0, 1.0, 1.0)
    g, g_lo, g_hi = grid_fig or (t_sample * ratio, t_sample * ratio_lo, t_sample * ratio_hi)
    work = None
    if k and calibration.counts.get("grid") is not None:
        # counts instead of the sample's time: the same rays through the same grid give the
        # same counts, so the estimate repeats exactly with a fixed calibration
        work = grid_work(grid, o, d, sample.t, tmin, tmax, refs=calibration.uses_term("refs"),
                         traversal=traversal).to_dict()
        surface = mesh.is_surface()
        g, g_lo, g_hi = calibration.count_per_ray("grid", mesh.triangle_count, work, surface)
        per_ray = {kk: e for kk in kinds if kk != "grid"
                   if (e := calibration.count_per_ray(kk, mesh.triangle_count, work, surface)) is not None}
    p = plan_from_timings(mesh.triangle_count, expected_rays, calibration, float(grid.build_time), g,
                          grid_per_ray_low=g_lo, grid_per_ray_high=g_hi, kinds=kinds, samples=k,
                          answered=k if idx is not None else 0, per_ray=per_ray, unavailable=unavailable,
                          notes=notes, floor=floor)
    p.grid_sample_per_ray = t_sample if k else 0.0
    if not k and mesh.triangle_count:
        p.no_sample = NO_SAMPLE_DEAR if grid_fig is not None else NO_SAMPLE_FLOOR
    p.grid_sample_ratio = ratio if work is None else (g / t_sample if t_sample > 0 else 1.0)
    p.work = work
    if work is not None:
        p.grid_terms = calibration.counts["grid"].weighed
        refs = "" if work["refs"] is None else f", {work['refs']:.1f} references"
        walked = "" if work.get("steps") is None else (f" ({work['steps']:.1f} traversal steps, "
                                                       f"{work['candidates']:.1f} candidate triangles, "
                                                       f"{work['tests']:.1f} triangle tests)")
        p.notes.append(f"grid time per ray from the work counts of {k:,} sample rays ({what}): {work['cells']:.1f} cells"
                       f"{refs} per ray{walked}; its count model weighs {', '.join(p.grid_terms)}; "
                       + ", ".join(sorted(per_ray)) + " per ray from the same counts")
    elif k:
        p.notes.append(f"grid time per ray from {k:,} sample rays ({what}) x {ratio:.2f}, the calibration's "
                       f"large-workload / {k:,}-ray-batch ratio [{ratio_lo:.2f}, {ratio_hi:.2f}]")
    if idx is not None and k:
        # keep the sample's answers: Plan.trace on the same arrays traces only the other rays
        p.sample = (rays[0], rays[1], idx, sample)
        p.workload_samples = k
    if reused:
        p.notes.append("grid reused (built before this plan)")
    p.estimate_time = time.perf_counter() - t1
    p.plan_time = time.perf_counter() - t0
    p.grid_reused = reused
    p.grid, p.mesh, p.configs = grid, mesh, dict(configs or {})
    return p


def sample_pays(calibration: Calibration, samples: int, expected_rays) -> bool:
    """Whether the K = ``sample_count`` rays a plan samples for ``expected_rays`` cost at most
    SAMPLE_COST_SHARE of the workload's own trace through the grid: K t_K <= share R t_G,
    with t_K = t_G / ratio(K) the calibration's time per ray of a K-ray batch
    (``Calibration.grid_sample_ratio``; N's own time per ray cancels)."""
    r = float(expected_rays)
    k = sample_count(samples, r)
    return k / max(calibration.grid_sample_ratio(k)[0], 1e-9) <= SAMPLE_COST_SHARE * r


def _settled_without_grid(mesh, expected_rays, calibration, pri, cands, kinds, unavailable, notes) -> Plan | None:
    """The plan when the calibration alone settles it for a hierarchical structure H, the one
    with the least estimated total (``rule.settle_bound``): the expected rays pass the
    calibration's ceiling on the break-even against H (``Calibration.prior``), so H wins
    whatever a sample would say; or, for a surface mesh, the rays from which building H costs
    at most ``rule.SETTLE_SLACK`` more than building the grid (``rule.regret_bound``).  Neither
    the grid nor a sample is paid for.  None otherwise.  The grid's figures are then the
    calibration's: its time per ray the least it allows (t_H + the least gain) under a
    ceiling, its estimate for N within the slack."""
    r = float(expected_rays)
    n = mesh.triangle_count
    est = {kk: calibration.estimate(kk, n) for kk in cands}
    best = min(est, key=lambda kk: (est[kk].build_time + r * est[kk].per_ray, kk))
    grid = calibration.grid_estimate(n)
    ceiling = pri.ceiling.get(best)
    sure = settle_bound(grid, est[best], ceiling)
    bound = settle_bound(grid, est[best], ceiling, surface=mesh.is_surface())
    if r < bound:
        return None
    near = bound < sure  # settled within the slack, not because H surely wins
    if near:
        g, why = grid.per_ray, (f"{r:,.0f} expected rays are above the rays from which building {best} costs at most "
                                f"{SETTLE_SLACK:.0%} more than building the grid on the calibration's estimates for "
                                f"{n:,} triangles ({bound:,.0f}; a surface mesh, on which those estimates lean to the "
                                f"grid)")
    else:
        g = est[best].per_ray + pri.gain_low[best]
        why = (f"{r:,.0f} expected rays are above the rays from which building {best} beats building the grid on the "
               f"calibration's estimates for {n:,} triangles ({bound:,.0f})" if bound > 0
               else f"{best} builds faster than the grid and traces faster on the calibration's estimates for "
                    f"{n:,} triangles")
    p = plan_from_timings(n, r, calibration, 0.0, g, kinds=kinds, samples=0, unavailable=unavailable,
                          notes=list(notes) + [why + f": {best} without a grid or a sample; the grid's figures are "
                                                     f"the calibration's"],
                          floor=pri.floor)
    # the rule weighs the grid's build as sunk; here nothing is built yet, and the bound is
    # on the rays from which building ``best`` beats building the grid (or comes within the slack)
    p.decision, p.certain = best.upper(), True
    p.grid_built = False
    p.break_even_ceiling = float(bound)
    p.settled_slack = SETTLE_SLACK if near else 0.0
    # what the calibration alone says of the break-even: above its floor, and under a
    # ceiling at most that (its estimate for N, extrapolated far from the calibration's
    # sizes, may fall outside); within the slack it bounds it no further
    p.break_even_low, p.break_even_high = min(pri.floor, float(bound)), (math.inf if near else float(bound))
    p.break_even = min(max(p.break_even, p.break_even_low), p.break_even_high)
    p.grid_sample_per_ray = 0.0
    return p


# -- online mode -------------------------------------------------------------------------------

@dataclass
class OnlineRecord:
    """What ``trace_online`` did.  Times in seconds from the given clock.

    switch_ray: rays traced with the grid before the switch (None when it never switched).
    """

    kind: str
    rays: int
    batch: int
    estimated_build_time: float
    switched: bool = False
    switch_ray: int | None = None
    grid_build_time: float | None = None
    grid_trace_time: float = 0.0
    hds_build_time: float = 0.0
    hds_trace_time: float = 0.0
    total_time: float = 0.0
    note: str = ""

    def to_dict(self) -> dict:
        """JSON-able; an infinite estimated build (no constants) is written as null."""
        d = dict(self.__dict__)
        d["estimated_build_time"] = _json_float(d["estimated_build_time"])
        return d


def ski_rental(grid_time: float, grid_rays: int, estimate) -> str:
    """The online rule, given what the grid has spent so far: 'switch' once the grid's
    accumulated trace time reaches the structure's estimated build time (Karlin et al.
    1988: never worse than about twice the best fixed choice), 'never' when the estimate
    is not faster per ray than the grid has measured (building could never pay),
    'wait' otherwise.  ``estimate`` is a ``decide.cost.Cost`` or None (no constants)."""
    if estimate is None or grid_time < estimate.build_time:
        return "wait" if estimate is not None else "never"
    if grid_rays <= 0 or estimate.per_ray >= grid_time / grid_rays:
        return "never"
    return "switch"


def trace_online(
    mesh: TriangleMesh,
    origins,
    directions,
    calibration: Calibration | None = None,
    *,
    grid: Accel | None = None,
    kind: str = "bvh",
    batch: int = DEFAULT_BATCH,
    tmin=0.0,
    tmax=np.inf,
    grid_config: dict | None = None,
    config: dict | None = None,
    clock=time.perf_counter,
    builder=build,
) -> tuple[Hits, OnlineRecord]:
    """Trace with the grid in batches; switch to ``kind`` once the grid's accumulated trace
    time reaches ``kind``'s estimated build time (``ski_rental``).  Needs no ray count.

    It switches only while the estimate says ``kind`` is faster per ray than the grid has
    measured so far (else building it could never pay).  ``clock`` and ``builder`` are
    seams for tests (a fake clock, fake structures).
    """
    o = np.asarray(origins)
    d = np.asarray(directions)
    m = len(o)
    batch = max(1, int(batch))
    if calibration is None:
        calibration = load_default()
    t_start = clock()
    est = calibration.estimate(kind, mesh.triangle_count) if kind in calibration.fits else None
    rec = OnlineRecord(kind, m, batch, est.build_time if est else math.inf)
    if est is None:
        rec.note = f"no calibration constants for {kind!r}: the grid traces everything"
    elif kind == "embree" and not available_kinds(("embree",))[0]:
        est, rec.estimated_build_time, rec.note = None, math.inf, "embreex is not installed: the grid traces everything"
    if grid is None:
        c0 = clock()
        grid = builder(mesh, "grid", **(grid_config or {}))
        rec.grid_build_time = clock() - c0

    def per_ray(x, a, b):
        x = np.asarray(x)
        return x[a:b] if x.ndim == 1 and len(x) == m else x

    out = Hits.empty(m)

    def put(h, a, b):
        out.t[a:b], out.triangle[a:b], out.u[a:b], out.v[a:b] = h.t, h.triangle, h.u, h.v

    done = 0
    while done < m:
        b = min(m, done + batch)
        c0 = clock()
        put(grid.trace(o[done:b], d[done:b], per_ray(tmin, done, b), per_ray(tmax, done, b)), done, b)
        rec.grid_trace_time += clock() - c0
        done = b
        if done < m and est is not None:
            rule = ski_rental(rec.grid_trace_time, done, est)
            if rule == "never":
                rec.note = f"{kind} would not be faster per ray than the grid: not switching"
                est = None
                continue
            if rule == "wait":
                continue
            c0 = clock()
            hds = builder(mesh, kind, **(config or {}))
            rec.hds_build_time = clock() - c0
            rec.switched, rec.switch_ray = True, done
            c0 = clock()
            put(hds.trace(o[done:], d[done:], per_ray(tmin, done, m), per_ray(tmax, done, m)), done, m)
            rec.hds_trace_time = clock() - c0
            done = m
    rec.total_time = clock() - t_start
    return out, rec
