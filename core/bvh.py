"""Bounding volume hierarchy in pure numpy: a 4-wide BVH, built and traversed level by level.

Build (whole-array numpy over one tree level at a time, O(N log N) in total):
  1. sort triangles along a 30-bit Morton curve of their centroids;
  2. split top-down, all nodes of a level at once, until a node holds ``leaf_size`` or fewer:
     - ``"sah"``: binned surface area heuristic on the widest centroid axis (Wald, "On fast
       construction of SAH-based bounding volume hierarchies", IEEE RT 2007), by segmented
       bincount / ufunc.at over all nodes of a level and a stable partition inside every
       node; big nodes are binned from an even sample of their Morton-ordered triangles;
     - ``"hlbvh"`` (default): the same SAH first over the occupied cells of a 2**cluster_bits
       grid (Morton prefixes; Garanzha, Pantaleoni, McAllister, "Simpler and faster HLBVH
       with work queues", HPG 2011), then inside each cell: nearly SAH quality, a fraction
       of the top levels' cost (their Karras splits inside cells: ``sah_min`` > cell size);
     - ``"morton"``: split at the highest differing Morton bit (Karras, "Maximizing
       parallelism in the construction of BVHs, octrees and k-d trees", HPG 2012);
     - ``"median"``: object median in Morton order (a balanced LBVH, like a complete tree);
  3. boxes bottom-up, then the binary tree is collapsed into 4-wide nodes (open the child of
     largest surface area until there are four), each node storing its children's boxes.

Traversal: a pool of rays steps in lockstep, one 4-wide node per ray per step, with per-ray
stacks stored (depth, rays); finished rays are compacted away and the pool refilled from
the chunk.  Leaf children are tested at once with the shared kernel (``intersect``, t_hi =
the best hit so far); inner children are sorted nearest first, the nearest is visited next
and the others are pushed with their entry distance, so a popped node that starts beyond
the best hit is dropped without a box test.

Robust slab test (Ize, "Robust BVH Ray Traversal", JCGT 2(2), 2013): with the reciprocal
direction each slab distance carries at most 3 roundings, so exit distances (and the best
hit they are compared with) are widened by ``1 + 2*gamma(3)`` and no ray misses a box it
touches.  A zero direction component gives a reciprocal of +-inf, and ``0 * inf = NaN``
when the origin lies on that slab's plane: the axis then says nothing (the ray runs inside
the plane), so the three axes are combined with ``fmax``/``fmin``, which skip NaN.  Empty
child slots get NaN boxes: all three axes NaN is the only way to get a NaN distance, and
NaN compares false, so they are never entered.
"""

from __future__ import annotations

import numpy as np

from .accel import LOCKSTEP_CHUNK, Accel
from .proximity import TreeIndex
from .intersect import UNIT_ROUNDOFF, NearestHits, Rays, intersect

F32 = np.float32
WIDTH = 4


def gamma(n: int) -> float:
    """pbrt's error bound gamma(n) = n*u / (1 - n*u) for n float32 roundings (u: ``UNIT_ROUNDOFF``)."""
    return n * UNIT_ROUNDOFF / (1 - n * UNIT_ROUNDOFF)


#: Ize 2013: exit distances (and the best-hit bound) widened by 1 + 2*gamma(3).
WIDEN = F32(1 + 2 * gamma(3))
MISS = np.uint64(0xFFFFFFFFFFFFFFFF)
LOW32 = np.uint64(0xFFFFFFFF)
#: rays per block of the traversal's transpose of gathered node boxes (24 floats a ray:
#: 192 KiB a block, within a core's L2 cache)
_TRANSPOSE_BLOCK = 2048
SAH_SAMPLE = 1024  # bin a bigger node from this many of its triangles
SMALL_BINS = 4  # bins for nodes of at most 8 * SMALL_BINS triangles
BUILDERS = ("hlbvh", "sah", "morton", "median")


# -- build ---------------------------------------------------------------------------------


def morton30(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) uint32 30-bit Morton codes of points quantised to 1024 cells per axis of [lo, hi]."""
    lo = np.asarray(lo, np.float64)
    ext = np.asarray(hi, np.float64) - lo
    scale = np.where(ext > 0, 1024.0 / np.where(ext > 0, ext, 1.0), 0.0)
    q = np.clip(((points - lo) * scale).astype(np.int64), 0, 1023).astype(np.uint32)
    code = np.zeros(len(points), np.uint32)
    for axis in range(3):
        x = q[:, axis]
        x = (x | (x << 16)) & np.uint32(0x030000FF)
        x = (x | (x << 8)) & np.uint32(0x0300F00F)
        x = (x | (x << 4)) & np.uint32(0x030C30C3)
        x = (x | (x << 2)) & np.uint32(0x09249249)
        code |= x << np.uint32(2 - axis)
    return code


class _Scratch:
    """Named work arrays one build reuses from level to level.

    A level's temporaries are as long as the triangles it splits.  Allocated afresh at
    every level, glibc handed them back to the kernel and took them again, so a
    1M-triangle build first-touched ~0.5 GB, a page fault every 4 KiB: a large share of its
    time, and a cost that moves with the machine's state.  ``get(name, n)`` is a view of
    the first n items of the buffer called ``name``, made on first use at the ``capacity``
    the build needs at most; no two live temporaries share a name."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self._buf = {}
        self._arange = np.arange(self.capacity)

    def get(self, name, n, dtype=np.intp):
        a = self._buf.get(name)
        if a is None or a.dtype != dtype or len(a) < n:
            a = self._buf[name] = np.empty(max(n, self.capacity), dtype)
        return a[:n]

    def arange(self, n):
        """0 .. n-1, read only (shared by every caller)."""
        if n > len(self._arange):
            self._arange = np.arange(n)
        return self._arange[:n]


def _gather(a, index, out, axis=None):
    """``np.take`` into ``out``.  Mode "clip", because "raise" fills a fresh copy of out and
    copies it back (numpy checks every index before it writes); the build's indices are
    in range by construction, so clipping never changes one."""
    return np.take(a, index, axis=axis, out=out, mode="clip")


def _segments(start, count, scratch=None):
    """For ranges [start, start+count): segment id and global position of every element,
    and each range's first element.  With ``scratch`` and every count > 0 (each split's
    case) the first two are its buffers "seg" and "pos"."""
    first = np.cumsum(count) - count
    p = int(count.sum())
    if scratch is None or not (count > 0).all():
        return np.repeat(np.arange(len(count)), count), np.arange(p) + np.repeat(start - first, count), first
    seg = scratch.get("seg", p)
    seg.fill(0)
    seg[first[1:]] = 1
    np.cumsum(seg, out=seg)
    pos = scratch.get("pos", p)
    _gather(start - first, seg, pos)
    pos += scratch.arange(p)
    return seg, pos, first


def _split_median(start, count, leaf_size):
    leaves = -(-count // leaf_size)
    return start + leaf_size * ((leaves + 1) // 2)


def _split_morton(codes, order, start, count):
    """Karras 2012: split where the highest Morton bit that differs inside the range flips.

    ``codes`` are per triangle; inside every node range ``order`` lists them sorted (the
    SAH partition is stable), so the flip is found by a bisection over all nodes at once.
    """
    end = start + count
    a = codes.take(order.take(start)).astype(np.int64)
    x = a ^ codes.take(order.take(end - 1)).astype(np.int64)
    bit = np.frexp(x.astype(np.float64))[1] - 1  # exact: codes have 30 bits
    bit = np.maximum(bit, 0)
    prefix = ((a >> bit) | 1) << bit
    lo, hi = start.copy(), end - 1  # codes[lo] < prefix <= codes[hi]
    while True:
        gap = hi - lo > 1
        if not gap.any():
            break
        mid = (lo + hi) >> 1
        ge = codes.take(order.take(mid)) >= prefix
        hi = np.where(gap & ge, mid, hi)
        lo = np.where(gap & ~ge, mid, lo)
    return np.where(x > 0, hi, start + count // 2)


def _half_area(lo, hi):
    """Half the surface area of boxes given as (3, ...) lo and hi (empty boxes: 0)."""
    d = np.maximum(hi - lo, 0)
    return d[0] * d[1] + d[1] * d[2] + d[2] * d[0]


def _split_sah(order, soa, start, count, bins, weight=None, sample=SAH_SAMPLE, scratch=None):
    """Binned SAH on the widest centroid axis, every node of a level at once.

    soa: (9, N) float32 per item (stored in ``order``'s initial, Morton order): centroid
    xyz, box lo xyz, box hi xyz.  Items may carry a ``weight`` (triangles per cluster) that
    counts in the cost instead of 1.  A node of more than ``sample``
    items is binned from ``sample`` of them taken evenly along its (Morton-ordered) range, a
    stratified sample of its space; all its items are then classified against the chosen
    plane.  Partitions ``order`` in place (stable within each node, so Morton order survives
    inside the children) and returns the split positions.  The item-long temporaries live
    in ``scratch`` (a ``_Scratch`` of at least len(order); a new one when None).
    """
    ws = _Scratch(len(order)) if scratch is None else scratch
    k = len(start)
    # -- bin statistics from (a sample of) each node
    m = np.minimum(count, sample)
    sampled = bool((m < count).any())
    sseg, spos, sfirst = _segments(start, m, ws)
    ps = len(spos)
    if sampled:  # spread each node's m positions evenly over its range
        st = ws.get("start", ps)
        _gather(start, sseg, st)
        f64 = ws.get("f64", ps, np.float64)
        _gather(count / m, sseg, f64)
        np.subtract(spos, st, out=spos)
        np.multiply(spos, f64, out=f64)
        np.copyto(spos, f64, casting="unsafe")  # truncation, as astype(np.intp)
        spos += st
    stri = ws.get("item", ps)
    _gather(order, spos, stri)
    c = ws.get("centroid", 3 * ps, F32).reshape(3, ps)
    _gather(soa[0:3], stri, c, axis=1)
    cmin = np.minimum.reduceat(c, sfirst, axis=1)
    ext = np.maximum.reduceat(c, sfirst, axis=1) - cmin
    axis = np.argmax(ext, axis=0)
    flat_k = axis * k + np.arange(k)
    e = ext.ravel().take(flat_k).astype(np.float64)
    scale = (bins / np.where(e > 0, e, 1.0)).astype(F32)  # float64 quotient: a tiny extent must not overflow
    amin = cmin.ravel().take(flat_k)
    idx, x, f32 = ws.get("index", ps), ws.get("x", ps, F32), ws.get("f32", ps, F32)
    _gather(axis, sseg, idx)  # each item's coordinate on its node's axis
    idx *= ps
    idx += ws.arange(ps)
    _gather(c.ravel(), idx, x)
    x -= _gather(amin, sseg, f32)
    x *= _gather(scale, sseg, f32)
    b = ws.get("bin", ps)
    np.copyto(b, x, casting="unsafe")  # truncation, as astype(np.intp)
    np.clip(b, 0, bins - 1, out=b)
    key = ws.get("key", ps)
    np.multiply(b, k, out=key)  # bins-major: (bins, k) tables, scans run along contiguous rows
    key += sseg
    w = None if weight is None else weight.take(stri)
    cnt = np.bincount(key, weights=w, minlength=bins * k).reshape(bins, k)
    blo = np.full((3, bins * k), np.inf, F32)
    bhi = np.full((3, bins * k), -np.inf, F32)
    for ax in range(3):
        np.minimum.at(blo[ax], key, _gather(soa[3 + ax], stri, f32))
        np.maximum.at(bhi[ax], key, _gather(soa[6 + ax], stri, f32))
    blo = blo.reshape(3, bins, k)
    bhi = bhi.reshape(3, bins, k)
    # split j (1 .. bins-1): left = bins [0, j), right = bins [j, bins); a sample's counts
    # are proportional to the node's, so the same j minimises the cost
    nl = np.cumsum(cnt, axis=0)[:-1]
    nr = cnt.sum(axis=0) - nl
    al = _half_area(_scan(np.minimum, blo.copy()), _scan(np.maximum, bhi.copy()))[:-1]
    ar = _half_area(_scan(np.minimum, blo, True), _scan(np.maximum, bhi, True))[1:]
    cost = al * nl + ar * nr
    cost[(nl == 0) | (nr == 0)] = np.inf
    j = np.argmin(cost, axis=0) + 1
    usable = np.isfinite(cost[j - 1, np.arange(k)])  # False when all centroids coincide: median
    # -- classify every item against its node's plane, partition stably
    left = ws.get("left", int(count.sum()), bool)
    if not sampled:  # the sample was every item: reuse its segments and bins
        seg, pos, first, tri = sseg, spos, sfirst, stri
        np.less(b, _gather(j, seg, key), out=left)
    else:
        seg, pos, first = _segments(start, count, ws)
        p = len(pos)
        tri = ws.get("item", p)
        _gather(order, pos, tri)
        idx, xa, f32, bi, jt = (ws.get(n, p, d) for n, d in
                                (("index", np.intp), ("x", F32), ("f32", F32), ("bin", np.intp), ("key", np.intp)))
        _gather(axis, seg, idx)
        idx *= soa.shape[1]
        idx += tri
        _gather(soa.ravel(), idx, xa)
        xa -= _gather(amin, seg, f32)
        xa *= _gather(scale, seg, f32)  # same rounding as the bins above
        np.copyto(bi, xa, casting="unsafe")
        np.less(bi, _gather(j, seg, jt), out=left)
    p = len(pos)
    local = ws.get("local", p)
    np.subtract(ws.arange(p), _gather(first, seg, local), out=local)
    if not usable.all():
        np.copyto(left, local < (count // 2).take(seg), where=~usable.take(seg))
    last = first + count - 1
    excl, lrank = ws.get("excl", p), ws.get("rank", p)

    def ranks():
        np.cumsum(left, out=excl)
        np.subtract(excl, left, out=excl)
        at_first = excl.take(first)
        np.subtract(excl, _gather(at_first, seg, lrank), out=lrank)
        return excl.take(last) + left.take(last) - at_first

    nleft = ranks()
    # a sampled plane may leave one side empty: fall back to the median there
    lopsided = (nleft == 0) | (nleft == count)
    if lopsided.any():
        np.copyto(left, local < (count // 2).take(seg), where=lopsided.take(seg))
        nleft = ranks()
    # left items to s + rank, right ones to s + nleft + (local - rank)
    dst = ws.get("index", p)
    _gather(nleft, seg, dst)
    dst += local
    dst -= lrank
    np.copyto(dst, lrank, where=left)
    dst += _gather(start, seg, local)
    order.put(dst, tri, mode="clip")  # "raise" would copy order first
    return start + nleft


def _scan(fn, a, reverse=False):
    """In-place running ``fn`` (minimum/maximum) over the bins axis of a (3, bins, k) table
    (a loop over bins: contiguous rows are much faster than ``accumulate`` on axis 1)."""
    n = a.shape[1]
    for i in range(n - 2, -1, -1) if reverse else range(1, n):
        fn(a[:, i], a[:, i + 1 if reverse else i - 1], out=a[:, i])
    return a


def _grow(start, count, ids, depth, splittable, split, next_id, records):
    """Split the frontier nodes ``ids`` (ranges start, count) level by level until
    ``splittable(start, count)`` is False everywhere; ``split(start, count)`` returns the
    split positions.  Appends (ids, start, count, depth, left child or -1) per level to
    ``records`` and returns the next free node id (children get consecutive ids)."""
    while len(ids):
        left = np.full(len(ids), -1, np.int64)
        S = np.flatnonzero(splittable(start, count))
        records.append((ids, start, count, depth, left))
        if len(S) == 0:
            break
        ss, cs = start[S], count[S]
        mid = split(ss, cs)
        left[S] = next_id + 2 * np.arange(len(S))
        next_id += 2 * len(S)
        ids = np.stack([left[S], left[S] + 1], axis=1).ravel()
        start = np.stack([ss, mid], axis=1).ravel()
        count = np.stack([mid - ss, ss + cs - mid], axis=1).ravel()
        depth = np.repeat(depth[S] + 1, 2)
    return next_id


def build_binary(tlo, thi, leaf_size=4, method="hlbvh", bins=16, cluster_bits=6, sah_min=0):
    """Top-down binary BVH over N triangle boxes, one level of nodes per numpy pass.

    Returns (order, start, count, left, right, depth): ``order`` lists the triangles (indices
    into tlo) leaf by leaf; node i covers order[start[i] : start[i]+count[i]]; left/right are
    child node ids (-1 for a leaf); the root is node 0.
    """
    if method not in BUILDERS:
        raise ValueError(f"unknown BVH builder {method!r}; expected one of {', '.join(BUILDERS)}")
    n = len(tlo)
    cen = (tlo + thi) * F32(0.5)
    codes = morton30(cen, cen.min(axis=0), cen.max(axis=0))
    order = np.argsort(codes, kind="stable")
    records = []
    zero, root = np.zeros(1, np.int64), np.full(1, n, np.int64)

    def splittable(s, c):
        return c > leaf_size

    def morton(s, c):
        return _split_morton(codes, order, s, c)

    def sah_splitter(order):
        """SAH splits of triangle ranges of ``order`` (Karras below ``sah_min`` triangles).
        Triangle data is stored in ``order``: the partition is stable, so the gathers
        inside every node stay (nearly) sequential.  Returns (perm, split): the split
        permutes ``perm``, positions into ``order``."""
        soa = np.ascontiguousarray(np.concatenate([cen, tlo, thi], axis=1).take(order, axis=0).T)
        perm = np.arange(n)
        pcodes = codes.take(order)
        scratch = _Scratch(n)  # one set of work arrays for every level

        def split(s, c):
            mid = np.empty(len(s), np.int64)
            big = c > sah_min
            # small nodes need fewer bins (the (bins, nodes) tables dominate deep levels)
            nb = np.where(c > 8 * SMALL_BINS, bins, np.minimum(bins, SMALL_BINS))
            for nbins in np.unique(nb[big]):
                g = big & (nb == nbins)
                mid[g] = _split_sah(perm, soa, s[g], c[g], int(nbins), scratch=scratch)
            if not big.all():
                mid[~big] = _split_morton(pcodes, perm, s[~big], c[~big])
            return mid

        return perm, split

    if method == "hlbvh":
        # Garanzha et al., "Simpler and faster HLBVH with work queues", HPG 2011: binned SAH
        # over the occupied cells of a 2**cluster_bits grid (Morton prefixes); inside each
        # cell binned SAH again (their Karras splits: sah_min above the cell size), which
        # keeps SAH quality where big triangles overlap (teapot in a stadium).
        key = codes.take(order) >> np.uint32(30 - 3 * cluster_bits)
        cstart = np.flatnonzero(np.diff(key, prepend=key[0] ^ np.uint32(1)))
        ccount = np.diff(cstart, append=n)
        clo = np.minimum.reduceat(tlo.take(order, axis=0), cstart, axis=0)
        chi = np.maximum.reduceat(thi.take(order, axis=0), cstart, axis=0)
        soa = np.ascontiguousarray(np.concatenate([(clo + chi) * F32(0.5), clo, chi], axis=1).T)
        corder = np.arange(len(cstart))
        cscratch = _Scratch(len(cstart))
        crec = []
        wcum = [None]

        def c_splittable(s, c):
            wcum[0] = np.concatenate([[0], np.cumsum(ccount.take(corder))])
            return (c > 1) & (wcum[0][s + c] - wcum[0][s] > leaf_size)

        def c_split(s, c):
            return _split_sah(corder, soa, s, c, bins, ccount, scratch=cscratch)

        next_id = _grow(zero, np.full(1, len(cstart), np.int64), zero, zero, c_splittable, c_split, 1, crec)
        # back to triangle ranges: clusters laid out in their final order
        _, pos, _ = _segments(cstart.take(corder), ccount.take(corder))
        order = order.take(pos)
        tcum = np.concatenate([[0], np.cumsum(ccount.take(corder))])
        for ids, s, c, d, left in crec:
            records.append((ids, tcum[s], tcum[s + c] - tcum[s], d, left))
        ids, s, c, d, left = (np.concatenate(x) for x in zip(*crec))
        ts, tc = tcum[s], tcum[s + c] - tcum[s]
        big = (left < 0) & (tc > leaf_size)  # cluster leaves still too big: one cell each
        perm, split = sah_splitter(order)
        next_id = _grow(ts[big], tc[big], ids[big], d[big], splittable, split, next_id, records)
        order = order.take(perm)
    elif method == "sah":
        perm, split = sah_splitter(order)
        next_id = _grow(zero, root, zero, zero, splittable, split, 1, records)
        order = order.take(perm)
    elif method == "morton":
        next_id = _grow(zero, root, zero, zero, splittable, morton, 1, records)
    else:
        next_id = _grow(zero, root, zero, zero, splittable, lambda s, c: _split_median(s, c, leaf_size), 1, records)
    start = np.zeros(next_id, np.int64)
    count = np.zeros(next_id, np.int64)
    left = np.zeros(next_id, np.int64)
    depth = np.zeros(next_id, np.int64)
    for ids, s, c, d, lf in records:  # later records (finer phases) override
        start[ids], count[ids], depth[ids], left[ids] = s, c, d, lf
    right = np.where(left >= 0, left + 1, -1)
    return order, start, count, left, right, depth


def _binary_boxes(tlo, thi, order, start, left, right, depth):
    """(nodes, 3) lo/hi of every binary node: leaves by a reduction over their triangles, inner
    nodes bottom-up, one level per step."""
    nn = len(start)
    lo = np.empty((nn, 3), F32)
    hi = np.empty((nn, 3), F32)
    leaves = np.flatnonzero(left < 0)
    leaves = leaves[np.argsort(start[leaves])]  # leaves tile order[0:N] in this order
    lo[leaves] = np.minimum.reduceat(tlo.take(order, axis=0), start[leaves], axis=0)
    hi[leaves] = np.maximum.reduceat(thi.take(order, axis=0), start[leaves], axis=0)
    inner = np.flatnonzero(left >= 0)
    inner = inner[np.argsort(-depth[inner], kind="stable")]  # deepest level first
    cuts = np.flatnonzero(np.diff(depth[inner])) + 1
    for p in np.split(inner, cuts):
        lo[p] = np.minimum(lo.take(left[p], axis=0), lo.take(right[p], axis=0))
        hi[p] = np.maximum(hi.take(left[p], axis=0), hi.take(right[p], axis=0))
    return lo, hi


def collapse_wide(left, right, area, width=WIDTH):
    """Collapse a binary tree into ``width``-wide nodes: start from a node's two children and
    repeatedly open the inner child of largest surface area.  Returns the binary node of
    every wide node (breadth-first), their (W, width) binary children (-1: empty slot) and
    the number of wide levels."""
    frontier = np.zeros(1, np.int64)
    nodes, kids = [], []
    while len(frontier):
        n = len(frontier)
        cand = np.full((n, width), -1, np.int64)
        if left[frontier[0]] < 0:  # only a leaf root: a wide root with one child
            cand[:, 0] = frontier
        else:
            cand[:, 0] = left[frontier]
            cand[:, 1] = right[frontier]
            for slot in range(2, width):
                safe = np.maximum(cand, 0)
                score = np.where((cand >= 0) & (left[safe] >= 0), area[safe], -1.0)
                j = np.argmax(score, axis=1)
                rows = np.flatnonzero(score[np.arange(n), j] >= 0)
                x = cand[rows, j[rows]]
                cand[rows, j[rows]] = left[x]
                cand[rows, slot] = right[x]
        nodes.append(frontier)
        kids.append(cand)
        flat = cand.ravel()
        frontier = flat[(flat >= 0) & (left[np.maximum(flat, 0)] >= 0)]
    return np.concatenate(nodes), np.concatenate(kids), len(nodes)


# -- traversal helpers -----------------------------------------------------------------------


def _widen(x, out=None):
    """Ize's widened upper bound, for non-negative distances (tmin >= 0): x * (1 + 2*gamma(3))."""
    return np.multiply(x, WIDEN, out=out)


def _widen_signed(x, out=None):
    """The same bound for distances of either sign: x + |x| * 2*gamma(3)."""
    return np.add(x, np.abs(x) * (WIDEN - F32(1)), out=out)


def _reciprocal(d):
    """1 / direction in float32; +-0.0 gives +-inf: see the module docstring."""
    with np.errstate(divide="ignore"):
        return F32(1.0) / d


def _sort4(a, b, c, d):
    """Five-comparator sorting network on four key arrays."""
    a, b = np.minimum(a, b), np.maximum(a, b)
    c, d = np.minimum(c, d), np.maximum(c, d)
    a, c = np.minimum(a, c), np.maximum(a, c)
    b, d = np.minimum(b, d), np.maximum(b, d)
    b, c = np.minimum(b, c), np.maximum(b, c)
    return a, b, c, d


class BVH(Accel):
    """4-wide BVH over the valid triangles, built level by level, traversed in lockstep.

    Config (keyword arguments, with their defaults):
      ``builder="hlbvh"``: "hlbvh", "sah", "morton" or "median" (see the module docstring);
      ``leaf_size=4``: split nodes until they hold at most this many triangles;
      ``sah_bins=16``: SAH bins per node (on the node's widest centroid axis);
      ``cluster_bits=6``: "hlbvh" grid of 2**cluster_bits cells per axis;
      ``sah_min=0``: nodes of at most this many triangles split at the highest differing
      Morton bit instead of by SAH (faster build, more node visits per ray);
      ``batch=65536``: rays stepping in lockstep per thread (bounds the working set; bigger
      pools amortise the per-step numpy calls, which two threads contend for: BENCHMARKS.md,
      "Threads: 1 -> 2 against the hardware's ceiling");
      plus ``threads`` and ``chunk_size`` of every structure (default 2**20 rays: the pool
      refills finished rays' slots in place, so it stays full until the chunk runs out and
      only the last steps of a chunk run on few rays; the threads trace every chunk
      together, each with its own pool refilled from one ``RaySupply``).

    Layout (read by tests and the cost model): ``node_boxes`` (W, 24) float32 per wide node
    the boxes of its 4 children as lo x, y, z then hi x, y, z, each for children 0..3 (NaN
    for an empty slot); ``node_children`` (W, 4) int32: >= 0 a wide node, < 0 the leaf
    ``~code``; leaf i holds ``leaf_triangles[leaf_start[i] : leaf_start[i] + leaf_count[i]]``
    (mesh triangle indices).  Node 0 is the root.
    """

    kind = "bvh"
    chunk_size = LOCKSTEP_CHUNK
    shares_chunks = True  # the threads trace each chunk together (``Accel._shared``)

    def __init__(self, mesh, *, builder: str = "hlbvh", leaf_size: int = 4, sah_bins: int = 16, cluster_bits: int = 6,
                 sah_min: int = 0, batch: int = 65536, **kw):
        if builder not in BUILDERS:
            raise ValueError(f"unknown BVH builder {builder!r}; expected one of {', '.join(BUILDERS)}")
        self.builder = builder
        self.leaf_size = max(1, int(leaf_size))
        self.sah_bins = max(2, int(sah_bins))
        self.batch = max(1, int(batch))
        self.cluster_bits = min(10, max(1, int(cluster_bits)))
        self.sah_min = max(0, int(sah_min))
        self._counters = []
        super().__init__(mesh, **kw)

    # -- build -----------------------------------------------------------------------------
    def _build(self):
        tv = self.mesh.tri_vertices
        ids = np.flatnonzero(self.mesh.valid)
        self.depth = 0
        if len(ids) == 0:
            self.node_boxes = np.empty((0, 6 * WIDTH), F32)
            self.node_children = np.empty((0, WIDTH), np.int32)
            self.leaf_start = self.leaf_count = np.empty(0, np.int32)
            self._tv = np.empty((0, 3, 3), F32)
            self.leaf_triangles = np.empty(0, np.int32)
            return
        tri = tv.take(ids, axis=0)
        tlo = np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2])
        thi = np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2])
        order, start, count, left, right, depth = build_binary(tlo, thi, self.leaf_size, self.builder, self.sah_bins, self.cluster_bits, self.sah_min)
        lo, hi = _binary_boxes(tlo, thi, order, start, left, right, depth)
        wnode, wkids, wdepth = collapse_wide(left, right, _half_area(lo.T, hi.T).astype(np.float64))
        # leaves numbered in triangle order, wide nodes in breadth-first order
        leaves = np.flatnonzero(left < 0)
        leaves = leaves[np.argsort(start[leaves])]
        code = np.zeros(len(start), np.int64)
        code[wnode] = np.arange(len(wnode))
        code[leaves] = ~np.arange(len(leaves))  # after: a root that is a leaf stays a leaf child
        pad = wkids < 0
        k = np.maximum(wkids, 0)
        box = np.stack([lo[k], hi[k]], axis=1)  # (W, 2, width, 3)
        box[np.broadcast_to(pad[:, None, :, None], box.shape)] = np.nan
        self.node_boxes = np.ascontiguousarray(box.transpose(0, 1, 3, 2)).reshape(len(wnode), 6 * WIDTH)
        self.node_children = np.where(pad, 0, code[k]).astype(np.int32)
        self.leaf_start = start[leaves].astype(np.int32)
        self.leaf_count = count[leaves].astype(np.int32)
        self.leaf_triangles = ids[order].astype(np.int32)
        self._tv = tv.take(self.leaf_triangles, axis=0)
        self.depth = int(wdepth)
        self._stack_depth = 3 * self.depth + 2

    def _point_index(self):
        return point_index_of(self)

    # -- traversal -------------------------------------------------------------------------
    def trace(self, *args, **kw):
        self._counters = []
        return super().trace(*args, **kw)

    def occluded(self, *args, **kw):
        self._counters = []
        return super().occluded(*args, **kw)

    def _trace_rays(self, rays: Rays):
        best = NearestHits(len(rays))
        if len(self.node_boxes):
            self._shared(lambda supply: self._traverse(rays, best, None, supply), len(rays))
        return self._finished(best, rays, self.mesh.tri_vertices)

    def _occluded_rays(self, rays: Rays):
        hit = np.zeros(len(rays), bool)
        if len(self.node_boxes):
            self._shared(lambda supply: self._traverse(rays, None, hit, supply), len(rays))
        return hit

    def _traverse(self, rays: Rays, best: NearestHits | None, anyhit: np.ndarray | None, supply):
        """Nearest hit (into ``best``) or any hit (into ``anyhit``) for the rays of one chunk
        this thread draws from ``supply`` (``RaySupply``; other threads fill other rays).

        A pool of at most ``batch`` rays steps in lockstep, one wide node per ray per step;
        finished rays are compacted away and the pool is refilled from the supply, so every
        step works on many rays and the per-ray state stays in cache.
        """
        with np.errstate(invalid="ignore", over="ignore"):  # 0 * inf: see the module docstring
            self._lockstep(rays, best, anyhit, supply)

    def _lockstep(self, rays: Rays, best: NearestHits | None, anyhit: np.ndarray | None, supply):
        m = len(rays)
        P = int(min(m, self.batch))
        D = self._stack_depth
        box, child, leaf_start, leaf_count = self.node_boxes, self.node_children, self.leaf_start, self.leaf_count
        # pool state, rays packed at the front [0, A)
        rid = np.empty(P, np.intp)
        cur = np.zeros(P, np.intp)  # the wide node each ray visits this step
        ptr = np.zeros(P, np.intp)  # next free stack slot, flat: depth * P + pool column
        org = np.empty((3, P), F32)  # origin and 1/direction, one row per axis
        inv = np.empty((3, P), F32)
        tmin = np.empty(P, F32)
        tlim = np.empty(P, F32)  # min(tmax, best hit so far); -inf once the ray is finished
        dead = np.zeros(P, bool)
        stack = np.empty((D, P), np.uint64)  # (depth, rays): pushes of neighbouring rays stay close
        sflat = stack.reshape(-1)
        # workspace, reused every step (fresh large temporaries cost page faults).  The node
        # boxes are gathered one row per ray (one cache line per node) and then transposed
        # once, so every later operation runs along the rays: long contiguous inner loops
        # instead of rows of four children.
        w_g = np.empty((P, 6 * WIDTH), F32)
        w_t = np.empty(6 * WIDTH * P, F32)
        w_near = np.empty(3 * WIDTH * P, F32)
        w_far = np.empty(3 * WIDTH * P, F32)
        w_tn = np.empty(WIDTH * P, F32)
        w_tf = np.empty(WIDTH * P, F32)
        w_cg = np.empty((P, WIDTH), np.int32)
        w_ch = np.empty(WIDTH * P, np.int32)
        w_hit = np.empty(WIDTH * P, bool)
        w_leaf = np.empty(WIDTH * P, bool)
        w_mask = np.empty(WIDTH * P, bool)
        w_key = np.empty(WIDTH * P, np.uint64)
        w_lim = np.empty(P, F32)
        w_flag = np.empty(P, bool)
        cols = np.arange(P)
        widen = _widen_signed if (rays.tmin < 0).any() else _widen
        visits = leaf_visits = pairs = steps = 0
        A = ndead = taken = 0
        compact = True
        while True:
            if compact:  # refill finished rays' slots from the chunk, else drop them
                compact = False
                if ndead and supply.left:
                    # in place: a finished ray's column (its stack empty, ptr at its own
                    # column) takes a new ray, so nothing moves while the chunk lasts
                    free = np.flatnonzero(dead[:A])
                    new = supply.take(len(free))
                    k = new.stop - new.start
                    f = free[:k]
                    rid[f] = np.arange(new.start, new.stop)
                    cur[f] = 0
                    ptr[f] = f
                    org[:, f] = rays.origins[new].T
                    inv[:, f] = _reciprocal(rays.directions[new]).T
                    tmin[f] = rays.tmin[new]
                    tlim[f] = rays.tmax[new]
                    dead[f] = False
                    taken += k
                    ndead -= k
                if ndead:
                    keep = np.flatnonzero(~dead[:A])
                    n = len(keep)
                    for arr in (rid, cur, tmin, tlim):
                        arr[:n] = arr.take(keep)
                    org[:, :n] = org[:, :A].take(keep, axis=1)
                    inv[:, :n] = inv[:, :A].take(keep, axis=1)
                    ptr[:n] = ptr.take(keep) - keep + cols[:n]
                    top = int(ptr[:n].max()) // P if n else 0
                    if top:
                        stack[:top, :n] = stack[:top, :A].take(keep, axis=1)
                    A, ndead = n, 0
                new = supply.take(P - A)
                k = new.stop - new.start
                if k:
                    sl = slice(A, A + k)
                    rid[sl] = np.arange(new.start, new.stop)
                    cur[sl] = 0
                    ptr[sl] = cols[sl]
                    org[:, sl] = rays.origins[new].T
                    inv[:, sl] = _reciprocal(rays.directions[new]).T
                    tmin[sl] = rays.tmin[new]
                    tlim[sl] = rays.tmax[new]
                    A, taken = A + k, taken + k
                dead[:A] = False
                if A == 0:
                    break
            steps += 1
            visits += A - ndead
            # slab test of the four children (Ize 2013), all rays at once, as (.., child, ray)
            g = box.take(cur[:A], axis=0, out=w_g[:A], mode="clip")
            t = w_t[: 6 * WIDTH * A].reshape(2, 3, WIDTH, A)
            t2 = t.reshape(6 * WIDTH, A)
            for b in range(0, A, _TRANSPOSE_BLOCK):  # blocks that stay in cache while transposed
                np.copyto(t2[:, b : b + _TRANSPOSE_BLOCK], g[b : b + _TRANSPOSE_BLOCK].T)
            np.subtract(t, org[None, :, None, :A], out=t)
            np.multiply(t, inv[None, :, None, :A], out=t)
            near = np.minimum(t[0], t[1], out=w_near[: 3 * WIDTH * A].reshape(3, WIDTH, A))  # a NaN (0*inf) stays in its axis ...
            far = np.maximum(t[0], t[1], out=w_far[: 3 * WIDTH * A].reshape(3, WIDTH, A))
            tn = np.fmax(near[0], near[1], out=w_tn[: WIDTH * A].reshape(WIDTH, A))  # ... and fmax/fmin skip it
            np.fmax(tn, near[2], out=tn)
            tf = np.fmin(far[0], far[1], out=w_tf[: WIDTH * A].reshape(WIDTH, A))
            np.fmin(tf, far[2], out=tf)
            np.maximum(tn, tmin[None, :A], out=tn)
            widen(tf, tf)
            np.minimum(tf, widen(tlim[:A], w_lim[:A])[None, :], out=tf)
            hit = np.less_equal(tn, tf, out=w_hit[: WIDTH * A].reshape(WIDTH, A))
            ch = w_ch[: WIDTH * A].reshape(WIDTH, A)
            np.copyto(ch, child.take(cur[:A], axis=0, out=w_cg[:A], mode="clip").T)
            isleaf = np.less(ch, 0, out=w_leaf[: WIDTH * A].reshape(WIDTH, A))
            # leaf children: their triangles through the shared kernel, now
            lh = np.flatnonzero(np.logical_and(hit, isleaf, out=w_mask[: WIDTH * A].reshape(WIDTH, A)))
            if len(lh):
                leaf = ~ch.reshape(-1).take(lh)
                # pairs (ray, triangle) leaf by leaf; the leaf of every pair from a running
                # count of leaf starts (np.repeat with per-leaf counts holds the GIL, this
                # scatter and cumsum do not; every leaf holds at least one triangle)
                cnt = leaf_count.take(leaf)
                first = np.cumsum(cnt) - cnt
                seg = np.zeros(int(first[-1] + cnt[-1]), np.intp)
                seg[first[1:]] = 1
                np.cumsum(seg, out=seg)
                pa = (lh % A).take(seg)
                pos = np.arange(len(seg)) + (leaf_start.take(leaf) - first).take(seg)
                leaf_visits += len(lh)
                pairs += len(pa)
                r = rid.take(pa)
                if best is not None:
                    th = intersect(rays, r, pos, self._tv, t_hi=tlim.take(pa))
                    # only the few pairs that hit reach the scattered minimum (ufunc.at
                    # runs element by element and holds the GIL: on every pair it
                    # serialised the pool's threads)
                    got = np.flatnonzero(th != F32(np.inf))
                    if len(got):
                        pg, tg = pa.take(got), th.take(got)
                        best.update(r.take(got), self.leaf_triangles.take(pos.take(got)), tg)
                        np.minimum.at(tlim, pg, tg)
                else:
                    th = intersect(rays, r, pos, self._tv)
                    got = pa[np.isfinite(th)]
                    anyhit[rid.take(got)] = True
                    dead[got] = True
                    tlim[got] = -np.inf
            # inner children sorted nearest first: key = entry distance bits << 32 | node
            key = w_key[: WIDTH * A].reshape(WIDTH, A)
            kv = key.view(np.uint32).reshape(WIDTH, A, 2)
            kv[:, :, 1] = tn.view(np.uint32)
            kv[:, :, 0] = ch.view(np.uint32)
            np.copyto(key, MISS, where=~np.logical_and(hit, ~isleaf, out=w_mask[: WIDTH * A].reshape(WIDTH, A)))
            k0, k1, k2, k3 = _sort4(key[0], key[1], key[2], key[3])
            # the nearest is visited next, the others pushed, farthest first
            pa_ = ptr[:A]
            for k in (k3, k2, k1):
                sflat.put(pa_, k, mode="clip")
                np.add(pa_, P, out=pa_, where=np.not_equal(k, MISS, out=w_flag[:A]))
            cur[:A] = k0.view(np.uint32)[::2]  # low word: the node
            # no child entered: pop, dropping nodes that start beyond the best hit
            need = np.equal(k0, MISS, out=w_flag[:A])
            need &= ~dead[:A]
            np.subtract(pa_, P, out=pa_, where=need)
            e = sflat.take(pa_, mode="clip").view(np.uint32)
            np.copyto(cur[:A], e[::2], where=need)
            # popped beyond the best hit, or nothing left: a few rays, by index
            bad = e[1::2].view(F32) <= widen(tlim[:A], w_lim[:A])
            np.logical_not(bad, out=bad)
            bad |= pa_ < 0
            bad &= need
            pop = np.flatnonzero(bad)
            if len(pop):
                self._pop_beyond(pop, ptr, cur, dead, tlim, stack, widen)
            ndead = int(np.count_nonzero(dead[:A]))
            compact = ndead * 4 >= A or (supply.left and ndead * 16 >= P)
        self._counters.append((taken, visits, leaf_visits, pairs, steps))

    @staticmethod
    def _pop_beyond(pop, ptr, cur, dead, tlim, stack, widen):
        """Pool rays ``pop`` popped a node that starts beyond their best hit (or found their
        stack empty): each takes the topmost entry below it that starts within the hit
        (``widen(tlim)``), or is finished when there is none.

        The same result as popping again and again until an entry passes, but in one pass
        over the stacks of all these rays at once: a loop of pops took several rounds a
        step, each a dozen numpy calls on a few hundred rays, which is per-call overhead
        under the GIL (a large share of the 2-thread traversal's GIL time, py-spy --gil).
        ``ptr[pop]`` is the slot just popped (depth * P + column; negative when the stack
        was empty), so the candidates are the depths below it in the ray's own column.
        """
        P = stack.shape[1]
        level = ptr.take(pop) // P  # the popped slot's depth; -1 for an empty stack
        top = int(level.max())
        found = np.zeros(len(pop), bool)
        if top > 0:
            below = stack[:top].take(pop, axis=1).view(np.uint32).reshape(top, len(pop), 2)
            ok = below[:, :, 1].view(F32) <= widen(tlim.take(pop))[None, :]
            ok &= np.arange(top)[:, None] < level[None, :]
            down = ok[::-1]  # depths from the top: the first True is the highest passing depth
            up = down.argmax(axis=0)
            found = down.take(up * len(pop) + np.arange(len(pop)))
            depth = top - 1 - up
            keep = pop[found]
            d = depth[found]
            ptr[keep] = d * P + keep
            cur[keep] = below[:, :, 0].reshape(-1).take(d * len(pop) + np.flatnonzero(found))
        fin = pop[~found]
        if len(fin):
            dead[fin] = True
            tlim[fin] = -np.inf
            ptr[fin] = fin  # its own column: unconditional pushes must not land elsewhere

    # -- statistics ------------------------------------------------------------------------
    def stats(self) -> dict:
        """The base stats plus the tree (wide ``nodes``, ``leaves``, ``depth`` in wide levels,
        leaf sizes, ``memory_bytes`` of the traversal arrays) and, after a trace or occluded
        call, its counters averaged per ray: ``nodes_per_ray`` (wide nodes whose 4 child boxes
        were tested), ``leaves_per_ray``, ``triangles_per_ray`` (kernel pairs), and
        ``lockstep_steps`` (most steps of one thread's pool on one chunk)."""
        s = super().stats()
        leaf_count = self.leaf_count
        s.update(
            builder=self.builder,
            leaf_size=self.leaf_size,
            nodes=int(len(self.node_boxes)),
            leaves=int(len(leaf_count)),
            depth=int(self.depth),
            leaf_triangles_mean=float(leaf_count.mean()) if len(leaf_count) else 0.0,
            leaf_triangles_max=int(leaf_count.max()) if len(leaf_count) else 0,
            leaf_histogram={int(k): int(v) for k, v in zip(*np.unique(leaf_count, return_counts=True))},
            memory_bytes=int(
                self.node_boxes.nbytes + self.node_children.nbytes + self.leaf_start.nbytes + self.leaf_count.nbytes
                + self._tv.nbytes + self.leaf_triangles.nbytes
            ),
        )
        if self._counters:
            c = np.array(self._counters, np.float64)
            m = max(1.0, c[:, 0].sum())
            s.update(
                last_rays=int(c[:, 0].sum()),
                nodes_per_ray=float(c[:, 1].sum() / m),
                leaves_per_ray=float(c[:, 2].sum() / m),
                triangles_per_ray=float(c[:, 3].sum() / m),
                lockstep_steps=int(c[:, 4].max()),
            )
        return s


def point_index_of(accel: Accel) -> TreeIndex:
    """The point queries' tree over ``accel``'s mesh (``proximity.TreeIndex``): a BVH's own
    arrays; for another structure a BVH built on first use, kept on the structure so that
    later queries reuse it."""
    index = getattr(accel, "_tree_index", None)
    if index is None:
        tree = accel if isinstance(accel, BVH) else BVH(accel.mesh, threads=accel.threads)
        index = TreeIndex(accel.mesh, tree.node_boxes, tree.node_children, tree.leaf_start, tree.leaf_count,
                          tree.leaf_triangles)
        accel._tree_index = index
    return index

