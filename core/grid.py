"""Uniform grid: O(N) build, 3D-DDA traversal, in pure numpy.

- Resolution: Cleary and Wyvill, "Analysis of an algorithm for fast ray tracing using
  uniform space subdivision", The Visual Computer 4(2), 1988: about ``density * N``
  cells, shaped to the scene so cells are near-cubes.
- References: each triangle's bounding-box cell range, refined by the separating-axis
  triangle/box test of Akenine-Moeller, "Fast 3D Triangle-Box Overlap Testing",
  JGT 6(1), 2001; then a counting sort into CSR arrays (``cell_start``, ``cell_tris``).
- Traversal: Amanatides and Woo, "A Fast Voxel Traversal Algorithm for Ray Tracing",
  Eurographics 1987, with every live ray of a chunk stepping in lockstep, plus an
  empty-space skip over the same cells (a per-cell radius of empty cells around it, the
  idea of Cohen and Sheffer's "Proximity clouds: an acceleration technique for 3D grid
  traversal", The Visual Computer, 1994): a ray in an empty cell jumps through that cube
  in one step.  It stays the paper's uniform grid (Hapala et al. 2011): the plan times
  this traversal on its K sample rays, so the cost model measures the grid as it runs.

Why the result equals brute force hit for hit (same kernel, same tie rule): the kernel
reports a hit only where the exact ray passes within its float32 slack (about 2u times
the origin's distance, u = ``UNIT_ROUNDOFF``) of the triangle, at a t whose ray point is that close
to it.  Every cell is enlarged by ``delta`` (far above that slack for origins within a
few scene sizes) when its references are chosen, and a ray stops in a cell only when its
best t plus ``mu`` (a bound on the kernel's error in t) is at most the cell's exit
distance.  So any triangle the kernel could report with a t <= the best lies in an
enlarged cell already visited and was tested.  Equal t across a cell face is covered
because the comparison is ``<=`` and a point on a face belongs to both enlarged cells.
"""

from __future__ import annotations

import threading

import numpy as np

from . import proximity
from .accel import LOCKSTEP_CHUNK, Accel
from .intersect import UNIT_ROUNDOFF, NearestHits, Rays, intersect

F64 = np.float64
#: empty-space skip: empty cubes of radius up to 2**SKIP_LEVELS - 1 cells (``empty_radius``)
SKIP_LEVELS = 4


def grid_resolution(extent, n, density, max_cells):
    """Cells per axis by Cleary and Wyvill's rule: ``res_i = e_i * (density*n / V)^(1/k)``.

    k counts the axes with extent; an axis that would get less than one cell (flat or
    thin) gets exactly one and leaves the budget to the others, so a flat scene gets
    about ``density * n`` cells in its plane.  The total is capped at
    ``min(max_cells, 2 * density * n)`` (rounding can overshoot; memory must not).
    """
    ext = np.asarray(extent, F64)
    target = max(1.0, float(density) * max(int(n), 1))
    diag = float(np.sqrt((ext * ext).sum()))
    res = np.ones(3, F64)
    active = ext > 1e-9 * diag if diag > 0 else np.zeros(3, bool)
    while active.any():
        k = int(active.sum())
        scale = (target / float(np.prod(ext[active]))) ** (1.0 / k)
        r = ext * scale
        thin = active & (r < 1.0)
        if thin.any():
            active &= ~thin
            continue
        res[active] = r[active]
        break
    res = np.maximum(1, np.round(res)).astype(np.int64)
    cap = max(1, int(min(max_cells, 2 * target)))
    while int(np.prod(res)) > cap:
        k = max(1, int((res > 1).sum()))
        f = (cap / float(np.prod(res))) ** (1.0 / k)
        res = np.maximum(1, np.minimum(res - 1, np.floor(res * f))).astype(np.int64)
    return res


def _expand(counts, lo, hi):
    """The virtual pairs [lo, hi) of ``repeat(arange(len(counts)), counts)``.

    Returns (owner, rank): owner index and rank inside the owner's block, so callers
    can walk huge pair sets in bounded pieces without materialising them.
    """
    cum = np.cumsum(counts)
    first = cum - counts
    if lo == 0 and hi == int(cum[-1]):
        owner = np.repeat(np.arange(len(counts)), counts)
        rank = np.arange(hi, dtype=np.int64) - np.repeat(first, counts)
        return owner, rank
    i0 = int(np.searchsorted(cum, lo, side="right"))
    i1 = int(np.searchsorted(cum, hi - 1, side="right"))
    cnt = np.clip(cum[i0 : i1 + 1], lo, hi) - np.clip(first[i0 : i1 + 1], lo, hi)
    owner = np.repeat(np.arange(i0, i1 + 1), cnt)
    rank = np.arange(lo, hi, dtype=np.int64) - first[owner]
    return owner, rank


def _pieces(counts, cap):
    """(owner, rank) pieces of at most ``cap`` pairs covering all pairs of ``counts``."""
    total = int(counts.sum())
    for lo in range(0, total, cap):
        yield _expand(counts, lo, min(total, lo + cap))


def empty_radius(occupied, levels=SKIP_LEVELS, inside: bool = True):
    """Per cell, a radius r such that the cube of (2r+1)^3 cells around it holds no
    occupied cell and, with ``inside``, lies inside the grid (r = 0: no such cube beyond
    the cell itself).

    r is the largest of 0, 1, 3, 7, ..., 2**levels - 1 that fits: the occupied set is
    dilated by cubes of those radii, each from the one before (a cube of radius m
    unioned with its shifts by +-(m+1) along an axis covers radius 2m+1), so ``levels``
    rounds of three shifted ORs per axis instead of a full distance transform; r is at
    most a factor of two below the exact chessboard distance.
    """
    shape = occupied.shape
    covered = occupied.copy()
    r = np.zeros(shape, np.uint8)
    m = 0
    for _ in range(levels):
        s = m + 1
        for axis in range(3):
            if shape[axis] <= s:
                continue
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(0, shape[axis] - s), slice(s, shape[axis])
            lo, hi = tuple(lo), tuple(hi)
            src = covered.copy()
            covered[lo] |= src[hi]
            covered[hi] |= src[lo]
        m = 2 * m + 1
        np.copyto(r, np.uint8(m), where=~covered)
    # the cube must stay inside the grid: at most the cells left to the nearest face
    for axis in range(3 if inside else 0):
        n = shape[axis]
        idx = np.arange(n)
        face = np.minimum(np.minimum(idx, n - 1 - idx), 255).astype(np.uint8)
        np.minimum(r, face.reshape([-1 if a == axis else 1 for a in range(3)]), out=r)
    return r


def _radix_order(keys, nkeys):
    """Stable order of non-negative integer keys < nkeys < 2**32 in O(len(keys)).

    numpy's stable argsort of 16-bit keys is an LSD radix (counting) sort, so two passes
    over 16-bit digits give a counting sort of 32-bit cell ids without an O(R log R) sort.
    """
    if nkeys <= 1 << 16:
        return np.argsort(keys.astype(np.uint16), kind="stable")
    order = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    high = np.take(keys, order) >> 16
    high = high.astype(np.uint8 if nkeys <= 1 << 24 else np.uint16)  # one byte pass if it fits
    return np.take(order, np.argsort(high, kind="stable"))


class UniformGrid(Accel):
    """A uniform grid of about ``density * N`` cells over the valid triangles.

    Config (keyword arguments of ``core.build(mesh, 'grid', ...)``):

    ``density`` (lambda, default 2.0): cells per triangle in Cleary and Wyvill's rule.
        On a torus and a random soup (single thread, uniform rays) the trace time is
        flat in lambda up to 2 and grows beyond it; on large scenes 2 traces fastest
        while 1 builds faster.  The prefilter makes each reference cheap, which pulls
        the optimum down (without it larger lambdas were fastest).
    ``max_cells`` (default 2**24): memory bound on the cell count (cell_start is one
        int32 per cell, so 64 MB at the bound).
    ``margin`` (default 1e-3): each cell is enlarged by ``margin`` times the smallest
        cell extent when its references are chosen (the grid box is padded by twice
        that), so neither the kernel's float32 slack nor rounding here can hide a
        triangle the kernel would report; it costs only a few more references.
    ``pair_cap`` (default 2**17): at most this many (ray, triangle) pairs per kernel
        call, and candidate (triangle, cell) pairs per overlap batch: bounds memory.
    ``prefilter`` (default True): before the kernel, drop pairs whose ray line misses
        the triangle's bounding box enlarged by a bound on the kernel's float32 slack
        (see ``_box_filter``); most pairs of a cell miss, and the test costs a fraction
        of the kernel.  The kernel alone still decides every hit.
    ``skip`` (default True): empty-space skipping over the same cells.  Each cell's code
        holds (negated) the radius r of a cube of empty cells around it (``empty_radius``:
        0, 1, 3, 7 or 15 cells); a ray in an empty cell with r >= 1 jumps through that
        cube in one DDA step, to the last cell of the cube on its path.  Cells skipped
        hold no reference, so the hits are those of the plain DDA.
    ``pool`` (default 2**17): live rays stepping in lockstep; the pool is refilled from
        the chunk (``chunk_size``, default 2**20 rays) as rays finish, so only a chunk's
        last steps run on few rays, whose numpy calls cost as much as full ones.
    """

    kind = "grid"
    chunk_size = LOCKSTEP_CHUNK
    shares_chunks = True  # the threads trace each chunk together (``Accel._shared``)

    def __init__(self, mesh, *, density: float = 2.0, max_cells: int = 1 << 24, margin: float = 1e-3,
                 pair_cap: int = 1 << 17, prefilter: bool = True, skip: bool = True, pool: int = 1 << 17, **kw):
        if not density > 0:
            raise ValueError(f"density must be > 0, got {density}")
        self.density = float(density)
        self.max_cells = max(1, int(max_cells))
        self.margin = float(margin)
        self.pair_cap = max(1, int(pair_cap))
        self.prefilter = bool(prefilter)
        self.skip = bool(skip)
        self.pool = max(1, int(pool))
        self._work = {}  # calling thread: its traces' totals (``traversal_work``)
        self._work_lock = threading.Lock()
        super().__init__(mesh, **kw)

    # -- build -----------------------------------------------------------------------
    #: triangles per build block: keeps the per-triangle temporaries in cache
    build_block = 1 << 16

    def _point_index(self):
        from .bvh import point_index_of  # a BVH for the tree's point queries, built on first use

        return point_index_of(self)

    def _closest_search(self):
        index = self.cell_index()
        return lambda p, md: proximity.closest_grid(index, p, md)

    def closest_within(self, points, max_distance, reach: int):
        """(``proximity.Nearest``, left): ``closest`` on the grid's cells, on the threads,
        leaving unanswered the points whose rings would span more than ``reach`` cells
        (``proximity.closest_grid``)."""
        index = self.cell_index()
        p = proximity.check_points(points)
        got = self._in_pool(lambda sl: proximity.closest_grid(index, p[sl], max_distance, reach=reach),
                            self._point_parts(len(p)))
        return proximity.Nearest.concat(n for n, _ in got), np.concatenate([left for _, left in got])

    def cell_index(self) -> proximity.CellIndex:
        """The grid's own cells as the closest point's index (``proximity.CellIndex``), kept."""
        index = getattr(self, "_cells", None)
        if index is None:
            occupied = (np.diff(self.cell_start) > 0).reshape(self.res[::-1])
            index = proximity.CellIndex(self.mesh, self.lo, self.cell_size, self.res, self.cell_start,
                                        self.cell_tris, self.delta,
                                        empty_radius(occupied, inside=False).ravel())
            self._cells = index
        return index

    def _build(self):
        mesh = self.mesh
        ids = np.flatnonzero(mesh.valid).astype(np.int32)
        n = len(ids)
        tv = mesh.tri_vertices if n == mesh.triangle_count else mesh.tri_vertices[ids]
        # per-triangle float32 boxes (lo xyz, hi xyz), copied per reference by _set_csr
        tri_box = np.zeros((mesh.triangle_count, 6), np.float32)
        if n == 0:
            self.lo = np.zeros(3)
            self.res = np.ones(3, np.int64)
            self.cell_size = np.ones(3)
            self.delta = 0.0
            self._finish_geometry()
            self._set_csr(np.zeros(2, np.int32), np.zeros(0, np.int32), tri_box)
            return
        lo = np.array([tv[:, :, k].min() for k in range(3)], F64)
        hi = np.array([tv[:, :, k].max() for k in range(3)], F64)
        ext = hi - lo
        res = grid_resolution(ext, n, self.density, self.max_cells)
        # delta: a fraction of the smallest real cell extent (flat axes excluded), and
        # never below float64 rounding of the coordinates themselves.
        real = ext > 1e-9 * float(np.linalg.norm(ext))
        mag = float(np.abs(np.concatenate([lo, hi])).max())
        delta = max(self.margin * float((ext / res)[real].min()), 64 * np.finfo(F64).eps * mag, np.finfo(F64).tiny)
        # padding by 2*delta keeps every triangle's enlarged box strictly inside the grid,
        # so the cell ranges below need no clamping
        pad = 2.0 * delta
        self.lo = lo - pad
        self.res = res
        self.cell_size = (ext + 2 * pad) / res
        self.delta = delta
        self._finish_geometry()

        cells, tris = [], []
        for b0 in range(0, n, self.build_block):
            b1 = min(n, b0 + self.build_block)
            self._block_refs(tv[b0:b1], ids[b0:b1], slice(b0, b1) if n == mesh.triangle_count else ids[b0:b1],
                             tri_box, cells, tris)
        ref_cell = np.concatenate(cells)
        ref_tri = np.concatenate(tris)
        # Counting sort into CSR: bincount + cumsum for the offsets, radix order to scatter.
        ncells = self.ncells
        cell_start = np.zeros(ncells + 1, np.int32 if len(ref_cell) < 2**31 - 1 else np.int64)
        np.cumsum(np.bincount(ref_cell, minlength=ncells), out=cell_start[1:])
        self._set_csr(cell_start, np.take(ref_tri, _radix_order(ref_cell, ncells)), tri_box)

    def _block_refs(self, tv, ids, box_at, tri_box, cells, tris):
        """References of one block of triangles: (cell ids, triangle ids) appended to the
        lists; the triangles' boxes into rows ``box_at`` of ``tri_box``."""
        tlo = [np.minimum(np.minimum(tv[:, 0, k], tv[:, 1, k]), tv[:, 2, k]) for k in range(3)]
        thi = [np.maximum(np.maximum(tv[:, 0, k], tv[:, 1, k]), tv[:, 2, k]) for k in range(3)]
        for k in range(3):
            tri_box[box_at, k] = tlo[k]
            tri_box[box_at, 3 + k] = thi[k]
        # cell range of each triangle's box enlarged by delta (float64: exact enough that
        # only delta, not rounding, decides)
        c_lo = self.lo + self.delta
        c_hi = self.lo - self.delta
        inv = 1.0 / self.cell_size
        i0 = [np.floor(np.subtract(tlo[k], c_lo[k], dtype=F64) * inv[k]).astype(np.int64) for k in range(3)]
        span = [np.floor(np.subtract(thi[k], c_hi[k], dtype=F64) * inv[k]).astype(np.int64) - i0[k] + 1
                for k in range(3)]
        multi = [sp > 1 for sp in span]
        nm = multi[0].astype(np.int8) + multi[1] + multi[2]
        st = self.stride
        base = i0[0] + i0[1] * st[1] + i0[2] * st[2]
        # One cell, or a run of cells along one axis: the box range is exact (the triangle
        # is connected and lies within one cell on the other axes), no overlap test needed.
        one = nm == 0
        cells.append(base[one])
        tris.append(ids[one])
        for k in range(3):
            sel = np.flatnonzero(multi[k] & (nm == 1))
            if sel.size:
                b, t = base[sel], ids[sel]
                for owner, rank in _pieces(span[k][sel], self.pair_cap):
                    cells.append(b[owner] + rank * st[k])
                    tris.append(t[owner])
        # Several cells on two or three axes: separating-axis test per candidate.  The
        # edge axes in the plane perpendicular to axis k can only separate when the box
        # spans several cells on both other axes (else the argument above applies to
        # that projection), so 2-axis spans need one plane of edge axes, 3-axis spans three.
        for k in range(3):
            sel = np.flatnonzero((nm == 2) & ~multi[k])
            if sel.size:
                self._sat_refs(tv[sel], ids[sel], [i[sel] for i in i0], [sp[sel] for sp in span], (k,), cells, tris)
        sel = np.flatnonzero(nm == 3)
        if sel.size:
            self._sat_refs(tv[sel], ids[sel], [i[sel] for i in i0], [sp[sel] for sp in span], (0, 1, 2), cells, tris)

    def _finish_geometry(self):
        self.ncells = int(np.prod(self.res))
        self.hi = self.lo + self.cell_size * self.res
        self.stride = np.array([1, self.res[0], self.res[0] * self.res[1]], np.int64)
        # traversal looks cells up with this offset; one step past the box on each axis
        # stays inside the (empty) padding
        self._pad = int(self.stride[2] + self.stride[1] + 2)

    def _set_csr(self, cell_start, cell_tris, tri_box):
        pad = self._pad
        full = np.empty(len(cell_start) + 2 * pad, cell_start.dtype)
        full[:pad] = cell_start[0]
        full[pad : pad + len(cell_start)] = cell_start
        full[pad + len(cell_start) :] = cell_start[-1]
        self.cell_start = full[pad : pad + len(cell_start)]
        self.cell_tris = cell_tris.astype(np.int32, copy=False)
        # the triangles' boxes for _box_filter, one float32 row (lo xyz, hi xyz) per
        # reference in cell order: a cell's pairs read a few contiguous cache lines, not
        # one line per triangle scattered over the mesh, which speeds up the whole trace on
        # large scenes (BENCHMARKS.md, "Trace speed: engine table"); twice the bytes of
        # per-triangle rows at ~2 refs per triangle
        self._ref_box = tri_box.take(self.cell_tris, axis=0)
        self._starts = full[:-1]
        # one lookup per step tells what a ray's cell holds: its reference count (> 0), or
        # minus the empty-space skip radius (< 0), or 0 (empty, no jump; the padding too)
        counts = np.diff(full)
        self._cell_code = counts.astype(np.int16 if counts.max(initial=0) < 2**15 else np.int32)
        if self.skip:
            occupied = (counts[pad : pad + self.ncells] > 0).reshape(self.res[::-1])
            self._cell_code[pad : pad + self.ncells] -= empty_radius(occupied).ravel()  # 0 where occupied

    def _sat_refs(self, tv, ids, i0, span, planes, cells, tris):
        """Akenine-Moeller's separating-axis test for (triangle, cell) candidates.

        All cells have the same half size, so per triangle each axis a gives an interval
        [min_i a.w_i - r_a, max_i a.w_i + r_a] (w_i: corners relative to the centre of
        the first cell of its range, r_a = sum_k h_k |a_k|) and the candidate at cell
        offset o passes iff a.(o * cell_size) lies in it.  The box-face axes are the
        candidate range itself.  float64, with the enlarged half size cell_size/2 + delta.
        Triangles whose range is at most 4 cells per axis are grouped by range shape and
        tested by broadcasting over the shape's offsets; larger ones in bounded pieces.
        """
        # order the triangles by range shape (key 64: larger than 4 cells on some axis)
        small = (span[0] <= 4) & (span[1] <= 4) & (span[2] <= 4)
        key = np.where(small, (span[0] - 1) + 4 * (span[1] - 1) + 16 * (span[2] - 1), 64).astype(np.uint8)
        order = np.argsort(key, kind="stable")
        bounds = np.concatenate([[0], np.cumsum(np.bincount(key, minlength=65))])
        tv, ids = tv[order], ids[order]
        i0 = [i[order] for i in i0]
        span = [sp[order] for sp in span]

        cs = self.cell_size
        h = cs / 2 + self.delta
        # w[c][k]: corner c, axis k, relative to the first cell's centre (1D arrays)
        c0 = [self.lo[k] + (i0[k] + 0.5) * cs[k] for k in range(3)]
        w = [[np.subtract(tv[:, c, k], c0[k], dtype=F64) for k in range(3)] for c in range(3)]
        e = [[w[(c + 1) % 3][k] - w[c][k] for k in range(3)] for c in range(3)]
        nrm = [e[0][1] * e[1][2] - e[0][2] * e[1][1],
               e[0][2] * e[1][0] - e[0][0] * e[1][2],
               e[0][0] * e[1][1] - e[0][1] * e[1][0]]
        axes = [nrm]  # the triangle's normal
        for k in planes:  # unit_k x edge, zero on axis k
            i, j = (k + 1) % 3, (k + 2) % 3
            for ed in e:
                a = [None, None, None]
                a[i], a[j] = -ed[j], ed[i]
                axes.append(a)
        lo_a, hi_a, sc_a = [], [], []
        for a in axes:
            ks = [k for k in range(3) if a[k] is not None]
            proj = [sum(a[k] * w[c][k] for k in ks) for c in range(3)]
            r = sum(h[k] * np.abs(a[k]) for k in ks)
            lo_a.append(np.minimum(np.minimum(proj[0], proj[1]), proj[2]) - r)
            hi_a.append(np.maximum(np.maximum(proj[0], proj[1]), proj[2]) + r)
            sc_a.append([a[k] * cs[k] if a[k] is not None else None for k in range(3)])
        st = self.stride
        base = i0[0] + i0[1] * st[1] + i0[2] * st[2]

        for kk in np.flatnonzero(np.diff(bounds[:65])):
            g = slice(bounds[kk], bounds[kk + 1])
            shape = (kk % 4 + 1, kk // 4 % 4 + 1, kk // 16 + 1)
            off = np.indices(shape[::-1]).reshape(3, -1)[::-1]  # x fastest, like cell ids
            ok = None
            for A in range(len(axes)):
                v = 0.0
                for k in range(3):
                    if shape[k] > 1 and sc_a[A][k] is not None:
                        v = v + sc_a[A][k][g, None] * off[k]
                t = (v >= lo_a[A][g, None]) & (v <= hi_a[A][g, None])
                ok = t if ok is None else ok & t
            r_, c_ = np.nonzero(ok)
            cells.append(base[g][r_] + (off[:, c_].T @ st))
            tris.append(ids[g][r_])

        if bounds[64] == bounds[65]:
            return
        big = slice(bounds[64], bounds[65])
        spr = [sp[big] for sp in span]
        for owner, rank in _pieces(spr[0] * spr[1] * spr[2], self.pair_cap):
            o = [rank % spr[0][owner], None, None]
            q = rank // spr[0][owner]
            o[1] = q % spr[1][owner]
            o[2] = q // spr[1][owner]
            g = owner + bounds[64]
            ok = np.ones(len(owner), bool)
            for A in range(len(axes)):
                v = sum(sc_a[A][k][g] * o[k] for k in range(3) if sc_a[A][k] is not None)
                ok &= (v >= lo_a[A][g]) & (v <= hi_a[A][g])
            keep = np.flatnonzero(ok)
            gk = g[keep]
            cells.append(base[gk] + o[0][keep] + o[1][keep] * st[1] + o[2][keep] * st[2])
            tris.append(ids[gk])

    # -- traversal ---------------------------------------------------------------------
    def _setup(self, rays: Rays):
        """Clip rays to the grid box (slab test), find entry cells, DDA state per live ray.

        Returns F (9, L) float64 rows: t_max x/y/z (parameter of the next boundary per
        axis), t_delta x/y/z, t_end (leaving the box or tmax), best t + mu, mu; and
        I (5, L) int64 rows: padded cell id, cell-id step per axis, ray index.
        Component-major, so each row is a contiguous array and one take compacts all.
        """
        o = rays.origins.astype(F64)
        d = rays.directions.astype(F64)
        zero = d == 0  # +0.0 and -0.0 alike: never step on that axis (t_delta = inf)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            inv = 1.0 / d
            t0 = (self.lo - o) * inv
            t1 = (self.hi - o) * inv
        inside = (o >= self.lo) & (o <= self.hi)
        tn = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
        tf = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
        ts = np.maximum(tn.max(axis=1), rays.tmin.astype(F64))
        te = np.minimum(tf.min(axis=1), rays.tmax.astype(F64))
        live = np.flatnonzero(ts <= te)
        o, d, inv, zero, ts, te = o[live], d[live], inv[live], zero[live], ts[live], te[live]
        res = self.res
        p = o + ts[:, None] * d
        # float rounding of the entry point may pick a neighbour cell: harmless, the first
        # step corrects it and the cells' delta margin covers the sliver in between
        idx = np.clip(np.floor((p - self.lo) / self.cell_size), 0, res - 1).astype(np.int64)
        step = np.where(zero, 0, np.where(d > 0, 1, -1)).astype(np.int64)
        L = len(live)
        F = np.empty((9, L), F64)
        I = np.empty((5, L), np.int64)
        with np.errstate(invalid="ignore", over="ignore"):
            bnd = self.lo + (idx + (step > 0)) * self.cell_size
            F[0:3] = np.where(zero, np.inf, (bnd - o) * inv).T
            F[3:6] = np.where(zero, np.inf, self.cell_size * np.abs(inv)).T
        F[6] = te
        F[7] = np.inf
        # mu: a bound on the kernel's float32 error in t, relative to the largest depth of
        # a grid point seen from the origin; a hit reported a little early still has its
        # true point inside a visited cell.
        far = np.maximum(np.abs(o - self.lo), np.abs(o - self.hi))
        F[8] = 128 * UNIT_ROUNDOFF * np.sqrt((far * far).sum(axis=1) / (d * d).sum(axis=1))
        I[0] = idx @ self.stride + self._pad
        I[1:4] = (step * self.stride).T
        I[4] = live
        return F, I

    def _traverse(self, rays: Rays, any_hit: bool):
        """Amanatides-Woo 3D-DDA of one chunk: the nearest hits (``Hits``) or the any-hit mask."""
        m = len(rays)
        best = None if any_hit else NearestHits(m)
        hit = np.zeros(m, bool)
        R = np.empty((7, m), np.float32) if self.prefilter else None  # filled as rays are handed out
        done = self._shared(lambda supply: self._lockstep(rays, best, hit, R, supply), m)
        got = (m, *(sum(c[i] for c in done) for i in range(3)))
        with self._work_lock:
            me = threading.get_ident()
            self._work[me] = tuple(a + b for a, b in zip(self._work.get(me, (0, 0, 0, 0)), got))
        return hit if any_hit else self._finished(best, rays, self.mesh.tri_vertices)

    def __getstate__(self):  # a lock does not pickle; the counts are this process's
        return {k: v for k, v in self.__dict__.items() if k not in ("_work", "_work_lock")}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._work, self._work_lock = {}, threading.Lock()

    def traversal_work(self) -> dict:
        """What the calling thread's traces and occlusion queries through this grid cost so
        far, summed over their rays (counts, not times: the same rays give the same
        numbers on any machine and with any number of threads):

        - rays: the rays traced;
        - steps: lockstep iterations a ray took part in (a DDA step, a jump over empty
          space, or a finished ray's last check);
        - candidates: (ray, triangle reference) pairs of the non-empty cells stepped;
        - tests: the pairs left for the intersection kernel by the box prefilter.

        Take the difference of two calls around a trace for that trace's counts
        (``decide.work.traversal_counts``); other threads' traces are not in it."""
        with self._work_lock:
            w = self._work.get(threading.get_ident(), (0, 0, 0, 0))
        return dict(zip(("rays", "steps", "candidates", "tests"), w))

    def _lockstep(self, rays: Rays, best: NearestHits | None, hit: np.ndarray, R, supply):
        """The DDA for the rays this thread draws from ``supply`` (``RaySupply``), all live
        rays of its pool in lockstep; nearest hits into ``best``, or (``best`` None) any hit
        into ``hit``.

        A ray finishes when its segment ends in the current cell (box exit or tmax), when
        (nearest hit) its best t + mu is at most the cell's exit distance, or (any hit) on
        its first hit.  Stepping out of the box by float rounding lands in the padding of
        ``cell_start`` (empty) or in a wrapped-around cell (extra tests never change a
        nearest hit), and the next check ends the ray.
        Returns this thread's (steps, candidate pairs, pairs tested), for ``traversal_work``.
        """
        any_hit = best is None
        tv = self.mesh.tri_vertices
        F, I = np.empty((9, 0), F64), np.empty((5, 0), np.int64)
        count = [0, 0, 0]  # (steps, candidate pairs, pairs tested) of this thread
        starts, code_of, tris, tmax = self._starts, self._cell_code, self.cell_tris, rays.tmax

        def pairs(rr, ss, cc):
            Rz = None if R is None else np.take(R, rr, axis=1)  # per ray, gathered per pair below
            for owner, rank in _pieces(cc, self.pair_cap):
                ref = np.take(ss, owner) + rank
                count[1] += len(owner)
                if Rz is not None:
                    k = self._box_filter(Rz, owner, ref)
                    owner, ref = np.take(owner, k), np.take(ref, k)
                count[2] += len(owner)
                tri = np.take(tris, ref)
                yield owner, np.take(rr, owner), tri
        while True:
            if supply.left and I.shape[1] * 8 <= self.pool * 7:  # refill the pool from the chunk
                new = supply.take(self.pool - I.shape[1])
                part = rays.subset(new)
                if R is not None:
                    R[:, new] = self._filter_rays(part)
                Fn, In = self._setup(part)
                In[4] += new.start
                F, I = np.concatenate([F, Fn], axis=1), np.concatenate([I, In], axis=1)
            if not I.shape[1]:
                if supply.left:
                    continue
                return count
            count[0] += I.shape[1]
            # empty-space skip: a ray in an empty cell whose cube of radius r around it is
            # empty moves to the cell of that cube where its path leaves the cube.  Per axis
            # it crosses n = ceil((t_out - t_next) / t_delta) boundaries before t_out,
            # clamped to [0, r]: whatever the rounding, it lands inside the (empty) cube, with
            # the boundary parameters of the cell it lands in.
            # (the cell it lands in is empty, so ``code`` read before the jump still says
            # which rays have references to test)
            code = np.take(code_of, I[0])
            j = np.flatnonzero(code < 0)
            if j.size:
                r = -np.take(code, j).astype(F64)
                Fj = np.take(F[0:6], j, axis=1)
                with np.errstate(invalid="ignore"):  # inf - inf on axes the ray never steps on
                    t_out = np.minimum(np.minimum(Fj[0] + r * Fj[3], Fj[1] + r * Fj[4]), Fj[2] + r * Fj[5])
                    cell = np.take(I[0], j)
                    for a in range(3):
                        n = np.ceil((t_out - Fj[a]) / Fj[3 + a])
                        n = np.minimum(np.where(n > 0, n, 0.0), r)  # NaN (never steps): 0
                        F[a, j] = np.where(n > 0, Fj[a] + n * Fj[3 + a], Fj[a])
                        cell += n.astype(np.int64) * np.take(I[1 + a], j)
                I[0, j] = cell
            nz = np.flatnonzero(code > 0)
            found = None
            if nz.size:
                rr, ss, cc = np.take(I[4], nz), np.take(starts, np.take(I[0], nz)), np.take(code, nz)
                if any_hit:
                    got = np.zeros(nz.size, bool)
                    for owner, r, tri in pairs(rr, ss, cc):
                        t = intersect(rays, r, tri, tv)
                        got[owner[np.isfinite(t)]] = True
                    hit[rr[got]] = True
                    found = np.zeros(I.shape[1], bool)
                    found[nz[got]] = True
                else:
                    bz = np.minimum(best.t(rr), np.take(tmax, rr))
                    for owner, r, tri in pairs(rr, ss, cc):
                        best.update(r, tri, intersect(rays, r, tri, tv, t_hi=np.take(bz, owner)))
                    F[7, nz] = best.t(rr) + np.take(F[8], nz)
            t_exit = np.minimum(np.minimum(F[0], F[1]), F[2])
            done = (t_exit >= F[6]) | (F[7] <= t_exit)
            if found is not None:
                done |= found
            n_done = np.count_nonzero(done)
            if n_done * 8 > done.size:  # compact once enough rays have finished ...
                keep = np.flatnonzero(~done)
                F, I, t_exit = np.take(F, keep, axis=1), np.take(I, keep, axis=1), np.take(t_exit, keep)
            elif n_done:  # ... until then park them: an empty padding cell, never moving
                k = np.flatnonzero(done)
                F[0:3, k] = np.inf
                I[0:4, k] = 0
            # one step on the axis whose boundary comes first (x, then y, on exact ties)
            sx = F[0] == t_exit
            sy = np.greater(F[1] == t_exit, sx)  # and not sx
            sz = ~(sx | sy)
            np.add(F[0], F[3], out=F[0], where=sx)
            np.add(F[1], F[4], out=F[1], where=sy)
            np.add(F[2], F[5], out=F[2], where=sz)
            np.add(I[0], I[1], out=I[0], where=sx)
            np.add(I[0], I[2], out=I[0], where=sy)
            np.add(I[0], I[3], out=I[0], where=sz)

    def _filter_rays(self, rays: Rays):
        """(7, M) float32 rows: origin xyz, 1/direction xyz, slack eps, for _box_filter."""
        o = rays.origins
        far = np.maximum(np.abs(o - self.lo), np.abs(o - self.hi))
        R = np.empty((7, len(rays)), np.float32)
        R[0:3] = o.T
        with np.errstate(divide="ignore", over="ignore"):
            R[3:6] = (np.float32(1) / rays.directions).T
        R[6] = 128 * UNIT_ROUNDOFF * np.sqrt((far * far).sum(axis=1))
        return R

    def _box_filter(self, R, r, ref):
        """Indices of the pairs (column r of R, reference ref: a position in ``cell_tris``)
        whose ray line meets the referenced triangle's box enlarged by eps; R as made by
        ``_filter_rays``.

        The kernel can report a hit only where the exact ray passes within about
        2u|v - o| of the triangle (u = 2**-24: its shear is float32; measured, not just
        bounded).  eps = 128u times the largest origin-to-grid distance covers that and
        this float32 slab test's own rounding (each step errs by at most u|v - o|).
        NaN from 0 * inf (a zero direction component on a box face) keeps the pair:
        the test is ``not (t_near > t_far)``.
        """
        B = self._ref_box.take(ref, axis=0)  # a cell's rows are contiguous: few cache lines per cell
        e = np.take(R[6], r)
        t_near = t_far = None
        with np.errstate(invalid="ignore", over="ignore"):
            for k in range(3):
                o = np.take(R[k], r)
                iv = np.take(R[3 + k], r)
                a = (B[:, k] - o - e) * iv
                b = (B[:, 3 + k] - o + e) * iv
                lo_k, hi_k = np.minimum(a, b), np.maximum(a, b)
                t_near = lo_k if t_near is None else np.maximum(t_near, lo_k)
                t_far = hi_k if t_far is None else np.minimum(t_far, hi_k)
            return np.flatnonzero(~(t_near > t_far))

    def _trace_rays(self, rays: Rays):
        return self._traverse(rays, any_hit=False)

    def _occluded_rays(self, rays: Rays):
        return self._traverse(rays, any_hit=True)

    # -- report ------------------------------------------------------------------------
    def stats(self) -> dict:
        counts = np.diff(self.cell_start)
        n_valid = int(self.mesh.valid.sum()) if self.mesh.triangle_count else 0
        refs = int(len(self.cell_tris))
        return {
            **super().stats(),
            "density": self.density,
            "resolution": tuple(int(r) for r in self.res),
            "cells": self.ncells,
            "references": refs,
            "refs_per_triangle": refs / n_valid if n_valid else 0.0,
            "empty_cell_fraction": float((counts == 0).mean()),
            # cells from which a ray jumps (an empty cube of radius >= 1 around them)
            "skippable_cell_fraction": float(np.count_nonzero(self._cell_code < 0) / max(1, self.ncells)),
            "max_refs_per_cell": int(counts.max()) if counts.size else 0,
            "cell_size": tuple(float(c) for c in self.cell_size),
            "delta": self.delta,
            "memory_bytes": int(self._starts.nbytes + self.cell_start.itemsize + self.cell_tris.nbytes
                                + self._ref_box.nbytes + self._cell_code.nbytes),
        }
