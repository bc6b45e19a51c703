"""Point queries (core/proximity.py, ``Accel.closest`` / ``winding_number`` / ``inside`` /
``signed_distance`` / ``count_hits``): every tree against the float64 brute force, the brute
force against an independent check, inside/outside against the exact winding number on
closed meshes, meshes with holes, open meshes and overlapping shells."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_raycast import core
from hybrid_raycast.core import scenes as S
from reference import cube, icosphere, kind_params

KINDS = kind_params(["bvh", "grid", "embree"])


def mesh_of(v, f):
    return core.TriangleMesh(np.asarray(v, np.float32), np.asarray(f, np.int32))


def around(mesh, n, seed=0, pad=0.3):
    lo, hi = mesh.bounds()
    lo, hi = lo.astype(float), hi.astype(float)
    return np.random.default_rng(seed).uniform(lo - pad * (hi - lo), hi + pad * (hi - lo), size=(n, 3))


def meshes():
    v, f = icosphere(2)
    yield "icosphere", mesh_of(v, f)
    yield "torus", S.torus(800, seed=1)
    yield "soup", S.soup(400, seed=2)
    yield "terrain (open)", S.terrain(500, seed=3)
    v, f = cube()
    far = mesh_of(np.asarray(v) * 0.5 + 1e5, f)
    yield "far from the origin", far
    yield "tiny", mesh_of(np.asarray(v) * 1e-5, f)


@pytest.mark.parametrize("kind", KINDS)
def test_closest_equals_the_float64_brute_force_on_every_mesh(kind):
    for name, mesh in meshes():
        pts = around(mesh, 700, seed=len(name))
        want = core.build(mesh, "brute").closest(pts)
        got = core.build(mesh, kind).closest(pts)
        assert np.array_equal(got.triangle, want.triangle), name
        assert np.array_equal(got.distance, want.distance), name  # the same float64 arithmetic
        assert np.allclose(got.points, want.points, rtol=0, atol=1e-9 * (1 + np.abs(want.points).max())), name
        assert got.distance.dtype == np.float64 and got.triangle.dtype == np.int32 and got.u.dtype == np.float32


def test_the_brute_force_is_no_farther_than_any_sampled_point_of_any_triangle():
    """An independent check of the closest-point arithmetic: dense barycentric samples of every
    triangle (its vertices and edges among them) are never nearer than the answer, and the
    answer lies on its triangle at the distance it reports."""
    mesh = S.soup(40, seed=5)
    pts = around(mesh, 60, seed=1)
    got = core.build(mesh, "brute").closest(pts)
    k = 24
    a, b = np.meshgrid(np.arange(k + 1), np.arange(k + 1))
    keep = a + b <= k
    uu, vv = a[keep] / k, b[keep] / k
    tv = mesh.tri_vertices.astype(np.float64)
    samples = ((1 - uu - vv)[None, :, None] * tv[:, None, 0] + uu[None, :, None] * tv[:, None, 1]
               + vv[None, :, None] * tv[:, None, 2]).reshape(-1, 3)
    nearest_sample = np.sqrt(((pts[:, None, :] - samples[None]) ** 2).sum(-1)).min(axis=1)
    assert (got.distance <= nearest_sample + 1e-12).all()
    assert (got.u >= 0).all() and (got.v >= 0).all() and (got.u + got.v <= 1 + 1e-6).all()
    assert np.allclose(np.linalg.norm(pts - got.points, axis=1), got.distance, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS + ["brute"])
def test_an_exact_tie_goes_to_the_lowest_triangle_index(kind):
    """Two copies of a square (four triangles, the copies coplanar and identical): every
    point's closest triangle is one of the first copy's."""
    v, f = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]])
    mesh = mesh_of(v, np.concatenate([f, f]))
    pts = np.random.default_rng(3).uniform([-0.5, -0.5, -1], [1.5, 1.5, 1], size=(300, 3))
    got = core.build(mesh, kind).closest(pts)
    assert (got.triangle < 2).all() and (got.triangle >= 0).all()


@pytest.mark.parametrize("kind", KINDS)
def test_ties_across_leaves_go_to_the_lowest_index_as_the_brute_force(kind):
    """Points right above (and on) the vertices and edge midpoints of a flat grid of 800
    triangles: equally close to up to six triangles that sit in different leaves; the
    search keeps every box that ties its bound open, so it picks the brute force's."""
    k = 20
    x, y = np.meshgrid(np.linspace(0, 1, k + 1), np.linspace(0, 1, k + 1))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    i = np.arange(k * k)
    a = (i // k) * (k + 1) + i % k
    mesh = mesh_of(v, np.concatenate([np.stack([a, a + 1, a + k + 2], 1), np.stack([a, a + k + 2, a + k + 1], 1)]))
    g = np.linspace(0, 1, 2 * k + 1)
    gx, gy = np.meshgrid(g, g)
    pts = np.concatenate([np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1) for z in (0.0, 0.01, 0.3)])
    want = core.build(mesh, "brute").closest(pts)
    got = core.build(mesh, kind).closest(pts)
    assert np.array_equal(got.triangle, want.triangle) and np.array_equal(got.distance, want.distance)


@pytest.mark.parametrize("kind", KINDS + ["brute"])
def test_max_distance_is_inclusive_and_a_miss_is_documented(kind):
    v, f = cube()
    acc = core.build(mesh_of(v, f), kind)
    pts = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 1.5], [5.0, 5.0, 5.0]])
    got = acc.closest(pts, max_distance=2.0)
    assert got.triangle[0] >= 0 and got.distance[0] == 2.0, "max_distance is inclusive"
    assert got.distance[1] == pytest.approx(0.5) and got.triangle[1] >= 0
    assert got.distance[2] == np.inf and got.triangle[2] == -1 and np.isnan(got.points[2]).all()
    assert got.u[2] == 0 and got.v[2] == 0 and list(got.found) == [True, True, False]


@pytest.mark.parametrize("bad, words", [
    ((np.array([[0.0, np.nan, 0.0]]), {}), "NaN or infinite"),
    ((np.array([[0.0, np.inf, 0.0]]), {}), "NaN or infinite"),
    ((np.zeros((4, 2)), {}), "shaped"),
    ((np.zeros((1, 3)), {"max_distance": 0.0}), "max_distance must be positive"),
    ((np.zeros((1, 3)), {"max_distance": -1.0}), "max_distance must be positive"),
    ((np.zeros((1, 3)), {"max_distance": np.nan}), "max_distance must be positive"),
    ((np.zeros((1, 3)), {"max_distance": "far"}), "max_distance must be a number"),
])
@pytest.mark.parametrize("kind", ["bvh", "brute"])
def test_bad_input_is_an_error_naming_the_argument(kind, bad, words):
    v, f = cube()
    acc = core.build(mesh_of(v, f), kind)
    pts, kw = bad
    with pytest.raises(ValueError, match=words):
        acc.closest(pts, **kw)
    if not kw:
        with pytest.raises(ValueError, match=words):
            acc.winding_number(pts)


@pytest.mark.parametrize("kind", KINDS + ["brute"])
def test_an_empty_mesh_answers_every_query_with_a_documented_miss(kind):
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)  # one degenerate triangle: nothing valid
    acc = core.build(mesh_of(v, [[0, 1, 2]]), kind)
    pts = np.zeros((3, 3))
    got = acc.closest(pts)
    assert (got.triangle == -1).all() and np.isinf(got.distance).all()
    assert (acc.winding_number(pts) == 0).all() and not acc.inside(pts).any()
    assert np.isinf(acc.signed_distance(pts)).all()
    assert (acc.count_hits(pts, np.ones((3, 3))) == 0).all()


def with_holes(v, f, drop):
    keep = np.ones(len(f), bool)
    keep[drop] = False
    return mesh_of(v, np.asarray(f)[keep])


def winding_cases():
    v, f = icosphere(3)
    yield "closed sphere", mesh_of(v, f)
    yield "a cap cut off", mesh_of(v, np.asarray(f)[np.asarray(v)[np.asarray(f)].mean(axis=1)[:, 2] < 0.7])
    yield "faces removed", with_holes(v, f, np.random.default_rng(1).choice(len(f), 40, replace=False))
    yield "torus", S.torus(2000, seed=2)
    yield "open terrain", S.terrain(800, seed=3)
    v2 = np.asarray(v) + [0.8, 0.0, 0.0]  # two overlapping shells: w = 2 where both hold the point
    yield "overlapping shells", mesh_of(np.concatenate([v, v2]), np.concatenate([f, np.asarray(f) + len(v)]))
    yield "soup (self-intersecting)", S.soup(600, seed=4)


@pytest.fixture(scope="module")
def exact_windings():
    """(name, mesh, points, the exact winding number) of every case, computed once."""
    out = []
    for name, mesh in winding_cases():
        pts = around(mesh, 1500, seed=7)
        out.append((name, mesh, pts, core.build(mesh, "brute").winding_number(pts)))
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_inside_agrees_with_the_exact_winding_number_wherever_it_is_clear(kind, exact_windings):
    for name, mesh, pts, exact in exact_windings:
        acc = core.build(mesh, kind)
        w = acc.winding_number(pts)
        clear = np.abs(exact - 0.5) > 0.1
        assert clear.sum() > 500, name
        assert np.array_equal(acc.inside(pts)[clear], (exact > 0.5)[clear]), name
        assert np.abs(w - exact).max() < 0.1, (name, np.abs(w - exact).max())


def test_the_winding_number_is_one_inside_a_closed_mesh_zero_outside_and_two_in_both_shells():
    v, f = icosphere(2)
    exact, tree = core.build(mesh_of(v, f), "brute"), core.build(mesh_of(v, f), "bvh")
    pts = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [3.0, 0.0, 0.0]])
    assert exact.winding_number(pts) == pytest.approx([1.0, 1.0, 0.0], abs=1e-9)
    # the tree's far field is a dipole per subtree: near, not equal (Barill et al.'s bound)
    assert tree.winding_number(pts) == pytest.approx([1.0, 1.0, 0.0], abs=0.05)
    assert tree.winding_number(pts, accuracy=20.0) == pytest.approx([1.0, 1.0, 0.0], abs=1e-3)
    one = tree
    v2 = np.asarray(v) + [0.8, 0.0, 0.0]
    two = core.build(mesh_of(np.concatenate([v, v2]), np.concatenate([f, np.asarray(f) + len(v)])), "brute")
    assert two.winding_number(np.array([[0.4, 0.0, 0.0]])) == pytest.approx([2.0], abs=1e-9)
    with pytest.raises(ValueError, match="accuracy must be at least 1"):
        one.winding_number(np.zeros((1, 3)), accuracy=0.5)


@pytest.mark.parametrize("kind", KINDS + ["brute"])
def test_signed_distance_is_the_closest_distance_negative_inside(kind):
    v, f = icosphere(3)
    acc = core.build(mesh_of(v, f), kind)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.5, 0.0, 0.0]])
    sd = acc.signed_distance(pts)
    d = acc.closest(pts).distance
    assert sd[0] == -d[0] and sd[1] == d[1] and sd[2] == -d[2]
    assert sd[0] == pytest.approx(-1.0, abs=0.01) and sd[1] == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("kind", KINDS)
def test_count_hits_equals_the_brute_force_and_all_hits(kind):
    for name, mesh in meshes():
        o = around(mesh, 300, seed=11)
        d = np.random.default_rng(12).normal(size=(300, 3))
        want = core.build(mesh, "brute").count_hits(o, d)
        acc = core.build(mesh, kind)
        got = acc.count_hits(o, d)
        assert np.array_equal(got, want), name
        ray = core.all_hits(core.build(mesh, "bvh"), o, d, max_hits=1000)[0]  # the same kernel
        assert np.array_equal(got, np.bincount(ray, minlength=len(o))), name
        assert got.dtype == np.int32


def test_count_hits_counts_a_shared_edge_once_and_keeps_the_interval():
    v, f = cube()
    acc = core.build(mesh_of(v, f), "bvh")
    # through the cube's face diagonals (shared edges of two triangles each) and along an axis
    o = np.array([[-3.0, -3.0, 0.0], [0.0, 0.0, -5.0], [0.0, 0.0, -5.0]])
    d = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    assert list(acc.count_hits(o, d)) == [2, 2, 2]
    assert list(acc.count_hits(o, d, tmax=np.array([10.0, 4.5, 6.5]))) == [2, 1, 2]
    assert list(acc.count_hits(o, d, tmin=5.0)) == [0, 1, 1]


def test_many_points_on_the_thread_pool_give_the_one_thread_answer(monkeypatch):
    from hybrid_raycast.core import accel

    monkeypatch.setattr(accel, "MIN_SPLIT", 1000)  # so that 5,000 points take both threads
    mesh = S.torus(3000, seed=5)
    pts = around(mesh, 5000, seed=9)
    one = core.build(mesh, "bvh", threads=1)
    two = core.build(mesh, "bvh", threads=2)
    assert len(two._point_parts(len(pts))) == 2
    a, b = one.closest(pts), two.closest(pts)
    assert np.array_equal(a.triangle, b.triangle) and np.array_equal(a.distance, b.distance)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.u, b.u)
    # the same terms, summed in another order
    assert np.allclose(one.winding_number(pts), two.winding_number(pts), rtol=0, atol=1e-12)


# -- the grid's own search (rings of cells) and the decision for point queries ------------------------

def test_the_grid_searches_its_own_cells_exactly_on_flat_sparse_and_far_scenes():
    """The ring search (``proximity.closest_grid``) against the brute force where it is hardest:
    a flat mesh (one layer of cells), points far outside the grid, points deep inside a closed
    sphere (past the empty cube about their cell) and a sparse scene of clusters."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    flat = S.terrain(400, seed=4)
    flat = core.TriangleMesh(flat.vertices * np.array([1, 1, 0], np.float32), flat.triangles)
    sphere = mesh_of(*icosphere(3))
    cases = [("flat", flat, around(flat, 500, seed=1, pad=2.0)),
             ("inside a sphere", sphere, np.random.default_rng(2).uniform(-0.5, 0.5, size=(300, 3))),
             ("clusters", S.clusters(2000, seed=3), None),
             ("square, far points", mesh_of(v, [[0, 1, 2], [0, 2, 3]]), around(mesh_of(v, [[0, 1, 2], [0, 2, 3]]), 300, pad=50))]
    for name, mesh, pts in cases:
        pts = around(mesh, 400, seed=5) if pts is None else pts
        grid = core.build(mesh, "grid")
        want = core.build(mesh, "brute").closest(pts)
        work = [0, 0, 0, 0]
        got = core.proximity.closest_grid(grid.cell_index(), pts, work=work)
        assert np.array_equal(got.triangle, want.triangle), name
        assert np.array_equal(got.distance, want.distance), name
        assert work[0] == len(pts) and work[1] >= len(pts) and work[3] >= len(pts), (name, work)
    assert getattr(core.build(sphere, "grid"), "_tree_index", None) is None  # no BVH was built for it


def test_the_grid_search_honours_max_distance_and_an_empty_grid():
    mesh = S.torus(600, seed=1)
    pts = around(mesh, 500, seed=7)
    want = core.build(mesh, "brute").closest(pts, max_distance=0.1)
    got = core.build(mesh, "grid").closest(pts, max_distance=0.1)
    assert np.array_equal(got.triangle, want.triangle)
    assert np.array_equal(got.distance, want.distance)
    assert (got.triangle == -1).any() and np.isinf(got.distance[got.triangle == -1]).all()
    empty = core.build(mesh_of(np.zeros((3, 3)), [[0, 1, 2]]), "grid").closest(pts[:5])
    assert (empty.triangle == -1).all() and np.isinf(empty.distance).all()


def _records():
    """Calibration records made by hand: the grid's time per point grows with its cells, the
    BVH's with log N; three kinds of points on three sizes."""
    from hybrid_raycast.core.decide.points import PointRecord

    out = []
    for n in (1000, 10000, 100000):
        for kind, (rings, cells, pairs) in (("box", (6, 5000, 300)), ("near", (2, 80, 100)), ("surface", (1.5, 14, 30))):
            work = [1000, rings * 1000, cells * 1000, pairs * 1000]
            grid_t = 1e-6 * rings + 5e-8 * cells + 1e-7 * pairs
            bvh_t = 2e-6 * np.log(n) * (pairs ** 0.3)
            out.append(PointRecord(f"s{n}", kind, n, 1000, 1e-6 * n ** 0.9, 3e-6 * n ** 0.95, grid_t, bvh_t, work,
                                   [w // 4 for w in work]))
    return out


def test_the_point_decision_fits_its_records_and_picks_the_least_total():
    from hybrid_raycast.core.decide import points as P

    model = P.fit_points(_records())
    back = P.PointModel.from_dict(model.to_dict())
    assert back.grid_terms == model.grid_terms and back.bvh_terms == model.bvh_terms
    r = {x.points_kind: x for x in model.records if x.triangles == 10000}
    # far points: the grid's rings of empty cells cost more than a BVH after a few dozen points
    far = P.decide(model, 10000, 100_000, r["box"].sample_work)
    assert far.kind == "bvh" and 0 < far.break_even < 1000
    assert P.decide(model, 10000, 5, r["box"].sample_work).kind == "grid"
    # on the surface the grid is as fast per point: it keeps them
    assert P.decide(model, 10000, 100_000, r["surface"].sample_work).kind == "grid"
    # a BVH already built costs nothing to own
    assert P.decide(model, 10000, 5, r["box"].sample_work, built={"grid", "bvh"}).kind == "bvh"
    ev = P.evaluate(model, model.records)
    assert ev["picks"] / ev["picked"] >= 0.9 and ev["finite"] + ev["agree_never"] > 0
    assert P.decide(None, 10000, 100, r["box"].sample_work).kind == "bvh"  # no calibration: the BVH


def test_a_calibration_keeps_its_point_model_and_an_old_file_takes_the_shipped_one(tmp_path):
    from hybrid_raycast.core.decide import points as P

    cal = core.decide.load_default()
    assert cal.point_model() is not None, "the shipped calibration carries the point decision's constants"
    mine = core.decide.Calibration(dict(cal.fits), source="measured", points=P.fit_points(_records()).to_dict())
    path = tmp_path / "c.json"
    mine.save(path)
    back = core.decide.load(path, check_version=False)
    assert back.point_model().grid_terms == mine.point_model().grid_terms
    old = core.decide.Calibration(dict(cal.fits), source="measured")
    assert old.point_model().grid_terms == cal.point_model().grid_terms


def test_a_planned_search_hands_far_points_to_the_bvh_and_answers_every_point_exactly(monkeypatch):
    """Points far outside the scene would cost the grid ~(2r+1)^3 cells each: a planned search
    (``closest_planned``) leaves those past ``REACH`` to the BVH, built once, and the answers
    are still the brute force's."""
    from hybrid_raycast.core.decide import points as P

    mesh = S.torus(2000, seed=2)
    near = around(mesh, 600, seed=3, pad=0.05)
    far = around(mesh, 200, seed=4, pad=30.0)
    pts = np.concatenate([near, far])
    want = core.build(mesh, "brute").closest(pts)
    grid = core.build(mesh, "grid")
    built = []

    def bvh():
        built.append(1)
        return core.build(mesh, "bvh")

    monkeypatch.setattr(P, "REACH", 4000)
    model = P.fit_points(_records())
    got, kind, plan = P.closest_planned(pts, np.inf, model, grid, bvh, mesh.triangle_count)
    assert np.array_equal(got.triangle, want.triangle) and np.array_equal(got.distance, want.distance)
    assert plan.handed_over > 0 and len(built) == 1
    _, left = core.proximity.closest_grid(grid.cell_index(), far, reach=4000)
    assert left.mean() > 0.5  # most far points would have needed more than REACH cells


def test_far_points_in_the_sample_make_the_bvh_free_for_the_decision():
    """The BVH the far points need is built anyway: the grid then keeps the rest only where it
    is faster per point."""
    from hybrid_raycast.core.decide import points as P

    model = P.fit_points(_records())
    box = next(r for r in model.records if r.points_kind == "box" and r.triangles == 10000)
    alone = P.decide(model, 10000, 20, box.sample_work, built={"grid"})
    shared = P.decide(model, 10000, 20, box.sample_work, built={"grid"}, far_share=0.1)
    assert alone.kind == "grid" and shared.kind == "bvh" and "far points" in shared.reason
