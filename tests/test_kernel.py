"""The shared watertight kernel (core/intersect.py), through brute force and directly."""

import numpy as np
import pytest

from hybrid_raycast import core
from hybrid_raycast.core.intersect import NearestHits, intersect, prepare_rays

from reference import describe_ray


def _mesh(tris):
    tris = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    return core.TriangleMesh(tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3))


def _random_hitting_rays(rng, n):
    """n random triangles and, per triangle, a ray aimed at an interior point of it."""
    tris = rng.uniform(-5, 5, (n, 3, 3))
    w = rng.dirichlet([2, 2, 2], n)  # well inside: no edge grazing
    target = np.einsum("nk,nkj->nj", w, tris)
    origins = rng.uniform(-5, 5, (n, 3))
    return tris, origins, target - origins


def test_barycentrics_reproduce_the_hit_point():
    rng = np.random.default_rng(1)
    tris, o, d = _random_hitting_rays(rng, 200)
    acc = core.build(_mesh(tris), "brute")
    for i in range(len(tris)):  # one triangle at a time: the ray must hit exactly that one
        h = core.build(_mesh(tris[i]), "brute").trace(o[i], d[i])
        assert h.triangle[0] == 0, f"{describe_ray(i, o, d)} aimed inside triangle {i} missed it"
        tv = tris[i].astype(np.float32).astype(np.float64)
        p_bary = (1 - h.u[0] - h.v[0]) * tv[0] + h.u[0] * tv[1] + h.v[0] * tv[2]
        p_ray = h.points(o[i:i + 1].astype(np.float32), d[i:i + 1].astype(np.float32))[0]
        err = np.linalg.norm(p_bary - p_ray)
        assert err <= 1e-5 * (1 + np.abs(tv).max()), f"{describe_ray(i, o, d)}: barycentric point {p_bary} vs ray point {p_ray}"
    # and in one batch, against the whole soup
    h = acc.trace(o, d)
    assert h.hit.all(), f"{(~h.hit).sum()} rays aimed inside a triangle missed everything"


def test_t_is_measured_in_units_of_the_unnormalised_direction():
    m = _mesh([[0, 0, 2], [4, 0, 2], [0, 4, 2]])
    acc = core.build(m, "brute")
    o = np.array([[0.5, 0.5, 0.0]] * 4)
    scales = np.array([1.0, 0.25, 3.0, 1e3])
    d = np.array([0.0, 0.0, 1.0])[None, :] * scales[:, None]
    h = acc.trace(o, d)
    np.testing.assert_allclose(h.t, 2.0 / scales, rtol=1e-6, err_msg="t * |d| must be the distance 2")


def test_degenerate_triangles_are_never_hit():
    degenerate = [
        [[0, 0, 1], [1, 1, 1], [2, 2, 1]],  # collinear
        [[0, 0, 1], [0, 0, 1], [1, 0, 1]],  # repeated corner
        [[0, 0, 1], [0, 0, 1], [0, 0, 1]],  # a point
    ]
    m = _mesh(degenerate + [[[-5, -5, 3], [5, -5, 3], [0, 5, 3]]])
    assert m.valid.tolist() == [False, False, False, True]
    acc = core.build(m, "brute")
    # aim exactly at points of the degenerate triangles, from several sides
    targets = np.array([[0, 0, 1], [1, 1, 1], [0.5, 0.5, 1], [0.5, 0, 1], [2, 2, 1]], float)
    o = np.array([[0.1, 0.3, -2.0], [1, 1, -1.0], [1, 1, 0.0], [0.5, -1, 1.0], [-3, -3, 1.0]])
    d = targets - o
    h = acc.trace(o, d)
    bad = np.flatnonzero(h.triangle != np.where(d[:, 2] > 0, 3, -1))
    assert bad.size == 0, f"{describe_ray(bad[0], o, d)} returned triangle {h.triangle[bad[0]]}, degenerate ones must be skipped"
    assert not acc.occluded(o[d[:, 2] == 0], d[d[:, 2] == 0]).any()


def test_rays_in_the_plane_of_a_triangle_miss_it():
    m = _mesh([[[0, 0, 1], [4, 0, 1], [0, 4, 1]]])
    acc = core.build(m, "brute")
    # in the plane z=1, through the interior, along an edge, and through a vertex
    o = np.array([[-1, 1, 1], [-1, 0, 1], [-1, -1, 1], [5, 5, 1]], float)
    d = np.array([[1, 0, 0], [1, 0, 0], [1, 1, 0], [-1, -1, 0]], float)
    h = acc.trace(o, d)
    assert (h.triangle == -1).all(), f"in-plane rays hit triangles {h.triangle.tolist()}"
    assert not acc.occluded(o, d).any()


def test_exact_tie_in_t_goes_to_the_lowest_triangle_index():
    # triangle 0 elsewhere; duplicates at 1 and 3 (and a coplanar overlap at 2) at z = 1
    tris = [
        [[10, 10, 5], [11, 10, 5], [10, 11, 5]],
        [[-1, -1, 1], [2, -1, 1], [-1, 2, 1]],
        [[-2, 0, 1], [2, -2, 1], [2, 2, 1]],
        [[-1, -1, 1], [2, -1, 1], [-1, 2, 1]],
    ]
    acc = core.build(_mesh(tris), "brute")
    o = np.array([[0.25, 0.25, 0.0], [0.25, 0.25, 3.0], [1.5, 0.0, 0.0]])
    d = np.array([[0, 0, 1.0], [0, 0, -2.0], [0, 0, 0.5]])
    h = acc.trace(o, d)
    assert h.triangle.tolist() == [1, 1, 2], f"tie winners {h.triangle.tolist()}, expected [1, 1, 2] (lowest index of those at equal t)"
    # reversing the triangle order must still pick the lowest index
    h2 = core.build(_mesh(tris[::-1]), "brute").trace(o, d)
    assert h2.triangle.tolist() == [0, 0, 1], f"reversed order: {h2.triangle.tolist()}, expected [0, 0, 1]"


def test_rays_through_a_shared_edge_and_a_shared_vertex_hit_and_tie_to_lowest_index():
    # four triangles fanned around the vertex (0,0,0) in z=0, in a scrambled index order
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    t = np.array([[0, 3, 4], [0, 1, 2], [0, 4, 1], [0, 2, 3]])
    acc = core.build(core.TriangleMesh(v, t), "brute")
    o = np.array([[0, 0, 1], [0.5, 0, 1], [0, -0.25, -1], [0.3, 0.7, 2]], float)
    target = np.array([[0, 0, 0], [0.5, 0, 0], [0, -0.25, 0], [0, 0, 0]], float)
    h = acc.trace(o, target - o)
    # axis-aligned, exactly representable: vertex -> all four tie; edge (0,1): triangles
    # 1 and 2; edge (0,4): 0 and 2.  The slanted ray 3 through the vertex must hit one.
    assert h.triangle[:3].tolist() == [0, 1, 0], f"got {h.triangle[:3].tolist()}, expected [0, 1, 0]"
    np.testing.assert_array_equal(h.t[:3], np.ones(3, np.float32))
    assert h.triangle[3] >= 0 and abs(h.t[3] - 1) < 1e-6, f"slanted ray through the shared vertex: {h.triangle[3]}, t={h.t[3]}"


def test_tmin_exclusive_and_tmax_inclusive():
    m = _mesh([[[-1, -1, 1], [2, -1, 1], [-1, 2, 1]], [[-1, -1, 3], [2, -1, 3], [-1, 2, 3]]])
    acc = core.build(m, "brute")
    o = np.zeros((6, 3))
    d = np.tile([0.0, 0.0, 1.0], (6, 1))
    tmin = np.array([0.0, 1.0, 0.999, 0.0, 0.0, -5.0])
    tmax = np.array([np.inf, np.inf, np.inf, 1.0, 0.999, np.inf])
    h = acc.trace(o, d, tmin=tmin, tmax=tmax)
    expected = [(0, 1.0), (1, 3.0), (0, 1.0), (0, 1.0), (-1, np.inf), (0, 1.0)]
    got = list(zip(h.triangle.tolist(), h.t.tolist()))
    assert got == expected, f"(triangle, t) per ray {got}, expected {expected} (tmin < t <= tmax)"
    occ = acc.occluded(o, d, tmin=tmin, tmax=tmax)
    assert occ.tolist() == [True, True, True, True, False, True]
    # a negative tmin reaches hits behind the origin
    h = acc.trace([[0, 0, 2.0]], [[0, 0, 1.0]], tmin=-5.0)
    assert h.triangle[0] == 0 and h.t[0] == -1.0, f"tmin=-5: {h.triangle[0]}, t={h.t[0]}, expected 0 at t=-1"


@pytest.mark.parametrize(
    "field, bad_value",
    [("origins", np.nan), ("origins", np.inf), ("directions", np.nan), ("directions", -np.inf), ("directions", 1e39)],
)
def test_nan_or_infinite_rays_raise_a_value_error_naming_count_and_first_ray(field, bad_value):
    acc = core.build(_mesh([[[0, 0, 1], [1, 0, 1], [0, 1, 1]]]), "brute")
    o = np.zeros((6, 3))
    d = np.tile([0.0, 0.0, 1.0], (6, 1))
    arr = o if field == "origins" else d
    arr[2, 1] = bad_value
    arr[4, 0] = bad_value
    for call in (acc.trace, acc.occluded):
        with pytest.raises(ValueError) as e:
            call(o, d)
        msg = str(e.value)
        assert "2 of 6" in msg and "[2, 4]" in msg and field in msg, f"unhelpful message: {msg}"


def test_zero_length_directions_raise_a_value_error_naming_count_and_first_ray():
    acc = core.build(_mesh([[[0, 0, 1], [1, 0, 1], [0, 1, 1]]]), "brute")
    d = np.tile([0.0, 0.0, 1.0], (5, 1))
    d[3] = 0.0
    d[1] = [1e-46, 0, 0]  # non-zero in float64, zero after rounding to float32
    with pytest.raises(ValueError, match=r"2 of 5 rays have a zero-length direction, first at ray \[1, 3\]"):
        acc.trace(np.zeros((5, 3)), d)


def test_nan_tmin_or_tmin_above_tmax_raise():
    with pytest.raises(ValueError, match="tmin contains NaN"):
        prepare_rays(np.zeros((2, 3)), np.ones((2, 3)), tmin=[0.0, np.nan])
    with pytest.raises(ValueError, match=r"1 rays have tmin > tmax, first at ray \[1\]"):
        prepare_rays(np.zeros((2, 3)), np.ones((2, 3)), tmin=[0.0, 2.0], tmax=1.0)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e39])
def test_nan_or_infinite_vertices_raise_a_value_error_naming_the_vertex(bad):
    v = np.zeros((5, 3))
    v[1:4, 0] = [1, 0, 1]
    v[3, 2] = bad
    with pytest.raises(ValueError, match=r"1 of 5 vertices are NaN or infinite.*\[3\]"):
        core.TriangleMesh(v, [[0, 1, 2]])


def test_kernel_t_hi_only_narrows_the_interval():
    tv = np.array([[[-1, -1, 1], [2, -1, 1], [-1, 2, 1]]], np.float32)
    rays = prepare_rays(np.zeros((3, 3)), np.tile([0, 0, 1.0], (3, 1)), tmax=[np.inf, 0.5, np.inf])
    z = np.zeros(3, np.intp)
    t = intersect(rays, np.arange(3), z, tv, t_hi=np.array([np.inf, np.inf, 0.9], np.float32))
    assert t.tolist() == [1.0, np.inf, np.inf], f"t {t.tolist()}: tmax and t_hi must both bound the hit"


def test_nearest_hit_reduction_orders_by_t_then_index_including_negative_t():
    nh = NearestHits(3)
    ray = np.array([0, 0, 1, 1, 2, 2, 2])
    tri = np.array([5, 2, 7, 3, 9, 4, 6])
    t = np.array([2.0, 2.0, -1.0, 0.5, np.inf, -3.0, -3.0], np.float32)
    nh.update(ray, tri, t)
    assert nh.triangle().tolist() == [2, 7, 4], nh.triangle().tolist()
    assert nh.t().tolist() == [2.0, -1.0, -3.0]


def test_occluded_agrees_with_trace_hit():
    rng = np.random.default_rng(3)
    v = rng.uniform(-1, 1, (60, 3))
    m = core.TriangleMesh(v, rng.integers(0, 60, (40, 3)))
    acc = core.build(m, "brute")
    o, d = core.uniform_rays(m, 500, seed=4)
    tmax = rng.uniform(0.1, 3, 500)
    h = acc.trace(o, d, tmax=tmax)
    occ = acc.occluded(o, d, tmax=tmax)
    w = np.flatnonzero(occ != h.hit)
    assert w.size == 0, f"{w.size} rays: occluded != trace().hit, first {describe_ray(w[0], o, d)}: occluded {occ[w[0]]}, trace triangle {h.triangle[w[0]]}"


def test_mesh_bounds_are_those_of_the_used_vertices_and_a_caller_cannot_change_them():
    # vertex 3 is used by no triangle, so it must not widen the box
    v = np.array([[0, 0, 0], [1, 2, 0], [0, 1, 3], [-9, 9, 9]], np.float32)
    mesh = core.TriangleMesh(v, np.array([[0, 1, 2]]))
    lo, hi = mesh.bounds()
    assert lo.tolist() == [0, 0, 0] and hi.tolist() == [1, 2, 3]
    lo[:] = 100  # bounds are computed once; what a caller does with its copy stays its own
    assert mesh.bounds()[0].tolist() == [0, 0, 0]
    empty = core.TriangleMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    assert [b.tolist() for b in empty.bounds()] == [[0, 0, 0], [0, 0, 0]]
