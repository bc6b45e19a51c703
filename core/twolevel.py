"""Two levels: instances of bottom-level structures, and a top level over their world boxes.

One bottom level per unique mesh, built once in the mesh's object space
(``core.build(mesh, kind)``), placed any number of times by 4x4 object-to-world
matrices; only the top level, over the instances' world boxes, is rebuilt when the
matrices change (``with_matrices``).  The idea is pbrt-v4's ``TransformedPrimitive``
under a top-level BVH, and Embree's instancing (``RTC_GEOMETRY_TYPE_INSTANCE``).

A ray enters an instance in object space, ``o' = A^-1 (o - b)``, ``d' = A^-1 d`` (``M =
[A b; 0 1]``, in float64, then rounded to float32 by the bottom), and ``d'`` is not
renormalised, so ``t``, ``tmin`` and ``tmax`` keep their world meaning and the
barycentrics (affine invariants) need no mapping.  The answer is the one a flat
world-space soup of every instance's transformed triangles gives, traced by the same
kind, within float32 rounding: the nearest hit with tmin < t <= tmax, an exact tie in t
going to the lowest *global* triangle index (``tri_base[instance] + local``).

The top level culls with each instance's world box: the object-space bounds of its
bottom mesh, whose 8 corners are transformed in float64, padded outward by ``BOX_PAD``
of the box's coordinate scale (the float32 rounding of the object-space ray and of the
bottom's arithmetic moves a hit by a few ulps of that scale), against the segment
[tmin, best t so far] with a slab test widened as Ize's (JCGT 2013, ``1 + 2 gamma(3)``).

Two ways to visit the instances, chosen by the number of instances with a box
(``pairs_from``, default 64).  The crossover depends on the bottoms: with one shared
numpy BVH the batched pairs path wins from a handful of instances on, with Embree
bottoms or one distinct bottom per instance only from several tens, as each bottom call
is then cheap or the batching gains nothing; 64 is where both were about even
(BENCHMARKS.md, "Two-level scenes"):

- few instances (``_trace_loop``): per chunk of rays, every instance's slab interval for
  every ray, then one bottom call per instance, nearest mean box entry first, each
  tracing only the rays that reach its box before their best hit so far, with that best
  as their tmax;
- many instances (``_trace_pairs``, geometry-nodes scattering): a top-level tree over
  the boxes (instances sorted by the Morton code of their box centres, a complete binary
  tree over that order, built bottom-up in whole-array steps: O(I log I)) is traversed
  one level per numpy step, giving candidate (ray, instance) pairs with their box entry;
  these are traced in rounds by entry rank per ray (the 1st, the 2nd, the 3rd-4th,
  5th-8th, ...), each round dropping the pairs whose box starts beyond their ray's best
  hit and tracing all pairs of one bottom in one call (tmax per pair).  When a chunk's
  pairs would pass ``pair_limit``, the chunk is split, so memory stays bounded.

An instance whose matrix is singular (det A = 0, e.g. a zero scale) or whose inverse
overflows is never hit (its world triangles are degenerate, and degenerate triangles
are never hit); a pair whose object-space ray overflows float32 or rounds to a zero
direction is a miss for that instance.  NaN or inf in a matrix is a ValueError naming
the instance, as is a bottom row other than (0, 0, 0, 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .hits import Hits
from .intersect import UNIT_ROUNDOFF, Rays, prepare_rays
from .mesh import TriangleMesh

F32 = np.float32
#: instances (with a non-empty box) from which the top-level tree and the batched pairs
#: path are used instead of a loop over instances (crossover: BENCHMARKS.md, "Two-level scenes")
PAIRS_FROM = 64
#: rays per chunk: bounds the per-chunk working set
RAY_CHUNK = 1 << 16
#: (ray, box) pairs a chunk may hold at once, in the tree traversal and in the loop
#: path's (instances x rays) intervals; a chunk that needs more is split
PAIR_LIMIT = 1 << 21
#: a world box is padded by this times its largest coordinate magnitude plus its extent:
#: 16 float32 ulps of the box's scale, more than the rounding of the object-space ray
#: (one ulp of each coordinate) and of the watertight kernel (a few) move a hit
BOX_PAD = 16 * UNIT_ROUNDOFF
_GAMMA3 = 3 * np.finfo(np.float64).eps / 2 / (1 - 3 * np.finfo(np.float64).eps / 2)
_NO_GLOBAL = np.iinfo(np.int64).max


@dataclass
class InstanceHits(Hits):
    """``Hits`` of a two-level trace, one entry per ray.

    t: (M,) float32, +inf on a miss, in world units of the given direction
    triangle: (M,) GLOBAL triangle index (``tri_base[instance] + local_triangle``), -1 on
      a miss; int32, or int64 when the global indices can pass the int32 range
    u, v: (M,) float32 barycentrics of the local triangle (0 on a miss)
    instance: (M,) int32 instance hit, -1 on a miss
    local_triangle: (M,) int32 triangle of the instance's bottom mesh, -1 on a miss
    """

    instance: np.ndarray
    local_triangle: np.ndarray

    @classmethod
    def empty(cls, m: int, triangle_dtype=np.int32) -> "InstanceHits":
        return cls(t=np.full(m, np.inf, F32), triangle=np.full(m, -1, triangle_dtype),
                   u=np.zeros(m, F32), v=np.zeros(m, F32),
                   instance=np.full(m, -1, np.int32), local_triangle=np.full(m, -1, np.int32))


class _Best:
    """Per-ray nearest hit so far, global triangle as the tie-break (int64: any index)."""

    def __init__(self, m: int):
        self.t = np.full(m, np.inf, F32)
        self.g = np.full(m, _NO_GLOBAL, np.int64)
        self.inst = np.full(m, -1, np.int32)
        self.local = np.full(m, -1, np.int32)
        self.u = np.zeros(m, F32)
        self.v = np.zeros(m, F32)

    def into(self, out: "InstanceHits", rows=None) -> "InstanceHits":
        """Write the nearest hits into ``out`` (``InstanceHits.empty``: a miss stays as it
        is), at ``rows`` of it when this holds only those rays (the rest stay misses)."""
        at = slice(None) if rows is None else rows
        out.t[at] = self.t
        out.u[at], out.v[at] = self.u, self.v
        out.instance[at], out.local_triangle[at] = self.inst, self.local
        hit = self.inst >= 0
        out.triangle[np.flatnonzero(hit) if rows is None else rows[hit]] = self.g[hit]
        return out

    def fold(self, ray, inst, h: Hits, tri_base, unique: bool = False):
        """Fold in one bottom call's hits for pairs (ray, inst): the nearest per ray, an
        exact tie in t to the lowest global triangle (a ray may come several times, unless
        ``unique``: one instance's call, each ray once)."""
        k = np.flatnonzero(h.triangle >= 0)
        if k.size == 0:
            return
        ray, inst, t, loc = ray[k], inst[k], h.t[k], h.triangle[k].astype(np.int64)
        g = tri_base[inst] + loc
        if unique:
            w = np.arange(k.size)  # each ray's only candidate of this call
        else:
            order = np.lexsort((g, t, ray))
            first = np.ones(order.size, bool)
            first[1:] = ray[order[1:]] != ray[order[:-1]]
            w = order[first]  # each ray's nearest candidate of this call
        r = ray[w]
        better = (t[w] < self.t[r]) | ((t[w] == self.t[r]) & (g[w] < self.g[r]))
        w, r = w[better], r[better]
        self.t[r] = t[w]
        self.g[r] = g[w]
        self.inst[r] = inst[w]
        self.local[r] = loc[w]
        self.u[r] = h.u[k][w]
        self.v[r] = h.v[k][w]


class TwoLevel:
    """Instances of bottom-level structures under a top level over their world boxes.

    Parameters
    ----------
    bottoms : sequence of Accel
        One structure per unique mesh (any kind of ``core.build``), each over an
        object-space ``TriangleMesh`` (``bottom.mesh``); shared, never modified.
    instance_bottom : (I,) int
        Which bottom each instance places.
    matrices : (I, 4, 4) float
        Object-to-world matrices, row-major as Blender's ``matrix_world``
        (``p_world = M @ [p, 1]``); used in float64.
    tri_base : (I,) int, optional
        The global index of each instance's triangle 0 (a hit's ``triangle`` is
        ``tri_base[i] + local``); default: consecutive in instance order.
    pairs_from : int
        Instances with a box from which the tree and the batched pairs path are used.
    ray_chunk, pair_limit : int
        Rays per chunk; (ray, box) pairs a chunk may hold before it is split.

    Raises ValueError for shapes that do not fit, a bottom index out of range, a negative
    ``tri_base``, NaN or inf in a matrix, or a bottom row other than (0, 0, 0, 1); the
    message names the first bad instance.
    """

    kind = "twolevel"

    def __init__(self, bottoms, instance_bottom, matrices, tri_base=None, *, pairs_from: int = PAIRS_FROM,
                 ray_chunk: int = RAY_CHUNK, pair_limit: int = PAIR_LIMIT):
        self.bottoms = tuple(bottoms)
        for k, b in enumerate(self.bottoms):
            if not isinstance(getattr(b, "mesh", None), TriangleMesh) or not hasattr(b, "trace"):
                raise TypeError(f"bottom {k} is not a structure over a core.TriangleMesh (core.build), got {type(b).__name__}")
        ib = np.asarray(instance_bottom)
        if ib.ndim != 1 or (ib.size and not np.issubdtype(ib.dtype, np.integer)):
            raise ValueError(f"instance_bottom must be a (I,) integer array, got shape {ib.shape} dtype {ib.dtype}")
        if ib.size and (ib.min() < 0 or ib.max() >= len(self.bottoms)):
            bad = np.flatnonzero((ib < 0) | (ib >= len(self.bottoms)))
            raise ValueError(f"instance {bad[0]} places bottom {ib[bad[0]]}, outside 0..{len(self.bottoms) - 1}")
        self.instance_bottom = ib.astype(np.int32)
        n = len(ib)
        self._bottom_triangles = np.array([b.mesh.triangle_count for b in self.bottoms], np.int64)
        counts = self._bottom_triangles[self.instance_bottom] if n else np.zeros(0, np.int64)
        if tri_base is None:
            tri_base = np.concatenate([[0], np.cumsum(counts)[:-1]]) if n else np.zeros(0, np.int64)
        base = np.asarray(tri_base)
        if base.shape != (n,) or (base.size and not np.issubdtype(base.dtype, np.integer)):
            raise ValueError(f"tri_base must be a ({n},) integer array, got shape {base.shape} dtype {base.dtype}")
        if base.size and base.min() < 0:
            raise ValueError(f"tri_base is negative at instance {np.flatnonzero(base < 0)[0]}")
        self.tri_base = base.astype(np.int64)
        self.triangle_count = int(counts.sum())
        top = int((self.tri_base + counts).max()) if n else 0
        #: dtype of the global ``triangle`` of the hits
        self.triangle_dtype = np.dtype(np.int32 if top - 1 <= np.iinfo(np.int32).max else np.int64)
        self.pairs_from = int(pairs_from)
        self.ray_chunk = max(1, int(ray_chunk))
        self.pair_limit = max(2, int(pair_limit))
        self._place(matrices)

    # -- the top level ----------------------------------------------------------------
    def _place(self, matrices):
        """Validate the matrices, invert them, make the world boxes and (for many
        instances) the top-level tree.  O(I log I)."""
        n = self.instance_count
        m = np.asarray(matrices, dtype=np.float64)
        if m.shape != (n, 4, 4):
            raise ValueError(f"matrices must have shape ({n}, 4, 4), got {m.shape}")
        bad = ~np.isfinite(m).all(axis=(1, 2))
        if bad.any():
            raise ValueError(f"{bad.sum()} instance matrices contain NaN or inf, first at instance {np.flatnonzero(bad)[0]}")
        bad = (m[:, 3] != (0.0, 0.0, 0.0, 1.0)).any(axis=1)
        if bad.any():
            i = np.flatnonzero(bad)[0]
            raise ValueError(f"instance {i}: the bottom row of its matrix is {m[i, 3].tolist()}, not (0, 0, 0, 1) (affine only)")
        self.matrices = m
        a, b = m[:, :3, :3], m[:, :3, 3]
        self._translation = np.ascontiguousarray(b)
        with np.errstate(all="ignore"):
            det = np.linalg.det(a) if n else np.zeros(0)
            ok = np.isfinite(det) & (det != 0)
            inv = np.zeros((n, 3, 3))
            if ok.any():
                inv[ok] = np.linalg.inv(a[ok])
        ok &= np.isfinite(inv).all(axis=(1, 2))
        #: (I,) bool: instances whose matrix is singular (or its inverse overflows): never hit
        self.singular = ~ok
        ok &= self._bottom_triangles[self.instance_bottom] > 0
        self._inverse = inv
        # world boxes: the 8 corners of the object box through M, in float64
        lo = np.full((n, 3), np.inf)
        hi = np.full((n, 3), -np.inf)
        active = np.flatnonzero(ok)
        if active.size:
            blo = np.array([bt.mesh.bounds()[0] for bt in self.bottoms], np.float64)
            bhi = np.array([bt.mesh.bounds()[1] for bt in self.bottoms], np.float64)
            wlo, whi = placed_boxes(blo[self.instance_bottom[active]], bhi[self.instance_bottom[active]], m[active])
            pad = BOX_PAD * (np.maximum(np.abs(wlo), np.abs(whi)).max(axis=1) + (whi - wlo).max(axis=1))
            lo[active] = wlo - pad[:, None]
            hi[active] = whi + pad[:, None]
        self._lo, self._hi = lo, hi
        self._active = active.astype(np.int32)
        self._tree = _TopTree(lo[active], hi[active]) if active.size >= self.pairs_from else None
        # the loop path first keeps the rays near some instance (``near_rays``); the tree
        # path's top level culls by itself
        self._balls = balls(lo[active], hi[active]) if self._tree is None else None

    def with_matrices(self, matrices) -> "TwoLevel":
        """The same bottoms, instances and global indices at new placements: only the top
        level (boxes, inverses, tree) is rebuilt; the bottoms are shared."""
        new = TwoLevel.__new__(TwoLevel)
        new.__dict__.update({k: v for k, v in self.__dict__.items()})
        new._place(matrices)
        return new

    @property
    def instance_count(self) -> int:
        return int(len(self.instance_bottom))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) float32 world box over the instances that can be hit (their padded
        boxes, rounded outward); zeros when there is none."""
        if self._active.size == 0:
            return np.zeros(3, F32), np.zeros(3, F32)
        lo = self._lo[self._active].min(axis=0)
        hi = self._hi[self._active].max(axis=0)
        lo32, hi32 = lo.astype(F32), hi.astype(F32)
        lo32 = np.where(lo32 > lo, np.nextafter(lo32, F32(-np.inf)), lo32)
        hi32 = np.where(hi32 < hi, np.nextafter(hi32, F32(np.inf)), hi32)
        return lo32, hi32

    def flatten(self) -> TriangleMesh:
        """The equivalent flat world-space soup: every instance's triangles through its
        matrix (float64, then float32), ordered by global index, with ``instance_index``.
        Assumes the default consecutive ``tri_base`` (raises ValueError otherwise)."""
        counts = self._bottom_triangles[self.instance_bottom]
        if self.instance_count and not np.array_equal(self.tri_base, np.concatenate([[0], np.cumsum(counts)[:-1]])):
            raise ValueError("flatten() needs the default consecutive tri_base")
        verts, tris, owner, nv = [], [], [], 0
        for i, k in enumerate(self.instance_bottom):
            mesh = self.bottoms[k].mesh
            w = mesh.vertices.astype(np.float64) @ self.matrices[i, :3, :3].T + self.matrices[i, :3, 3]
            verts.append(w)
            tris.append(mesh.triangles.astype(np.int64) + nv)
            owner.append(np.full(mesh.triangle_count, i, np.int32))
            nv += len(w)
        if not verts:
            return TriangleMesh(np.zeros((0, 3), F32), np.zeros((0, 3), np.int32))
        return TriangleMesh(np.vstack(verts), np.vstack(tris), instance_index=np.concatenate(owner))

    # -- rays -------------------------------------------------------------------------
    @staticmethod
    def _prepare(origins, directions, tmin, tmax):
        """prepare_rays (validation, float32) after broadcasting one origin or one
        direction row against the other's (M, 3)."""
        o, d = np.asarray(origins), np.asarray(directions)
        o2 = o[None, :] if o.ndim == 1 else o
        d2 = d[None, :] if d.ndim == 1 else d
        if o2.ndim == 2 and d2.ndim == 2 and o2.shape[1:] == d2.shape[1:] == (3,) and len(o2) != len(d2) \
                and 1 in (len(o2), len(d2)):
            o2, d2 = np.broadcast_arrays(o2, d2)
        return prepare_rays(o2, d2, tmin, tmax, shear=False)

    def _chunks(self, m: int, per: int):
        return [slice(a, min(m, a + per)) for a in range(0, m, per)]

    def _object_rays(self, ray, inst, o64, d64, single: bool):
        """The pairs' rays in their instances' object space (float64), and which of them
        the bottom can take (finite in float32, a direction that does not round to zero)."""
        # the same float64 operations in the same order on both paths (``_mul``), so the
        # loop and the tree hand a bottom bit-identical rays
        key = inst[0] if single else inst
        ai = self._inverse[key]
        oo = _mul(ai, o64[ray] - self._translation[key])
        dd = _mul(ai, d64[ray])
        with np.errstate(over="ignore", invalid="ignore"):
            o32, d32 = oo.astype(F32), dd.astype(F32)
        return o32, d32, _usable(o32, d32)

    def _call_bottom(self, bottom, ray, inst, rays, o64, d64, tmax_pair, occluded: bool, single=False):
        """One call to ``bottom`` for pairs (ray, inst): Hits (or an (P,) bool) per pair."""
        o32, d32, good = self._object_rays(ray, inst, o64, d64, single)
        if not good.all():
            k = np.flatnonzero(good)
            sub = self._call_bottom_ok(bottom, o32[k], d32[k], rays.tmin[ray[k]], tmax_pair[k], occluded)
            if occluded:
                out = np.zeros(len(ray), bool)
                out[k] = sub
                return out
            out = Hits.empty(len(ray))
            out.t[k], out.triangle[k], out.u[k], out.v[k] = sub.t, sub.triangle, sub.u, sub.v
            return out
        return self._call_bottom_ok(bottom, o32, d32, rays.tmin[ray], tmax_pair, occluded)

    @staticmethod
    def _call_bottom_ok(bottom, o32, d32, tmin, tmax, occluded):
        if len(o32) == 0:
            return np.zeros(0, bool) if occluded else Hits.empty(0)
        return bottom.occluded(o32, d32, tmin, tmax) if occluded else bottom.trace(o32, d32, tmin, tmax)

    # -- the public interface ---------------------------------------------------------
    def trace(self, origins, directions, tmin=0.0, tmax=np.inf) -> InstanceHits:
        """Nearest hit per ray over all instances, with tmin < t <= tmax (world units of
        the given directions); an exact tie in t goes to the lowest global triangle.

        origins, directions: (M, 3), or one (3,) row broadcast against the other's M rows;
        tmin, tmax: scalars or (M,).  Returns ``InstanceHits``."""
        return self.trace_rays(self._prepare(origins, directions, tmin, tmax), one_origin(origins))

    def trace_rays(self, rays, same_origin: bool) -> InstanceHits:
        """``trace`` of rays prepared already (``prepare_rays(..., shear=False)`` or the
        same arrays validated by the caller: ``Split``, whose first soup's trace checked
        them); ``same_origin``: every ray starts at ``rays.origins[0]``."""
        out = InstanceHits.empty(len(rays), self.triangle_dtype)
        if len(rays) == 0 or self._active.size == 0:
            return out
        rows = None if self._balls is None else near_rays(rays, *self._balls, same_origin)
        return _nearest_of(rays, rows, out, lambda sub, rows, best: self._run(sub, best, None))

    def occluded(self, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
        """(M,) bool: True where some instance's triangle is hit with tmin < t <= tmax
        (each ray stops at its first hit instance)."""
        rays = self._prepare(origins, directions, tmin, tmax)
        if len(rays) == 0 or self._active.size == 0:
            return np.zeros(len(rays), bool)
        return _any_of(rays, self._near(rays, origins), lambda sub, rows, hit: self._run(sub, None, hit))

    def _near(self, rays, origins):
        """The loop path's rays that come near some instance (``near_rays``), or None on
        the tree path (all rays)."""
        return None if self._balls is None else near_rays(rays, *self._balls, one_origin(origins))

    def _run(self, rays, best, occluded):
        o64 = rays.origins.astype(np.float64)
        d64 = rays.directions.astype(np.float64)
        seg = _Segments(o64, d64, rays.tmin, rays.tmax)
        if self._tree is None:
            per = max(1, min(self.ray_chunk, self.pair_limit // max(1, self._active.size)))
            for sl in self._chunks(len(rays), per):
                self._trace_loop(np.arange(sl.start, sl.stop), rays, o64, d64, seg, best, occluded)
        else:
            for sl in self._chunks(len(rays), self.ray_chunk):
                self._trace_pairs(np.arange(sl.start, sl.stop), rays, o64, d64, seg, best, occluded)

    # few instances: a loop over instances, nearest box entry first -----------------------
    def _trace_loop(self, rid, rays, o64, d64, seg, best, occluded):
        act = self._active
        lo, hi = self._lo[act], self._hi[act]
        # (A, m): where each ray's segment enters each box, and whether it meets it
        near, touch = seg.enter([x[rid][None] for x in seg.o], [x[rid][None] for x in seg.inv],
                                [c[:, None] for c in lo.T], [c[:, None] for c in hi.T], seg.tmin[rid], seg.tmax[rid])

        def call(i, sel):
            ray = rid[sel]
            inst = np.full(sel.size, i, np.int32)
            bottom = self.bottoms[self.instance_bottom[i]]
            if occluded is not None:
                occluded[ray] |= self._call_bottom(bottom, ray, inst, rays, o64, d64, rays.tmax[ray], True, single=True)
            else:
                tmax_pair = np.minimum(rays.tmax[ray], best.t[ray])
                h = self._call_bottom(bottom, ray, inst, rays, o64, d64, tmax_pair, False, single=True)
                best.fold(ray, inst, h, self.tri_base, unique=True)

        _nearest_first(act, near, touch, rid, best, occluded, call)

    # many instances: candidate pairs from the tree, traced in rounds per bottom --------
    def _trace_pairs(self, rid, rays, o64, d64, seg, best, occluded):
        got = self._tree.candidates(rid, seg, self.pair_limit)
        if got is None:  # too many pairs for one chunk: split it
            h = len(rid) // 2
            self._trace_pairs(rid[:h], rays, o64, d64, seg, best, occluded)
            self._trace_pairs(rid[h:], rays, o64, d64, seg, best, occluded)
            return
        ray, leaf, near = got
        if ray.size == 0:
            return
        inst = self._active[leaf]
        order = np.lexsort((near, ray))  # by ray, then box entry
        ray, inst, near = ray[order], inst[order], near[order]
        start = np.ones(ray.size, bool)
        start[1:] = ray[1:] != ray[:-1]
        first = np.flatnonzero(start)
        rank = np.arange(ray.size) - np.repeat(first, np.diff(np.append(first, ray.size)))
        a, width = 0, 1
        top = int(rank.max()) + 1
        while a < top:
            sel = (rank >= a) & (rank < a + width)
            if occluded is not None:
                sel &= ~occluded[ray]
            else:
                sel &= near <= best.t[ray]
            k = np.flatnonzero(sel)
            a, width = a + width, 2 * width
            if k.size == 0:
                continue
            kb = self.instance_bottom[inst[k]]
            by = np.argsort(kb, kind="stable")
            k, kb = k[by], kb[by]
            cuts = np.flatnonzero(np.diff(kb)) + 1
            for part in np.split(k, cuts):  # one call per bottom
                r, i = ray[part], inst[part]
                bottom = self.bottoms[self.instance_bottom[i[0]]]
                if occluded is not None:
                    hit = self._call_bottom(bottom, r, i, rays, o64, d64, rays.tmax[r], True)
                    occluded[r[hit]] = True
                else:
                    tmax_pair = np.minimum(rays.tmax[r], best.t[r])
                    best.fold(r, i, self._call_bottom(bottom, r, i, rays, o64, d64, tmax_pair, False), self.tri_base)

    def stats(self) -> dict:
        return {"kind": self.kind, "instances": self.instance_count, "hittable_instances": int(self._active.size),
                "bottoms": len(self.bottoms), "triangles": self.triangle_count,
                "top_level": "tree" if self._tree is not None else "loop"}

    def __repr__(self):
        return (f"<TwoLevel {self.instance_count} instances of {len(self.bottoms)} bottoms, "
                f"{self.triangle_count} triangles, top level: {'tree' if self._tree is not None else 'loop'}>")


def _nearest_first(act, near, touch, rid, best, occluded, call):
    """The loop path's visit of instances ``act`` (near, touch: (A, m) each ray's box entry
    and whether it meets the box): nearest mean entry first, each with the rays of ``rid``
    that reach its box before their best hit so far (or, for ``occluded``, that are not
    occluded yet), as ``call(instance, selected positions in rid)``."""
    count = touch.sum(axis=1)
    mean_entry = np.where(touch, near, 0.0).sum(axis=1) / np.maximum(count, 1)
    for j in np.lexsort((mean_entry, count == 0)):
        if count[j] == 0:
            break
        if occluded is not None:
            sel = np.flatnonzero(touch[j] & ~occluded[rid])
        else:
            sel = np.flatnonzero(touch[j] & (near[j] <= best.t[rid]))
        if sel.size:
            call(int(act[j]), sel)


def _usable(o32, d32) -> np.ndarray:
    """(P,) bool: object-space rays a bottom can take (finite in float32, a direction that
    does not round to zero).  Whole-array tests first, then by columns: a row-wise reduce
    over 3 columns costs several times more."""
    if np.isfinite(o32).all() and np.isfinite(d32).all() and d32.all():
        return np.ones(len(o32), bool)
    fin = np.isfinite(o32) & np.isfinite(d32)
    return (fin[:, 0] & fin[:, 1] & fin[:, 2]) & ((d32[:, 0] != 0) | (d32[:, 1] != 0) | (d32[:, 2] != 0))


def placed_boxes(lo, hi, matrices) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (A, 3) float64 world boxes of object boxes (lo, hi) (A, 3) placed by
    ``matrices`` (A, 4, 4): their 8 corners through each matrix, in float64."""
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1  # (8, 3) corner selectors
    corners = np.where(bits[None], np.asarray(hi, np.float64)[:, None, :], np.asarray(lo, np.float64)[:, None, :])
    m = np.asarray(matrices, np.float64)
    world = np.einsum("aij,akj->aki", m[:, :3, :3], corners) + m[:, None, :3, 3]
    return world.min(axis=1), world.max(axis=1)


def balls(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """(centres (A, 3), radii (A,)) float64 of the balls around boxes (lo, hi) (A, 3)."""
    lo, hi = np.asarray(lo, np.float64).reshape(-1, 3), np.asarray(hi, np.float64).reshape(-1, 3)
    return 0.5 * (lo + hi), 0.5 * np.sqrt(((hi - lo) ** 2).sum(axis=1))


#: ``near_rays``' margin: a ball's radius grows by this share of itself and of the origin's
#: distance to its centre, and each ray's interval by this share of its own reach, far
#: beyond float32's rounding of the distances (a few 1e-7 of them), so the test only lets
#: through more rays than an exact one, never fewer
REACH_MARGIN = 1e-3


def near_rays(rays, centres, radii, same_origin: bool) -> np.ndarray:
    """The rows of prepared ``rays`` whose segment [tmin, tmax] may come within ``radii``
    of some of ``centres``: a float32 test with ``REACH_MARGIN``, before the exact float64
    box tests of a few instances.  A rotating sensor's or a camera's rays mostly miss a few
    movers, which then cost only for the rays that pass near them.  ``same_origin``: every
    ray starts at the first one's origin.  A NaN or overflow in the test keeps the ray.

    Written with products by (3, k) matrices and per-coordinate columns: numpy's
    reductions and broadcasts over rows of 3 cost several times more."""
    m = len(rays)
    if m == 0 or len(radii) == 0:
        return np.zeros(0, np.intp)
    o, d = rays.origins, rays.directions
    dd = np.square(d) @ np.ones(3, F32)
    eps = F32(REACH_MARGIN)
    centres = np.asarray(centres, np.float64)
    # the radius also covers the centre's rounding to float32
    grown = (np.asarray(radii, np.float64) * (1.0 + REACH_MARGIN)
             + 4.0 * np.spacing(np.abs(centres).max(axis=1).astype(F32))).astype(F32)
    keep = np.zeros(m, bool)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if same_origin:  # the centres seen from the origin, exactly in float64
            w = centres - o[0].astype(np.float64)
            ww_all = (w * w).sum(axis=1).astype(F32)
            wd_all = np.ascontiguousarray((d @ w.T.astype(F32)).T)
        else:
            o_cols = np.ascontiguousarray(o.T)
            d_cols = np.ascontiguousarray(d.T)
        for a in range(len(grown)):
            if same_origin:
                ww, wd = ww_all[a], wd_all[a]
            else:
                ca = centres[a].astype(F32)
                w = [ca[k] - o_cols[k] for k in range(3)]
                ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
                wd = w[0] * d_cols[0] + w[1] * d_cols[1] + w[2] * d_cols[2]
            re = grown[a] + eps * np.sqrt(ww)
            # the line's squared distance from the centre, times dd: most rays pass wide of
            # every ball, and only the rest take the interval's test (NaN keeps the ray)
            near = np.flatnonzero(~(ww * dd - wd * wd > re * re * dd))
            if not near.size:
                continue
            ddn, wdn = dd[near], wd[near]
            ww_n, re_n = (ww, re) if np.ndim(ww) == 0 else (ww[near], re[near])  # scalars from one origin
            tp = wdn / ddn                 # where the line comes nearest the centre
            off2 = ww_n - tp * tp * ddn    # its squared distance from it there
            h = np.sqrt(np.maximum(re_n * re_n - off2, F32(0)) / ddn)  # half the chord, in t
            slack = eps * (np.abs(tp) + h)
            out = (off2 > re_n * re_n) | (tp + h < rays.tmin[near] - slack) | (tp - h > rays.tmax[near] + slack)
            keep[near[~out]] = True
    return np.flatnonzero(keep)


def _nearest_of(rays, rows, out: InstanceHits, run) -> InstanceHits:
    """The nearest hits of ``rays`` into ``out``, traced only for ``rows`` (None: all; the
    rest stay misses): ``run(those rays, rows, _Best over them)``."""
    if rows is not None and rows.size == 0:
        return out
    best = _Best(len(rays) if rows is None else rows.size)
    run(rays if rows is None else rays.subset(rows), slice(None) if rows is None else rows, best)
    return best.into(out, rows)


def _any_of(rays, rows, run) -> np.ndarray:
    """(M,) bool any-hit of ``rays``, traced only for ``rows`` (None: all):
    ``run(those rays, rows, their (R,) bool to set)``."""
    hit = np.zeros(len(rays), bool)
    if rows is None:
        run(rays, slice(None), hit)
    elif rows.size:
        sub = np.zeros(rows.size, bool)
        run(rays.subset(rows), rows, sub)
        hit[rows] = sub
    return hit


def one_origin(origins) -> bool:
    """Whether every row of ``origins`` is the first: one row, or a broadcast of one."""
    o = np.asarray(origins)
    return o.ndim == 1 or len(o) <= 1 or o.strides[0] == 0


def _mul(a, x):
    """(P, 3) rows ``a @ x`` for one (3, 3) ``a`` or one per row (P, 3, 3), in float64."""
    out = np.empty_like(x)
    for k in range(3):
        out[:, k] = a[..., k, 0] * x[:, 0] + a[..., k, 1] * x[:, 1] + a[..., k, 2] * x[:, 2]
    return out


class _Segments:
    """A chunk's ray segments for the box tests, in float64 columns: origins, reciprocal
    directions and [tmin, tmax].

    The slab test (Kay and Kajiya; robust as Ize, JCGT 2013: far widened by 1 + 2 gamma(3))
    is written out here rather than through ``intersect.slab_interval``, whose per-axis
    branches for zero components took most of the top level's time.  Instead a zero
    component (+0.0 or -0.0) gets the reciprocal +-1e308 and tmax is capped at 1e300: an
    origin inside the slab then gives an interval of about (-1e308, 1e308) and one outside
    an entry beyond the cap, or inf; no NaN can arise (the differences and reciprocals are
    finite), and where the cap lets through a box the exact test would not (an origin
    within 1e-8 of a slab it does not move along), the pair is only traced for nothing.
    """

    CAP = 1e300

    def __init__(self, o64, d64, tmin, tmax):
        self.o = [np.ascontiguousarray(o64[:, k]) for k in range(3)]
        self.inv = [1.0 / np.where(d64[:, k] == 0, np.copysign(1e-308, d64[:, k]), d64[:, k]) for k in range(3)]
        self.tmin = tmin.astype(np.float64)
        self.tmax = np.minimum(tmax.astype(np.float64), self.CAP)

    @staticmethod
    def enter(o, inv, lo, hi, tmin, tmax):
        """(near, meets): where each segment [tmin, tmax] enters each box (clipped to
        tmin) and whether it meets the box.  o, inv, lo, hi: three arrays each (x, y, z),
        broadcasting with tmin and tmax."""
        near, far = tmin, tmax
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(3):
                t0 = (lo[k] - o[k]) * inv[k]
                t1 = (hi[k] - o[k]) * inv[k]
                near = np.maximum(near, np.minimum(t0, t1))
                far = np.minimum(far, np.maximum(t0, t1))
            return near, near <= far + (2 * _GAMMA3) * np.abs(far)


def _morton3(q):
    """30-bit Morton codes of (N, 3) integer coordinates in 0..1023."""
    q = q.astype(np.uint64)
    out = np.zeros(len(q), np.uint64)
    for k in range(3):
        x = q[:, k]
        x = (x | (x << np.uint64(16))) & np.uint64(0x030000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x0300F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x030C30C3)
        x = (x | (x << np.uint64(2))) & np.uint64(0x09249249)
        out |= x << np.uint64(k)
    return out


class _TopTree:
    """A complete binary tree over instance boxes in Morton order of their centres.

    Level 0 is the root; level L holds the leaves, one box each (padded to a power of
    two with empty boxes); a node j of level k has the children 2j and 2j+1 of level
    k + 1, so the tree is only its levels' boxes.  Built bottom-up, one numpy step a
    level: O(I) after the O(I log I) sort (the LBVH idea, Lauterbach et al. 2009, with
    median splits of the sorted order instead of Morton-bit splits)."""

    def __init__(self, lo, hi):
        n = len(lo)
        c = (lo + hi) / 2
        clo, chi = c.min(axis=0), c.max(axis=0)
        q = np.clip((c - clo) / np.where(chi > clo, chi - clo, 1.0) * 1023, 0, 1023)
        self.order = np.argsort(_morton3(q), kind="stable").astype(np.int32)
        size = 1 << max(0, int(np.ceil(np.log2(max(n, 1)))))
        llo = np.zeros((size, 3))
        lhi = np.zeros((size, 3))
        llo[:n], lhi[:n] = lo[self.order], hi[self.order]
        levels = [(llo, lhi)]
        while len(levels[-1][0]) > 1:
            a, b = levels[-1]
            levels.append((np.minimum(a[0::2], a[1::2]), np.maximum(b[0::2], b[1::2])))
        self.levels = [(list(np.ascontiguousarray(a.T)), list(np.ascontiguousarray(b.T))) for a, b in levels[::-1]]
        # nodes of level k holding real boxes: the first ceil(n / 2^(L-k)) (the padding
        # leaves are at the end); the empty ones are masked by index, not by their boxes
        depth = len(levels) - 1
        self.filled = [-(-n // (1 << (depth - k))) for k in range(depth + 1)]

    def candidates(self, rid, seg: "_Segments", limit):
        """(ray, leaf, near): the pairs whose ray segment [tmin, tmax] meets the leaf's
        box (leaf = position in the caller's active instances), near = max(box entry,
        tmin); None when a level would hold more than ``limit`` pairs (and there is more
        than one ray to split)."""
        ray = rid.astype(np.int64)
        node = np.zeros(len(rid), np.int64)
        last = len(self.levels) - 1
        for k, (lo, hi) in enumerate(self.levels):
            near, ok = seg.enter([x.take(ray) for x in seg.o], [x.take(ray) for x in seg.inv],
                                 [c.take(node) for c in lo], [c.take(node) for c in hi],
                                 seg.tmin.take(ray), seg.tmax.take(ray))
            ok &= node < self.filled[k]
            ray, node, near = ray[ok], node[ok], near[ok]
            if k == last:
                break
            if 2 * ray.size > limit and len(rid) > 1:
                return None
            ray = np.repeat(ray, 2)
            node = (2 * node[:, None] + np.arange(2)).reshape(-1)
        return ray, self.order[node], near


class Swept:
    """A ``TwoLevel``'s instances at K instants, each ray seeing them at its own: the
    instants of a sensor's sweep, whose firings each happen at their own time while objects
    move rigidly.

    ``matrices`` (K, I, 4, 4): instance i's object-to-world matrix at instant k (each
    instant validated as ``TwoLevel`` does).  ``trace(..., slot=)`` takes per ray its
    instant (M,) int in 0..K-1 and gives per ray exactly what
    ``two.with_matrices(matrices[slot]).trace`` gives it (the same float64 object-space
    rays, the same nearest hit and tie-break), with one bottom call per instance for all
    rays whatever K.  Each instance is visited for every ray of the chunk (the loop path of
    ``TwoLevel``), so this is for a few instances (fewer than ``PAIRS_FROM``)."""

    kind = "twolevel"

    def __init__(self, two: TwoLevel, matrices):
        m = np.asarray(matrices, np.float64)
        if m.ndim != 4 or m.shape[1:] != (two.instance_count, 4, 4) or len(m) == 0:
            raise ValueError(f"matrices must have shape (K, {two.instance_count}, 4, 4) with K >= 1, got {m.shape}")
        k, n = m.shape[:2]
        try:  # every instant's placements validated, inverted and boxed in one pass
            every = TwoLevel(two.bottoms, np.tile(two.instance_bottom, k), m.reshape(-1, 4, 4), np.tile(two.tri_base, k),
                             pairs_from=np.iinfo(np.int64).max)
        except ValueError:
            for mk in m:  # the message names the instance within its instant
                two.with_matrices(mk)
            raise
        self.two = two
        self.matrices = m
        self._inverse = every._inverse.reshape(k, n, 3, 3)
        self._translation = every._translation.reshape(k, n, 3)
        lo, hi = every._lo.reshape(k, n, 3), every._hi.reshape(k, n, 3)
        # per instance, (3, K) box corners: a chunk gathers its rays' instants as whole rows
        self._lo = np.ascontiguousarray(lo.transpose(1, 2, 0))
        self._hi = np.ascontiguousarray(hi.transpose(1, 2, 0))
        self._live = np.ascontiguousarray(np.isfinite(lo[:, :, 0]).T)  # (I, K): can be hit at that instant
        self._active = np.flatnonzero(self._live.any(axis=1)).astype(np.int32)
        with np.errstate(invalid="ignore"):  # (I, 3) each instance's box over every instant (inf where never)
            self._sweep_lo, self._sweep_hi = lo.min(axis=0), hi.max(axis=0)
        # the active instances' balls around their boxes over the sweep, for ``near_rays``
        self._balls = balls(self._sweep_lo[self._active], self._sweep_hi[self._active])
        self.triangle_count = two.triangle_count
        self.triangle_dtype = two.triangle_dtype
        self.ray_chunk = max(1, min(two.ray_chunk, two.pair_limit // max(1, self._active.size)))

    @property
    def instance_count(self) -> int:
        return self.two.instance_count

    def _slots(self, slot, m):
        s = np.asarray(slot)
        if s.shape != (m,) or (m and not np.issubdtype(s.dtype, np.integer)):
            raise ValueError(f"slot must be a ({m},) integer array, got shape {s.shape} dtype {s.dtype}")
        if m and (s.min() < 0 or s.max() >= len(self.matrices)):
            raise ValueError(f"slot must lie in 0..{len(self.matrices) - 1}")
        return s.astype(np.intp)

    def trace(self, origins, directions, tmin=0.0, tmax=np.inf, *, slot) -> InstanceHits:
        """Nearest hit per ray over all instances placed at the ray's instant ``slot``."""
        return self.trace_rays(TwoLevel._prepare(origins, directions, tmin, tmax), one_origin(origins), slot=slot)

    def trace_rays(self, rays, same_origin: bool, *, slot) -> InstanceHits:
        """``trace`` of rays prepared already (``TwoLevel.trace_rays``)."""
        m = len(rays)
        slot = self._slots(slot, m)
        out = InstanceHits.empty(m, self.triangle_dtype)
        return _nearest_of(rays, near_rays(rays, *self._balls, same_origin), out,
                           lambda sub, rows, best: self._run(sub, slot[rows], best, None))

    def occluded(self, origins, directions, tmin=0.0, tmax=np.inf, *, slot) -> np.ndarray:
        """(M,) bool: some instance, placed at the ray's instant, hit with tmin < t <= tmax."""
        rays = TwoLevel._prepare(origins, directions, tmin, tmax)
        m = len(rays)
        slot = self._slots(slot, m)
        return _any_of(rays, near_rays(rays, *self._balls, one_origin(origins)),
                       lambda sub, rows, hit: self._run(sub, slot[rows], None, hit))

    def _run(self, rays, slot, best, occluded):
        two = self.two
        o64 = rays.origins.astype(np.float64)
        d64 = rays.directions.astype(np.float64)
        seg = _Segments(o64, d64, rays.tmin, rays.tmax)
        act = self._active
        for sl in two._chunks(len(rays), self.ray_chunk):
            rid = np.arange(sl.start, sl.stop)
            s = slot[sl]  # the chunk's columns as views: a chunk is a run of rays
            o, inv = [x[sl] for x in seg.o], [x[sl] for x in seg.inv]
            tmin, tmax = seg.tmin[sl], seg.tmax[sl]
            near, touch = np.full((act.size, rid.size), np.inf), np.zeros((act.size, rid.size), bool)
            for j, i in enumerate(act.tolist()):
                # the rays that meet the instance's box over the whole sweep, then each of them
                # against the box at its own instant
                _, meets = seg.enter(o, inv, self._sweep_lo[i], self._sweep_hi[i], tmin, tmax)
                c = np.flatnonzero(meets)
                if not c.size:
                    continue
                sc = s[c]
                near[j, c], touch[j, c] = seg.enter([x[c] for x in o], [x[c] for x in inv], self._lo[i][:, sc],
                                                    self._hi[i][:, sc], tmin[c], tmax[c])
                touch[j, c] &= self._live[i][sc]

            def call(i, sel, rid=rid, s=s):
                ray, ks = rid[sel], s[sel]
                ai = self._inverse[ks, i]
                oo = _mul(ai, o64[ray] - self._translation[ks, i])
                dd = _mul(ai, d64[ray])
                with np.errstate(over="ignore", invalid="ignore"):
                    o32, d32 = oo.astype(F32), dd.astype(F32)
                good = _usable(o32, d32)
                if not good.all():
                    ray, o32, d32 = ray[good], o32[good], d32[good]
                bottom = two.bottoms[two.instance_bottom[i]]
                if occluded is not None:
                    occluded[ray] |= TwoLevel._call_bottom_ok(bottom, o32, d32, rays.tmin[ray], rays.tmax[ray], True)
                else:
                    tmax_pair = np.minimum(rays.tmax[ray], best.t[ray])
                    h = TwoLevel._call_bottom_ok(bottom, o32, d32, rays.tmin[ray], tmax_pair, False)
                    best.fold(ray, np.full(len(ray), i, np.int32), h, two.tri_base, unique=True)

            _nearest_first(act, near, touch, rid, best, occluded, call)

    def __repr__(self):
        return f"<Swept {self.instance_count} instances at {len(self.matrices)} instants, {self.triangle_count} triangles>"


def _first_soup(out: InstanceHits, h: Hits, acc, glob, inst, local):
    """Write the first soup's hits ``h`` over every ray of ``out`` (empty so far): a soup
    triangle's global index, instance and local triangle are taken from its tables with one
    more row for a miss (triangle -1 picks it), kept on the soup's structure while it serves."""
    ext = getattr(acc, "_miss_rows", None)
    if ext is None or ext[0] is not glob:
        tail = np.array([-1])
        ext = acc._miss_rows = (glob, np.concatenate([glob, tail]), np.concatenate([inst, tail]).astype(np.int32),
                                np.concatenate([local, tail]).astype(np.int32))
    k = h.triangle
    hit = k >= 0
    out.t = np.where(hit, h.t, F32(np.inf))
    out.triangle = np.take(ext[1], k)
    out.u, out.v = np.where(hit, h.u, F32(0)), np.where(hit, h.v, F32(0))
    out.instance, out.local_triangle = np.take(ext[2], k), np.take(ext[3], k)
    out.soup = hit.astype(np.int32) - 1  # 0 for the first soup, -1 on a miss
    out.soup_triangle = k.astype(np.int64)


class Split:
    """A scene cut in parts: flat structures over the world-space triangles of some
    instances (``soups``: the instances that stay put, built once while they do; a few
    small movers, rebuilt when they move), and a ``TwoLevel`` over the rest (``moving``, or
    None).  A scene whose few objects move rigidly keeps the fast flat trace for everything
    else and pays per frame only for what moved.

    soups: a list of (Accel over a world-space ``TriangleMesh``, global (Ts,) int64,
    instance (Ts,) int32, local (Ts,) int32): per soup triangle its global index, instance
    and triangle of the instance's bottom mesh (a soup holds whole instances, in increasing
    global order); moving_instances: (I_moving,) the instance number each of ``moving``'s
    instances reports.  Hits are ``InstanceHits`` as ``TwoLevel``'s, plus ``soup`` (M,)
    int32, the soup a hit came from (-1: from ``moving`` or none), ``soup_triangle`` (M,)
    its triangle in that soup and ``soups`` (the soups' structures): a soup's u, v are its
    triangles' as a flat scene lays them out (mirrored corners swapped).  An exact tie in
    t between parts goes to the lower global triangle.
    """

    kind = "twolevel"

    def __init__(self, soups, moving=None, moving_instances=None):
        self.soups = [(acc, np.asarray(g, np.int64), np.asarray(i, np.int32), np.asarray(loc, np.int32))
                      for acc, g, i, loc in soups]
        for acc, g, i, loc in self.soups:
            if not (len(g) == len(i) == len(loc)):
                raise ValueError("a soup's global, instance and local arrays must have one entry per triangle")
        self.moving = moving
        self.moving_instances = None if moving_instances is None else np.asarray(moving_instances, np.int32)
        self.triangle_count = sum(len(g) for _, g, _, _ in self.soups) + (
            moving.triangle_count if moving is not None else 0)

    def trace(self, origins, directions, tmin=0.0, tmax=np.inf, *, slot=None) -> InstanceHits:
        """``slot``: per ray its instant, when ``moving`` is a ``Swept``."""
        o32 = np.asarray(origins, np.float32)
        d32 = np.asarray(directions, np.float32)
        m = max(len(o32) if o32.ndim == 2 else 1, len(d32) if d32.ndim == 2 else 1)
        out = InstanceHits.empty(m, np.int64)
        out.soup = np.full(m, -1, np.int32)
        out.soup_triangle = np.full(m, -1, np.int64)
        out.soups = [acc for acc, _, _, _ in self.soups]
        lo = np.broadcast_to(np.asarray(tmin, np.float64), (m,))
        hi = np.broadcast_to(np.asarray(tmax, np.float64), (m,)).copy()
        for si, (acc, glob, inst, local) in enumerate(self.soups):
            if si == 0 and np.ndim(tmin) == 0 and np.ndim(tmax) == 0 and tmin <= tmax:
                h = acc.trace(o32, d32, tmin, tmax)  # one interval for all: no per-ray arrays
            else:
                h = acc.trace(o32, d32, lo, np.maximum(hi, lo))
            if si == 0:  # nothing found before: every ray takes the first soup's answer, by whole arrays
                _first_soup(out, h, acc, glob, inst, local)
                hi = np.minimum(hi, out.t)
                continue
            rows = np.flatnonzero(h.triangle >= 0)
            k = h.triangle[rows]
            g, t = glob[k], h.t[rows]
            cur_t, cur_g = out.t[rows], out.triangle[rows]  # against what the soups before found
            take = (cur_g < 0) | (t < cur_t) | ((t == cur_t) & (g < cur_g))
            rows, k, g, t = rows[take], k[take], g[take], t[take]
            out.t[rows] = t
            out.triangle[rows] = g
            out.u[rows], out.v[rows] = h.u[rows], h.v[rows]
            out.instance[rows] = inst[k]
            out.local_triangle[rows] = local[k]
            out.soup[rows] = si
            out.soup_triangle[rows] = k
            hi[rows] = np.minimum(hi[rows], t)
        if self.moving is None or m == 0:
            return out
        extra = {} if slot is None else {"slot": slot}
        if self.soups:  # the first soup's trace validated these rays and their interval: not again
            rays = Rays(np.broadcast_to(o32, (m, 3)), np.broadcast_to(d32, (m, 3)), lo.astype(F32),
                        np.maximum(hi, lo).astype(F32), None, None, None, None)
            hm = self.moving.trace_rays(rays, one_origin(o32), **extra)
        else:
            hm = self.moving.trace(np.broadcast_to(o32, (m, 3)), np.broadcast_to(d32, (m, 3)), lo, np.maximum(hi, lo),
                                   **extra)
        mg = hm.triangle >= 0
        take = mg & ((out.triangle < 0) | (hm.t < out.t) | ((hm.t == out.t) & (hm.triangle.astype(np.int64) < out.triangle)))
        out.t[take] = hm.t[take]
        out.triangle[take] = hm.triangle[take]
        out.u[take], out.v[take] = hm.u[take], hm.v[take]
        out.instance[take] = hm.instance[take] if self.moving_instances is None \
            else self.moving_instances[hm.instance[take]]
        out.local_triangle[take] = hm.local_triangle[take]
        out.soup[take] = -1
        out.soup_triangle[take] = -1
        return out

    def occluded(self, origins, directions, tmin=0.0, tmax=np.inf, *, slot=None) -> np.ndarray:
        o = np.asarray(origins, np.float32)
        d = np.asarray(directions, np.float32)
        m = max(len(o) if o.ndim == 2 else 1, len(d) if d.ndim == 2 else 1)
        lo = np.broadcast_to(np.asarray(tmin, np.float64), (m,))
        hi = np.broadcast_to(np.asarray(tmax, np.float64), (m,))
        hit = np.zeros(m, bool)
        parts = [acc for acc, _, _, _ in self.soups] + ([self.moving] if self.moving is not None else [])
        for acc in parts:
            rest = np.flatnonzero(~hit)
            if not len(rest):
                break
            extra = {"slot": slot[rest]} if slot is not None and acc is self.moving else {}
            hit[rest] = acc.occluded(o if o.ndim == 1 else o[rest], d if d.ndim == 1 else d[rest], lo[rest], hi[rest],
                                     **extra)
        return hit

    def __repr__(self):
        soups = ", ".join(f"{acc.kind} over {len(g):,}" for acc, g, _, _ in self.soups)
        return f"Split(soups=[{soups}], moving={self.moving!r})"
