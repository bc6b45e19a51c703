"""The one ray/triangle kernel shared by every numpy structure (grid, BVH, brute force).

Watertight ray/triangle intersection after Woop, Benthin and Wald, "Watertight
Ray/Triangle Intersection", JCGT 2(1), 2013: the ray is sheared into a frame where it
runs along +z, and the three 2D edge functions U, V, W decide the hit.  Because a
shared edge yields the same edge function (negated) for both of its triangles, a ray
can never slip between them.  Edge functions are evaluated in float32 and recomputed
in float64 where one of them is exactly zero (section 3 of the paper).

Conventions (../shared/DESIGN.md): nearest hit with tmin < t <= tmax; ties in t go
to the lowest triangle index; both faces hit; degenerate triangles never hit;
directions need not be normalised.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # hits.py is imported when a result is finished (see NearestHits.finish)
    from .hits import Hits

F32 = np.float32
#: u, the unit roundoff of float32 (half its machine epsilon 2**-23): one correctly rounded
#: float32 operation errs by at most u times its result (Higham, "Accuracy and Stability of
#: Numerical Algorithms", 2.2).  The numpy structures' error bounds are multiples of it:
#: the BVH's slab widening 1 + 2*gamma(3) (bvh.py) and the grid's slack 128u times the
#: origin's distance to the grid (grid.py).
UNIT_ROUNDOFF = 2.0**-24
MISS_KEY = np.uint64(0xFFFFFFFFFFFFFFFF)


@dataclass
class Rays:
    """A validated, prepared ray batch (per-ray shear constants of Woop et al.)."""

    origins: np.ndarray  # (M, 3) float32
    directions: np.ndarray  # (M, 3) float32
    tmin: np.ndarray  # (M,) float32
    tmax: np.ndarray  # (M,) float32
    kx: np.ndarray | None  # (M,) int8: the three axes, kz the dominant one
    ky: np.ndarray | None
    kz: np.ndarray | None
    shear: np.ndarray | None  # (M, 3) float32: Sx, Sy, Sz (None: prepared with shear=False)

    def __len__(self):
        return len(self.origins)

    def subset(self, idx) -> "Rays":
        return Rays(*(None if (a := getattr(self, f)) is None else a[idx] for f in self.__dataclass_fields__))


def _as_rays_array(a, name):
    a = np.asarray(a)
    if a.ndim == 1 and a.shape[0] == 3:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (M, 3), got {a.shape}")
    if not np.issubdtype(a.dtype, np.number):
        raise ValueError(f"{name} must be numeric, got dtype {a.dtype}")
    return a


_NEXT_AXIS = np.array([1, 2, 0], np.int8)


def _per_ray(x, m, name):
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 0:
        if np.isnan(x):
            raise ValueError(f"{name} contains NaN")
        return np.broadcast_to(x, (m,))  # a scalar: no per-ray array, same values
    if x.shape != (m,):
        raise ValueError(f"{name} must be a scalar or shape ({m},), got {x.shape}")
    if np.isnan(x).any():
        raise ValueError(f"{name} contains NaN")
    return x


def _fresh_f32(x):
    """A fresh (M,) float32 copy of ``x``; a broadcast scalar is rounded once (the same
    cast as ``astype``) and filled, not converted ray by ray."""
    if x.size and x.strides == (0,):
        return np.full(x.shape, x[0], dtype=F32)
    return x.astype(F32)


def _rows_f32(a) -> np.ndarray:
    """(M, 3) C-contiguous float32 of ``a``; a broadcast of one row (one sensor origin for
    every ray) is filled by columns, which numpy does many times faster than copying rows
    of 3."""
    if a.ndim == 2 and len(a) > 1 and a.strides[0] == 0:
        out = np.empty(a.shape, F32)
        for k in range(a.shape[1]):
            out[:, k] = a[0, k]
        return out
    return np.ascontiguousarray(a, dtype=F32)


def prepare_rays(origins, directions, tmin=0.0, tmax=np.inf, *, shear: bool = True) -> Rays:
    """Validate a ray batch and precompute its shear (``shear=False``: validate only,
    for a structure that does not run this module's kernel).

    Raises ValueError for mismatched shapes, NaN or infinite origins or directions,
    zero-length directions (after rounding to float32), NaN interval bounds, or
    tmin > tmax on any ray; the message counts the bad rays and names the first.
    """
    o = _as_rays_array(origins, "origins")
    d = _as_rays_array(directions, "directions")
    if o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} differ in shape")
    m = len(o)
    with np.errstate(over="ignore", invalid="ignore"):  # overflow to inf is reported below
        o32, d32 = _rows_f32(o), _rows_f32(d)
        # whole-array checks first (a row-wise reduce over 3 columns costs far more); the
        # rows are found only to name them in the error
        for name, a in (("origins", o32), ("directions", d32)):
            if not np.isfinite(a).all():
                w = np.flatnonzero(~np.isfinite(a).all(axis=1))
                raise ValueError(f"{w.size} of {m} rays have NaN or infinite {name} (or overflow float32), first at ray {w[:5].tolist()}")
    if not d32.all():  # some component is zero: is a whole direction zero? (by columns: a
        # row-wise reduce over 3 columns costs several times more)
        w = np.flatnonzero((d32[:, 0] == 0) & (d32[:, 1] == 0) & (d32[:, 2] == 0))
        if w.size:
            raise ValueError(f"{w.size} of {m} rays have a zero-length direction, first at ray {w[:5].tolist()}")
    lo = _per_ray(tmin, m, "tmin")
    hi = _per_ray(tmax, m, "tmax")
    # two scalars (the common call) are compared once, not per ray: a chunk of an Embree
    # trace is short enough for per-ray passes over broadcasts to show
    both_scalar = m > 0 and lo.strides == (0,) and hi.strides == (0,)
    if (lo[0] > hi[0]) if both_scalar else (lo > hi).any():
        w = np.flatnonzero(lo > hi)
        raise ValueError(f"{w.size} rays have tmin > tmax, first at ray {w[:5].tolist()}")
    lo, hi = _fresh_f32(lo), _fresh_f32(hi)
    rays = Rays(o32, d32, lo, hi, None, None, None, None)
    return shear_rays(rays) if shear else rays


def shear_rays(rays: Rays) -> Rays:
    """The same validated rays with Woop et al.'s per-ray shear constants added."""
    o32, d32, lo, hi = rays.origins, rays.directions, rays.tmin, rays.tmax
    m = len(o32)
    ad = np.abs(d32)
    ax, ay, az = ad[:, 0], ad[:, 1], ad[:, 2]
    # the dominant axis, the first on ties (as argmax), without a reduction over rows of three
    kz = np.where(ax >= ay, np.where(ax >= az, 0, 2), np.where(ay >= az, 1, 2)).astype(np.int8)
    rows3 = np.arange(0, 3 * m, 3)
    dflat = d32.reshape(-1)
    dz = dflat.take(rows3 + kz)
    # int8 axis indices: 3 bytes a ray instead of 24 (240 MB saved at 10M rays)
    kx = _NEXT_AXIS.take(kz)
    ky = _NEXT_AXIS.take(kx)
    # Keep the winding of the sheared frame: swap x and y when the dominant axis is negative.
    neg = dz < 0
    kx, ky = np.where(neg, ky, kx), np.where(neg, kx, ky)
    sxyz = np.empty((m, 3), F32)
    sxyz[:, 0] = dflat.take(rows3 + kx) / dz
    sxyz[:, 1] = dflat.take(rows3 + ky) / dz
    sxyz[:, 2] = F32(1.0) / dz
    with np.errstate(over="ignore"):
        return Rays(o32, d32, lo, hi, kx, ky, kz, sxyz)


def slab_interval(o, d, lo, hi):
    """(near, far): per axis, the ray parameters t where ``o + t d`` enters and leaves the
    slab ``lo..hi`` (float64, shapes broadcast).  An axis the ray does not move along is
    every t when ``o`` lies in the slab and none otherwise, so a zero component (+0.0 or
    -0.0) needs no division by it; the box's interval is max(near) .. min(far) over the axes."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = 1.0 / d
        t0, t1 = (lo - o) * inv, (hi - o) * inv
    zero = d == 0
    inside = (o >= lo) & (o <= hi)
    near = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    far = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    return near, far


def _edge_functions(ax, ay, bx, by, cx, cy):
    return cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax


def _sheared(rays: Rays, ray_idx, tri_idx, tri_vertices, dtype):
    """Triangle corners in the ray's sheared frame, as tuples of (P,) arrays: px, py, rz
    (one array per corner A, B, C) and the shear s (Sx, Sy, Sz).

    Every coordinate is gathered straight from the flat (T*9) corner array at
    ``9*triangle + 3*corner + axis`` (and the origin's at ``3*ray + axis``), so each value
    is one ``take`` into a contiguous 1D array: no (P, 3, 3) temporary, no broadcasting
    over rows of three (whose short inner loops dominated the kernel), the same
    float32 operations in the same order.
    """
    ray_idx = ray_idx.astype(np.intp, copy=False)
    tri_idx = tri_idx.astype(np.intp, copy=False)
    flat = np.ascontiguousarray(tri_vertices).reshape(-1)
    oflat = rays.origins.reshape(-1)
    r3 = ray_idx * 3
    t9 = tri_idx * 9
    ks = (rays.kx.take(ray_idx), rays.ky.take(ray_idx), rays.kz.take(ray_idx))
    rel = []
    for k in ks:  # x, y, z of the sheared frame
        bk = t9 + k
        ok = oflat.take(r3 + k)
        if dtype == F32:
            rel.append(tuple(flat[c:].take(bk) - ok for c in (0, 3, 6)))
        else:
            ok = ok.astype(dtype)
            rel.append(tuple(flat[c:].take(bk).astype(dtype) - ok for c in (0, 3, 6)))
    rx, ry, rz = rel
    if dtype == F32:
        sflat = rays.shear.reshape(-1)
        s = (sflat.take(r3), sflat[1:].take(r3), sflat[2:].take(r3))
    else:  # recompute the shear itself in the wider type
        dflat = rays.directions.reshape(-1)
        dx, dy, dz = (dflat.take(r3 + k).astype(dtype) for k in ks)
        s = (dx / dz, dy / dz, 1.0 / dz)
    px = tuple(x - s[0] * z for x, z in zip(rx, rz))
    py = tuple(y - s[1] * z for y, z in zip(ry, rz))
    return px, py, rz, s


def precise_tuv(rays: Rays, ray_idx, tri_idx, tri_vertices):
    """t, u, v in float64 for pairs already known to hit (no inside test): the reported values."""
    px, py, rz, s = _sheared(rays, ray_idx, tri_idx, tri_vertices, np.float64)
    U, V, W = _edge_functions(px[0], py[0], px[1], py[1], px[2], py[2])
    det = U + V + W
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        return (U * (s[2] * rz[0]) + V * (s[2] * rz[1]) + W * (s[2] * rz[2])) * inv, V * inv, W * inv


def intersect(rays: Rays, ray_idx, tri_idx, tri_vertices, t_hi=None, want_uv=False):
    """Intersect the pairs (rays[ray_idx[k]], triangle tri_idx[k]).

    tri_vertices: (T, 3, 3) float32 (``TriangleMesh.tri_vertices``).
    t_hi: optional (P,) float32 upper bound (the current nearest hit), applied on top of
    rays.tmax for these pairs, so the kernel reports only hits that could improve it.
    Returns t (P,) float32, +inf where the pair does not hit within (tmin, t_hi];
    with ``want_uv`` also u, v (P,) float32 so that p = (1-u-v) v0 + u v1 + v v2.
    """
    ray_idx = np.asarray(ray_idx)
    tri_idx = np.asarray(tri_idx)
    p = ray_idx.shape[0]
    if p == 0:
        e = np.empty(0, F32)
        return (e, e.copy(), e.copy()) if want_uv else e
    px, py, rz, s = _sheared(rays, ray_idx, tri_idx, tri_vertices, F32)
    U, V, W = _edge_functions(px[0], py[0], px[1], py[1], px[2], py[2])
    zero = (U == 0) | (V == 0) | (W == 0)
    if zero.any():
        # Section 3 of Woop et al.: recompute in double where float32 cannot tell the side.
        z = np.flatnonzero(zero)
        pxd = [a[z].astype(np.float64) for a in px]
        pyd = [a[z].astype(np.float64) for a in py]
        Ud, Vd, Wd = _edge_functions(pxd[0], pyd[0], pxd[1], pyd[1], pxd[2], pyd[2])
        # Keep the sign exactly; float32 rounding of a tiny double must not flip it to zero.
        tiny = np.finfo(F32).smallest_subnormal
        for full, dbl in ((U, Ud), (V, Vd), (W, Wd)):
            r = dbl.astype(F32)
            r = np.where((r == 0) & (dbl != 0), np.copysign(tiny, dbl).astype(F32), r)
            full[z] = r
    det = U + V + W
    inside = ~(((U < 0) | (V < 0) | (W < 0)) & ((U > 0) | (V > 0) | (W > 0))) & (det != 0)
    T = U * (s[2] * rz[0]) + V * (s[2] * rz[1]) + W * (s[2] * rz[2])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = np.where(inside, T / det, np.inf).astype(F32, copy=False)
        lo = rays.tmin[ray_idx]
        # t_hi narrows (never widens) the ray's own interval: a caller's "best so far"
        # starts at +inf, and hits beyond tmax must stay out.
        hi = rays.tmax[ray_idx] if t_hi is None else np.minimum(t_hi, rays.tmax[ray_idx])
        ok = inside & (t > lo) & (t <= hi) & np.isfinite(t)
        t = np.where(ok, t, F32(np.inf))
        if not want_uv:
            return t
        inv = np.where(ok, F32(1.0) / det, F32(0.0))
        return t, (V * inv).astype(F32), (W * inv).astype(F32)


# -- nearest-hit reduction -----------------------------------------------------------

def _sortable(t32):
    """Map float32 to uint32 so that unsigned order equals float order (no NaN here)."""
    b = np.ascontiguousarray(t32, dtype=F32).view(np.uint32)
    return np.where(b & np.uint32(0x80000000), ~b, b | np.uint32(0x80000000))


def _unsortable(k32):
    k32 = k32.astype(np.uint32)
    b = np.where(k32 & np.uint32(0x80000000), k32 & np.uint32(0x7FFFFFFF), ~k32)
    return b.view(F32)


class NearestHits:
    """Per-ray nearest (t, triangle) with the tie rule, packed in one uint64 key.

    The key is (sortable bits of t) << 32 | triangle, so the minimum key is the nearest
    hit and, among equal t, the lowest triangle index (the hit convention stated at the top of this module).
    """

    def __init__(self, m: int):
        self.key = np.full(m, MISS_KEY, np.uint64)

    def part(self, rows: slice) -> "NearestHits":
        """The same hits for the rays ``rows`` (a view: updates go through)."""
        p = NearestHits.__new__(NearestHits)
        p.key = self.key[rows]
        return p

    def update(self, ray_idx, tri_idx, t):
        """Fold in kernel results t (P,) for pairs (ray_idx, tri_idx); inf means no hit."""
        m = np.isfinite(t)
        if not m.any():
            return
        r = ray_idx[m]
        k = (_sortable(t[m]).astype(np.uint64) << np.uint64(32)) | tri_idx[m].astype(np.uint64)
        np.minimum.at(self.key, r, k)

    def t(self, ray_idx=None) -> np.ndarray:
        """Current nearest t (float32, inf for no hit yet), for all rays or a subset."""
        k = self.key if ray_idx is None else self.key[ray_idx]
        t = _unsortable((k >> np.uint64(32)).astype(np.uint32))
        return np.where(k == MISS_KEY, F32(np.inf), t)

    def triangle(self, ray_idx=None) -> np.ndarray:
        k = self.key if ray_idx is None else self.key[ray_idx]
        tri = (k & np.uint64(0xFFFFFFFF)).astype(np.int64)
        return np.where(k == MISS_KEY, -1, tri).astype(np.int32)

    def finish(self, rays: Rays, tri_vertices) -> "Hits":
        """Hits with barycentrics, recomputed once per hit ray by the same kernel."""
        from .hits import Hits

        t = self.t()
        tri = self.triangle()
        u = np.zeros(len(t), F32)
        v = np.zeros(len(t), F32)
        h = np.flatnonzero(tri >= 0)
        if h.size:
            th, uh, vh = precise_tuv(rays, h, tri[h], tri_vertices)
            # keep the float32 t where float64 would round it out of (tmin, tmax]
            th = th.astype(F32)
            ok = np.isfinite(th) & (th > rays.tmin[h]) & (th <= rays.tmax[h])
            t[h] = np.where(ok, th, t[h])
            u[h] = uh
            v[h] = vh
        return Hits(t=t, triangle=tri, u=u, v=v)
