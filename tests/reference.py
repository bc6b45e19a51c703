"""An independent float64 ray/triangle reference for the tests (does not use core/intersect.py).

Möller and Trumbore, "Fast, minimum storage ray-triangle intersection" (JGT 1997),
evaluated in float64 over every (ray, triangle) pair that survives a conservative
bounding-sphere cull.  Conventions follow ../shared/DESIGN.md: nearest hit with
tmin < t <= tmax, lowest triangle index on an exact tie, both faces hit, degenerate
(zero-area) triangles never hit, t in units of the given (unnormalised) direction.

Inputs are rounded to float32 first and then widened to float64: the project's
structures store float32 vertices and round rays (and tmin/tmax) to float32, so this
compares like with like and the only differences left are the structures' arithmetic.

A float32 kernel and this reference may legitimately disagree on a ray that passes
within float32 noise of a triangle's edge or vertex, runs (nearly) in a triangle's
plane, hits two triangles at nearly the same t, or hits right at tmin or tmax.
``RefHits.ambiguous`` marks those rays; tests demand identical triangles elsewhere.
"Grazing" is measured where a float32 kernel makes its error, in world units: the
ray's line passes within ``GRAZE_EPS * scale`` of an edge (segment), where scale is
the largest coordinate magnitude of the triangle and the ray origin.  (A barycentric
margin would call a ray through a tiny triangle far from the origin "clear" although
the triangle is only a few float32 ulps wide there.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a ray whose line passes within GRAZE_EPS * (coordinate scale) of an edge grazes it
GRAZE_EPS = 1e-5
#: hits of different triangles closer than this (relative) are a near tie
TIE_RTOL = 1e-6
#: |cos(ray, normal)| below this: the ray runs (nearly) in the triangle's plane
PARALLEL_COS = 1e-7


@dataclass
class RefHits:
    t: np.ndarray  # (M,) float64, inf on a miss
    triangle: np.ndarray  # (M,) int64, -1 on a miss
    u: np.ndarray  # (M,) float64 barycentrics (0 on a miss)
    v: np.ndarray
    ambiguous: np.ndarray  # (M,) bool: grazing, near-tie or near tmin/tmax: triangle may differ

    @property
    def hit(self):
        return self.triangle >= 0


def _as64(a, shape_tail):
    a = np.asarray(a, dtype=np.float32).astype(np.float64)
    return a.reshape((-1,) + shape_tail)


def reference_trace(tri_vertices, origins, directions, tmin=0.0, tmax=np.inf, pairs_per_block=1 << 22) -> RefHits:
    """Nearest hits of rays against triangles, all pairs, in float64.

    tri_vertices: (T, 3, 3) corners (``TriangleMesh.tri_vertices``, or any array).
    origins, directions: (M, 3); tmin, tmax: scalars or (M,).
    """
    tv = _as64(tri_vertices, (3, 3))
    o = _as64(origins, (3,))
    d = _as64(directions, (3,))
    m, n = len(o), len(tv)
    lo = np.broadcast_to(np.asarray(tmin, np.float32).astype(np.float64), (m,))
    hi = np.broadcast_to(np.asarray(tmax, np.float32).astype(np.float64), (m,))
    out_t = np.full(m, np.inf)
    out_tri = np.full(m, -1, np.int64)
    out_u = np.zeros(m)
    out_v = np.zeros(m)
    if m == 0 or n == 0:
        return RefHits(out_t, out_tri, out_u, out_v, np.zeros(m, bool))

    e1 = tv[:, 1] - tv[:, 0]
    e2 = tv[:, 2] - tv[:, 0]
    normal = np.cross(e1, e2)
    degenerate = ~(normal != 0).any(axis=1)
    nlen = np.linalg.norm(normal, axis=1)
    tri_scale = np.abs(tv).max(axis=(1, 2))

    # bounding spheres for the cull: centre = mean of the corners, radius = farthest corner
    c = tv.mean(axis=1)
    r = np.sqrt(((tv - c[:, None, :]) ** 2).sum(axis=2)).max(axis=1)
    cc = (c * c).sum(axis=1)
    dlen = np.linalg.norm(d, axis=1)
    dn = d / dlen[:, None]
    oo = (o * o).sum(axis=1)
    od = (o * dn).sum(axis=1)
    ray_scale = np.abs(o).max(axis=1)

    parts = []
    block = max(1, pairs_per_block // m)
    for s in range(0, n, block):
        sl = slice(s, min(n, s + block))
        # distance^2 from each sphere centre to each ray's line, via two matrix products
        # (|c|^2 - 2 c.o + |o|^2 - ((c - o).dn)^2), in place to keep the (B, M) passes few;
        # the slack covers the cancellation of this expanded form.  Candidates behind the
        # origin are not culled here: the exact test below rejects them.
        dist2 = c[sl] @ (-2.0 * o).T
        dist2 += cc[sl, None]
        dist2 += oo[None, :]
        proj = c[sl] @ dn.T
        proj -= od[None, :]
        proj *= proj
        dist2 -= proj
        slack = 1e-12 * (cc[sl].max() + oo.max()) + 1e-300
        # keep near misses too (they decide which rays are ambiguous): pad by the graze distance
        rr = r[sl] * (1 + 1e-9) + GRAZE_EPS * max(tri_scale[sl].max(), ray_scale.max())
        near = dist2 <= (rr * rr + slack)[:, None]
        ti, ri = np.nonzero(near)
        if ti.size == 0:
            continue
        ti = ti + s
        keep = ~degenerate[ti]
        ti, ri = ti[keep], ri[keep]
        t, u, v, par = _moller_trumbore(o[ri], d[ri], tv[ti, 0], e1[ti], e2[ti], nlen[ti], dlen[ri])
        marg = np.minimum(np.minimum(u, v), 1.0 - u - v)
        hit = (~par) & (marg >= 0) & (t > lo[ri]) & (t <= hi[ri])
        # grazing: the ray's line passes within graze distance of an edge; tg is where
        gd, tg = _edge_distance(o[ri], d[ri], dn[ri], tv[ti])
        graze = gd <= GRAZE_EPS * np.maximum(tri_scale[ti], ray_scale[ri])
        keep = hit | graze | par
        parts.append((ri[keep], ti[keep], np.where(hit, t, np.inf)[keep], u[keep], v[keep],
                      np.where(graze, tg, np.inf)[keep], par[keep]))

    if not parts:
        return RefHits(out_t, out_tri, out_u, out_v, np.zeros(m, bool))
    ray, tri, t, u, v, tg, par = (np.concatenate(x) for x in zip(*parts))

    # nearest hit by the stated convention: by ray, then t, then triangle index
    order = np.lexsort((tri, t, ray))
    first = np.ones(order.size, bool)
    first[1:] = ray[order][1:] != ray[order][:-1]
    win = order[first & np.isfinite(t[order])]
    out_t[ray[win]] = t[win]
    out_tri[ray[win]] = tri[win]
    out_u[ray[win]] = u[win]
    out_v[ray[win]] = v[win]

    # ambiguous rays: another triangle hits within a near tie of the winner; or the ray
    # grazes an edge at or before the winner, within the interval; or runs in a plane;
    # or the winner sits right at tmin or tmax
    tb = out_t[ray]
    near_tb = tb + TIE_RTOL * np.where(np.isfinite(tb), np.abs(tb), 0.0)
    tie = np.isfinite(t) & (tri != out_tri[ray]) & (t <= near_tb)
    tol = TIE_RTOL * np.abs(tg)
    grazing = np.isfinite(tg) & (tg > lo[ray] - tol) & (tg <= hi[ray] + tol) & (tg <= near_tb)
    ambiguous = np.zeros(m, bool)
    ambiguous[ray[tie | grazing | par]] = True
    tw = out_t[np.isfinite(out_t)]
    edge = np.isfinite(out_t)
    edge[edge] = (np.abs(tw - lo[edge]) <= TIE_RTOL * np.abs(tw)) | (np.abs(tw - hi[edge]) <= TIE_RTOL * np.abs(tw))
    ambiguous |= edge
    return RefHits(out_t, out_tri, out_u, out_v, ambiguous)


def _moller_trumbore(o, d, v0, e1, e2, nlen, dlen):
    """float64 Möller-Trumbore for pairs: t, u, v (inf/-inf where det = 0), near-parallel flag."""
    pvec = np.cross(d, e2)
    det = (e1 * pvec).sum(axis=1)  # = -d . (e1 x e2)
    par = np.abs(det) <= PARALLEL_COS * nlen * dlen
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(det != 0, 1.0 / det, 0.0)
        s = o - v0
        u = (s * pvec).sum(axis=1) * inv
        q = np.cross(s, e1)
        v = (d * q).sum(axis=1) * inv
        t = (e2 * q).sum(axis=1) * inv
    t = np.where(det != 0, t, np.inf)
    u = np.where(det != 0, u, -np.inf)
    v = np.where(det != 0, v, -np.inf)
    return t, u, v, par


def _edge_distance(o, d, dn, tv):
    """Smallest distance from each ray's line to its triangle's three edge segments,
    and the ray parameter t of the closest point on that edge."""
    best = np.full(len(o), np.inf)
    best_t = np.full(len(o), np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        A = tv[:, a]
        e = tv[:, b] - A
        w = A - o
        ex = np.cross(e, dn)
        wx = np.cross(w, dn)
        # |(w + s e) x dn|^2 = qa s^2 + 2 qb s + qc, minimised over s in [0, 1]
        qa = (ex * ex).sum(axis=1)
        qb = (wx * ex).sum(axis=1)
        qc = (wx * wx).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            sc = np.clip(np.where(qa > 0, -qb / qa, 0.0), 0.0, 1.0)
        dist = np.sqrt(np.maximum(qa * sc * sc + 2 * qb * sc + qc, 0.0))
        q = A + sc[:, None] * e
        tq = ((q - o) * d).sum(axis=1) / (d * d).sum(axis=1)
        better = dist < best
        best = np.where(better, dist, best)
        best_t = np.where(better, tq, best_t)
    return best, best_t


def reference_for_mesh(mesh, origins, directions, tmin=0.0, tmax=np.inf) -> RefHits:
    """``reference_trace`` over a core.TriangleMesh's corners (only its arrays are used)."""
    verts = np.asarray(mesh.vertices)
    tris = np.asarray(mesh.triangles)
    return reference_trace(verts[tris].reshape(-1, 3, 3), origins, directions, tmin, tmax)


# -- structures and scenes shared by the tests ----------------------------------------------

#: the structures that share the numpy kernel and must agree hit for hit
NUMPY_KINDS = ("brute", "grid", "bvh")


def kind_missing_reason(kind):
    """Why ``kind`` cannot be tested here (None when it can).

    Only Embree is optional (embreex may be missing); every numpy structure must exist,
    so a missing module fails the test instead of skipping it.
    """
    from hybrid_raycast import core

    if kind == "embree" and not core.embree_available():
        return "embreex is not installed"
    return None


def kind_params(kinds):
    """pytest params for ``kinds``, each skipped with its reason where unavailable."""
    import pytest

    out = []
    for k in kinds:
        why = kind_missing_reason(k)
        out.append(pytest.param(k, marks=pytest.mark.skip(reason=why)) if why else pytest.param(k))
    return out



def icosphere(subdivisions=1, radius=1.0):
    """Closed, consistently wound icosphere: (vertices float64, triangles int32)."""
    p = (1 + 5 ** 0.5) / 2
    v = [(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p), (0, -1, -p), (0, 1, -p),
         (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(x, float) / np.linalg.norm(x) for x in v]
    for _ in range(subdivisions):
        mid = {}

        def midpoint(a, b):
            key = (min(a, b), max(a, b))
            if key not in mid:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                mid[key] = len(verts) - 1
            return mid[key]

        nf = []
        for a, b, c in f:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = nf
    return np.array(verts) * radius, np.array(f, np.int32)


def cube(lo=(-1.0, -1.0, -1.0), hi=(1.0, 1.0, 1.0)):
    """Closed box of 12 triangles: (vertices float64, triangles int32)."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return corners, np.array(tris, np.int32)


def uv_sphere(rings=16, segments=24, radius=1.0, center=(0.0, 0.0, 0.0)):
    """Tessellated sphere with poles (shared vertices, fans at the poles)."""
    th = np.linspace(0, np.pi, rings + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)
    v = np.vstack([[0, 0, 1], ring, [0, 0, -1]]) * radius + np.asarray(center)
    s = segments
    tris = []
    for j in range(s):
        tris.append((0, 1 + j, 1 + (j + 1) % s))
    for i in range(rings - 2):
        for j in range(s):
            a, b = 1 + i * s + j, 1 + i * s + (j + 1) % s
            c, d = a + s, b + s
            tris += [(a, c, d), (a, d, b)]
    last = len(v) - 1
    base = 1 + (rings - 2) * s
    for j in range(s):
        tris.append((last, base + (j + 1) % s, base + j))
    return v, np.array(tris, np.int32)


def terrain(n=24, size=10.0, height=1.0, seed=0):
    """Height field over an n x n grid of quads (2 triangles each)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(x, x, indexing="ij")
    Z = height * (np.sin(X) * np.cos(0.7 * Y) + 0.2 * rng.standard_normal(X.shape))
    v = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, tris.astype(np.int32)


def triangle_soup(n=300, seed=0, size=10.0):
    """Random triangles of widely varying size in a box (unshared vertices)."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-size / 2, size / 2, (n, 1, 3))
    scale = size * 10 ** rng.uniform(-3, -0.5, (n, 1, 1))
    v = (centre + scale * rng.standard_normal((n, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * n, dtype=np.int32).reshape(n, 3)


def vertex_and_edge_targets(vertices, triangles):
    """Points exactly at the used vertices and at every edge midpoint (float64)."""
    v = np.asarray(vertices, np.float32).astype(np.float64)
    t = np.asarray(triangles)
    used = v[np.unique(t)]
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    return np.vstack([used, 0.5 * (v[e[:, 0]] + v[e[:, 1]])])


def describe_ray(i, origins, directions):
    o = np.asarray(origins, np.float32)[i]
    d = np.asarray(directions, np.float32)[i]
    return f"ray {i} (origin {o.tolist()}, direction {d.tolist()})"


def first_differences(a, b, mask=None, limit=5):
    """Indices where a != b (optionally within mask), at most ``limit``, and the count."""
    diff = np.asarray(a) != np.asarray(b)
    if mask is not None:
        diff &= mask
    w = np.flatnonzero(diff)
    return w[:limit], w.size
