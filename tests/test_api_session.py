"""api.cast after every kind of scene change equals Blender's own scene.ray_cast, field by
field, with the API called first (so a stale session would show); bad input raises a
clear error and leaves the session as it was."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, add_plane, addon, fresh  # noqa: E402,F401

pytestmark = pytest.mark.blender

RAYS = 300


def rays(seed=0):
    """Rays from a ring around the scene toward its middle: they cross every object."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, RAYS)
    o = np.stack([9 * np.cos(a), 9 * np.sin(a), rng.uniform(-0.8, 2.5, RAYS)], axis=1)
    target = np.stack([rng.uniform(-3, 3, RAYS), rng.uniform(-3, 3, RAYS), rng.uniform(-1.2, 1.5, RAYS)], axis=1)
    return o, target - o


def assert_like_ray_cast(addon, depsgraph=None, seed=0, **kw):
    """Every field of api.cast against scene.ray_cast on the same depsgraph; returns the result."""
    from mathutils import Vector

    o, d = rays(seed)
    r = addon.api.cast(o, d, depsgraph=depsgraph, **kw)
    dg = depsgraph if depsgraph is not None else bpy.context.evaluated_depsgraph_get()
    scene = dg.scene
    wrong = []
    for i in range(RAYS):
        ok, loc, n, face, ob, mat = scene.ray_cast(dg, Vector(o[i]), Vector(d[i]))
        if ok != bool(r.hit[i]):
            wrong.append((i, "hit", ok, bool(r.hit[i]), ob.name if ob else None))
            continue
        if not ok:
            assert r.object_index[i] == -1 and r.instance_index[i] == -1 and r.polygon_index[i] == -1
            assert np.isnan(r.points[i]).all() and np.isnan(r.normals[i]).all() and np.isinf(r.t[i])
            continue
        got = r.objects[r.object_index[i]]
        checks = {
            "point": np.allclose(r.points[i], loc[:], atol=2e-4),
            "t": abs(r.t[i] * np.linalg.norm(d[i]) - (Vector(loc) - Vector(o[i])).length) < 2e-4,
            "normal": np.allclose(r.normals[i], n[:], atol=2e-5),
            "polygon": r.polygon_index[i] == face,
            "object": got == ob.original,
            "matrix": np.allclose(r.instance_matrices[r.instance_index[i]], np.array(mat), atol=1e-5),
            "name": r.object_names[r.object_index[i]] == ob.name,
        }
        bad = [k for k, v in checks.items() if not v]
        # Blender's BVH may pick the other triangle at a shared edge: same point, same t
        if bad and set(bad) <= {"normal", "polygon", "object", "matrix", "name"} and (
                np.linalg.norm(np.asarray(loc) - r.points[i]) < 1e-5):
            continue
        if bad:
            wrong.append((i, bad, ob.name, got.name))
    assert not wrong, f"{len(wrong)} of {RAYS} rays differ from scene.ray_cast, first {wrong[:4]}"
    assert r.hit.sum() > RAYS // 4, "the rays should hit the scene"
    return r


def build():
    """A ground, a cube, a ball in its own collection, a collection instance and a
    geometry-nodes instancer, each distinct."""
    scene = bpy.context.scene
    add_plane("Ground", 12.0, location=(0, 0, -1.0))
    cube = add_cube("Cube", 1.5, (1.5, 0.0, 0.0))
    col = bpy.data.collections.new("Col")
    scene.collection.children.link(col)
    ball = add_cube("Ball", 1.0, (-1.5, 1.0, 0.3))
    scene.collection.objects.unlink(ball)
    col.objects.link(ball)
    # a collection instanced twice (not itself in the scene)
    src_col = bpy.data.collections.new("Src")
    src = add_cube("SrcCube", 0.6)
    scene.collection.objects.unlink(src)
    src_col.objects.link(src)
    for i, x in enumerate((-2.5, 2.5)):
        e = bpy.data.objects.new(f"Inst{i}", None)
        e.instance_type = "COLLECTION"
        e.instance_collection = src_col
        e.location = (x, -2.0, 0.0)
        e.rotation_euler = (0.0, 0.0, 0.3 * (i + 1))
        scene.collection.objects.link(e)
    bpy.context.view_layer.update()
    return cube, ball, col


def test_every_field_equals_ray_cast_through_every_change(fresh, addon):
    cube, ball, col = build()
    scene = bpy.context.scene
    vl = bpy.context.view_layer
    assert_like_ray_cast(addon)
    cube.location.x += 0.7  # moved
    assert_like_ray_cast(addon, seed=1)
    mod = cube.modifiers.new("Bevel", "BEVEL")  # modifier added, then changed
    mod.width = 0.1
    assert_like_ray_cast(addon, seed=2)
    mod.width = 0.3
    assert_like_ray_cast(addon, seed=3)
    ball.hide_set(True)
    r = assert_like_ray_cast(addon, seed=4)
    assert "Ball" not in set(r.object_names[r.object_index[r.hit]])
    ball.hide_set(False)
    r = assert_like_ray_cast(addon, seed=4)
    assert "Ball" in set(r.object_names[r.object_index[r.hit]]), "hide_set(False) did not bring the ball back"
    lc = vl.layer_collection.children["Col"]
    lc.hide_viewport = True  # the eye icon
    r = assert_like_ray_cast(addon, seed=5)
    assert "Ball" not in set(r.object_names[r.object_index[r.hit]])
    lc.hide_viewport = False
    lc.exclude = True  # the checkbox
    r = assert_like_ray_cast(addon, seed=5)
    assert "Ball" not in set(r.object_names[r.object_index[r.hit]])
    lc.exclude = False
    assert_like_ray_cast(addon, seed=6)
    extra = add_cube("Extra", 1.0, (0.0, 2.5, 0.0))  # added, then removed
    r = assert_like_ray_cast(addon, seed=7)
    assert "Extra" in set(r.object_names[r.object_index[r.hit]])
    bpy.data.objects.remove(extra)
    r = assert_like_ray_cast(addon, seed=7)
    assert "Extra" not in set(r.object_names[r.object_index[r.hit]])
    # animation: frame_set moves the cube
    cube.keyframe_insert("location", frame=1)
    cube.location.z += 1.0
    cube.keyframe_insert("location", frame=10)
    scene.frame_set(1)
    assert_like_ray_cast(addon, seed=8)
    scene.frame_set(10)
    assert_like_ray_cast(addon, seed=8)


def test_another_view_layers_depsgraph_gets_its_own_geometry(fresh, addon):
    cube, ball, col = build()
    scene = bpy.context.scene
    other = scene.view_layers.new("Other")
    other.layer_collection.children["Col"].exclude = True
    r1 = assert_like_ray_cast(addon)
    assert "Ball" in set(r1.object_names[r1.object_index[r1.hit]])
    other.update()
    r2 = assert_like_ray_cast(addon, depsgraph=other.depsgraph)
    assert "Ball" not in set(r2.object_names[r2.object_index[r2.hit]]), "the other view layer saw the first one's ball"
    assert_like_ray_cast(addon)


def test_a_handler_registered_before_the_extensions_sees_the_current_frame(fresh, addon):
    cube, ball, col = build()
    scene = bpy.context.scene
    cube.keyframe_insert("location", frame=1)
    cube.location.y += 2.0
    cube.keyframe_insert("location", frame=2)
    scene.frame_set(1)
    addon.api.cast(*rays())  # a session for frame 1
    failures = []

    def before(scene, depsgraph):
        try:
            assert_like_ray_cast(addon, depsgraph=depsgraph, seed=9)
        except AssertionError as e:
            failures.append(str(e))

    bpy.app.handlers.frame_change_post.insert(0, before)
    try:
        scene.frame_set(2)
        scene.frame_set(1)
    finally:
        bpy.app.handlers.frame_change_post.remove(before)
    assert not failures, failures[0]


def test_results_carry_instances_objects_smooth_normals_and_uvs(fresh, addon):
    cube, ball, col = build()
    r = assert_like_ray_cast(addon, smooth=True, uv=True)
    h = r.hit
    names = set(r.object_names[r.object_index[h]])
    assert {"Cube", "Ground", "SrcCube"} <= names, names
    src = r.object_names[r.object_index] == "SrcCube"
    assert len(set(r.instance_index[h & src])) == 2, "the two instances of SrcCube must be told apart"
    # flat-shaded boxes: the interpolated corner normals are the face normals
    assert np.allclose(r.smooth_normals[h], r.normals[h], atol=1e-4)
    assert np.isnan(r.smooth_normals[~h]).all()
    # add_mesh makes no UV map: NaN; the ground gets one with a known layout (u = x-based)
    assert np.isnan(r.uv[h]).all()
    o, d = rays(1)
    ground = bpy.data.objects["Ground"]
    uvl = ground.data.uv_layers.new(name="UV")
    for loop in ground.data.loops:
        co = ground.data.vertices[loop.vertex_index].co
        uvl.data[loop.index].uv = (co.x / 12 + 0.5, co.y / 12 + 0.5)
    ground.data.update()
    r = addon.api.cast(o, d, uv=True)
    on = r.hit & (r.object_names[r.object_index] == "Ground")
    assert on.sum() > 10
    expect = np.stack([r.points[on, 0] / 12 + 0.5, r.points[on, 1] / 12 + 0.5], axis=1)
    assert np.allclose(r.uv[on], expect, atol=1e-4), "UV is not the active map interpolated at the hit"


def test_single_rays_lists_and_broadcasting(fresh, addon):
    """One origin or one direction broadcasts to the other's rays, bit for bit as the same
    rays written out.  The structure is pinned: across calls the session's ski rental may
    switch from the grid to Embree between two of them (it did on a CI run after the
    calibration changed), and two structures agree on t only to rounding."""
    build()
    api = addon.api
    one = api.cast((1.5, -9.0, 0.0), [0, 1, 0])
    assert len(one) == 1 and one.hit[0]
    o, d = rays()
    many = api.cast(o[0], d, structure="grid")
    each = api.cast(np.repeat(o[:1], RAYS, axis=0), d, structure="grid")
    assert np.array_equal(many.t, each.t) and np.array_equal(many.triangle, each.triangle)
    assert many.structure == each.structure == "grid"
    fan = api.cast(o, d[0].tolist(), structure="grid")
    assert np.array_equal(fan.t, api.cast(o, np.repeat(d[:1], RAYS, axis=0), structure="grid").t)


@pytest.mark.parametrize("call, kind, word", [
    (lambda api: api.cast(np.zeros((4, 2)), np.ones((4, 2))), ValueError, "origins"),
    (lambda api: api.cast(np.zeros((4, 3)), np.ones((5, 3))), ValueError, "directions"),
    (lambda api: api.cast([[0, 0, np.nan]], [[0, 1, 0]]), ValueError, "origins"),
    (lambda api: api.cast([[0, 0, 0]], [[0, np.inf, 0]]), ValueError, "directions"),
    (lambda api: api.cast([[0, 0, 0]], [[0, 0, 0]]), ValueError, "directions"),
    (lambda api: api.cast([[0, 0, 0j]], [[0, 1, 0]]), TypeError, "origins"),
    (lambda api: api.cast([[0, 0, 0]], [[0, 1, 0]], samples=0), ValueError, "samples"),
    (lambda api: api.cast([[0, 0, 0]], [[0, 1, 0]], samples=-5), ValueError, "samples"),
    (lambda api: api.cast([[0, 0, 0]], [[0, 1, 0]], depsgraph=bpy.context.scene), TypeError, "depsgraph"),
    (lambda api: api.cast([[0, 0, 0]], [[0, 1, 0]], structure="octree"), ValueError, "structure"),
    (lambda api: api.cast([[0, 0, 0]], [[0, 1, 0]], tmin=np.nan), ValueError, "tmin"),
    (lambda api: api.cast([[0, 0, 0]], [[0, 1, 0]], expected_rays=0), ValueError, "expected_rays"),
    (lambda api: api.cast_all([[0, 0, 0]], [[0, 1, 0]], max_hits=0), ValueError, "max_hits"),
    (lambda api: api.occluded([[0, 0, 0]], [["a", "b", "c"]]), TypeError, "directions"),
])
def test_bad_input_names_the_argument_and_changes_nothing(fresh, addon, call, kind, word):
    build()
    session = addon.operators.session
    addon.api.cast(*rays())
    before = {k: (s.mesh, s.head, s.body, dict(s.structures), s.chosen, s.grid_rays) for k, s in session.SESSIONS.items()}
    with pytest.raises(kind, match=word):
        call(addon.api)
    after = {k: (s.mesh, s.head, s.body, dict(s.structures), s.chosen, s.grid_rays) for k, s in session.SESSIONS.items()}
    assert before.keys() == after.keys()
    for k in before:
        assert before[k][0] is after[k][0] and before[k][1:3] == after[k][1:3] and before[k][4:] == after[k][4:]
        assert before[k][3] == after[k][3]


def test_big_casts_run_in_chunks_with_progress_and_stop_on_interrupt(fresh, addon, monkeypatch):
    build()
    api = addon.api
    o, d = rays()
    whole = api.cast(o, d, structure="bvh")  # one structure: the same answers bit for bit
    monkeypatch.setattr(addon.operators.query, "CHUNK", 64)
    seen = []
    chunked = api.cast(o, d, structure="bvh", progress=lambda done, total: seen.append((done, total)))
    assert seen == [(min(RAYS, k), RAYS) for k in range(64, RAYS + 64, 64)], seen
    for name in ("t", "triangle", "object_index", "instance_index", "polygon_index", "hit"):
        assert np.array_equal(getattr(whole, name), getattr(chunked, name)), f"{name} differs when chunked"
    assert np.allclose(whole.points, chunked.points, equal_nan=True)
    assert np.array_equal(api.occluded(o, d, structure="bvh"), whole.hit), "occluded is not 'a nearest hit exists'"
    # nothing lies nearer than the nearest hit; up to just past it the hit itself blocks
    half = np.where(whole.hit, whole.t * 0.5, 1.0)
    assert not api.occluded(o, d, tmax=half, structure="bvh").any(), "an occluder nearer than the nearest hit"
    upto = np.where(whole.hit, whole.t * (1 + 1e-5), 1.0)  # t is rounded to float32
    assert np.array_equal(api.occluded(o, d, tmax=upto, structure="bvh"), whole.hit)

    def stop(done, total):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        api.cast(o, d, progress=stop)


def test_cast_all_lists_every_surface_along_the_ray(fresh, addon):
    from mathutils import Vector

    build()
    api = addon.api
    o, d = rays()
    r = api.cast_all(o, d, max_hits=16)
    first = api.cast(o, d)
    assert np.all(np.diff(r.ray) >= 0)
    starts = np.flatnonzero(np.r_[True, r.ray[1:] != r.ray[:-1]])
    assert np.array_equal(r.ray[starts], np.flatnonzero(first.hit)), "rays with hits differ from cast"
    assert np.allclose(r.t[starts], first.t[first.hit], rtol=1e-5), "the first hit of each ray is cast's"
    # the second hit equals scene.ray_cast restarted just past the first
    dg = bpy.context.evaluated_depsgraph_get()
    scene = bpy.context.scene
    two = starts[np.flatnonzero(r.count[r.ray[starts]] >= 2)]
    assert two.size > 20
    for k in two[:40]:
        i = r.ray[k]
        dn = d[i] / np.linalg.norm(d[i])
        p = r.points[k] + 1e-4 * dn
        ok, loc, n, face, ob, mat = scene.ray_cast(dg, Vector(p), Vector(dn))
        assert ok and np.allclose(loc[:], r.points[k + 1], atol=2e-4), (i, loc[:], r.points[k + 1])
        assert np.allclose(n[:], r.normals[k + 1], atol=1e-4) and r.objects[r.object_index[k + 1]] == ob.original


def test_the_stale_flag_comes_from_the_same_fingerprint(fresh, addon):
    cube, ball, col = build()
    scene = bpy.context.scene
    p = scene.hybrid_raycast
    assert bpy.ops.hybrid_raycast.analyze() == {"FINISHED"}
    assert not p.stale, p.stale_reason
    scene.frame_set(5)  # nothing is animated: the geometry is the same
    assert not p.stale, f"a frame change that moves nothing made the results stale: {p.stale_reason}"
    lc = bpy.context.view_layer.layer_collection.children["Col"]
    lc.hide_viewport = True
    bpy.context.evaluated_depsgraph_get()
    assert p.stale, "hiding a collection with its eye icon changes what is extracted"
    lc.hide_viewport = False
    assert bpy.ops.hybrid_raycast.analyze() == {"FINISHED"}
    cube.keyframe_insert("location", frame=1)
    cube.location.z += 1.0
    cube.keyframe_insert("location", frame=10)
    scene.frame_set(1)
    assert bpy.ops.hybrid_raycast.analyze() == {"FINISHED"}
    assert not p.stale, p.stale_reason
    scene.frame_set(10)
    assert p.stale, "a frame change that moves the cube must make the results stale"


def test_a_session_plans_once_and_leaves_the_grid_by_the_online_rule(fresh, addon):
    """Small casts: one plan, then the grid until the rays of all casts pay for a build."""
    build()
    bpy.context.scene.hybrid_raycast.candidates = {"BVH"}  # Embree would be taken without a grid
    api, core = addon.api, addon.core
    session = addon.operators.session
    o, d = rays()
    first = api.cast(o, d)
    s = session.get(bpy.context.evaluated_depsgraph_get())
    assert first.plan is s.plan and first.structure == "grid", "a 300-ray cast keeps the grid it planned with"
    kinds = []
    for i in range(40):
        r = api.cast(o, d)
        assert r.plan is first.plan, "a later cast planned again"
        kinds.append(r.structure)
        if r.structure != "grid":
            break
    assert kinds[-1] in ("bvh", "embree"), f"never left the grid in 40 casts of {RAYS} rays: {kinds}"
    switched_at = len(kinds)
    # the rule that switched: the grid's time over all casts reached the estimate (or the break-even)
    est = s.calibration.estimate(kinds[-1], s.mesh.triangle_count)
    assert s.grid_rays == RAYS * switched_at
    assert (core.ski_rental(s.grid_time, s.grid_rays, est) == "switch"
            or s.grid_rays + RAYS > s.plan.break_even), (s.grid_time, est.build_time, s.grid_rays, s.plan.break_even)
    ref = core.build(s.mesh, "brute").trace(o, d)
    for kind in ("grid", "bvh"):
        forced = api.cast(o, d, structure=kind)
        assert forced.structure == kind
        assert np.array_equal(forced.hit, ref.hit) and np.allclose(forced.t[ref.hit], ref.t[ref.hit], rtol=1e-6)
