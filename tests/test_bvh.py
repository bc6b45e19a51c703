"""BVH-specific properties: the tree holds every valid triangle once, its boxes nest, and its
traversal reproduces brute force hit for hit (same kernel, same tie rule).

Cross-structure agreement against the float64 reference and the shared hard cases live in
test_agreement.py and test_hard_cases.py; here the BVH is compared with ``core.build(mesh,
'brute')``, which must give bit-identical t, triangle, u and v.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from hybrid_raycast import core
from hybrid_raycast.core.bvh import BUILDERS, WIDTH

#: every builder, plus classic HLBVH (Karras splits inside the grid cells)
CONFIGS = {b: {"builder": b} for b in BUILDERS} | {"hlbvh-karras": {"builder": "hlbvh", "sah_min": 1 << 30}}

# -- scenes ---------------------------------------------------------------------------------


def _mesh(tri_vertices) -> core.TriangleMesh:
    tv = np.asarray(tri_vertices, np.float64).reshape(-1, 3, 3)
    return core.TriangleMesh(tv.reshape(-1, 3), np.arange(3 * len(tv)).reshape(-1, 3))


def _soup(n=1500, seed=1):
    """Random triangles of random sizes, with a few degenerate ones mixed in."""
    rng = np.random.default_rng(seed)
    tv = rng.random((n, 1, 3)) + rng.choice([0.01, 0.05, 0.3], (n, 1, 1)) * rng.standard_normal((n, 3, 3))
    tv[::97, 2] = tv[::97, 1]  # two equal corners: zero area
    tv[5::131] = tv[5::131, :1]  # a point
    return _mesh(tv)


def _sphere(n=16):
    """Closed UV sphere; the pole quads yield degenerate triangles."""
    th = np.linspace(0, np.pi, n + 1)
    ph = np.linspace(0, 2 * np.pi, 2 * n + 1)
    p = np.stack(
        [np.outer(np.sin(th), np.cos(ph)), np.outer(np.sin(th), np.sin(ph)), np.outer(np.cos(th), np.ones_like(ph))], -1
    )
    a, b, c, d = p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]
    return _mesh(np.stack([np.stack([a, b, c], -2), np.stack([a, c, d], -2)], 2).reshape(-1, 3, 3))


def _grid(n=8, axis=2, level=0.0):
    """Flat n x n grid of unit quads (two triangles each) in the plane ``axis == level``."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    q = np.stack([np.stack([i, j], -1), np.stack([i + 1, j], -1), np.stack([i + 1, j + 1], -1), np.stack([i, j + 1], -1)], 2)
    q = q.reshape(-1, 4, 2).astype(np.float64)
    tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    other = [k for k in range(3) if k != axis]
    tv = np.full(tri.shape[:2] + (3,), level)
    tv[..., other[0]], tv[..., other[1]] = tri[..., 0], tri[..., 1]
    return tv


def _flat():
    return _mesh(_grid(8))


def _cube():
    """Surface of a 4x4x4 cube made of axis-aligned grids: boxes with zero extent everywhere."""
    return _mesh(np.concatenate([_grid(4, axis, level) for axis in range(3) for level in (0.0, 4.0)]))


def _identical():
    """Every triangle of a small sphere three times over: ties everywhere."""
    return _mesh(np.repeat(_sphere(6).tri_vertices, 3, axis=0))


def _stacked():
    """1100 copies of one triangle: every centroid coincides (median splits, sampled SAH)."""
    return _mesh(np.repeat([[[0, 0, 0], [1, 0, 0.5], [0, 1, 1]]], 1100, axis=0))


SCENES = {"soup": _soup, "sphere": _sphere, "flat": _flat, "cube": _cube, "identical": _identical, "stacked": _stacked}


@functools.lru_cache(maxsize=None)
def scene(name) -> core.TriangleMesh:
    return SCENES[name]()


@functools.lru_cache(maxsize=None)
def rays(name, seed=3):
    """Uniform rays in the scene box plus axis-parallel rays on the grid planes (+-0.0
    components, origins on box faces), with random tmin/tmax on a third of them."""
    mesh = scene(name)
    m = 100 if name == "stacked" else 1200  # there every ray visits every leaf
    rng = np.random.default_rng(seed)
    o, d = core.uniform_rays(mesh, m, seed=seed)
    lo, hi = mesh.bounds()
    k = m // 2
    o[:k] = np.round(rng.uniform(lo - 1, hi + 1, (k, 3)) * 2) / 2  # on planes and edges of cells
    d[:k] = 0.0
    d[np.arange(k), rng.integers(0, 3, k)] = rng.choice([-1.0, 1.0], k)
    d[:k] = np.where((d[:k] == 0) & (rng.random((k, 3)) < 0.5), -0.0, d[:k])
    tmin = np.where(rng.random(m) < 0.3, rng.uniform(0, 2, m), 0.0)
    tmax = np.where(rng.random(m) < 0.3, tmin + rng.uniform(0, 3, m), np.inf)
    return o, d, tmin, tmax


@functools.lru_cache(maxsize=None)
def brute(name):
    o, d, tmin, tmax = rays(name)
    acc = core.build(scene(name), "brute")
    return acc.trace(o, d, tmin, tmax), acc.occluded(o, d, tmin, tmax)


# -- structure ------------------------------------------------------------------------------


def _leaf_codes(bvh):
    """(node, slot, leaf) of every leaf child and (node, slot, child) of every inner child."""
    used = ~np.isnan(bvh.node_boxes.reshape(-1, 6, WIDTH)).all(axis=1)
    node, slot = np.nonzero(used)
    code = bvh.node_children[node, slot]
    leaf = code < 0
    return (node[leaf], slot[leaf], ~code[leaf]), (node[~leaf], slot[~leaf], code[~leaf]), used


@pytest.mark.parametrize("config", list(CONFIGS))
@pytest.mark.parametrize("name", ["soup", "sphere", "flat", "identical", "stacked"])
def test_every_valid_triangle_is_in_exactly_one_leaf_and_no_degenerate_one_is(config, name):
    mesh = scene(name)
    bvh = core.build(mesh, "bvh", **CONFIGS[config])
    (_, _, leaves), (_, _, inner), _ = _leaf_codes(bvh)
    n_leaves = len(bvh.leaf_count)
    refs = np.bincount(leaves, minlength=n_leaves)
    assert (refs == 1).all(), f"leaves referenced other than once by the nodes: {np.flatnonzero(refs != 1)[:5]}"
    wide_refs = np.bincount(inner, minlength=len(bvh.node_boxes))
    assert wide_refs[0] == 0 and (wide_refs[1:] == 1).all(), (
        f"wide nodes not referenced exactly once (root never): {np.flatnonzero(wide_refs[1:] != 1)[:5] + 1}"
    )
    assert (bvh.leaf_count >= 1).all() and (bvh.leaf_count <= bvh.leaf_size).all(), (
        f"leaf sizes outside 1..{bvh.leaf_size}: {np.unique(bvh.leaf_count)}"
    )
    tris = np.concatenate([bvh.leaf_triangles[s : s + c] for s, c in zip(bvh.leaf_start, bvh.leaf_count)])
    times = np.bincount(tris, minlength=mesh.triangle_count)
    missing = np.flatnonzero(mesh.valid & (times != 1))
    degenerate = np.flatnonzero(~mesh.valid & (times != 0))
    assert not len(missing), f"{len(missing)} valid triangles not in exactly one leaf, first {missing[:5]} ({times[missing[:5]]} times)"
    assert not len(degenerate), f"degenerate triangles in leaves: {degenerate[:5]}"


@pytest.mark.parametrize("config", list(CONFIGS))
@pytest.mark.parametrize("name", ["soup", "sphere", "cube"])
def test_every_node_box_contains_its_childrens_boxes_and_its_triangles(config, name):
    mesh = scene(name)
    bvh = core.build(mesh, "bvh", **CONFIGS[config], leaf_size=3)
    box = bvh.node_boxes.reshape(-1, 2, 3, WIDTH)  # node, lo/hi, axis, slot
    (ln, ls, leaf), (inn, ins, child), used = _leaf_codes(bvh)
    assert np.isnan(box.transpose(0, 3, 1, 2)[~used]).all(), "an empty child slot has a box that is not all NaN"
    assert not np.isnan(box.transpose(0, 3, 1, 2)[used]).any(), "a used child slot has NaN in its box"
    # inner child: the parent's box for it contains every box the child stores
    parent_lo, parent_hi = box[inn, 0, :, ins], box[inn, 1, :, ins]
    kid_lo = np.where(used[child][:, None, :], box[child, 0], np.inf).min(axis=2)
    kid_hi = np.where(used[child][:, None, :], box[child, 1], -np.inf).max(axis=2)
    bad = np.flatnonzero(((kid_lo < parent_lo) | (kid_hi > parent_hi)).any(axis=1))
    assert not len(bad), (
        f"{len(bad)} inner children stick out of their box, first node {inn[bad[0]]} slot {ins[bad[0]]}: "
        f"box {parent_lo[bad[0]]}..{parent_hi[bad[0]]}, children {kid_lo[bad[0]]}..{kid_hi[bad[0]]}"
    )
    # leaf child: its box contains every corner of its triangles
    lo, hi = box[ln, 0, :, ls], box[ln, 1, :, ls]
    for i in range(len(leaf)):
        s, c = bvh.leaf_start[leaf[i]], bvh.leaf_count[leaf[i]]
        corners = mesh.tri_vertices[bvh.leaf_triangles[s : s + c]].reshape(-1, 3)
        assert ((corners >= lo[i]) & (corners <= hi[i])).all(), (
            f"leaf {leaf[i]} (node {ln[i]} slot {ls[i]}) box {lo[i]}..{hi[i]} misses corners of its triangles {corners}"
        )


# -- traversal == brute force ---------------------------------------------------------------


def _assert_same_hits(got, want, what):
    for field in ("triangle", "t", "u", "v"):
        a, b = getattr(got, field), getattr(want, field)
        bad = np.flatnonzero(a != b)
        assert not len(bad), (
            f"{what}: {len(bad)} rays differ in {field} from brute force, first ray {bad[0]}: "
            f"bvh triangle {got.triangle[bad[0]]} t {got.t[bad[0]]!r}, brute triangle {want.triangle[bad[0]]} t {want.t[bad[0]]!r}"
        )


@pytest.mark.parametrize("config", list(CONFIGS))
@pytest.mark.parametrize("name", list(SCENES))
def test_bvh_returns_exactly_the_brute_force_hits_and_occlusion(config, name):
    o, d, tmin, tmax = rays(name)
    want, want_occ = brute(name)
    # a tiny lockstep batch exercises compaction and refill; leaf sizes vary the tree
    for leaf_size, batch in ((4, 8192), (1, 7), (6, 64)):
        bvh = core.build(scene(name), "bvh", **CONFIGS[config], leaf_size=leaf_size, batch=batch)
        what = f"{name}, {config}, leaf_size {leaf_size}, batch {batch}"
        _assert_same_hits(bvh.trace(o, d, tmin, tmax), want, what)
        occ = bvh.occluded(o, d, tmin, tmax)
        bad = np.flatnonzero(occ != want_occ)
        assert not len(bad), f"{what}: occluded differs from brute force on {len(bad)} rays, first {bad[:5]} (bvh says {occ[bad[:5]]})"


@pytest.mark.parametrize("name", ["soup", "flat"])
def test_pools_of_many_transpose_blocks_return_the_brute_force_hits(name, monkeypatch):
    """The traversal transposes the gathered node boxes in blocks of rays; blocks of 7 over
    a pool of 1,200 rays end in a partial block, and every block must land in its columns."""
    from hybrid_raycast.core import bvh as bvh_module

    monkeypatch.setattr(bvh_module, "_TRANSPOSE_BLOCK", 7)
    o, d, tmin, tmax = rays(name)
    want, want_occ = brute(name)
    bvh = core.build(scene(name), "bvh")
    _assert_same_hits(bvh.trace(o, d, tmin, tmax), want, f"{name}, transpose blocks of 7")
    assert np.array_equal(bvh.occluded(o, d, tmin, tmax), want_occ), f"{name}: occluded differs with blocks of 7"


def test_ties_between_identical_triangles_go_to_the_lowest_index():
    mesh = scene("identical")  # triangle 3k, 3k+1, 3k+2 are the same
    o = np.random.default_rng(0).normal(0, 0.05, (500, 3))
    d = np.random.default_rng(1).normal(0, 1, (500, 3))
    h = core.build(mesh, "bvh").trace(o, d)
    assert h.hit.all(), f"rays from inside a closed sphere escaped: {np.flatnonzero(~h.hit)[:5]}"
    bad = np.flatnonzero(h.triangle % 3 != 0)
    assert not len(bad), f"ties not resolved to the lowest index on rays {bad[:5]}: triangles {h.triangle[bad[:5]]}"


def test_rays_with_negative_tmin_match_brute_force():
    mesh = scene("sphere")
    rng = np.random.default_rng(4)
    o, d = rng.normal(0, 0.1, (600, 3)), rng.normal(0, 1, (600, 3))
    want = core.build(mesh, "brute").trace(o, d, tmin=-2.0, tmax=0.5)
    _assert_same_hits(core.build(mesh, "bvh").trace(o, d, tmin=-2.0, tmax=0.5), want, "negative tmin")


def test_more_rays_than_a_chunk_on_several_threads_match_one_thread():
    mesh = scene("soup")
    o, d = core.uniform_rays(mesh, 5000, seed=9)
    one = core.build(mesh, "bvh", threads=1).trace(o, d)
    many = core.build(mesh, "bvh", threads=3, chunk_size=700, batch=256).trace(o, d)
    _assert_same_hits(many, one, "3 threads, chunks of 700")


def test_any_hit_with_finished_rays_replaced_in_the_pool_matches_brute_force():
    # batch=64 of chunks of ~1700 rays: finished rays' slots (any hit ends a ray early,
    # its stack not empty) are refilled in place many times
    mesh = scene("soup")
    o, d = core.uniform_rays(mesh, 5000, seed=10)
    got = core.build(mesh, "bvh", threads=3, chunk_size=1700, batch=64).occluded(o, d, 0.0, 0.5)
    want = core.build(mesh, "brute").occluded(o, d, 0.0, 0.5)
    w = np.flatnonzero(got != want)
    assert 0.1 < want.mean() < 0.9, f"set-up: {want.mean():.2f} of the rays are occluded"
    assert w.size == 0, f"occluded differs on {w.size} rays, first {w[0] if w.size else None}: bvh {got[w[:1]]}"


# -- small and empty meshes -----------------------------------------------------------------


def test_one_triangle_mesh_is_hit_exactly_like_brute_force():
    mesh = _mesh([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    rng = np.random.default_rng(2)
    o = np.concatenate([rng.uniform(-1, 2, (300, 3)), [[0.25, 0.25, 1], [0, 0, 1], [0.5, 0.5, -1], [-1, 0, 0]]])
    d = np.concatenate([rng.normal(0, 1, (300, 3)), [[0, 0, -1], [-0.0, 0.0, -1], [0, -0.0, 1], [1, -0.0, 0.0]]])
    bvh = core.build(mesh, "bvh")
    want = core.build(mesh, "brute").trace(o, d)
    _assert_same_hits(bvh.trace(o, d), want, "one triangle")
    assert want.hit[-4:-1].all(), "the hand-made rays at the triangle should hit it"
    assert (bvh.occluded(o, d) == want.hit).all()
    s = bvh.stats()
    assert s["nodes"] == 1 and s["leaves"] == 1 and s["depth"] == 1, s
    # the root's three empty (NaN) slots are never entered: at most one leaf per ray
    assert s["leaves_per_ray"] <= 1.0 and s["nodes_per_ray"] == 1.0, s


@pytest.mark.parametrize("tri", [np.zeros((0, 3, 3)), np.array([[[0, 0, 0], [1, 1, 1], [2, 2, 2]]])], ids=["empty", "degenerate"])
def test_meshes_without_a_valid_triangle_never_hit(tri):
    mesh = _mesh(tri) if len(tri) else core.TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    bvh = core.build(mesh, "bvh")
    o, d = np.zeros((5, 3)), np.eye(3)[[0, 1, 2, 0, 1]]
    h = bvh.trace(o, d)
    assert not h.hit.any() and np.isinf(h.t).all(), f"hits in a mesh without valid triangles: {h}"
    assert not bvh.occluded(o, d).any()
    assert bvh.stats()["nodes"] == 0


# -- config and stats -----------------------------------------------------------------------


def test_unknown_builder_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown BVH builder 'octree'"):
        core.build(scene("soup"), "bvh", builder="octree")


def test_stats_describe_the_tree_and_the_last_trace():
    mesh = scene("soup")
    bvh = core.build(mesh, "bvh", leaf_size=4)
    s = bvh.stats()
    assert s["kind"] == "bvh" and s["triangles"] == mesh.triangle_count
    assert s["nodes"] == len(bvh.node_boxes) and s["leaves"] == len(bvh.leaf_count)
    assert sum(s["leaf_histogram"].values()) == s["leaves"], s["leaf_histogram"]
    assert sum(k * v for k, v in s["leaf_histogram"].items()) == int(mesh.valid.sum())
    assert 1 <= s["depth"] < 20 and s["memory_bytes"] > 0
    assert "nodes_per_ray" not in s, "counters before any trace"
    o, d = core.uniform_rays(mesh, 400, seed=1)
    bvh.trace(o, d)
    s = bvh.stats()
    assert s["last_rays"] == 400 and s["nodes_per_ray"] >= 1 and s["triangles_per_ray"] >= s["leaves_per_ray"] > 0, s


# -- the build's reused work arrays ------------------------------------------------------------


def test_segments_in_reused_buffers_equal_freshly_allocated_ones():
    from hybrid_raycast.core.bvh import _Scratch, _segments

    rng = np.random.default_rng(3)
    ws = _Scratch(5000)
    for k in (1, 7, 300):
        count = rng.integers(1, 12, k)
        start = np.cumsum(rng.integers(0, 5, k)) + np.concatenate([[0], np.cumsum(count)[:-1]])
        ref = _segments(start, count)
        got = _segments(start, count, ws)
        for a, b in zip(ref, got):
            np.testing.assert_array_equal(a, b)
    # a zero count (no split makes one) falls back to np.repeat, still correct
    count, start = np.array([2, 0, 3]), np.array([0, 2, 2])
    for a, b in zip(_segments(start, count), _segments(start, count, ws)):
        np.testing.assert_array_equal(a, b)


def test_sah_splits_sharing_one_scratch_equal_splits_each_with_its_own():
    """Levels of different sizes, sampled (nodes over SAH_SAMPLE) and not, reuse buffers a
    larger level left behind: the partitions must be those of fresh buffers."""
    from hybrid_raycast.core.bvh import _Scratch, _split_sah

    rng = np.random.default_rng(5)
    n = 6000
    cen = rng.random((n, 3)).astype(np.float32)
    soa = np.ascontiguousarray(np.concatenate([cen, cen - 0.01, cen + 0.01], axis=1).T)
    shared = _Scratch(n)
    levels = [(np.array([0]), np.array([n])),  # one node binned from a sample
              (np.array([0, 2500]), np.array([2500, 3500])),  # sampled, two nodes
              (np.arange(0, n, 600), np.full(10, 600)),  # every item binned
              (np.arange(0, 300, 30), np.full(10, 30))]  # a small level after large ones
    for start, count in levels:
        a, b = np.arange(n), np.arange(n)
        mid_a = _split_sah(a, soa, start, count, 16)
        mid_b = _split_sah(b, soa, start, count, 16, scratch=shared)
        np.testing.assert_array_equal(mid_a, mid_b)
        np.testing.assert_array_equal(a, b)
        assert ((mid_b > start) & (mid_b < start + count)).all()
        for s, c, m in zip(start, count, mid_b):  # a stable partition inside each node
            np.testing.assert_array_equal(np.sort(b[s:s + c]), np.arange(s, s + c))
            assert (np.diff(b[s:m]) > 0).all() and (np.diff(b[m:s + c]) > 0).all()
