"""core.TwoLevel (instances of bottom-level structures) against a flat world-space soup.

The reference for every scene is the flat soup of all instances' triangles, transformed
in float64 and rounded to float32 (as Blender's world-space extraction would), traced by
brute force; tests/reference.py's independent float64 tracer marks the ambiguous rays
(grazing an edge or vertex within float32 noise of the scene's scale, near ties, in a
triangle's plane, a hit at tmin or tmax).  The two answers are float32 computations in
different frames (object space vs world space), so on those rays either may be right.
"""

from functools import lru_cache

import reference

import numpy as np
import pytest

from hybrid_raycast import core
from hybrid_raycast.core import twolevel
from hybrid_raycast.core.twolevel import InstanceHits, TwoLevel
from reference import cube, describe_ray, icosphere, kind_params, reference_for_mesh

ALL_KINDS = ("grid", "bvh", "brute", "embree")
KINDS = kind_params(ALL_KINDS)
NUMPY_KINDS = kind_params(("grid", "bvh", "brute"))
FAR = np.array([1e5, -1e5, 0.5e5])  # the far-from-origin placement
T_RTOL = 1e-5  # relative to the ray's scale |t| + |o| / |d| (float32 rounding of either frame)
MAX_AMBIGUOUS = 0.25  # share of the rays not aimed at a vertex the reference may call ambiguous
#: grazing distance, relative to the coordinate scale, that makes a ray ambiguous here:
#: 8 float32 ulps (the flat soup's vertices are rounded at that scale, the instance's
#: ray in its own frame).  tests/reference.py's 1e-5 would call every ray of an instance
#: 1e5 from the origin ambiguous (1 world unit, more than the instances' size).
GRAZE_EPS = 2.0**-21


# -- scenes ---------------------------------------------------------------------------------

@lru_cache(maxsize=None)
def object_meshes():
    """Three small object-space meshes: a closed icosphere, a closed box, a random soup."""
    v1, t1 = icosphere(1)
    v2, t2 = cube((-0.5, -0.7, -0.3), (0.6, 0.4, 0.9))
    # a soup of triangles not much smaller than the instance: tiny ones placed 1e5 from the
    # origin collapse when the flat soup rounds their world vertices to float32
    rng = np.random.default_rng(3)
    v3 = (rng.uniform(-1.0, 1.0, (30, 1, 3)) + 0.5 * rng.standard_normal((30, 3, 3))).reshape(-1, 3)
    t3 = np.arange(90).reshape(30, 3)
    return tuple(core.TriangleMesh(v, t) for v, t in ((v1, t1), (v2, t2), (v3, t3)))


def rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else q[:, ::-1]


def affine(a, b):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = a, b
    return m


def scene_matrices(n, rng):
    """n object-to-world matrices: rotations and non-uniform scales everywhere, and
    among them a mirror, a shear and a placement far from the origin (all in one when n = 1)."""
    out = []
    for i in range(n):
        a = rotation(rng) @ np.diag(rng.uniform(0.4, 1.8, 3))
        feature = i % 5 if n > 1 else -1
        if feature in (1, -1):  # mirror
            a = a @ np.diag([1.0, -1.0, 1.0])
        if feature in (2, -1):  # shear
            a = a @ np.array([[1.0, 0.6, 0.0], [0.0, 1.0, -0.4], [0.0, 0.0, 1.0]])
        spread = 4.0 * max(1.0, n ** (1 / 3))
        b = rng.uniform(-spread, spread, 3)
        if feature in (3, -1):  # far from the origin, and larger: float32 world vertices there
            a = 8.0 * a  # are 1/128 apart, so small triangles would be mostly edge
            b = FAR + rng.uniform(-4 * spread, 4 * spread, 3)
        out.append(affine(a, b))
    return np.array(out)


def flatten(meshes, instance_bottom, matrices):
    """The flat world-space soup (vertices through M in float64, then float32), triangles
    in global order (instance by instance), written here independently of TwoLevel."""
    verts, tris, nv = [], [], 0
    for i, k in enumerate(instance_bottom):
        m = meshes[k]
        w = np.c_[m.vertices.astype(np.float64), np.ones(len(m.vertices))] @ matrices[i].T
        verts.append(w[:, :3])
        tris.append(m.triangles + nv)
        nv += len(m.vertices)
    return core.TriangleMesh(np.vstack(verts).astype(np.float32), np.vstack(tris))


def aimed_rays(meshes, instance_bottom, matrices, m, rng):
    """Rays from a few instance sizes away aimed into random instances (a fifth of them at
    an object vertex: grazing on purpose), with a band of per-ray tmin and tmax."""
    inst = rng.integers(0, len(matrices), m)
    lo = np.array([meshes[k].bounds()[0] for k in instance_bottom], np.float64)[inst]
    hi = np.array([meshes[k].bounds()[1] for k in instance_bottom], np.float64)[inst]
    p = lo + rng.random((m, 3)) * (hi - lo)
    at_vertex = rng.random(m) < 0.2
    for j in np.flatnonzero(at_vertex):
        verts = meshes[instance_bottom[inst[j]]].vertices
        p[j] = verts[rng.integers(len(verts))]
    target = np.einsum("mij,mj->mi", matrices[inst, :3, :3], p) + matrices[inst, :3, 3]
    size = np.linalg.norm(np.einsum("mij,mj->mi", matrices[inst, :3, :3], hi - lo), axis=1)
    away = rng.standard_normal((m, 3))
    away *= (size * rng.uniform(1.0, 4.0, m) / np.linalg.norm(away, axis=1))[:, None]
    o = (target + away).astype(np.float32)
    d = ((target - o.astype(np.float64)) * rng.uniform(0.3, 3.0, m)[:, None]).astype(np.float32)
    tmin = np.where(rng.random(m) < 0.2, rng.uniform(0.0, 0.5, m), 0.0)
    tmax = np.where(rng.random(m) < 0.2, tmin + rng.uniform(0.1, 1.5, m), np.inf)
    return (o, d, tmin, tmax), at_vertex


SCENE_SIZES = (1, 5, 300)
RAYS = {1: 500, 5: 800, 300: 1200}


@lru_cache(maxsize=None)
def random_scene(n):
    """(instance_bottom, matrices, rays, flat brute hits, float64 reference) for n instances."""
    rng = np.random.default_rng(100 + n)
    meshes = object_meshes()
    ib = rng.integers(0, len(meshes), n) if n > 1 else np.array([0])
    matrices = scene_matrices(n, rng)
    rays, at_vertex = aimed_rays(meshes, ib, matrices, RAYS[n], rng)
    flat = flatten(meshes, ib, matrices)
    brute = core.build(flat, "brute").trace(*rays)
    # the float64 reference, with this file's graze distance and one more kind of graze
    saved, reference.GRAZE_EPS = reference.GRAZE_EPS, GRAZE_EPS
    try:
        ref = reference_for_mesh(flat, *rays)
    finally:
        reference.GRAZE_EPS = saved
    ref.ambiguous |= hit_near_its_own_edge(flat, rays, ref)
    ref.at_vertex = at_vertex
    return ib, matrices, rays, flat, brute, ref


def hit_near_its_own_edge(flat, rays, ref):
    """(M,) bool: the reference hit lies within GRAZE_EPS of the coordinate scale of an
    edge of its own triangle.  tests/reference.py flags a graze only at or before the hit,
    but a ray through a vertex passes the vertex a hair after its hit point."""
    o, d = (np.asarray(a, np.float32).astype(np.float64) for a in rays[:2])
    out = np.zeros(len(o), bool)
    h = np.flatnonzero(ref.hit)
    p = o[h] + ref.t[h, None] * d[h]
    tv = flat.tri_vertices[ref.triangle[h]].astype(np.float64)
    dist = np.full(len(h), np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        e = tv[:, b] - tv[:, a]
        s = np.clip(((p - tv[:, a]) * e).sum(axis=1) / (e * e).sum(axis=1), 0.0, 1.0)
        dist = np.minimum(dist, np.linalg.norm(p - tv[:, a] - s[:, None] * e, axis=1))
    scale = np.maximum(np.abs(tv).max(axis=(1, 2)), np.abs(o[h]).max(axis=1))
    out[h] = dist <= GRAZE_EPS * scale
    return out
    return ib, matrices, rays, flat, brute, ref


@lru_cache(maxsize=None)
def bottoms_of(kind):
    return tuple(core.build(m, kind) for m in object_meshes())


def where(i, rays):
    o, d, tmin, tmax = rays
    return f"{describe_ray(i, o, d)} tmin={float(np.asarray(tmin)[i])} tmax={float(np.asarray(tmax)[i])}"


# -- agreement with the flat soup --------------------------------------------------------------

@pytest.mark.parametrize("n", SCENE_SIZES)
@pytest.mark.parametrize("kind", KINDS)
def test_two_level_matches_flat_world_soup_on_unambiguous_rays(kind, n):
    ib, matrices, rays, flat, brute, ref = random_scene(n)
    o, d, tmin, tmax = rays
    tl = TwoLevel(bottoms_of(kind), ib, matrices)
    h = tl.trace(*rays)
    assert isinstance(h, InstanceHits) and h.triangle.dtype == np.int32
    assert not (np.isnan(h.t).any() or np.isnan(h.u).any() or np.isnan(h.v).any()), f"{kind}, {n} instances: NaN in the hits"
    amb = ref.ambiguous
    # rays aimed at vertices graze by design; of the others, those through the random soup's
    # intersections (near ties) and past edges within float32 noise, which at 1e5 from the
    # origin is some 0.05 world units: a bounded share, or the comparison says too little
    other = amb[~ref.at_vertex].mean()
    assert other <= MAX_AMBIGUOUS, (f"{n} instances: {amb[~ref.at_vertex].sum()} of {(~ref.at_vertex).sum()} rays not "
                                    f"aimed at a vertex are ambiguous (bound {MAX_AMBIGUOUS:.0%})")
    for what, got, exp in (("hit/miss", h.hit, brute.hit), ("hit/miss vs float64", h.hit, ref.hit),
                           ("global triangle", h.triangle, brute.triangle)):
        bad = np.flatnonzero((got != exp) & ~amb)
        if bad.size:
            i = bad[0]
            pytest.fail(f"{kind}, {n} instances: {what} differs from the flat soup on {bad.size} of {(~amb).sum()} "
                        f"unambiguous rays; first {where(i, rays)}: flat triangle {brute.triangle[i]} t={brute.t[i]!r} "
                        f"(float64 {ref.t[i]!r}), two-level triangle {h.triangle[i]} (instance {h.instance[i]}, local "
                        f"{h.local_triangle[i]}) t={h.t[i]!r}")
    both = h.hit & (h.triangle == ref.triangle) & ~amb
    scale = np.abs(ref.t[both]) + np.abs(o[both]).max(axis=1) / np.abs(d[both]).max(axis=1)
    err = np.abs(h.t[both] - ref.t[both]) / scale
    if err.size and err.max() > T_RTOL:
        i = np.flatnonzero(both)[np.argmax(err)]
        pytest.fail(f"{kind}, {n} instances: t off by {err.max():.3g} of the ray's scale (bound {T_RTOL}) on "
                    f"{where(i, rays)}: float64 t={ref.t[i]!r}, two-level t={h.t[i]!r}")
    # barycentrics: float32 rounding of the far placement's world vertices moves them by
    # up to an ulp of 1e5 over the triangle's size
    tv = flat.tri_vertices[ref.triangle[both]].astype(np.float64)
    edge = np.linalg.norm(tv - np.roll(tv, 1, axis=1), axis=2).min(axis=1)
    uv_tol = 1e-4 + 1e-5 * np.abs(tv).max(axis=(1, 2)) / edge
    uv_err = np.maximum(np.abs(h.u[both] - ref.u[both]), np.abs(h.v[both] - ref.v[both]))
    if uv_err.size and (uv_err > uv_tol).any():
        k = np.argmax(uv_err / uv_tol)
        i = np.flatnonzero(both)[k]
        pytest.fail(f"{kind}, {n} instances: barycentrics off by {uv_err[k]:.3g} (bound {uv_tol[k]:.3g}) on "
                    f"{where(i, rays)}: float64 u, v = {ref.u[i]:.7g}, {ref.v[i]:.7g}; two-level {h.u[i]}, {h.v[i]}")
    # the per-hit fields agree with each other and the hit respects the ray's interval
    hit = h.hit
    assert np.array_equal(h.triangle[hit], tl.tri_base[h.instance[hit]] + h.local_triangle[hit])
    counts = np.array([m.triangle_count for m in object_meshes()])
    assert (h.local_triangle[hit] < counts[ib[h.instance[hit]]]).all(), "a local triangle outside its instance's mesh"
    lo = np.broadcast_to(np.asarray(tmin, np.float32), h.t.shape)
    hi = np.broadcast_to(np.asarray(tmax, np.float32), h.t.shape)
    out = np.flatnonzero(hit & ((h.t <= lo) | (h.t > hi)))
    assert out.size == 0, f"{kind}: hit outside (tmin, tmax] on {out.size} rays; first {where(out[0], rays)} t={h.t[out[0]]}"
    assert (h.instance[~hit] == -1).all() and (h.local_triangle[~hit] == -1).all() and np.isinf(h.t[~hit]).all()


@pytest.mark.parametrize("n", SCENE_SIZES)
@pytest.mark.parametrize("kind", KINDS)
def test_occluded_equals_trace_hit(kind, n):
    ib, matrices, rays, *_ = random_scene(n)
    tl = TwoLevel(bottoms_of(kind), ib, matrices)
    hit, occ = tl.trace(*rays).hit, tl.occluded(*rays)
    bad = np.flatnonzero(hit != occ)
    assert bad.size == 0, (f"{kind}, {n} instances: occluded differs from trace().hit on {bad.size} rays; first "
                           f"{where(bad[0], rays)}: hit={hit[bad[0]]}, occluded={occ[bad[0]]}")


@pytest.mark.parametrize("kind, n", [(k, 5) for k in ("grid", "bvh", "brute")] + [("bvh", 300)])
def test_instance_loop_and_top_level_tree_give_identical_hits(kind, n):
    """Both ways of visiting instances hand each bottom bit-identical object-space rays,
    so they agree exactly, ties included; a tiny pair budget (chunks split) changes nothing."""
    ib, matrices, rays, *_ = random_scene(n)
    bottoms = bottoms_of(kind)
    loop = TwoLevel(bottoms, ib, matrices, pairs_from=10**9)
    tree = TwoLevel(bottoms, ib, matrices, pairs_from=0)
    split = TwoLevel(bottoms, ib, matrices, pairs_from=0, pair_limit=256, ray_chunk=500)
    assert loop.stats()["top_level"] == "loop" and tree.stats()["top_level"] == "tree"
    a = loop.trace(*rays)
    for name, tl in (("tree", tree), ("tree, split chunks", split)):
        b = tl.trace(*rays)
        for field in ("t", "triangle", "instance", "local_triangle", "u", "v"):
            bad = np.flatnonzero(getattr(a, field) != getattr(b, field))
            assert bad.size == 0, (f"{kind}, {n} instances: {field} differs between the loop and the {name} on "
                                   f"{bad.size} rays; first {where(bad[0], rays)}: {getattr(a, field)[bad[0]]} vs "
                                   f"{getattr(b, field)[bad[0]]}")
        occ = tl.occluded(*rays)
        assert np.array_equal(occ, a.hit), f"{kind}: occluded on the {name} differs from the loop's hits"


# -- watertight -------------------------------------------------------------------------------

@pytest.mark.parametrize("far", (False, True), ids=("near-origin", "offset-1e5"))
@pytest.mark.parametrize("kind", KINDS)
def test_rays_from_inside_a_closed_instance_aimed_at_vertices_and_edges_never_escape(kind, far):
    """An icosphere placed with rotation, non-uniform scale, shear and a mirror (and a box
    overlapping it): rays from its centre aimed exactly at its world vertices, edge midpoints
    and quarter points all hit (the ray is one ray in object space, where the kernel is watertight)."""
    v, t = icosphere(2)
    sphere = core.TriangleMesh(v, t)
    box = core.TriangleMesh(*cube())
    rng = np.random.default_rng(5)
    a = rotation(rng) @ np.diag([1.7, 0.6, 1.1]) @ np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.3], [0.0, 0.0, 1.0]])
    mirrored = a @ np.diag([-1.0, 1.0, 1.0])
    b = FAR if far else np.array([0.25, -1.5, 2.0])
    matrices = np.array([affine(a, b), affine(mirrored, b + 40.0), affine(0.5 * rotation(rng), b + [0.9, 0.0, 0.0])])
    tl = TwoLevel([core.build(sphere, kind), core.build(box, kind)], [0, 0, 1], matrices)
    e = np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)
    v64 = sphere.vertices.astype(np.float64)
    p, q = v64[e[:, 0]], v64[e[:, 1]]
    targets = np.vstack([v64, (p + q) / 2, p + (q - p) / 4, p + 3 * (q - p) / 4])
    for which in (0, 1):  # the plain and the mirrored copy
        m = matrices[which]
        world = targets @ m[:3, :3].T + m[:3, 3]
        origin = m[:3, 3]  # the object's centre, exactly representable
        d = (world - origin).astype(np.float32)
        h = tl.trace(origin, d)
        leak = np.flatnonzero(~h.hit)
        assert leak.size == 0, (f"{kind}: {leak.size} of {len(d)} rays from inside instance {which} escape; first "
                                f"{describe_ray(leak[0], np.broadcast_to(origin, d.shape), d)}")
        occ = tl.occluded(origin, d)
        assert occ.all(), f"{kind}: occluded() lets {(~occ).sum()} rays from inside instance {which} escape"


# -- ties between instances ---------------------------------------------------------------------

@pytest.mark.parametrize("kind", NUMPY_KINDS)
def test_touching_and_overlapping_instances_tie_to_the_lowest_global_triangle(kind):
    """Box 0 at the origin, box 1 sharing its +x face plane (translated by 2 in x), box 2
    exactly on top of box 0: every hit on those planes is an exact tie in t, which goes
    to the lowest global triangle, whichever order tri_base gives the instances."""
    box = core.TriangleMesh(*cube())
    matrices = np.array([affine(np.eye(3), [0.0, 0.0, 0.0]), affine(np.eye(3), [2.0, 0.0, 0.0]),
                         affine(np.eye(3), [0.0, 0.0, 0.0])])
    rng = np.random.default_rng(9)
    yz = rng.uniform(-0.9, 0.9, (200, 2))
    # from inside box 1 towards -x: the shared plane x = 1 at t = 1; from outside box 0's -x face: x = -1
    o = np.vstack([np.c_[np.full(200, 2.0), yz], np.c_[np.full(200, -3.0), yz]]).astype(np.float32)
    d = np.vstack([np.tile([-1.0, 0, 0], (200, 1)), np.tile([1.0, 0, 0], (200, 1))]).astype(np.float32)
    for tri_base in (None, np.array([24, 12, 0]), np.array([0, 24, 12])):
        tl = TwoLevel([core.build(box, kind)], [0, 0, 0], matrices, tri_base)
        h = tl.trace(o, d)
        base = tl.tri_base
        # expected: among the instances whose face lies on the plane hit, the one with the lowest base
        exp_first = np.argmin(base)  # plane x = 1: instances 0, 1, 2 all have a face there
        exp_second = 0 if base[0] < base[2] else 2  # plane x = -1: instances 0 and 2
        for rows, exp, plane in ((slice(0, 200), exp_first, "x = 1"), (slice(200, 400), exp_second, "x = -1")):
            got = h.instance[rows]
            assert (got == exp).all(), (f"{kind}, tri_base {base.tolist()}: on plane {plane} the tie went to instances "
                                        f"{np.unique(got).tolist()}, expected instance {exp} (lowest global triangle)")
            assert np.all(h.t[rows] == (1.0 if plane == "x = 1" else 2.0))
        flat = flatten([box], [0, 0, 0], matrices)
        if tri_base is None:  # the flat soup numbers triangles the same way: the same winners
            hb = core.build(flat, "brute").trace(o, d)
            assert np.array_equal(h.triangle, hb.triangle), f"{kind}: tie winners differ from the flat soup's"


# -- placements, errors and shapes ---------------------------------------------------------------

@pytest.mark.parametrize("kind", NUMPY_KINDS)
def test_with_matrices_equals_a_fresh_two_level(kind):
    ib, matrices, rays, *_ = random_scene(5)
    first = TwoLevel(bottoms_of(kind), ib, matrices)
    moved = scene_matrices(5, np.random.default_rng(77))
    a = first.with_matrices(moved).trace(*rays)
    b = TwoLevel(bottoms_of(kind), ib, moved).trace(*rays)
    for field in ("t", "triangle", "instance", "local_triangle", "u", "v"):
        assert np.array_equal(getattr(a, field), getattr(b, field)), f"{kind}: with_matrices differs in {field}"
    again = first.trace(*rays)  # the original is untouched
    assert np.array_equal(again.triangle, TwoLevel(bottoms_of(kind), ib, matrices).trace(*rays).triangle)


@pytest.mark.parametrize("kind", NUMPY_KINDS)
def test_a_singular_instance_is_never_hit(kind):
    box = core.TriangleMesh(*cube())
    flat_z = affine(np.diag([1.0, 1.0, 0.0]), [0.0, 0.0, 0.0])
    zero = affine(np.zeros((3, 3)), [5.0, 0.0, 0.0])
    visible = affine(np.eye(3), [0.0, 0.0, -5.0])
    tl = TwoLevel([core.build(box, kind)], [0, 0, 0], np.array([flat_z, zero, visible]))
    assert tl.singular.tolist() == [True, True, False]
    o = np.array([[0.1, 0.2, 3.0], [5.0, 0.0, 3.0], [4.0, 0.0, 0.0]], np.float32)
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], np.float32)
    h = tl.trace(o, d)
    assert h.instance.tolist() == [2, -1, -1], f"{kind}: instances hit {h.instance.tolist()}, expected [2, -1, -1]"
    assert tl.occluded(o, d).tolist() == [True, False, False]


def test_nan_or_inf_in_a_matrix_is_an_error_naming_the_instance():
    box = core.TriangleMesh(*cube())
    m = np.tile(np.eye(4), (5, 1, 1))
    m[3, 1, 2] = np.nan
    with pytest.raises(ValueError, match="instance 3"):
        TwoLevel([core.build(box, "bvh")], np.zeros(5, int), m)
    ok = TwoLevel([core.build(box, "bvh")], np.zeros(5, int), np.tile(np.eye(4), (5, 1, 1)))
    m[3, 1, 2] = 0.0
    m[1, 0, 3] = np.inf
    with pytest.raises(ValueError, match="instance 1"):
        ok.with_matrices(m)
    m[1, 0, 3] = 0.0
    m[4, 3, 0] = 0.5
    with pytest.raises(ValueError, match="instance 4"):
        ok.with_matrices(m)


@pytest.mark.parametrize("kind", NUMPY_KINDS)
def test_per_ray_tmin_and_tmax_are_respected(kind):
    """Rays through a row of boxes with per-ray intervals: the hit is the flat soup's and
    lies in (tmin, tmax]; a hit exactly at tmin is excluded, exactly at tmax included."""
    box = core.TriangleMesh(*cube())
    matrices = np.array([affine(np.eye(3) * 0.5, [3.0 * k, 0.0, 0.0]) for k in range(6)])
    tl = TwoLevel([core.build(box, kind)], np.zeros(6, int), matrices)
    m = 300
    rng = np.random.default_rng(4)
    o = np.c_[np.full(m, -2.0), rng.uniform(-0.4, 0.4, (m, 2))].astype(np.float32)
    d = np.tile(np.float32([1.0, 0.0, 0.0]), (m, 1))
    tmin = rng.uniform(0.0, 12.0, m)
    tmax = tmin + rng.uniform(0.0, 6.0, m)
    tmin[:10] = 1.5  # exactly on box 0's near face (x = -0.5): excluded, its far face next
    tmax[10:20] = 1.5  # included
    tmin[10:20] = 0.0
    h = tl.trace(o, d, tmin, tmax)
    hb = core.build(flatten([box], np.zeros(6, int), matrices), "brute").trace(o, d, tmin, tmax)
    bad = np.flatnonzero(h.triangle != hb.triangle)
    assert bad.size == 0, f"{kind}: {bad.size} rays differ from the flat soup under per-ray tmin/tmax; first ray {bad[0]}"
    assert np.all(h.t[:10] == 2.5) and np.all(h.t[10:20] == 1.5)
    assert np.array_equal(tl.occluded(o, d, tmin, tmax), hb.hit)


def test_empty_ray_batches_and_empty_scenes():
    box = core.TriangleMesh(*cube())
    tl = TwoLevel([core.build(box, "bvh")], [0], np.eye(4)[None])
    h = tl.trace(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(h) == 0 and h.triangle.dtype == np.int32 and h.instance.dtype == np.int32 and h.t.dtype == np.float32
    assert tl.occluded(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
    none = TwoLevel([core.build(box, "bvh")], np.zeros(0, int), np.zeros((0, 4, 4)))
    assert none.instance_count == 0 and none.triangle_count == 0
    assert not none.trace([0, 0, 5], [0, 0, -1]).hit.any() and not none.occluded([0, 0, 5], [0, 0, -1]).any()
    empty = core.TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    tl = TwoLevel([core.build(empty, "bvh"), core.build(box, "bvh")], [0, 1], np.tile(np.eye(4), (2, 1, 1)))
    h = tl.trace([0, 0, 5], [0, 0, -1])
    assert h.instance.tolist() == [1] and tl.tri_base.tolist() == [0, 0]


@pytest.mark.parametrize("pairs_from", (10**9, 0), ids=("loop", "tree"))
def test_one_origin_broadcasts_against_many_directions(pairs_from):
    ib, matrices, rays, *_ = random_scene(5)
    tl = TwoLevel(bottoms_of("bvh"), ib, matrices, pairs_from=pairs_from)
    d = rays[1]
    origin = np.float32([0.5, -0.25, 0.125])
    a = tl.trace(origin, d)
    b = tl.trace(np.tile(origin, (len(d), 1)), d)
    assert np.array_equal(a.triangle, b.triangle) and np.array_equal(a.t, b.t)
    one = tl.trace(rays[0][:1], d[:1])
    assert len(one) == 1
    assert np.array_equal(tl.occluded(origin, d), b.hit)


def test_global_triangles_past_the_int32_range_are_int64():
    box = core.TriangleMesh(*cube())
    base = np.array([0, 2**31 + 5], np.int64)
    tl = TwoLevel([core.build(box, "bvh")], [0, 0], np.array([affine(np.eye(3), [0, 0, 0]), affine(np.eye(3), [5, 0, 0])]), base)
    h = tl.trace(np.float32([[5, 0, 3], [0, 0, 3]]), np.float32([[0, 0, -1], [0, 0, -1]]))
    assert h.triangle.dtype == np.int64 and tl.triangle_dtype == np.int64
    assert h.triangle[0] == 2**31 + 5 + int(h.local_triangle[0]) and h.triangle[1] == h.local_triangle[1]
    assert h.instance.tolist() == [1, 0]


def test_bounds_cover_every_instance_and_flatten_matches_the_independent_soup():
    ib, matrices, rays, flat, *_ = random_scene(300)
    tl = TwoLevel(bottoms_of("bvh"), ib, matrices)
    lo, hi = tl.bounds()
    flo, fhi = flat.bounds()
    assert lo.dtype == np.float32 and (lo <= flo).all() and (hi >= fhi).all(), "bounds() misses part of the world soup"
    mine = tl.flatten()
    assert np.array_equal(mine.vertices, flat.vertices) and np.array_equal(mine.triangles, flat.triangles)
    assert np.array_equal(np.bincount(mine.instance_index), [object_meshes()[k].triangle_count for k in ib])



# -- Swept: each ray at its own instant ---------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
def test_swept_gives_each_ray_what_its_instants_two_level_gives_it(kind):
    """Per ray, exactly the hit of ``with_matrices(matrices[slot])`` (bit for bit), with a
    singular instance at one instant and rays spread over four instants."""
    ib, matrices, rays, *_ = random_scene(5)
    two = TwoLevel(bottoms_of(kind), ib, matrices)
    rng = np.random.default_rng(5)
    instants = np.stack([matrices] + [scene_matrices(5, rng) for _ in range(3)])
    instants[2, 1, :3, :3] = 0.0  # instance 1 collapses at instant 2: never hit then
    slot = rng.integers(0, len(instants), len(rays[0]))
    swept = core.Swept(two, instants)
    got = swept.trace(*rays, slot=slot)
    hit_any = swept.occluded(*rays, slot=slot)
    o, d, tmin, tmax = rays
    for k in range(len(instants)):
        rows = np.flatnonzero(slot == k)
        want = two.with_matrices(instants[k]).trace(o[rows], d[rows], tmin[rows], tmax[rows])
        for field in ("t", "triangle", "instance", "local_triangle", "u", "v"):
            assert np.array_equal(getattr(got, field)[rows], getattr(want, field)), \
                f"{kind}: instant {k} differs in {field}"
        assert np.array_equal(hit_any[rows], want.triangle >= 0), f"{kind}: occluded differs at instant {k}"
    assert not (got.instance[slot == 2] == 1).any()
    assert got.hit[slot == 0].mean() > 0.3  # aimed at the first instant (a fifth with a short tmax)


@pytest.mark.parametrize("one_origin", [False, True])
@pytest.mark.parametrize("far", [0.0, 1e4])
def test_swept_reach_keeps_every_ray_that_meets_a_sweep_box(far, one_origin):
    """The float32 cull before the exact box tests (``twolevel.near_rays``) keeps every ray whose
    float64 test meets some instance's box over the sweep: rays aimed at the boxes'
    corners, edges and faces with a relative jitter of 1e-7, some with a zero direction
    component, segments ending at the target or starting just past it, origins inside the
    boxes; near the world origin and 1e4 from it.  Rays pointing away are culled."""
    ib, matrices, *_ = random_scene(5)
    two = TwoLevel(bottoms_of("brute"), ib, matrices)
    rng = np.random.default_rng(11)
    instants = np.stack([matrices, scene_matrices(5, rng)])
    instants[:, :, :3, 3] += far
    swept = core.Swept(two, instants)
    lo, hi = swept._sweep_lo[swept._active], swept._sweep_hi[swept._active]
    m = 20000
    box = rng.integers(0, len(lo), m)
    corner = rng.integers(0, 2, (m, 3)).astype(float)
    kind = rng.integers(0, 3, m)  # 0 a corner, 1 on an edge, 2 on a face
    free = rng.uniform(0, 1, (m, 3))
    ax = rng.integers(0, 3, m)
    frac = corner.copy()
    frac[kind >= 1, ax[kind >= 1]] = free[kind >= 1, ax[kind >= 1]]
    ax2 = (ax + 1) % 3
    frac[kind == 2, ax2[kind == 2]] = free[kind == 2, ax2[kind == 2]]
    target = lo[box] + frac * (hi[box] - lo[box])
    target *= 1.0 + rng.choice([-1e-7, 0.0, 1e-7], (m, 3))
    centre = 0.5 * (lo + hi).mean(axis=0)
    if one_origin:
        origins = np.broadcast_to(centre + rng.uniform(-30, 30, 3), (m, 3))
    else:
        origins = centre + rng.uniform(-30, 30, (m, 3))
        inside = rng.random(m) < 0.1  # some start inside their box
        origins[inside] = lo[box][inside] + rng.uniform(0, 1, (inside.sum(), 3)) * (hi - lo)[box][inside]
    d = target - origins
    flat_axis = rng.random(m) < 0.2
    if not one_origin:  # a zero component: the origin moved onto the target's plane
        origins[flat_axis, ax[flat_axis]] = target[flat_axis, ax[flat_axis]]
        d[flat_axis, ax[flat_axis]] = 0.0
    d[rng.random(m) < 0.1] *= -1.0  # some pointing away
    o32, d32 = origins.astype(np.float32), d.astype(np.float32)
    tmin = np.where(rng.random(m) < 0.2, np.float32(1.0 + 1e-6), np.float32(0.0))
    tmax = np.where(rng.random(m) < 0.3, np.float32(1.0 - 1e-6), np.float32(np.inf))
    tmax = np.maximum(tmax, tmin)
    rays = core.prepare_rays(np.broadcast_to(o32[:1], (m, 3)) if one_origin else o32, d32, tmin, tmax, shear=False)
    seg = twolevel._Segments(rays.origins.astype(np.float64), rays.directions.astype(np.float64), rays.tmin, rays.tmax)
    meets = np.zeros(m, bool)
    for a in range(len(lo)):
        meets |= seg.enter(seg.o, seg.inv, lo[a], hi[a], seg.tmin, seg.tmax)[1]
    kept = np.zeros(m, bool)
    kept[twolevel.near_rays(rays, *swept._balls, one_origin)] = True
    missed = np.flatnonzero(meets & ~kept)
    assert missed.size == 0, f"{missed.size} rays meet a sweep box but were culled, first {describe_ray(missed[0], o32, d32)}"
    assert meets.mean() > 0.3
    # rays from far outside every ball, pointing away from the scene: all culled
    u = rng.normal(size=(1000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    reach = 100.0 + np.linalg.norm(np.concatenate([lo, hi]) - centre, axis=1).max()
    away = core.prepare_rays((centre + reach * u).astype(np.float32), u.astype(np.float32), shear=False)
    assert twolevel.near_rays(away, *swept._balls, False).size == 0, "rays pointing away from every box were kept"


def test_swept_rejects_bad_instants_and_slots():
    ib, matrices, rays, *_ = random_scene(5)
    two = TwoLevel(bottoms_of("brute"), ib, matrices)
    with pytest.raises(ValueError, match="matrices must have shape"):
        core.Swept(two, matrices)  # one instant without its axis
    bad = np.stack([matrices, matrices])
    bad[1, 3, 0, 0] = np.nan
    with pytest.raises(ValueError, match="instance 3"):
        core.Swept(two, bad)
    swept = core.Swept(two, np.stack([matrices, matrices]))
    with pytest.raises(ValueError, match="slot must lie in 0..1"):
        swept.trace(*rays, slot=np.full(len(rays[0]), 2))
    with pytest.raises(ValueError, match="slot must be"):
        swept.trace(*rays, slot=np.zeros(3, int))
