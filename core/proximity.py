"""Point queries on the structures' triangles: the closest point, the generalized winding
number (inside / outside on any mesh) and the number of hits along a ray.

Every function takes the triangles as a ``TriangleMesh`` and, for the hierarchical versions,
a ``TreeIndex``: the arrays of a 4-wide BVH (``bvh.BVH``'s layout), so this module imports
no structure.  ``accel.Accel`` exposes them as ``closest``, ``winding_number``, ``inside``,
``signed_distance`` and ``count_hits`` on every structure.

Conventions (those of the ray queries, ../shared/DESIGN.md):
- only valid triangles count (``TriangleMesh.valid``: a degenerate one is never hit, and never
  closest);
- the closest point: the least Euclidean distance, computed in float64 from the float32
  vertices; an exact tie goes to the lowest triangle index; ``max_distance`` is inclusive,
  and a point with nothing within it is a documented miss (distance inf, triangle -1);
- the winding number (Jacobson, Kavan and Sorkine-Hornung 2013): the sum of the triangles'
  signed solid angles over 4 pi, 1 inside a closed mesh whose triangles wind counter-clockwise
  seen from outside, 0 outside, and in between near holes; ``inside`` is w > 0.5, so it holds
  on open meshes, meshes with holes, self-intersections and overlapping shells.  The tree
  version is Barill et al. (2018): a subtree seen from farther than ``accuracy`` times its
  radius counts as its dipole (the area-weighted normal at its area centroid), nearer ones
  are opened, and leaves near the point are summed exactly;
- ``count_hits``: the distinct hits with tmin < t <= tmax, where hits of the same ray within
  ``multihit.SAME_POINT_ULPS`` float32 ulps of t are one point (a ray through a shared edge
  counts once), as ``core.all_hits`` counts them.

Bad input raises ``ValueError`` naming the argument: points that are not (M, 3) or (3,),
NaN or infinite coordinates, a ``max_distance`` that is not positive or is NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .intersect import Rays, intersect, prepare_rays, slab_interval
from .mesh import TriangleMesh
from .multihit import SAME_POINT_ULPS

F64 = np.float64
#: the default of ``winding_number``'s ``accuracy`` (Barill et al.'s beta): a subtree farther
#: than this many of its radii counts as its dipole.  Larger is more exact and slower; the
#: tests check inside/outside against the exact sum wherever |w - 0.5| > 0.1
ACCURACY = 2.5
#: (point, node) pairs stepping together in the tree searches: bounds the working memory
#: whatever the points' neighbourhoods look like (a point at a sphere's centre is equally far
#: from every box)
PAIRS = 1 << 18
#: point-triangle pairs per block of the brute force
BRUTE_PAIRS = 1 << 20
#: points searched together by the trees (the greedy descent holds every one's boxes)
POINT_CHUNK = 1 << 17


@dataclass
class Nearest:
    """The closest surface point of each query point; per point (M,).

    distance: float64 Euclidean distance (inf where nothing is within ``max_distance``)
    triangle: int32 index of the closest triangle (-1 on a miss)
    points: (M, 3) float64 the closest point on it (NaN on a miss)
    u, v: float32 its barycentrics, point = (1-u-v) v0 + u v1 + v v2 (0 on a miss)
    """

    distance: np.ndarray
    triangle: np.ndarray
    points: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def __len__(self):
        return len(self.distance)

    @property
    def found(self) -> np.ndarray:
        return self.triangle >= 0

    FIELDS = ("distance", "triangle", "points", "u", "v")

    @classmethod
    def concat(cls, parts) -> "Nearest":
        """The answers of consecutive parts of the points, as one."""
        parts = list(parts)
        return parts[0] if len(parts) == 1 else cls(*(np.concatenate([getattr(n, f) for n in parts])
                                                      for f in cls.FIELDS))

    @classmethod
    def gather(cls, m: int, parts) -> "Nearest":
        """The answers of (rows, ``Nearest``) parts that cover rows 0..m-1, each in its rows."""
        out = cls(np.empty(m), np.empty(m, np.int32), np.empty((m, 3)), np.empty(m, np.float32),
                  np.empty(m, np.float32))
        for rows, got in parts:
            for f in cls.FIELDS:
                getattr(out, f)[rows] = getattr(got, f)
        return out


# -- arguments -------------------------------------------------------------------------------

def check_points(points, name: str = "points") -> np.ndarray:
    """(M, 3) float64 finite points from (M, 3) or (3,) array-likes; a clear ValueError else."""
    try:
        p = np.asarray(points, F64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers, shaped (M, 3) or (3,)") from None
    if p.ndim == 1 and p.shape == (3,):
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must be shaped (M, 3) or (3,), got {p.shape}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} rows with NaN or infinite coordinates (first: row "
                         f"{int(np.flatnonzero(bad)[0])})")
    return p


def check_max_distance(max_distance) -> float:
    try:
        d = float(max_distance)
    except (TypeError, ValueError):
        raise ValueError(f"max_distance must be a number, got {max_distance!r}") from None
    if not d > 0:  # also NaN
        raise ValueError(f"max_distance must be positive (inf: no limit), got {max_distance!r}")
    return d


# -- one point against one triangle -------------------------------------------------------------

def closest_on_triangles(p, a, b, c):
    """The closest point of each triangle (a, b, c) to p, all (P, 3) float64: (squared
    distance (P,), u (P,), v (P,)) with the point (1-u-v) a + u b + v c.  Ericson's regions
    (Real-Time Collision Detection, 5.1.5), vectorised; the triangles are not degenerate."""
    return closest_on_columns(*([x[:, k] for k in range(3)] for x in (p, a, b, c)))


def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


#: point-triangle pairs ``closest_on_columns`` takes at a time: its forty-odd passes then
#: work on arrays that stay in the core's cache instead of streaming through memory
KERNEL_BLOCK = 1 << 13


def closest_on_columns(p, a, b, c):
    """``closest_on_triangles`` with each of p, a, b, c given as its three coordinate
    columns (P,), in blocks of ``KERNEL_BLOCK`` pairs."""
    n = len(p[0])
    if n <= KERNEL_BLOCK:
        return _closest_block(p, a, b, c)
    d2, u, v = np.empty(n), np.empty(n), np.empty(n)
    for s in range(0, n, KERNEL_BLOCK):
        sl = slice(s, s + KERNEL_BLOCK)
        d2[sl], u[sl], v[sl] = _closest_block(*([x[sl] for x in y] for y in (p, a, b, c)))
    return d2, u, v


def _closest_block(p, a, b, c):
    ab = [b[k] - a[k] for k in range(3)]
    ac = [c[k] - a[k] for k in range(3)]
    ap = [p[k] - a[k] for k in range(3)]
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = [p[k] - b[k] for k in range(3)]
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = [p[k] - c[k] for k in range(3)]
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    with np.errstate(divide="ignore", invalid="ignore"):
        in_a = (d1 <= 0) & (d2 <= 0)
        in_b = (d3 >= 0) & (d4 <= d3)
        in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        in_c = (d6 >= 0) & (d5 <= d6)
        in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        in_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        s_ab = d1 / (d1 - d3)
        s_ac = d2 / (d2 - d6)
        s_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        den = va + vb + vc
        f_u, f_v = vb / den, vc / den
    regions = [in_a, in_b, in_ab, in_c, in_ac, in_bc]
    u = np.select(regions, [0.0, 1.0, s_ab, 0.0, 0.0, 1.0 - s_bc], f_u)
    v = np.select(regions, [0.0, 0.0, 0.0, 1.0, s_ac, s_bc], f_v)
    d = [p[k] - (a[k] + u * ab[k] + v * ac[k]) for k in range(3)]
    return _dot(d, d), u, v


def _better(d2, tri, best_d2, best_tri):
    """Where (d2, tri) improves on (best_d2, best_tri): less distance, or the same and a lower index."""
    return (d2 < best_d2) | ((d2 == best_d2) & (tri < best_tri) & (tri >= 0))


def _reduce_pairs(owner, tri, d2, u, v, best):
    """Fold point-triangle pairs (owner = the point's row; a triangle at most once per owner)
    into ``best`` (d2, tri, u, v arrays): per owner the least d2, an exact tie to the lowest
    triangle index, and only where that improves on what ``best`` holds."""
    if owner.size == 0:
        return
    bd, bt, bu, bv = best
    low = bd.copy()
    np.minimum.at(low, owner, d2)
    at_low = d2 == low[owner]
    big = np.iinfo(np.int64).max
    first = np.where(bd == low, np.where(bt < 0, big, bt), big)  # a tie with best: its index counts too
    np.minimum.at(first, owner[at_low], tri[at_low])
    win = at_low & (tri == first[owner])
    o = owner[win]
    bd[o], bt[o], bu[o], bv[o] = d2[win], tri[win], u[win], v[win]


def _nearest(points, best, tv64) -> Nearest:
    d2, tri, u, v = best
    found = tri >= 0
    q = np.full(points.shape, np.nan)
    if found.any():
        t = tv64[tri[found]]
        uu, vv = u[found][:, None], v[found][:, None]
        q[found] = (1.0 - uu - vv) * t[:, 0] + uu * t[:, 1] + vv * t[:, 2]
    dist = np.where(found, np.sqrt(np.where(found, d2, 0.0)), np.inf)
    return Nearest(dist, tri.astype(np.int32), q, np.where(found, u, 0).astype(np.float32),
                   np.where(found, v, 0).astype(np.float32))


def _fresh_best(m, max_distance):
    md2 = max_distance * max_distance if math.isfinite(max_distance) else np.inf
    return [np.full(m, md2), np.full(m, -1, np.int64), np.zeros(m), np.zeros(m)]


# -- brute force (the reference) ------------------------------------------------------------------

def _all_pairs(m: int, tris):
    """(row, triangle) for every row in range(m) against every triangle in ``tris``, in blocks
    of about ``BRUTE_PAIRS`` pairs (whole rows each): the brute forces' loop."""
    if m == 0 or tris.size == 0:
        return
    per = max(1, BRUTE_PAIRS // tris.size)
    for s in range(0, m, per):
        rows = np.arange(s, min(m, s + per))
        yield np.repeat(rows, tris.size), np.tile(tris, rows.size)


def closest_brute(mesh: TriangleMesh, points, max_distance=np.inf) -> Nearest:
    """Every point against every valid triangle, in blocks: the reference for the tree."""
    p = check_points(points)
    md = check_max_distance(max_distance)
    tv64 = mesh.tri_vertices.astype(F64)
    best = _fresh_best(len(p), md)
    for owner, tri in _all_pairs(len(p), np.flatnonzero(mesh.valid)):
        t = tv64[tri]
        d2, u, v = closest_on_triangles(p[owner], t[:, 0], t[:, 1], t[:, 2])
        _reduce_pairs(owner, tri, d2, u, v, best)
    return _nearest(p, best, tv64)


def solid_angles(p, a, b, c) -> np.ndarray:
    """Signed solid angle of each triangle (a, b, c) seen from p, all (P, 3) float64 (Van
    Oosterom and Strackee): positive when p is behind the triangle's counter-clockwise face."""
    A, B, C = a - p, b - p, c - p
    la, lb, lc = (np.sqrt(np.einsum("ij,ij->i", x, x)) for x in (A, B, C))
    num = np.einsum("ij,ij->i", A, np.cross(B, C))
    den = (la * lb * lc + np.einsum("ij,ij->i", A, B) * lc + np.einsum("ij,ij->i", A, C) * lb
           + np.einsum("ij,ij->i", B, C) * la)
    return 2.0 * np.arctan2(num, den)


def winding_number_brute(mesh: TriangleMesh, points) -> np.ndarray:
    """The exact generalized winding number of every point: the sum over all valid triangles."""
    p = check_points(points)
    tv64 = mesh.tri_vertices.astype(F64)
    w = np.zeros(len(p))
    for owner, tri in _all_pairs(len(p), np.flatnonzero(mesh.valid)):
        t = tv64[tri]
        a, b = owner[0], owner[-1] + 1  # a block is whole consecutive rows
        w[a:b] += np.bincount(owner - a, solid_angles(p[owner], t[:, 0], t[:, 1], t[:, 2]), minlength=b - a)
    return w / (4.0 * math.pi)


def _distinct_counts(ray, t, m) -> np.ndarray:
    """Hits per ray, those within SAME_POINT_ULPS of the ray's previous one counted once."""
    if ray.size == 0:
        return np.zeros(m, np.int32)
    order = np.lexsort((t, ray))
    ray, t = ray[order], t[order]
    new = np.ones(ray.size, bool)
    same_ray = ray[1:] == ray[:-1]
    near = np.abs(t[1:] - t[:-1]) <= SAME_POINT_ULPS * np.spacing(np.abs(t[1:]))
    new[1:] = ~(same_ray & near)
    return np.bincount(ray[new], minlength=m).astype(np.int32)


def count_hits_brute(mesh: TriangleMesh, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
    """(M,) int32 distinct hits of every ray with every valid triangle (the reference)."""
    rays = prepare_rays(origins, directions, tmin, tmax)
    m = len(rays)
    found_r, found_t = [], []
    for r, tri in _all_pairs(m, np.flatnonzero(mesh.valid)):
        t = intersect(rays, r, tri, mesh.tri_vertices)
        ok = np.isfinite(t)
        found_r.append(r[ok])
        found_t.append(t[ok])
    if not found_r:
        return np.zeros(m, np.int32)
    return _distinct_counts(np.concatenate(found_r), np.concatenate(found_t), m)


# -- the tree ------------------------------------------------------------------------------------------

class TreeIndex:
    """A 4-wide BVH's arrays (``bvh.BVH``'s layout) over a mesh, for the point queries, with
    the per-subtree sums the winding number's far field needs, made on first use.

    boxes (W, 2, 3, 4) float64: lo / hi, axis, child slot (NaN for an empty slot); children
    (W, 4): >= 0 a wide node, < 0 the leaf ~code; leaf i holds triangles
    ``leaf_triangles[leaf_start[i]: leaf_start[i] + leaf_count[i]]``.
    """

    def __init__(self, mesh: TriangleMesh, node_boxes, node_children, leaf_start, leaf_count, leaf_triangles):
        self.mesh = mesh
        w = len(node_boxes)
        self.boxes = np.asarray(node_boxes, F64).reshape(w, 2, 3, 4)
        self.children = np.asarray(node_children, np.int64)
        self.leaf_start = np.asarray(leaf_start, np.int64)
        self.leaf_count = np.asarray(leaf_count, np.int64)
        self.leaf_triangles = np.asarray(leaf_triangles, np.int64)
        self.tv64 = mesh.tri_vertices.astype(F64)
        # float32 boxes about the mesh's centre (so their rounding is the extent's, not the
        # position's), each rounded outward so it still holds everything the exact box does
        self.centre = np.nanmean(self.boxes.reshape(w, 2, 3, 4)[:1], axis=(0, 1, 3)) if w else np.zeros(3)
        rel = self.boxes.reshape(w, 6, 4) - np.tile(self.centre, 2)[None, :, None]
        b32 = rel.astype(np.float32)
        b32[:, :3] = np.where(b32[:, :3] > rel[:, :3], np.nextafter(b32[:, :3], np.float32(-np.inf)), b32[:, :3])
        b32[:, 3:] = np.where(b32[:, 3:] < rel[:, 3:], np.nextafter(b32[:, 3:], np.float32(np.inf)), b32[:, 3:])
        self.boxes32 = np.ascontiguousarray(b32)
        #: (T, 9) each triangle's corners in a row (v0 x, y, z, v1 ..., v2 ...): ``np.take``
        #: of whole rows gathers from a large mesh fastest
        self.corner_rows = self.tv64.reshape(-1, 9)
        self.slot = ~np.isnan(self.boxes[:, 0, 0, :])  # (W, 4) a child is there
        self._dipoles = None

    def __len__(self):
        return len(self.boxes)

    def leaf_pairs(self, owner, leaf):
        """(owner repeated, triangle) for every triangle of each (owner, leaf) pair."""
        return _expand(owner, self.leaf_start[leaf], self.leaf_count[leaf], self.leaf_triangles)

    # -- the winding number's far field: per child slot, area, area centroid, area-weighted
    #    normal (the dipole) and the radius of a ball around the centroid holding the subtree
    def dipoles(self):
        if self._dipoles is not None:
            return self._dipoles
        tv = self.tv64
        lt = self.leaf_triangles
        t = tv[lt]
        cross = 0.5 * np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        area = np.sqrt(np.einsum("ij,ij->i", cross, cross))
        cen = t.mean(axis=1)
        nl = len(self.leaf_start)
        starts = self.leaf_start
        l_area = np.add.reduceat(area, starts) if nl else np.zeros(0)
        l_n = np.add.reduceat(cross, starts, axis=0) if nl else np.zeros((0, 3))
        l_ac = np.add.reduceat(area[:, None] * cen, starts, axis=0) if nl else np.zeros((0, 3))
        l_c = l_ac / l_area[:, None]  # a leaf holds valid triangles only: its area is positive
        # a leaf's radius: the farthest of its triangles' vertices from its centroid
        owner = np.repeat(np.arange(nl), self.leaf_count)
        far = np.sqrt(((t - l_c[owner][:, None, :]) ** 2).sum(axis=2)).max(axis=1)
        l_r = np.zeros(nl)
        np.maximum.at(l_r, owner, far)
        w = len(self.boxes)
        s_area, s_n, s_c, s_r = np.zeros((w, 4)), np.zeros((w, 4, 3)), np.zeros((w, 4, 3)), np.zeros((w, 4))
        node_area, node_n, node_c, node_r = np.zeros(w), np.zeros((w, 3)), np.zeros((w, 3)), np.zeros(w)
        # wide nodes are numbered breadth first: children after parents, so from the last back
        for level in reversed(self._levels()):
            ch = self.children[level]
            slot = self.slot[level]
            leaf = slot & (ch < 0)
            node = slot & (ch >= 0)
            li = np.where(leaf, ~ch, 0)
            ni = np.where(node, ch, 0)
            a = np.where(leaf, l_area[li], np.where(node, node_area[ni], 0.0))
            n = np.where(leaf[..., None], l_n[li], np.where(node[..., None], node_n[ni], 0.0))
            c = np.where(leaf[..., None], l_c[li], np.where(node[..., None], node_c[ni], 0.0))
            r = np.where(leaf, l_r[li], np.where(node, node_r[ni], 0.0))
            s_area[level], s_n[level], s_c[level], s_r[level] = a, n, c, r
            tot = a.sum(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(tot[:, None] > 0, (a[..., None] * c).sum(axis=1) / tot[:, None],
                                (c * slot[..., None]).sum(axis=1) / np.maximum(slot.sum(axis=1), 1)[:, None])
            gap = np.sqrt(((c - mean[:, None, :]) ** 2).sum(axis=2)) + r
            node_area[level], node_n[level], node_c[level] = tot, n.sum(axis=1), mean
            node_r[level] = np.where(slot, gap, 0.0).max(axis=1)
        self._dipoles = (s_area, s_n, s_c, s_r)
        return self._dipoles

    def _levels(self) -> list[np.ndarray]:
        """The wide nodes by depth, the root's level first."""
        levels, cur = [], np.zeros(1 if len(self.boxes) else 0, np.int64)
        while cur.size:
            levels.append(cur)
            ch = self.children[cur]
            cur = ch[self.slot[cur] & (ch >= 0)]
        return levels


def _walk(m: int, start=None):
    """Depth first over pieces of (row, node) pairs, each at most ``PAIRS`` long, from every
    row at the root (or from the (rows, nodes) pieces ``start``): yields (rows, node,
    pieces), and the caller appends the next level's pairs to ``pieces``, so the working
    memory stays bounded whatever the tree holds."""
    pieces = [(np.arange(m), np.zeros(m, np.int64))] if start is None else list(start)
    while pieces:
        rows, node = pieces.pop()
        if rows.size > PAIRS:
            pieces += [(rows[PAIRS:], node[PAIRS:]), (rows[:PAIRS], node[:PAIRS])]
            continue
        yield rows, node, pieces


#: a float32 box distance is compared with the best float64 distance widened by the point's
#: own float32 rounding (``_rounding``) and this relative margin, so float32 arithmetic can
#: only open a box more, never prune one the exact arithmetic would open
OPEN_MARGIN = 1e-5


def _box_d2(p32, boxes32, node):
    """Squared distance (float32) from each p (F, 3) to each of the 4 child boxes of its
    ``node`` (F,) (``boxes32`` (W, 6, 4): lo x, y, z then hi x, y, z, by slot): (F, 4), NaN
    for an empty slot.  In blocks of ``KERNEL_BLOCK`` pairs, for the cache."""
    f = len(node)
    out = np.empty((f, 4), np.float32)
    for s in range(0, f, KERNEL_BLOCK):
        sl = slice(s, s + KERNEL_BLOCK)
        bx = np.take(boxes32, node[sl], axis=0)  # np.take of whole rows: faster than indexing
        q = p32[sl, :, None]
        gap = np.subtract(bx[:, :3], q)
        np.maximum(gap, q - bx[:, 3:], out=gap)
        np.maximum(gap, np.float32(0), out=gap)
        np.einsum("fak,fak->fk", gap, gap, out=out[sl])
    return out


def _rounding(p32) -> np.ndarray:
    """(F,) a bound on the float32 error of a point's distance to a box (both about the
    centre): a few ulps of its largest coordinate, at least the smallest normal float32."""
    big = np.abs(p32).max(axis=1)
    return 4.0 * np.spacing(np.maximum(big, np.float32(1.0))).astype(F64) + np.finfo(np.float32).tiny


def _open(d2_32, best_d2, slack):
    """Which boxes to open: float32 distances against the float64 best widened by ``slack``."""
    with np.errstate(invalid="ignore", over="ignore"):
        thr = (np.sqrt(best_d2) + slack) ** 2 * (1.0 + OPEN_MARGIN)
        return d2_32 <= thr[:, None]


def _measure(index: TreeIndex, p, owner, leaf, best):
    """Fold every triangle of each (point ``owner``, ``leaf``) pair into ``best`` exactly."""
    _measure_pairs(index.corner_rows, p, *index.leaf_pairs(owner, leaf), best)


def _measure_pairs(corner_rows, p, own, tri, best):
    """Fold each (point ``own``, triangle ``tri``) pair into ``best`` exactly."""
    c = np.take(corner_rows, tri, axis=0)
    q = np.take(p, own, axis=0)
    col = [c[:, k] for k in range(9)]
    d2, u, v = closest_on_columns([q[:, k] for k in range(3)], col[0:3], col[3:6], col[6:9])
    _reduce_pairs(own, tri, d2, u, v, best)


def _closest_chunk(index: TreeIndex, p, md) -> Nearest:
    """The closest point of checked points ``p`` by branch and bound, vectorised over
    (point, node) pairs: every child box nearer than the point's best distance so far is
    opened (a tie in distance still opened, for the lowest triangle index), leaves' triangles
    are measured exactly; a greedy descent to the nearest leaf first gives every point a
    bound."""
    m = len(p)
    best = _fresh_best(m, md)
    if m == 0 or len(index) == 0:
        return _nearest(p, best, index.tv64)
    tv = index.tv64
    # each (point, leaf) is measured once: the path's leaf, or a leaf under one sibling of it
    p32 = (p - index.centre).astype(np.float32)
    slack = _rounding(p32)
    # a bound for every point: down the nearest child box to a leaf, keeping each level's
    # box distances
    node = np.zeros(m, np.int64)
    rows = np.arange(m)
    path = []
    while rows.size:
        d2 = _box_d2(p32[rows], index.boxes32, node)
        j = np.argmin(np.where(np.isnan(d2), np.float32(np.inf), d2), axis=1)
        path.append((rows, node, d2, j))
        child = index.children[node, j]
        leaf = child < 0
        _measure(index, p, rows[leaf], ~child[leaf], best)
        rows, node = rows[~leaf], child[~leaf]
    # every box off a point's path lies under a sibling of a path node: the siblings its
    # bound does not rule out are where the search goes on (the path itself is done)
    start = []
    for rows, node, d2, j in path:
        near = _open(d2, best[0][rows], slack[rows])
        near[np.arange(len(rows)), j] = False
        r, jj = np.nonzero(near)
        own, child = rows[r], index.children[node[r], jj]
        leaf = child < 0
        _measure(index, p, own[leaf], ~child[leaf], best)
        if (~leaf).any():
            start.append((own[~leaf], child[~leaf]))
    # branch and bound, depth first over bounded pieces of (point, node) pairs
    for rows, node, pieces in _walk(m, start):
        r, j = np.nonzero(_open(_box_d2(p32[rows], index.boxes32, node), best[0][rows], slack[rows]))
        own, child = rows[r], index.children[node[r], j]
        leaf = child < 0
        _measure(index, p, own[leaf], ~child[leaf], best)
        if (~leaf).any():
            pieces.append((own[~leaf], child[~leaf]))
    return _nearest(p, best, tv)


def closest_tree(index: TreeIndex, points, max_distance=np.inf) -> Nearest:
    """The closest point by branch and bound over the tree (``_closest_chunk``), in chunks
    of ``POINT_CHUNK`` points."""
    p = check_points(points)
    md = check_max_distance(max_distance)
    if len(p) <= POINT_CHUNK:
        return _closest_chunk(index, p, md)
    return Nearest.concat(_closest_chunk(index, p[a:a + POINT_CHUNK], md) for a in range(0, len(p), POINT_CHUNK))


class CellIndex:
    """A uniform grid's arrays (``grid.UniformGrid``'s layout) over a mesh, for the closest
    point: cell (i, j, k) spans ``lo + (i, j, k) * cell_size`` to one cell further and holds
    the triangles ``cell_tris[cell_start[c]: cell_start[c + 1]]``, c = i + j * res[0] + k *
    res[0] * res[1]: every valid triangle that meets the cell grown by ``delta``; the cells
    cover every triangle."""

    def __init__(self, mesh: TriangleMesh, lo, cell_size, res, cell_start, cell_tris, delta: float, empty=None):
        self.mesh = mesh
        self.lo = np.asarray(lo, F64)
        self.cell_size = np.asarray(cell_size, F64)
        self.res = np.asarray(res, np.int64)
        self.hi = self.lo + self.cell_size * self.res
        self.stride = np.array([1, self.res[0], self.res[0] * self.res[1]], np.int64)
        self.cell_start = np.asarray(cell_start, np.int64)
        self.cell_tris = np.asarray(cell_tris, np.int64)
        self.delta = float(delta)
        self.count = np.diff(self.cell_start)
        #: per cell, a radius r such that the cells within Chebyshev distance r are all empty
        #: (0 when unknown): a search from that cell starts at ring r + 1
        self.empty = np.zeros(len(self.count), np.int64) if empty is None else np.asarray(empty, np.int64)
        self.tv64 = mesh.tri_vertices.astype(F64)
        self.corner_rows = self.tv64.reshape(-1, 9)
        self._shells = {}

    def __len__(self):
        return len(self.cell_tris)

    def shell(self, r: int) -> np.ndarray:
        """(K, 3) int64 the cell offsets at Chebyshev distance exactly r, on the axes where the
        grid has room for them (an offset of r along an axis of fewer than r + 1 cells can hold
        no cell): each face of the cube once, its edges with the lower axis' face."""
        got = self._shells.get(r)
        if got is not None:
            return got
        if r == 0:
            out = np.zeros((1, 3), np.int64)
        else:
            lim = self.res - 1
            faces = []
            for k in range(3):
                if r > lim[k]:
                    continue
                span = [np.arange(-min(r - 1 if j < k else r, lim[j]), min(r - 1 if j < k else r, lim[j]) + 1)
                        for j in range(3)]
                span[k] = np.array([-r, r])
                faces.append(np.stack(np.meshgrid(*span, indexing="ij"), -1).reshape(-1, 3))
            out = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        if len(self._shells) < 256:
            self._shells[r] = out
        return out

    def cell_pairs(self, owner, cell):
        """(owner repeated, triangle) for every triangle of each (owner, cell) pair."""
        return _expand(owner, self.cell_start[cell], self.count[cell], self.cell_tris)


def _expand(owner, start, count, items):
    """(owner repeated, item) for every item of each owner's run ``items[start: start + count]``."""
    own = np.repeat(owner, count)
    first = np.repeat(start, count)
    offset = np.arange(own.size) - np.repeat(np.cumsum(count) - count, count)
    return own, items[first + offset]


def _beyond_d2(index: CellIndex, p, cell, r):
    """(F,) squared distance from each p to the grid's cells outside the cube of Chebyshev
    radius r about its ``cell`` (inf where that cube covers the grid): the least over the
    six slabs of cells past the cube's faces, each slab as wide as the grid on its other axes."""
    lo, hi, cs = index.lo, index.hi, index.cell_size
    out_gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
    base = (out_gap * out_gap).sum(axis=1)
    out = np.full(len(p), np.inf)
    for k in range(3):
        rest = base - out_gap[:, k] ** 2
        up = cell[:, k] + r + 1  # the first cell past the cube's upper face
        has = up <= index.res[k] - 1
        g = np.maximum(lo[k] + up * cs[k] - p[:, k], 0.0)
        np.minimum(out, np.where(has, rest + g * g, np.inf), out=out)
        down = cell[:, k] - r  # cells below this one are past the lower face
        has = down >= 1
        g = np.maximum(p[:, k] - (lo[k] + down * cs[k]), 0.0)
        np.minimum(out, np.where(has, rest + g * g, np.inf), out=out)
    return out


#: a cell is opened when its box is within the best distance widened by this relative margin
#: (float64 rounding of the cell's bounds can then only open more, never prune)
CELL_MARGIN = 1e-9


#: the grid search's work counts (``closest_grid(work=...)``), in this order: the points, the
#: (point, ring) steps, the (point, cell) pairs the rings enumerate, the (point, triangle)
#: pairs measured
GRID_WORK = ("points", "rings", "cells", "pairs")


def _grid_chunk(index: CellIndex, p, md, work=None, reach=None):
    """(``Nearest``, left) for checked points ``p`` by rings of cells about each point's cell
    (the nearest cell of the grid for a point outside it): ring r holds the cells at Chebyshev
    distance r; its cells nearer than the point's best distance so far are measured, and a
    point stops once its best is nearer than every cell past the rings searched
    (``_beyond_d2``), so the search is exact; a tie in distance still opens a cell, for the
    lowest triangle index.  The rings start past the empty cube about the point's cell.

    A point far from every triangle (outside the grid, or deep in empty space) enumerates
    about (2r + 1)^3 cells before it stops, the grid's weakness: with ``reach``, a point whose
    rings span more cells than that stops unanswered, ``left`` True (its row of the answer
    is then meaningless), for a structure that searches far points well."""
    m = len(p)
    best = _fresh_best(m, md)
    left = np.zeros(m, bool)
    if work is not None:
        work[0] += m
    if m == 0 or len(index) == 0:
        return _nearest(p, best, index.tv64), left
    res, stride = index.res, index.stride
    cell = np.clip(np.floor((p - index.lo) / index.cell_size), 0, res - 1).astype(np.int64)
    slack = index.delta + 4.0 * np.spacing(np.abs(index.lo).max() + np.abs(index.hi).max())

    def measure(own, cid):
        o, tri = index.cell_pairs(own, cid)
        _measure_pairs(index.corner_rows, p, o, tri, best)
        if work is not None:
            work[3] += len(o)

    # every point starts past the empty cube about its cell: those rings hold nothing
    empty = index.empty[cell @ stride]
    ring = np.where(empty > 0, empty + 1, 0)
    rows = np.arange(m)
    while rows.size:
        for r in np.unique(ring[rows]):
            rr_all = rows[ring[rows] == r]
            off = index.shell(int(r))
            per = max(1, PAIRS // max(1, len(off)))
            for s in range(0, rr_all.size, per):
                rr = rr_all[s:s + per]
                cc = cell[rr][:, None, :] + off[None, :, :]                       # (A, K, 3)
                a, kk = np.nonzero(((cc >= 0) & (cc < res)).all(axis=2))
                cc = cc[a, kk]
                cid = cc @ stride
                full = index.count[cid] > 0
                own, cc, cid = rr[a[full]], cc[full], cid[full]
                q = p[own]
                blo = index.lo + cc * index.cell_size
                gap = np.maximum(np.maximum(blo - q, q - (blo + index.cell_size)), 0.0)
                d2 = (gap * gap).sum(axis=1)
                near = d2 <= best[0][own] * (1.0 + CELL_MARGIN)
                own, cid, d2 = own[near], cid[near], d2[near]
                if work is not None:
                    work[1] += len(rr)
                    work[2] += len(rr) * len(off)
                if own.size == 0:
                    continue
                # each point's nearest cell of the ring first: its distance then prunes the rest
                order = np.lexsort((d2, own))
                head = np.ones(len(order), bool)
                head[1:] = own[order[1:]] != own[order[:-1]]
                measure(own[order[head]], cid[order[head]])
                rest = order[~head]
                keep = rest[d2[rest] <= best[0][own[rest]] * (1.0 + CELL_MARGIN)]
                if keep.size:
                    measure(own[keep], cid[keep])
        bound = np.sqrt(_beyond_d2(index, p[rows], cell[rows], ring[rows])) - slack
        done = (np.sqrt(best[0][rows]) < bound) | np.isinf(bound)
        rows = rows[~done]
        ring[rows] += 1
        if reach is not None and rows.size:
            spans = np.minimum(2 * ring[rows, None] + 1, 2 * res - 1)
            far = spans.prod(axis=1) > reach
            left[rows[far]] = True
            rows = rows[~far]
    return _nearest(p, best, index.tv64), left


def closest_grid(index: CellIndex, points, max_distance=np.inf, work=None, reach=None):
    """The closest point by rings of grid cells (``_grid_chunk``), in chunks of
    ``POINT_CHUNK`` points; ``work``, a list of four numbers, gains the search's counts
    (``GRID_WORK``).  Without ``reach`` the ``Nearest`` of every point; with it (``Nearest``,
    left): the points whose rings would span more than ``reach`` cells are left unanswered."""
    p = check_points(points)
    md = check_max_distance(max_distance)
    got = [_grid_chunk(index, p[a:a + POINT_CHUNK], md, work, reach) for a in range(0, max(len(p), 1), POINT_CHUNK)]
    near = Nearest.concat(n for n, _ in got)
    return near if reach is None else (near, np.concatenate([left for _, left in got]))


def winding_number_tree(index: TreeIndex, points, accuracy: float = ACCURACY) -> np.ndarray:
    """The generalized winding number by Barill et al.'s tree sum: a child subtree whose
    centroid is farther than ``accuracy`` times its radius counts as its dipole, a leaf nearer
    than that as the exact sum of its triangles' solid angles, a nearer wide node is opened."""
    p = check_points(points)
    try:
        beta = float(accuracy)
    except (TypeError, ValueError):
        raise ValueError(f"accuracy must be a number, got {accuracy!r}") from None
    if not beta >= 1.0:
        raise ValueError(f"accuracy must be at least 1 (a subtree's radii), got {accuracy!r}")
    m = len(p)
    w = np.zeros(m)
    if m == 0 or len(index) == 0:
        return w
    s_area, s_n, s_c, s_r = index.dipoles()
    tv = index.tv64
    for rows, node, pieces in _walk(m):
        slot = index.slot[node]                                   # (F, 4)
        c, n, r = s_c[node], s_n[node], s_r[node]                 # (F, 4, 3), (F, 4, 3), (F, 4)
        d = c - p[rows][:, None, :]
        dist = np.sqrt((d * d).sum(axis=2))
        far = slot & (dist > beta * r)
        with np.errstate(invalid="ignore", divide="ignore"):
            dip = np.where(far, (d * n).sum(axis=2) / np.where(far, dist ** 3, 1.0), 0.0)
        w += np.bincount(rows, dip.sum(axis=1), minlength=m) / (4.0 * math.pi)
        near = slot & ~far
        i, j = np.nonzero(near)
        own, child = rows[i], index.children[node[i], j]
        leaf = child < 0
        if leaf.any():
            o, tri = index.leaf_pairs(own[leaf], ~child[leaf])
            t = tv[tri]
            w += np.bincount(o, solid_angles(p[o], t[:, 0], t[:, 1], t[:, 2]), minlength=m) / (4.0 * math.pi)
        if (~leaf).any():
            pieces.append((own[~leaf], child[~leaf]))
    return w


def _ray_box_pairs(rays: Rays, ray_idx, boxes):
    """(F, 4) bool: each ray's interval [tmin, tmax] meets each child box (F, 2, 3, 4), by
    slabs in float64 widened by a few ulps, so a ray that grazes a box is never missed."""
    o = rays.origins[ray_idx].astype(F64)[:, :, None]
    d = rays.directions[ray_idx].astype(F64)[:, :, None]
    near, far = slab_interval(o, d, boxes[:, 0], boxes[:, 1])
    tn = near.max(axis=1)
    tf = far.min(axis=1) * (1.0 + 1e-6) + 1e-300
    tmin = rays.tmin[ray_idx].astype(F64)[:, None]
    tmax = rays.tmax[ray_idx].astype(F64)[:, None]
    with np.errstate(invalid="ignore"):
        return (tn <= tf) & (tf >= tmin) & (tn <= tmax)


def count_hits_tree(index: TreeIndex, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
    """(M,) int32 distinct hits of each ray with tmin < t <= tmax, down the tree: every box
    the ray's interval meets is opened and every triangle of a leaf it meets is tested by the
    ray kernel (``intersect.intersect``); nothing but the hits' t is kept."""
    rays = prepare_rays(origins, directions, tmin, tmax)
    m = len(rays)
    if m == 0 or len(index) == 0:
        return np.zeros(m, np.int32)
    tv = index.mesh.tri_vertices
    found_r, found_t = [], []
    for rows, node, pieces in _walk(m):
        meet = _ray_box_pairs(rays, rows, index.boxes[node]) & index.slot[node]
        i, j = np.nonzero(meet)
        own, child = rows[i], index.children[node[i], j]
        leaf = child < 0
        if leaf.any():
            r, tri = index.leaf_pairs(own[leaf], ~child[leaf])
            t = intersect(rays, r, tri, tv)
            ok = np.isfinite(t)
            found_r.append(r[ok])
            found_t.append(t[ok])
        if (~leaf).any():
            pieces.append((own[~leaf], child[~leaf]))
    if not found_r:
        return np.zeros(m, np.int32)
    return _distinct_counts(np.concatenate(found_r), np.concatenate(found_t), m)
