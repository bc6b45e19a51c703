"""Uniform grid (core/grid.py): resolution rule, exact references, and hit-for-hit
agreement with brute force (same kernel, same tie rule) on the grid's own hard spots:
cell boundaries, signed-zero directions, flat grids, one-cell grids, huge spans.

Cross-structure agreement on the general hard cases lives in its own test module.
"""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_raycast import core
from hybrid_raycast.core.grid import UniformGrid, empty_radius, grid_resolution

# -- scenes ---------------------------------------------------------------------------


def soup(n, seed=0, size=0.08, flat_z=None):
    rng = np.random.default_rng(seed)
    v = rng.uniform(0, 1, (n, 1, 3)) + rng.normal(0, size, (n, 3, 3))
    if flat_z is not None:
        v[..., 2] = flat_z
    return core.TriangleMesh(v.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3))


def torus(nu=24, nv=12, R=1.0, r=0.35):
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    P = np.stack([(R + r * np.cos(V)) * np.cos(U), (R + r * np.cos(V)) * np.sin(U), r * np.sin(V)], -1)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, (i + 1) % nu * nv + j
    c, d = (i + 1) % nu * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    T = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return core.TriangleMesh(P.reshape(-1, 3), T)


def lattice(n=8, z=0.25, seed=3):
    """A bumpy height field on a regular n x n lattice over [0, 1]^2 (covers it without gaps)."""
    rng = np.random.default_rng(seed)
    g = np.arange(n + 1) / n
    X, Y = np.meshgrid(g, g, indexing="ij")
    Z = z * rng.uniform(0, 1, X.shape)
    P = np.stack([X, Y, Z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
    T = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return core.TriangleMesh(P, T)


def slivers(n_long=12, n_small=150, seed=5):
    """Long thin triangles across the whole scene among small ones (huge cell ranges)."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 1, (n_small, 1, 3)) + rng.normal(0, 0.07, (n_small, 3, 3))
    a = rng.uniform(0, 1, (n_long, 3))
    b = rng.uniform(0, 1, (n_long, 3))
    long = np.stack([a, b, b + rng.normal(0, 0.03, (n_long, 3))], 1)
    v = np.concatenate([long, small])
    return core.TriangleMesh(v.reshape(-1, 3), np.arange(3 * len(v)).reshape(-1, 3))


def random_rays(mesh, m, seed=1, grow=0.3):
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds()
    span = np.maximum(hi - lo, 1e-3)
    o = rng.uniform(lo - grow * span, hi + grow * span, (m, 3))
    d = rng.normal(size=(m, 3))
    return o, d


# -- helpers --------------------------------------------------------------------------


def assert_same_hits(got, want, what):
    bad = np.flatnonzero((got.triangle != want.triangle) | (got.t != want.t))
    if bad.size:
        rows = "\n".join(
            f"  ray {i}: grid tri {got.triangle[i]} t {got.t[i]!r}, brute tri {want.triangle[i]} t {want.t[i]!r}"
            for i in bad[:8])
        pytest.fail(f"{what}: grid differs from brute force on {bad.size} of {len(got)} rays:\n{rows}")
    assert np.array_equal(got.u, want.u) and np.array_equal(got.v, want.v), f"{what}: barycentrics differ"


def check_against_brute(mesh, o, d, what, tmin=0.0, tmax=np.inf, **config):
    grid = core.build(mesh, "grid", **config)
    brute = core.build(mesh, "brute")
    want = brute.trace(o, d, tmin, tmax)
    assert_same_hits(grid.trace(o, d, tmin, tmax), want, what)
    occ = grid.occluded(o, d, tmin, tmax)
    bad = np.flatnonzero(occ != want.hit)
    assert not bad.size, (f"{what}: occluded() differs from brute-force hit on {bad.size} rays, first "
                          f"{bad[:5].tolist()} (occluded {occ[bad[:5]].tolist()})")
    return grid, want


def brute_overlaps(tv, centres, half):
    """Plain float64 separating-axis test (all 13 axes) for (triangle, box) pairs."""
    v = tv - centres[:, None, :]
    e = [v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]]
    axes = [np.broadcast_to(np.eye(3)[k], v[:, 0].shape) for k in range(3)]
    axes.append(np.cross(e[0], e[1]))
    axes += [np.cross(np.broadcast_to(np.eye(3)[k], ed.shape), ed) for k in range(3) for ed in e]
    ok = np.ones(len(v), bool)
    for a in axes:
        p = np.einsum("pk,pck->pc", a, v)
        r = np.abs(a) @ half
        ok &= (p.min(axis=1) <= r) & (p.max(axis=1) >= -r)
    return ok


# -- resolution -----------------------------------------------------------------------


@pytest.mark.parametrize("density", [0.5, 2.0, 8.0])
def test_resolution_gives_about_density_times_n_cells_shaped_to_the_extents(density):
    ext = np.array([4.0, 2.0, 1.0])
    n = 5000
    res = grid_resolution(ext, n, density, 1 << 24)
    cells = int(np.prod(res))
    assert 0.5 * density * n <= cells <= 2 * density * n, f"{res} gives {cells} cells for lambda*N = {density * n}"
    per_unit = res / ext
    assert per_unit.max() / per_unit.min() < 1.5, f"cells are not near-cubes: {res} for extents {ext}"


def test_flat_scene_gets_one_cell_on_its_flat_axis_and_density_n_cells_in_its_plane():
    mesh = soup(400, flat_z=0.5)
    grid = core.build(mesh, "grid", density=2.0)
    res = grid.stats()["resolution"]
    assert res[2] == 1, f"flat (z) axis got {res[2]} cells, resolution {res}"
    assert 400 <= res[0] * res[1] <= 1600, f"plane got {res[0] * res[1]} cells for lambda*N = 800: {res}"


def test_thin_axis_gets_one_cell_and_the_rest_of_the_budget_goes_to_the_others():
    res = grid_resolution([1.0, 1.0, 1e-4], 1000, 2.0, 1 << 24)
    assert res[2] == 1 and 1000 <= res[0] * res[1] <= 4000, f"resolution {res}"


def test_resolution_never_exceeds_max_cells():
    res = grid_resolution([1.0, 3.0, 2.0], 10**6, 8.0, 5000)
    assert np.prod(res) <= 5000, f"{res} has {np.prod(res)} cells, cap 5000"
    assert (res >= 1).all()


def test_density_must_be_positive():
    with pytest.raises(ValueError, match="density"):
        core.build(soup(10), "grid", density=0)


# -- references -----------------------------------------------------------------------


@pytest.mark.parametrize("name, mesh, config", [
    ("soup", soup(300, seed=11), {}),
    ("torus", torus(), {"density": 6.0}),
    ("slivers", slivers(), {}),
    ("slivers in small pieces", slivers(seed=6), {"pair_cap": 37}),
    ("flat", soup(200, flat_z=0.25, seed=12), {}),
])
def test_references_are_exactly_the_cells_each_triangle_overlaps(name, mesh, config):
    """Every reference overlaps its cell (enlarged by delta), none is missing, no duplicates.

    Reference: a plain float64 separating-axis test over every (triangle, cell) pair of
    each triangle's padded box range.
    """
    grid = core.build(mesh, "grid", **config)
    cell_of_ref = np.repeat(np.arange(grid.ncells), np.diff(grid.cell_start))
    have = set(zip(cell_of_ref.tolist(), grid.cell_tris.tolist()))
    assert len(have) == len(grid.cell_tris), f"{name}: {len(grid.cell_tris) - len(have)} duplicate references"

    tv = mesh.tri_vertices.astype(np.float64)
    i0 = np.clip(np.floor((tv.min(1) - grid.lo) / grid.cell_size) - 1, 0, grid.res - 1).astype(int)
    i1 = np.clip(np.floor((tv.max(1) - grid.lo) / grid.cell_size) + 1, 0, grid.res - 1).astype(int)
    tri, idx = [], []
    for t in np.flatnonzero(mesh.valid):
        axes = [np.arange(i0[t, k], i1[t, k] + 1) for k in range(3)]
        c = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        tri.append(np.full(len(c), t))
        idx.append(c)
    tri, idx = np.concatenate(tri), np.concatenate(idx)
    centres = grid.lo + (idx + 0.5) * grid.cell_size
    cid = idx @ grid.stride
    exact = brute_overlaps(tv[tri], centres, grid.cell_size / 2)
    # a vertex exactly on an enlarged cell face may come out 1e-17 outside in this float64
    # reference: allow 1% of delta for rounding
    enlarged = brute_overlaps(tv[tri], centres, grid.cell_size / 2 + 1.01 * grid.delta)
    missing = set(zip(cid[exact].tolist(), tri[exact].tolist())) - have
    spurious = have - set(zip(cid[enlarged].tolist(), tri[enlarged].tolist()))
    assert not missing, (f"{name}: {len(missing)} overlapping (cell, triangle) pairs not referenced, "
                         f"e.g. {sorted(missing)[:5]}")
    assert not spurious, (f"{name}: {len(spurious)} references to cells the triangle does not touch, "
                          f"e.g. {sorted(spurious)[:5]}")


def test_degenerate_triangles_are_never_referenced():
    mesh = soup(100, seed=2)
    tris = mesh.triangles.copy()
    tris[::7, 2] = tris[::7, 1]  # zero area
    mesh = core.TriangleMesh(mesh.vertices, tris)
    grid = core.build(mesh, "grid")
    bad = np.intersect1d(grid.cell_tris, np.flatnonzero(~mesh.valid))
    assert not bad.size, f"degenerate triangles referenced: {bad[:10].tolist()}"


def test_pieces_and_blocks_do_not_change_the_references():
    mesh = slivers(seed=9)
    a = core.build(mesh, "grid")
    b = core.build(mesh, "grid", pair_cap=5)
    b.build_block = 7
    b._build()
    ref = lambda g: sorted(zip(np.repeat(np.arange(g.ncells), np.diff(g.cell_start)).tolist(), g.cell_tris.tolist()))
    assert ref(a) == ref(b), "references depend on pair_cap / build_block"


# -- traversal against brute force ------------------------------------------------------


@pytest.mark.parametrize("name, mesh, config", [
    ("soup", soup(400, seed=21), {}),
    ("closed torus", torus(), {}),
    ("fine torus grid", torus(), {"density": 30.0}),
    ("flat scene", soup(300, flat_z=0.5, seed=22), {}),
    ("all triangles in one cell", soup(200, seed=23), {"density": 1e-9}),
    ("long thin triangles", slivers(seed=24), {}),
    ("no prefilter", soup(300, seed=25), {"prefilter": False}),
    ("tiny pair_cap", soup(300, seed=26), {"pair_cap": 3}),
])
def test_grid_returns_the_brute_force_hits_on_random_rays(name, mesh, config):
    o, d = random_rays(mesh, 1500, seed=31)
    grid, want = check_against_brute(mesh, o, d, name, **config)
    assert want.hit.sum() > 50, f"{name}: only {want.hit.sum()} hits; the scene tests too little"


def test_grid_returns_the_brute_force_hits_with_tmin_and_tmax():
    mesh = torus()
    o, d = random_rays(mesh, 1500, seed=32)
    rng = np.random.default_rng(33)
    tmin = rng.uniform(0, 0.5, len(o))
    tmax = tmin + rng.uniform(0, 2, len(o))
    check_against_brute(mesh, o, d, "per-ray tmin/tmax", tmin=tmin, tmax=tmax)


def test_rays_starting_inside_and_outside_the_grid_match_brute_force():
    mesh = soup(300, seed=41)
    grid = core.build(mesh, "grid")
    rng = np.random.default_rng(42)
    inside = rng.uniform(grid.lo, grid.hi, (800, 3))
    outside = rng.uniform(grid.lo - 2, grid.hi + 2, (800, 3))
    outside = outside[((outside < grid.lo) | (outside > grid.hi)).any(axis=1)]
    for what, o in (("origins inside the grid", inside), ("origins outside the grid", outside)):
        d = rng.normal(size=o.shape)
        check_against_brute(mesh, o, d, what)


@pytest.mark.parametrize("zero", [0.0, -0.0])
def test_axis_parallel_rays_with_signed_zero_components_match_brute_force(zero):
    mesh = soup(300, seed=51)
    rng = np.random.default_rng(52)
    lo, hi = mesh.bounds()
    o, d = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            k = 150
            oo = rng.uniform(lo, hi, (k, 3))
            oo[:, axis] = lo[axis] - 0.5 if sign > 0 else hi[axis] + 0.5
            dd = np.full((k, 3), zero)
            dd[:, axis] = sign
            o.append(oo)
            d.append(dd)
    # and rays in an axis plane (one zero component)
    oo = rng.uniform(lo, hi, (300, 3))
    dd = rng.normal(size=(300, 3))
    dd[:, 1] = zero
    o.append(oo)
    d.append(dd)
    o, d = np.concatenate(o), np.concatenate(d)
    assert (np.signbit(d) & (d == 0)).any() == (np.signbit(zero)), "test set-up: signed zeros lost"
    check_against_brute(mesh, o, d, f"directions with {zero!r} components")


def test_rays_through_cell_boundaries_and_grid_corners_match_brute_force():
    """Origins and directions chosen so rays run along cell faces and through cell corners."""
    mesh = soup(300, seed=61)
    grid = core.build(mesh, "grid", density=4.0)
    rng = np.random.default_rng(62)
    k = 600
    cell = rng.integers(0, grid.res + 1, (k, 3))
    o = grid.lo + cell * grid.cell_size  # on a grid vertex (up to float32 rounding)
    step = rng.integers(-3, 4, (k, 3))
    step[(step == 0).all(axis=1), 0] = 1
    d = step * grid.cell_size  # towards another grid vertex: through corners and along faces
    o2 = grid.lo + (cell + 0.5) * grid.cell_size
    o2[:, 0] = grid.lo[0] + cell[:, 0] * grid.cell_size[0]  # on an x face, moving within it
    d2 = rng.normal(size=(k, 3))
    d2[:, 0] = 0.0
    check_against_brute(mesh, np.concatenate([o, o2]), np.concatenate([d, d2]), "rays on cell boundaries")


def test_vertical_rays_through_shared_vertices_and_edges_of_a_height_field_never_leak():
    """Every ray down through lattice vertices and edge midpoints hits, like brute force."""
    mesh = lattice(n=8)
    g = np.arange(0, 17) / 16  # vertices (even) and edge midpoints (odd)
    X, Y = np.meshgrid(g, g, indexing="ij")
    o = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 2.0)], 1)
    d = np.tile([0.0, -0.0, -1.0], (len(o), 1))
    for density in (0.5, 2.0, 9.0):
        grid, want = check_against_brute(mesh, o, d, f"lattice rays, density {density}", density=density)
        assert want.hit.all(), f"brute force leaks at {np.flatnonzero(~want.hit)[:5]} (kernel problem)"


def test_equal_t_on_a_cell_boundary_goes_to_the_lower_triangle_index():
    """Two triangles share a vertex on a cell face; rays hit that vertex.

    The higher-index triangle lies in the cell the rays enter first, the lower-index one
    beyond the face, so the grid must not stop at the first cell's hit.
    """
    base = soup(60, seed=71)

    def with_pair(p):
        beyond = p + np.array([[0, 0, 0], [0.05, 0.0, 0.03], [0.05, 0.03, -0.02]])
        before = p + np.array([[0, 0, 0], [-0.05, 0.02, 0.03], [-0.05, -0.03, 0.0]])
        v = np.concatenate([base.tri_vertices.reshape(-1, 3), beyond, before])
        n = base.triangle_count
        tris = np.arange(3 * n + 6).reshape(-1, 3)
        # the triangle beyond the face gets index 10, the one before it the last index
        order = np.concatenate([np.arange(10), [n], np.arange(10, n), [n + 1]])
        return core.TriangleMesh(v, tris[order])

    # the pair sits well inside the scene, so moving it keeps the grid: find a face, move there
    grid = core.build(with_pair(np.array([0.5, 0.5, 0.5])), "grid", density=4.0)
    i = int(np.floor((0.5 - grid.lo[0]) / grid.cell_size[0]))
    p = np.array([grid.lo[0] + i * grid.cell_size[0], 0.5, 0.5], np.float32).astype(np.float64)
    mesh = with_pair(p)
    moved = core.build(mesh, "grid", density=4.0)
    assert np.array_equal(moved.lo, grid.lo) and np.array_equal(moved.cell_size, grid.cell_size), "set-up: grid moved"
    rng = np.random.default_rng(72)
    d = np.column_stack([np.ones(200), rng.normal(0, 0.3, (200, 2))])
    o = p - d
    _, want = check_against_brute(mesh, o, d, "ties at a cell face", density=4.0)
    assert (want.triangle == 10).sum() > 20, "set-up: the shared vertex is rarely won by the lower triangle"


def test_threads_and_chunks_do_not_change_the_hits():
    mesh = torus()
    o, d = random_rays(mesh, 3000, seed=81)
    one = core.build(mesh, "grid", threads=1).trace(o, d)
    many = core.build(mesh, "grid", threads=3, chunk_size=257).trace(o, d)
    assert_same_hits(many, one, "threads=3, chunk_size=257 vs threads=1")


def test_a_pool_refilled_many_times_gives_brute_force_hits_and_occlusion():
    # pool=50 of chunks of ~1000 rays: the pool is refilled from the chunk some 20 times
    mesh = torus()
    o, d = random_rays(mesh, 3000, seed=82)
    brute = core.build(mesh, "brute")
    grid = core.build(mesh, "grid", threads=2, chunk_size=1000, pool=50)
    assert_same_hits(grid.trace(o, d), brute.trace(o, d), "pool=50 vs brute force")
    got, want = grid.occluded(o, d, 0.0, 0.7), brute.occluded(o, d, 0.0, 0.7)
    w = np.flatnonzero(got != want)
    assert w.size == 0, f"occluded differs on {w.size} rays, first {w[0] if w.size else None}: grid {got[w[:1]]}"


@pytest.mark.parametrize("shape", [(5, 7, 9), (1, 1, 40), (24, 3, 1), (30, 26, 33)])
def test_empty_radius_cubes_hold_no_occupied_cell_stay_inside_the_grid_and_are_at_least_half_the_largest(shape):
    rng = np.random.default_rng(sum(shape))
    occ = rng.random(shape) < 0.003
    occ[tuple(s // 2 for s in shape)] = True
    r = empty_radius(occ).astype(np.int64)
    cells = np.indices(shape).reshape(3, -1).T
    occupied = np.argwhere(occ)
    # brute force: the largest empty cube inside the grid, from the chessboard distance
    cheb = np.abs(cells[:, None, :] - occupied[None, :, :]).max(axis=2).min(axis=1)
    face = np.minimum(cells, np.array(shape) - 1 - cells).min(axis=1)
    largest = np.maximum(np.minimum(cheb - 1, face), 0)
    got = r.reshape(-1)
    over = np.flatnonzero(got > largest)
    assert not over.size, f"cells {cells[over[:5]].tolist()}: radius {got[over[:5]].tolist()} > largest empty cube {largest[over[:5]].tolist()}"
    short = np.flatnonzero(2 * got + 1 < np.minimum(largest, 15))
    assert not short.size, f"cells {cells[short[:5]].tolist()}: radius {got[short[:5]].tolist()} under half of {largest[short[:5]].tolist()}"


def test_empty_space_skip_changes_no_hit_on_a_sparse_scene():
    """Two dense clusters in the corners of a box sprinkled with tiny triangles: empty cubes
    of every radius, and an occupied cell just past many of them."""
    a, b, c = soup(300, seed=11, size=0.01), soup(300, seed=12, size=0.01), soup(60, seed=14, size=0.002)
    v = np.concatenate([a.vertices * 0.05, b.vertices * 0.05 + 0.95, c.vertices])
    t = np.concatenate([a.triangles, b.triangles + len(a.vertices), c.triangles + len(a.vertices) + len(b.vertices)])
    mesh = core.TriangleMesh(v, t)
    o, d = random_rays(mesh, 4000, seed=13, grow=0.1)
    d[::7, 0] = 0.0
    d[1::7, 1] = -0.0
    grid, want = check_against_brute(mesh, o, d, "empty-space skip", density=4.0)
    assert grid.stats()["skippable_cell_fraction"] > 0.25, "set-up: too few cells to jump from"
    plain = core.build(mesh, "grid", density=4.0, skip=False)
    assert plain.stats()["skippable_cell_fraction"] == 0.0
    assert_same_hits(plain.trace(o, d), want, "skip=False")


def test_a_cell_with_more_references_than_int16_holds():
    """40,000 triangles in one cell of a 4 x 4 x 4 grid: the per-cell code (reference count,
    or minus the skip radius) must widen past int16, and every hit still match."""
    rng = np.random.default_rng(21)
    n = 40_000
    cluster = 0.125 + rng.uniform(-0.02, 0.02, (n, 1, 3)) + rng.normal(0, 0.004, (n, 3, 3))
    corners = np.array([[0, 0, 0], [1, 1, 1]], float)[:, None, :] + rng.normal(0, 0.01, (2, 3, 3))
    v = np.concatenate([cluster, corners]).reshape(-1, 3)
    mesh = core.TriangleMesh(v, np.arange(len(v)).reshape(-1, 3))
    o = rng.uniform(-0.2, 1.2, (600, 3))
    d = 0.125 + rng.normal(0, 0.02, (600, 3)) - o  # most rays through the cluster
    d[::3] = rng.normal(size=(200, 3))
    grid, want = check_against_brute(mesh, o, d, "int32 cell codes", max_cells=64)
    assert grid.stats()["max_refs_per_cell"] >= 2**15, "set-up: the cluster is not in one cell"
    assert grid._cell_code.dtype == np.int32
    assert want.hit.mean() > 0.5, "set-up: too few rays hit the cluster"


def test_a_mesh_of_only_degenerate_triangles_is_all_misses():
    v = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]], float)
    mesh = core.TriangleMesh(v, [[0, 1, 2], [0, 0, 1]])
    grid = core.build(mesh, "grid")
    o, d = random_rays(soup(5), 50)
    h = grid.trace(o, d)
    assert not h.hit.any() and np.isinf(h.t).all()
    assert not grid.occluded(o, d).any()


# -- stats ----------------------------------------------------------------------------


def test_stats_report_resolution_cells_references_and_memory():
    mesh = soup(500, seed=91)
    grid = core.build(mesh, "grid", density=3.0)
    s = grid.stats()
    assert s["kind"] == "grid" and s["triangles"] == 500 and s["density"] == 3.0
    assert s["cells"] == int(np.prod(s["resolution"])) == grid.ncells
    assert s["references"] == len(grid.cell_tris) >= 500
    assert s["refs_per_triangle"] == pytest.approx(s["references"] / 500)
    assert 0.0 <= s["empty_cell_fraction"] < 1.0
    assert s["memory_bytes"] >= grid.cell_start.nbytes + grid.cell_tris.nbytes
    assert isinstance(grid, UniformGrid) and grid.build_time >= 0


# -- the traversal's own work counts (issue 14) ---------------------------------------------

def _counted(g, o, d):
    before = g.traversal_work()
    g.trace(o, d)
    after = g.traversal_work()
    return {k: after[k] - before[k] for k in after}


def test_traversal_steps_are_the_dda_cells_of_each_ray_without_skipping():
    """One ray at a time (no parked rays) and no empty-space skip: a ray takes one step per
    cell the DDA visits, the count ``decide.work.grid_work`` computes from the geometry."""
    from hybrid_raycast.core.decide.work import grid_work

    m = torus()
    g = UniformGrid(m, skip=False, threads=1)
    o, d = core.uniform_rays(m, 40, seed=5)
    apart = []
    for i in range(len(o)):
        got = _counted(g, o[i:i + 1], d[i:i + 1])
        cells = grid_work(g, o[i:i + 1], d[i:i + 1], g.trace(o[i:i + 1], d[i:i + 1]).t, refs=False).cells
        assert got["rays"] == 1
        apart.append(got["steps"] - cells)
    # grid_work ends a ray at the unpadded box: leaving near a boundary may take a step more
    assert set(apart) <= {0, 1} and apart.count(0) >= 0.9 * len(apart)


def test_traversal_counts_skip_prefilter_threads_and_callers():
    m = torus()
    o, d = core.uniform_rays(m, 3000, seed=6)
    plain = _counted(UniformGrid(m, skip=False, threads=1), o, d)
    skip1 = _counted(UniformGrid(m, threads=1), o, d)
    skip2 = _counted(UniformGrid(m, threads=2), o, d)
    assert skip1 == skip2  # each ray's work is its own, whichever thread steps it
    assert skip1["steps"] < plain["steps"]  # jumps over empty space are one step each
    assert skip1["candidates"] == plain["candidates"]  # skipped cells hold no reference
    assert 0 < skip1["tests"] < skip1["candidates"]  # the box prefilter drops pairs
    nofilter = _counted(UniformGrid(m, prefilter=False, threads=1), o, d)
    assert nofilter["tests"] == nofilter["candidates"] == skip1["candidates"]
    # another thread's traces are not in this thread's totals
    import threading

    g = UniformGrid(m, threads=1)
    t = threading.Thread(target=g.trace, args=(o, d))
    t.start()
    t.join()
    assert g.traversal_work() == {"rays": 0, "steps": 0, "candidates": 0, "tests": 0}
    import pickle

    g.trace(o[:10], d[:10])
    assert pickle.loads(pickle.dumps(g)).traversal_work()["rays"] == 0
