"""The paper's decision for point queries (the closest point): for N points, is the grid
enough, or does a BVH pay for its build?

The grid is cheap to build and searches rings of cells about each point: on the surface it
is about as fast per point as the BVH, farther out it enumerates many empty cells (a point
that would need more than ``REACH`` of them goes to the BVH whatever the decision).  The
BVH's branch and bound costs about the same wherever the point is.  As for rays, the decision
builds the grid, answers a sample of the points on it (the answers are kept), and from the
sample's work counts (``proximity.GRID_WORK``) estimates the time per point of both:

- the grid's, affine in its counts per point (rings, cells enumerated, triangles measured);
- the BVH's, affine in log2 N (its depth) and in the triangles the grid measured per point
  (how crowded the surface near the points is); it has no sample of its own: it is not
  built yet;

and the builds as power laws of N.  The least total for the points to come wins
(``rule.over_life``, a structure already built costing nothing), and the break-even is the
number of points from which the BVH beats the grid.

The constants are calibrated (``measure_points``, ``fit_points``) on scenes with three kinds
of points each: uniform in the scene's box grown by a fifth, near the surface (a normal
offset of 2% of the box's diagonal) and on it (0.2%).
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .. import proximity
from ..mesh import TriangleMesh
from .cost import Cost, _loglog_fit, nonneg_relative_lsq
from .rule import over_life

#: the points a plan answers on the grid first: this share of them, at least SAMPLE_MIN (all
#: of them when there are fewer)
SAMPLE_SHARE = 0.02
SAMPLE_MIN = 256
#: the most cells a point's rings may span on the grid in a planned search (``closest_planned``):
#: a point that needs more (far outside the scene, deep in empty space) goes to the BVH, which
#: answers it in a few dozen box tests
REACH = 1 << 13
#: the kinds the point decision weighs
KINDS = ("grid", "bvh")
#: points per calibration scene and kind of points: (box, near, on the surface); the box's are
#: few since the grid takes long on each
CALIBRATION_POINTS = (300, 4000, 4000)
#: the largest scene the point calibration measures (its builds are timed three times)
CALIBRATION_MAX_TRIANGLES = 400_000


def _per_point(work) -> np.ndarray:
    """The grid's counts per point (rings, cells, pairs) of a ``GRID_WORK`` list."""
    w = np.asarray(work, np.float64)
    return w[1:] / max(w[0], 1.0)


def _bvh_columns(work, triangles: int) -> list:
    """What the BVH's time per point is affine in: 1, log2 N, the grid's triangles per point."""
    return [1.0, math.log2(max(int(triangles), 2)), float(_per_point(work)[2])]


@dataclass
class PointRecord:
    """One calibration case: a scene and one kind of points, measured."""

    scene: str
    points_kind: str
    triangles: int
    points: int
    grid_build: float
    bvh_build: float
    grid_per_point: float
    bvh_per_point: float
    #: the grid's ``GRID_WORK`` counts on all the points, and on the plan's sample of them
    work: list
    sample_work: list


@dataclass
class PointModel:
    """The point decision's constants (the module docstring says what each models)."""

    #: (c, p) of build seconds = c N^p, per kind (the BVH's with its point index)
    builds: dict
    #: the grid's seconds per point: per ring, per cell enumerated, per triangle measured
    grid_terms: list
    #: the BVH's seconds per point: a constant, per log2 N, per triangle the grid measured per point
    bvh_terms: list
    #: the measured / fitted ratios' (10th, 90th) percentiles over the records, per kind
    spread: dict = field(default_factory=dict)
    records: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "PointModel":
        d = dict(d)
        d["records"] = [PointRecord(**r) for r in d.get("records", [])]
        return cls(**d)

    def build_time(self, kind: str, triangles: int) -> float:
        c, p = self.builds[kind]
        return float(c) * max(int(triangles), 1) ** float(p)

    def grid_per_point(self, work) -> float:
        return float(np.dot(self.grid_terms, _per_point(work)))

    def bvh_per_point(self, work, triangles: int) -> float:
        return float(np.dot(self.bvh_terms, _bvh_columns(work, triangles)))

    def estimates(self, triangles: int, sample_work) -> dict:
        """{kind: ``Cost``} for an N-triangle scene from the grid sample's counts: the builds
        and the time per point (``per_ray``), each with its spread as the interval."""
        out = {}
        for kind, per in (("grid", self.grid_per_point(sample_work)), ("bvh", self.bvh_per_point(sample_work, triangles))):
            b = self.build_time(kind, triangles)
            lo, hi = self.spread.get(kind, (1.0, 1.0))
            out[kind] = Cost(kind, b, b, b, per, per * lo, per * hi)
        return out


def fit_points(records) -> PointModel:
    """The constants from calibration records (``measure_points``)."""
    records = list(records)
    if len(records) < 3:
        raise ValueError(f"the point decision needs at least 3 calibration cases, got {len(records)}")
    n = np.array([r.triangles for r in records], np.float64)
    builds = {k: list(_loglog_fit(n, [getattr(r, f"{k}_build") for r in records])) for k in KINDS}
    full = np.array([_per_point(r.work) for r in records])
    grid_t = np.array([r.grid_per_point for r in records])
    grid_terms = [float(x) for x in nonneg_relative_lsq(full, grid_t)]
    bvh_t = np.array([r.bvh_per_point for r in records])
    cols = np.array([_bvh_columns(r.sample_work, r.triangles) for r in records])
    bvh_terms = [float(x) for x in nonneg_relative_lsq(cols, bvh_t)]
    model = PointModel(builds, grid_terms, bvh_terms, records=records)
    spread = {}
    for kind, truth, est in (("grid", grid_t, [model.grid_per_point(r.sample_work) for r in records]),
                             ("bvh", bvh_t, [model.bvh_per_point(r.sample_work, r.triangles) for r in records])):
        q = np.asarray(truth) / np.maximum(est, 1e-30)
        spread[kind] = [min(float(np.percentile(q, 10)), 1.0), max(float(np.percentile(q, 90)), 1.0)]
    model.spread = spread
    return model


# -- calibration cases -------------------------------------------------------------------------------

def box_points(mesh: TriangleMesh, n: int, rng) -> np.ndarray:
    """Points uniform in the mesh's box grown by a fifth on each side (a flat axis by a fifth
    of a fifth of the largest extent)."""
    lo, hi = (x.astype(np.float64) for x in mesh.bounds())
    pad = 0.2 * np.maximum(hi - lo, 0.2 * (hi - lo).max())
    return rng.uniform(lo - pad, hi + pad, size=(n, 3))


def surface_points(mesh: TriangleMesh, n: int, rng, offset: float) -> np.ndarray:
    """Points on random valid triangles (uniform barycentrics) moved by a normal offset of
    ``offset`` times the box's diagonal."""
    tv = mesh.tri_vertices.astype(np.float64)[np.flatnonzero(mesh.valid)]
    t = rng.integers(0, len(tv), n)
    a, b = rng.random((2, n))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    q = tv[t, 0] + a[:, None] * (tv[t, 1] - tv[t, 0]) + b[:, None] * (tv[t, 2] - tv[t, 0])
    lo, hi = mesh.bounds()
    diag = float(np.linalg.norm(hi.astype(np.float64) - lo))
    return q + rng.normal(size=(n, 3)) * offset * diag


def point_sets(mesh: TriangleMesh, counts=CALIBRATION_POINTS, seed: int = 0) -> list[tuple[str, np.ndarray]]:
    """The three kinds of points of a calibration case: ('box' | 'near' | 'surface', (M, 3))."""
    rng = np.random.default_rng(seed)
    return [("box", box_points(mesh, counts[0], rng)), ("near", surface_points(mesh, counts[1], rng, 0.02)),
            ("surface", surface_points(mesh, counts[2], rng, 0.002))]


def sample_size(m: int) -> int:
    """The points a plan answers on the grid before it decides (``SAMPLE_SHARE``, ``SAMPLE_MIN``)."""
    return min(int(m), max(SAMPLE_MIN, int(math.ceil(SAMPLE_SHARE * m))))


def sample_rows(m: int) -> np.ndarray:
    """The rows of ``m`` points a plan samples: ``sample_size(m)`` of them, evenly spaced (points
    often come in order over the surface, a scan's rows or a mesh's vertices)."""
    k = sample_size(m)
    return np.arange(k, dtype=np.int64) * m // max(k, 1)


def _median_time(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def measure_points(name: str, mesh: TriangleMesh, *, counts=CALIBRATION_POINTS, repeats: int = 3, threads=None,
                   seed: int = 0) -> list[PointRecord]:
    """One record per kind of points (``point_sets``) on ``mesh``: both structures built
    ``repeats`` times with their point indices (median), the closest point of every point
    on each (median of ``repeats``), and the grid's work counts on all of them and on the
    plan's sample."""
    from ..bvh import point_index_of
    from ..factory import build

    kw = {} if threads is None else {"threads": threads}
    mesh.prepare()

    def grid():
        g = build(mesh, "grid", **kw)
        g.cell_index()
        return g

    def bvh():
        b = build(mesh, "bvh", **kw)
        point_index_of(b)
        return b

    grid_build, g = _median_time(grid, repeats)
    bvh_build, b = _median_time(bvh, repeats)
    out = []
    for kind, pts in point_sets(mesh, counts, seed):
        work, sample = [0, 0, 0, 0], [0, 0, 0, 0]
        proximity.closest_grid(g.cell_index(), pts, work=work)
        proximity.closest_grid(g.cell_index(), pts[sample_rows(len(pts))], work=sample)
        tg, _ = _median_time(lambda: g.closest(pts), repeats)
        tb, _ = _median_time(lambda: b.closest(pts), repeats)
        out.append(PointRecord(name, kind, mesh.triangle_count, len(pts), grid_build, bvh_build, tg / len(pts),
                               tb / len(pts), work, sample))
    return out


def calibrate_points(scenes, *, progress=None, threads=None, counts=CALIBRATION_POINTS, repeats: int = 3,
                     max_triangles: int = CALIBRATION_MAX_TRIANGLES) -> PointModel:
    """Measure ``scenes`` ((name, mesh or factory) pairs; those above ``max_triangles`` are
    left out) and fit the point decision's constants."""
    records = []
    scenes = list(scenes)
    for i, (name, factory) in enumerate(scenes):
        mesh = factory if isinstance(factory, TriangleMesh) else factory()
        if mesh.triangle_count > max_triangles or mesh.triangle_count == 0:
            continue
        if progress is not None:
            progress(i / len(scenes), f"point queries: {name}")
        records += measure_points(name, mesh, counts=counts, repeats=repeats, threads=threads, seed=i)
    return fit_points(records)


# -- the plan ----------------------------------------------------------------------------------------------

@dataclass
class PointPlan:
    """What a point query's plan decided: ``kind`` answers the points the sample did not; its
    estimates ({kind: Cost}, per point as ``per_ray``), the totals for those points, and the
    break-even in points from which the BVH beats the grid (inf: never)."""

    kind: str
    estimates: dict
    totals: dict
    break_even: float
    sample: int
    reason: str = ""
    #: points too far from every triangle for the grid (``closest_planned``'s ``REACH``),
    #: answered by the BVH
    handed_over: int = 0

    def to_dict(self) -> dict:
        return {"kind": self.kind, "estimates": {k: c.to_dict() for k, c in self.estimates.items()},
                "totals": self.totals, "break_even": self.break_even if math.isfinite(self.break_even) else None,
                "sample": self.sample, "reason": self.reason, "handed_over": self.handed_over}


def decide(model: PointModel | None, triangles: int, points: int, sample_work, built=(), far_share: float = 0.0) -> PointPlan:
    """The structure for ``points`` points still to answer after the grid's sample (whose
    ``GRID_WORK`` counts are ``sample_work``), ``built`` kinds' builds sunk: the least
    estimated total (``rule.over_life``).  ``far_share``: the sample's share of points too far
    for the grid (``REACH``); where the rest should hold one, the BVH those points need is
    built whichever structure answers the rest, so its build weighs on neither.  Without a model (no calibration of point
    queries) the BVH, said so in the reason."""
    n_sample = int(np.asarray(sample_work)[0]) if len(sample_work) else 0
    if model is None:
        return PointPlan("bvh", {}, {}, math.nan, n_sample, "no point-query calibration: the BVH")
    est = model.estimates(triangles, sample_work)
    far = far_share * points >= 1 and "bvh" not in built
    if far:  # the BVH will be built for the far points whichever answers the rest: its build weighs on neither
        built = set(built) | {"bvh"}
    kind, totals, be, _ = over_life(est, points, built)
    why = f"least estimated total for {points:,} points" + (
        "; the sample's far points need the BVH anyway" if far else "")
    return PointPlan(kind, est, totals, be, n_sample, why)


# -- evaluation on held-out meshes -------------------------------------------------------------------

#: the point counts at which an evaluation checks the picks
EVALUATION_POINTS = (100, 1_000, 10_000, 100_000, 1_000_000)


def true_costs(r: PointRecord) -> dict:
    """{kind: Cost} measured in a record."""
    return {"grid": Cost.point("grid", r.grid_build, r.grid_per_point, measured=True),
            "bvh": Cost.point("bvh", r.bvh_build, r.bvh_per_point, measured=True)}


def evaluate(model: PointModel, records, points=EVALUATION_POINTS, margin: float = 0.10) -> dict:
    """The estimated break-even against the measured one on each record (nothing built yet),
    and the picks at each of ``points``: {'cases': [...], 'median_error': the median
    |estimated / measured - 1| where both are finite, 'finite': how many, 'picks': correct
    picks where the measured totals differ by more than ``margin``, 'picked': of how many,
    'agree_never': cases where both say never}."""
    cases, errors, right, judged, never = [], [], 0, 0, 0
    for r in records:
        truth = true_costs(r)
        _, _, be_true, _ = over_life(truth, 0)
        est = model.estimates(r.triangles, r.sample_work)
        _, _, be_est, _ = over_life(est, 0)
        err = abs(be_est / be_true - 1.0) if math.isfinite(be_true) and math.isfinite(be_est) and be_true > 0 else None
        if err is not None:
            errors.append(err)
        never += not math.isfinite(be_true) and not math.isfinite(be_est)
        picks = []
        for n in points:
            kt, tt, _, _ = over_life(truth, n)
            ke, _, _, _ = over_life(est, n)
            lo, hi = sorted(tt.values())
            if hi > (1.0 + margin) * lo:
                judged += 1
                right += ke == kt
                picks.append((n, kt, ke))
        cases.append({"scene": r.scene, "points_kind": r.points_kind, "triangles": r.triangles,
                      "break_even_true": be_true, "break_even_est": be_est, "error": err, "picks": picks})
    return {"cases": cases, "median_error": float(np.median(errors)) if errors else math.nan, "finite": len(errors),
            "picks": right, "picked": judged, "agree_never": never}


def closest_planned(points, max_distance, model: PointModel | None, grid, bvh_of, triangles: int):
    """(``proximity.Nearest``, the kind that answered the rest, ``PointPlan``): the decision
    run on checked ``points``.  ``grid`` (a built ``UniformGrid``) answers an evenly spaced
    sample (``sample_size``) with its work counts; ``decide`` weighs the rest, the grid's
    build sunk; the grid or ``bvh_of()`` (a BVH, built when called) answers them.  The grid
    searches no point farther than ``REACH`` cells' worth of rings: such points (far outside
    the scene, deep in empty space) go to the BVH, so no point costs the grid more than that
    (``PointPlan.handed_over`` counts them)."""
    m = len(points)
    rows = sample_rows(m)
    k = len(rows)
    work = [0, 0, 0, 0]
    out, left_sample = proximity.closest_grid(grid.cell_index(), points[rows], max_distance, work=work, reach=REACH)
    made = []

    def tree():  # the BVH, built once whoever asks first
        if not made:
            made.append(bvh_of())
        return made[0]

    plan = decide(model, triangles, m - k, work, built={"grid"}, far_share=float(left_sample.mean()) if k else 0.0)
    parts = [(rows, out, left_sample)]
    if k < m:
        rest = np.ones(m, bool)
        rest[rows] = False
        rest = np.flatnonzero(rest)
        if plan.kind == "grid":
            more, left_rest = grid.closest_within(points[rest], max_distance, REACH)
        else:
            more, left_rest = tree().closest(points[rest], max_distance), np.zeros(len(rest), bool)
        parts.append((rest, more, left_rest))
    far = np.concatenate([r[left] for r, _, left in parts])
    plan.handed_over = int(far.size)
    got = [(r, n) for r, n, _ in parts] + ([(far, tree().closest(points[far], max_distance))] if far.size else [])
    answer = proximity.Nearest.gather(m, got)  # the far points' BVH answers last, over the grid's
    return answer, plan.kind, plan


def _count(x) -> str:
    return "never" if not math.isfinite(x) else f"{x:,.0f}"


def table(result: dict) -> list[str]:
    """Markdown lines of an ``evaluate`` result: per case the measured and estimated
    break-evens and the picks, then the summary line."""
    lines = ["| mesh | triangles | points | break-even measured | estimated | error | picks right / judged |",
             "|---|--:|---|--:|--:|--:|--:|"]
    for c in result["cases"]:
        ok = sum(kt == ke for _, kt, ke in c["picks"])
        err = "-" if c["error"] is None else f"{c['error']:.0%}"
        lines.append(f"| {c['scene']} | {c['triangles']:,} | {c['points_kind']} | {_count(c['break_even_true'])} | "
                     f"{_count(c['break_even_est'])} | {err} | {ok} / {len(c['picks'])} |")
    lines.append("")
    lines.append(summary_line(result))
    return lines


def summary_line(result: dict) -> str:
    one = len(result["cases"]) - result["finite"] - result["agree_never"]
    return (f"median break-even error {result['median_error']:.1%} over {result['finite']} cases with both finite "
            f"({result['agree_never']} where both say never, {one} where one does); correct picks "
            f"{result['picks']}/{result['picked']} = {result['picks'] / max(result['picked'], 1):.1%} where the "
            f"measured totals differ by more than 10%")
