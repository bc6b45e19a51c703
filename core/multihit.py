"""Every hit along each ray, nearest first: repeated nearest-hit queries.

Each round traces the rays that hit something in the last round again, from just past
their last hit: tmin becomes the next float32 after the last t, so tmin strictly grows and
the loop ends (after at most one round per distinct float32 t).  A ray through a shared
edge or vertex of a closed mesh meets two or more triangles at the same point; their t
differ by rounding only, so a hit within ``SAME_POINT_ULPS`` float32 ulps of the
ray's previous hit is the same point and is dropped (the first, which by the hit
convention has the lowest triangle index at an exact tie, is kept).  Coplanar overlapping
surfaces are therefore reported once.
"""

from __future__ import annotations

import numpy as np

from .intersect import prepare_rays

#: hits closer than this many float32 ulps of t to the ray's previous hit are the same point
SAME_POINT_ULPS = 8


def all_hits(accel, origins, directions, tmin=0.0, tmax=np.inf, max_hits: int = 16):
    """(ray, t, triangle, u, v) flat arrays sorted by ray then t, at most ``max_hits`` per ray.

    ``accel`` is any structure (``core.build``); the hit convention is its ``trace``'s.
    """
    max_hits = int(max_hits)
    if max_hits < 1:
        raise ValueError(f"max_hits must be at least 1, got {max_hits}")
    rays = prepare_rays(origins, directions, tmin, tmax)
    m = len(rays)
    lo = rays.tmin.copy()
    hi = rays.tmax
    count = np.zeros(m, np.int32)
    last = np.full(m, -np.inf, np.float32)
    active = np.arange(m)
    parts = []
    while active.size:
        h = accel.trace(rays.origins[active], rays.directions[active], lo[active], hi[active])
        got = h.hit
        idx, t = active[got], h.t[got]
        with np.errstate(invalid="ignore"):  # no previous hit: inf - inf
            same = np.abs(t - last[idx]) <= SAME_POINT_ULPS * np.spacing(np.abs(t))
        keep = ~same
        k = idx[keep]
        parts.append((k, t[keep], h.triangle[got][keep], h.u[got][keep], h.v[got][keep]))
        count[k] += 1
        last[k] = t[keep]
        with np.errstate(over="ignore"):
            lo[idx] = np.nextafter(t, np.float32(np.inf))
        active = idx[(count[idx] < max_hits) & (lo[idx] <= hi[idx])]
    if parts:
        ray, t, tri, u, v = (np.concatenate(c) for c in zip(*parts))
    else:
        ray, t, tri, u, v = (np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.int32),
                             np.zeros(0, np.float32), np.zeros(0, np.float32))
    order = np.lexsort((t, ray))
    return ray[order], t[order], tri[order], u[order], v[order]
