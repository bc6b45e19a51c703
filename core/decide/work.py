"""What a grid sample tells about a scene besides its time: per-ray work counts.

Timings on a shared machine move between runs, and a K-ray sample's time per
ray depends on K (the lockstep traversal's fixed cost per step is spread over few rays).
Counts do neither: for the same rays through the same grid they are the same numbers.
From the sample's hits and the grid's public geometry (``lo``, ``cell_size``, ``res``,
``cell_start``) this computes, per ray,

- cells: the cells the 3D-DDA (Amanatides and Woo 1987) steps through, from the cell where
  the ray enters the grid to the cell of its hit (or where it leaves): a monotone line
  visits ``1 + |di| + |dj| + |dk|`` cells;
- refs: the triangle references tested in them, estimated as cells x the mean reference
  count of the cells at ``POINTS`` evenly spaced points of that segment (on at most
  ``REFS_RAYS`` of the rays, evenly spread); counted only when asked (calibration counts
  it for the models that may weigh it; a plan only when its calibration's models do,
  since it is a sizeable part of the estimate's cost);
- hit: whether it hit; length: its segment in the grid over the grid's diagonal;
- steps, candidates, tests: what the grid's traversal really did for these rays, counted
  by the grid as it traced them (``UniformGrid.traversal_work``): lockstep steps (a jump
  over empty space is one, where ``cells`` counts every cell it crosses), (ray, reference)
  pairs of the non-empty cells stepped, and pairs the kernel tested after the box
  prefilter.  Absent (None) where the rays were not traced by this grid with counting.

A cost model turns the means of these into times with constants fitted on the
calibration scenes (``cost.CountFit``), so a fixed calibration gives a fixed estimate.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..intersect import slab_interval

#: the default number of sample rays a plan traces through the grid (``core.plan``).  The
#: estimate reads the sample's work counts, not its time: a mean over K rays whose spread
#: between seeds the break-even multiplies by t_grid / (t_grid - t_bvh), large on the small
#: real meshes.  Five plans of one scene must agree within max / min 1.2: independent
#: uniform rays at 8,192 do not always; quasi-random rays (``rays.quasi_uniform_rays``) at
#: 16,384 have a much smaller spread between seeds than at 8,192 and keep five plans within
#: it.  The estimate's cost grows with K, and at 16,384 stays within what the decision allows
#: it for a workload of a million rays (BENCHMARKS.md, "Calibration and plan repeatability"
#: and "The decision report").
DEFAULT_SAMPLES = 16384

#: a plan samples at most this share of its expected rays, and at least SAMPLE_MIN rays (the
#: smallest batch the calibration times, so a sample's cost is known: ``sample_count``)
SAMPLE_SHARE = 0.02
SAMPLE_MIN = 1024
#: a plan samples only where the sample costs at most this share of the workload's own
#: trace through the grid (``core.plan.sample_pays``); for fewer rays it decides on the
#: calibration's estimates for N
SAMPLE_COST_SHARE = 0.10


def sample_count(samples: int, expected_rays: float) -> int:
    """The rays a plan samples for ``expected_rays``: ``samples``, cut to SAMPLE_SHARE of the
    expected rays (never below SAMPLE_MIN).  A small batch costs the lockstep grid about
    twice a large one's time per ray, so a full sample for a few thousand rays would cost
    more than the workload it decides for; the spread of a smaller sample's estimate is
    then paid on few rays, where a wrong pick costs little."""
    return max(1, min(int(samples), max(SAMPLE_MIN, int(SAMPLE_SHARE * float(expected_rays)))))

#: points per ray at which the reference count of the cells along the segment is read
POINTS = 16
#: rays whose references are counted (an even spread of the sample): the cells are counted
#: on every ray, the references, 16 gathers a ray, on at most this many.  Counting them on
#: a quarter of the default sample spread five plans' break-evens (of models weighing
#: references) far wider than counting them on all of it, so this is the whole default sample
REFS_RAYS = 1 << 14


@dataclass
class Work:
    """Means over the sample rays (see the module docstring); ``rays`` the sample size."""

    rays: int
    cells: float
    refs: float | None
    hit: float
    length: float
    steps: float | None = None
    candidates: float | None = None
    tests: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


#: the traversal's own counts (``UniformGrid.traversal_work``) a Work carries, per ray
TRAVERSAL = ("steps", "candidates", "tests")


def traversal_counts(before: dict, after: dict) -> dict:
    """The per-ray means of the traversal counts between two ``traversal_work()`` readings
    of one grid in one thread (the trace between them); {} when no ray was traced."""
    rays = after["rays"] - before["rays"]
    return {k: (after[k] - before[k]) / rays for k in TRAVERSAL} if rays > 0 else {}


def grid_work(grid, origins, directions, t_hit, tmin=0.0, tmax=np.inf, *, refs: bool = True,
              traversal: dict | None = None) -> Work:
    """Per-ray work counts of the rays ``origins + t directions`` through ``grid``, whose
    nearest hits are at ``t_hit`` (inf for a miss), averaged over the rays; ``refs=False``
    leaves the reference count out (None).  traversal: the grid's own counts of the trace
    that found ``t_hit`` (``traversal_counts``), kept as they are."""
    w = _geometric_work(grid, origins, directions, t_hit, tmin, tmax, refs)
    for k, v in (traversal or {}).items():
        setattr(w, k, float(v))
    return w


def _geometric_work(grid, origins, directions, t_hit, tmin, tmax, refs: bool) -> Work:
    """``grid_work``'s counts from the rays and the grid's geometry alone."""
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    m = len(o)
    if m == 0:
        return Work(0, 0.0, 0.0 if refs else None, 0.0, 0.0)
    lo = np.asarray(grid.lo, np.float64)
    cs = np.asarray(grid.cell_size, np.float64)
    res = np.asarray(grid.res, np.int64)
    hi = lo + cs * res
    tn, tf = slab_interval(o, d, lo, hi)
    ts = np.maximum(tn.max(axis=1), np.broadcast_to(np.asarray(tmin, np.float64), (m,)))
    te = np.minimum(tf.min(axis=1), np.broadcast_to(np.asarray(tmax, np.float64), (m,)))
    th = np.asarray(t_hit, np.float64)
    hit = np.isfinite(th)
    te = np.where(hit, np.minimum(te, th), te)
    live = ts <= te
    if not live.any():
        return Work(m, 0.0, 0.0 if refs else None, float(hit.mean()), 0.0)
    o, d, ts, te = o[live], d[live], ts[live], te[live]

    def cell(oo, dd, t):
        p = oo + t[:, None] * dd
        return np.clip(np.floor((p - lo) / cs), 0, res - 1).astype(np.int64)

    i0, i1 = cell(o, d, ts), cell(o, d, te)
    cells = 1 + np.abs(i1 - i0).sum(axis=1)
    diag = float(np.sqrt(((hi - lo) ** 2).sum())) or 1.0
    length = (te - ts) * np.sqrt((d * d).sum(axis=1)) / diag
    mean_cells, mean_length, hit_share = float(cells.sum() / m), float(length.sum() / m), float(hit.mean())
    if not refs:
        return Work(m, mean_cells, None, hit_share, mean_length)
    counts = np.diff(np.asarray(grid.cell_start)[: int(np.prod(res)) + 1])
    stride = np.array([1, res[0], res[0] * res[1]], np.int64)
    sub = np.unique(np.linspace(0, len(o) - 1, min(len(o), REFS_RAYS)).astype(np.int64))
    mean_refs = np.zeros(len(sub))
    so, sd, sts, ste = o[sub], d[sub], ts[sub], te[sub]
    for fj in (np.arange(POINTS) + 0.5) / POINTS:
        mean_refs += counts[cell(so, sd, sts + fj * (ste - sts)) @ stride]
    mean_refs /= POINTS
    live_share = len(ts) / m  # rays that miss the grid's box step through no cell: zeros in the means
    return Work(m, mean_cells, float((cells[sub] * mean_refs).mean()) * live_share, hit_share, mean_length)
