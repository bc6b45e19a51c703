"""The plan's one decision rule: which structure to trace R rays with, given their costs.

Hapala, Karlik and Havran (2011), section 3, step 5: keep the grid while R <= R*, else
build H.  With several candidates this is the least total cost, the grid's build sunk:
``R t_G`` for the grid against ``T_B^H + R t_H`` for each H, which is the same as
"the grid while R <= min_H R*_H, else the cheapest H" (R t_G <= T_B + R t_H exactly when
R <= T_B / (t_G - t_H)).  Ties go to the grid (nothing more to build), then to the first
name in alphabetical order.

When the plan's K samples are K of the workload's rays, their answers are kept by the
structures in REUSES_SAMPLES, so those trace only the R - K others; every other
structure retraces all R (``answered``).

Over a structure's life (``over_life``: the persistent scene's choice per mesh) nothing is
sunk but what is built already: each structure costs its build, unless built, plus the
rays it is expected to serve over its life times its time per ray.
"""

from __future__ import annotations

import math

import numpy as np

from .cost import Cost, break_even

#: structures that answer every ray bit for bit like the grid: a plan that drew its samples
#: from the workload keeps their answers when it chooses one of these
REUSES_SAMPLES = ("grid", "bvh")


def costs(rays, grid_per_ray: float, candidates: dict, answered: int = 0) -> tuple[list[str], np.ndarray]:
    """(names, costs): the grid first, then the candidates by name; ``costs[i, j]`` is the
    predicted time of names[i] for rays[j], the grid's build excluded (it is sunk).

    candidates: {kind: ``cost.Cost``} (its point figures); answered: rays of the workload the
    grid's samples have answered already."""
    r = np.atleast_1d(np.asarray(rays, np.float64))
    left = np.maximum(r - max(0, int(answered)), 0.0)
    names = ["grid"] + sorted(candidates)
    rows = [left * float(grid_per_ray)]
    for k in names[1:]:
        c = candidates[k]
        rows.append(float(c.build_time) + (left if k in REUSES_SAMPLES else r) * float(c.per_ray))
    return names, np.stack(rows)


def choose(rays, grid_per_ray: float, candidates: dict, answered: int = 0, floor: float = 0.0) -> np.ndarray:
    """The structure (a name) with the least predicted cost for each ray count in ``rays``.

    floor: the calibration's lower bound on the break-even (``Calibration.prior``); at most
    this many rays keep the grid whatever the costs say, since no structure pays back its
    build there on the calibration's own evidence (and the plan takes no sample)."""
    names, c = costs(rays, grid_per_ray, candidates, answered)
    picked = np.asarray(names, dtype=object)[np.argmin(c, axis=0)]
    return np.where(np.atleast_1d(np.asarray(rays, np.float64)) <= floor, "grid", picked).astype(object)


def over_life(estimates: dict, rays: float, built=()) -> tuple[str, dict, float, str | None]:
    """(kind, totals, break_even, break_even_kind) for a structure expected to serve ``rays``
    rays over its life: the least predicted total, ``built`` kinds' builds sunk, ties to the
    grid, then by name (as ``choose``).

    estimates: {kind: ``cost.Cost``}; totals: {kind: seconds}.  break_even: the rays of
    its life from which a structure beats the grid, both owned as they are (a built one
    free), the least over the candidates (0: one beats the grid at once; inf: none ever
    does), and the candidate that attains it; inf and None without a grid estimate."""
    r = max(float(rays), 0.0)
    owned = {k: (0.0 if k in built else float(c.build_time)) for k, c in estimates.items()}
    totals = {k: owned[k] + r * float(c.per_ray) for k, c in estimates.items()}
    kind = min(totals, key=lambda k: (totals[k], k != "grid", k))
    g = estimates.get("grid")
    best, be_kind = math.inf, None
    if g is not None:
        for k in sorted(estimates):
            if k == "grid":
                continue
            be = break_even(max(owned[k] - owned["grid"], 0.0), float(g.per_ray), float(estimates[k].per_ray))
            if be < best:
                best, be_kind = be, k
    return kind, totals, best, be_kind


#: a plan for a surface mesh (``TriangleMesh.is_surface``) builds a structure H at once, with
#: neither the grid nor a sample, from the rays where building H costs at most this share more
#: than building the grid, on the calibration's estimates for N (``regret_bound``)
SETTLE_SLACK = 0.05


def regret_bound(grid, estimate, slack: float = SETTLE_SLACK) -> float:
    """The rays from which building ``estimate``'s structure H (a ``cost.Cost`` for N) costs,
    builds included, at most ``slack`` more than building the grid, on the point figures of
    the calibration's estimates for N (``grid``: ``Calibration.grid_estimate``):
    R = (T_B^H - (1 + s) T_B^G) / ((1 + s) t_G - t_H), 0 where H's build is within the slack
    of the grid's, inf where H is not faster per ray than (1 + s) t_G.  For every R above it
    H's total is within the slack of the grid's, so a plan that builds H at once there loses
    little where the grid would have won, and saves the grid's build and the sample, which
    near the break-even cost more than a wrong pick does.

    Only for a surface: the calibration's scenes include soups, whose trees' boxes overlap, so
    its estimate of the numpy BVH's time per ray runs high on a surface mesh and the figures
    lean to the grid; on a soup the tree may trace slower than the grid, which only a sample
    sees (BENCHMARKS.md, "The new evaluation set")."""
    s = 1.0 + float(slack)
    gain = s * float(grid.per_ray) - float(estimate.per_ray)
    if not gain > 0:
        return math.inf
    return max(float(estimate.build_time) - s * float(grid.build_time), 0.0) / gain


def settle_bound(grid, estimate, ceiling: float | None, surface: bool = False) -> float:
    """The rays from which a plan builds ``estimate``'s structure H (a ``cost.Cost`` for N) at
    once, nothing being built yet, and neither the grid nor a sample (inf: never).

    Where the calibration bounds the break-even against H over all its scenes (``ceiling``;
    None where it does not), from where building H beats building the grid,
    R_0 = (T_B^H - T_B^G) / (t_G - t_H) with the grid's build and time per ray at the low end
    of the calibration's estimate for N (``grid``, ``Calibration.grid_estimate``; 0 where H
    builds faster, inf where the grid is faster per ray), never above the ceiling; for a
    ``surface`` mesh, from ``regret_bound`` if that comes first."""
    sure = math.inf
    if ceiling is not None:
        sure = float(ceiling)
        if grid is not None:
            sure = min(sure, break_even(max(float(estimate.build_time) - float(grid.build_low), 0.0),
                                        float(grid.per_ray_low), float(estimate.per_ray)))
    if surface and grid is not None:
        return min(sure, regret_bound(grid, estimate))
    return sure


def unsampled(grid, estimates: dict) -> tuple[float, dict]:
    """(grid time per ray, {kind: Cost}) the rule weighs when a plan decides on the
    calibration's estimates for N alone (no sample: ``core.plan.sample_pays``): the grid at
    the low end of its estimate (``Calibration.grid_estimate``), each candidate's time per ray
    at the high end of its own, so that a structure is built only where it wins on figures
    that favour the grid already built."""
    return float(grid.per_ray_low), {k: Cost.point(k, e.build_time, e.per_ray_high) for k, e in estimates.items()}
