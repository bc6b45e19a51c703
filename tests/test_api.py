"""api.cast: the same hits as core brute force on the same mesh, and as Blender's own ray cast;
the cache follows the scene."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, addon, fresh, simple_scene  # noqa: E402,F401

pytestmark = pytest.mark.blender


def test_cast_is_reachable_as_package_api(addon):
    assert addon.api.cast is not None
    import hybrid_raycast.api as api_mod

    assert api_mod.cast is addon.api.cast


@pytest.mark.parametrize("expected", [None, 1.0, 1e12])
def test_cast_equals_brute_force_on_the_extracted_mesh(fresh, addon, expected):
    from hybrid_raycast.operators.analyze import extract

    simple_scene()
    add_cube("Far", 0.5, (3.0, 2.0, 1.0))
    core = addon.core
    mesh, _ = extract(bpy.context.evaluated_depsgraph_get())
    o, d = core.uniform_rays(mesh, 3000, seed=7)
    r = addon.api.cast(o, d, expected)
    ref = core.build(mesh, "brute").trace(o, d)
    assert r.structure in {"grid", "bvh", "embree"}
    if expected == 1.0:  # one ray never pays for a numpy BVH; Embree only where it builds faster than the grid
        assert r.structure != "bvh", "one ray never pays for a BVH build"
        assert r.structure == "grid" or not r.plan.grid_built
    bad = np.flatnonzero(r.hit != ref.hit)
    assert bad.size == 0, f"{bad.size} rays differ in hit/miss, first {bad[:5]}"
    h = ref.hit
    dt = np.abs(r.t[h] - ref.t[h])
    assert np.all(dt <= 1e-5 * np.maximum(1.0, ref.t[h])), f"t differs by up to {dt.max()}"
    # a different triangle is only acceptable at a tie in t (a shared edge; Embree's t may
    # differ from ours by float32 rounding there, which the t check above bounds)
    other = np.flatnonzero(h)[r.triangle[h] != ref.triangle[h]]
    if r.structure != "embree":
        assert np.all(r.t[other] == ref.t[other]), (
            f"{r.structure}: different triangles at different t for rays {other[:5]}: "
            f"{r.triangle[other[:5]]} t={r.t[other[:5]]} vs {ref.triangle[other[:5]]} t={ref.t[other[:5]]}")
    assert other.size <= 0.01 * h.sum(), f"{other.size} of {h.sum()} hits on another triangle ({r.structure})"
    assert np.array_equal(r.object_index[h], mesh.object_index[r.triangle[h]])
    assert np.array_equal(r.polygon_index[h], mesh.polygon_index[r.triangle[h]])
    assert np.all(r.object_index[~h] == -1) and np.all(r.polygon_index[~h] == -1)
    assert np.all(np.isnan(r.points[~h]))
    tv = mesh.tri_vertices[r.triangle[h]].astype(np.float64)
    u, v = r.u[h, None].astype(np.float64), r.v[h, None].astype(np.float64)
    p_bary = (1 - u - v) * tv[:, 0] + u * tv[:, 1] + v * tv[:, 2]
    assert np.allclose(p_bary, r.points[h], atol=1e-4), "barycentrics do not give the hit point"
    assert list(r.object_names) == sorted(set(r.object_names), key=list(r.object_names).index)


@pytest.mark.parametrize("sky", [0.2, 0.8])
def test_every_field_is_the_same_whether_most_rays_miss_or_hit(fresh, addon, sky):
    """A cast where most rays miss gathers the per-triangle fields for its hits only: every
    field of every ray equals the same rays cast where most hit (the rays padded with hits),
    with the miss values (-1, NaN) on the misses."""
    simple_scene()
    core = addon.core
    from hybrid_raycast.operators.analyze import extract

    mesh, _ = extract(bpy.context.evaluated_depsgraph_get())
    o, d = core.uniform_rays(mesh, 2000, seed=3)
    ref = core.build(mesh, "brute").trace(o, d)
    rng = np.random.default_rng(0)
    hits, misses = np.flatnonzero(ref.hit), np.flatnonzero(~ref.hit)
    n_miss = int(sky * 1000)
    pick = np.concatenate([rng.choice(hits, 1000 - n_miss), rng.choice(misses, n_miss)])
    r = addon.api.cast(o[pick], d[pick], structure="bvh", materials=True)
    dense = addon.api.cast(o[pick[r.hit]], d[pick[r.hit]], structure="bvh", materials=True)
    assert (~r.hit).mean() == pytest.approx(sky, abs=0.01)
    for f in ("t", "triangle", "u", "v", "object_index", "instance_index", "polygon_index", "normals", "material_index"):
        got = getattr(r, f)
        assert np.array_equal(got[r.hit], getattr(dense, f)), f
    assert (r.object_index[~r.hit] == -1).all() and (r.polygon_index[~r.hit] == -1).all()
    assert np.isnan(r.normals[~r.hit]).all() and (r.material_index[~r.hit] == -1).all()


def test_cast_agrees_with_blenders_scene_ray_cast(fresh, addon):
    from mathutils import Vector

    simple_scene()
    scene = bpy.context.scene
    dg = bpy.context.evaluated_depsgraph_get()
    rng = np.random.default_rng(3)
    o = np.tile([[0.3, -6.0, 0.2]], (50, 1)).astype(np.float32)
    d = (np.array([0, 1, 0]) + rng.normal(0, 0.3, (50, 3))).astype(np.float32)
    r = addon.api.cast(o, d)
    for i in range(50):
        ok, loc, _n, face, ob, _m = scene.ray_cast(dg, Vector(o[i].tolist()), Vector(d[i].tolist()))
        assert ok == bool(r.hit[i]), f"ray {i}: blender hit={ok}, ours={r.hit[i]}"
        if ok:
            assert np.allclose(r.points[i], loc[:], atol=1e-4), f"ray {i}: {r.points[i]} vs {loc[:]}"
            assert r.objects[r.object_index[i]] == ob.original
            assert r.polygon_index[i] == face, f"ray {i}: polygon {r.polygon_index[i]} vs Blender's {face}"


def test_the_session_is_reused_until_the_scene_changes(fresh, addon):
    session = addon.operators.session
    simple_scene()
    o = np.array([[0.0, -6.0, 0.0]], np.float32)
    d = np.array([[0.0, 1.0, 0.0]], np.float32)
    r1 = addon.api.cast(o, d)
    key = session.session_key(bpy.context.evaluated_depsgraph_get(), False)
    mesh1 = session.SESSIONS[key].mesh
    r2 = addon.api.cast(o, d)
    assert session.SESSIONS[key].mesh is mesh1, "an unchanged scene was extracted again"
    assert r1.t[0] == pytest.approx(5.0) and r2.t[0] == pytest.approx(5.0)
    bpy.data.objects["Cube"].location.y += 1.0
    r3 = addon.api.cast(o, d)
    assert session.SESSIONS[key].mesh is not mesh1, "a moved object did not invalidate the session"
    assert r3.t[0] == pytest.approx(6.0), f"the cast saw the old scene: t={r3.t[0]}"


def test_cast_rejects_malformed_rays_and_empty_scenes(fresh, addon):
    from hybrid_raycast.operators.jobs import NoGeometry

    with pytest.raises(NoGeometry, match="no geometry"):
        addon.api.cast(np.zeros((1, 3)), np.ones((1, 3)))
    add_cube("Cube")
    with pytest.raises(ValueError, match="shape"):
        addon.api.cast(np.zeros((4, 2)), np.ones((4, 2)))
    with pytest.raises(ValueError, match="expected_rays"):
        addon.api.cast(np.zeros((1, 3)), np.ones((1, 3)), expected_rays=0)
    empty = addon.api.cast(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0 and empty.points.shape == (0, 3)
