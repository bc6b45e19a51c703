"""The scene persists across frames and calls: a frame where nothing moved keeps the session,
a frame that changed reads again only the meshes that changed, and every result still equals
a fresh extraction of the scene as it is now."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, add_plane, addon, fresh  # noqa: E402,F401

pytestmark = pytest.mark.blender


def _scene():
    """A ground, a static cube, a waving grid (deforms every frame), a cube keyframed to
    move, and an Empty keyframed to move (brings no triangles)."""
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 20
    add_plane("Ground", 20.0, z=-1.0)
    add_cube("Static", 1.0, (2.0, 0.0, 0.0))
    wave = add_plane("Wave", 4.0, z=0.0, location=(-3.0, 0.0, 0.0), subdivisions=16)
    wave.modifiers.new("w", "WAVE")
    mover = add_cube("Mover", 1.0, (0.0, 3.0, 0.0))
    empty = bpy.data.objects.new("Rig", None)
    scene.collection.objects.link(empty)
    for ob, frame, x in ((empty, 1, 0.0), (empty, 20, 5.0)):
        ob.location.x = x
        ob.keyframe_insert("location", frame=frame)
    scene.frame_set(1)
    return scene, wave, mover, empty


def _rays(n=400, seed=0):
    rng = np.random.default_rng(seed)
    o = np.stack([rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), np.full(n, 5.0)], axis=1)
    d = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), -np.ones(n)], axis=1)
    return o, d


def _reads(addon, monkeypatch):
    """Count the evaluated meshes extraction reads (``extract._mesh_triangles``)."""
    ext = addon.operators.extract
    seen = []
    real = ext._mesh_triangles

    def counting(me):
        seen.append(me.name)
        return real(me)

    monkeypatch.setattr(ext, "_mesh_triangles", counting)
    return seen


def _fresh_flat(addon, o, d):
    """The same rays through a flat world-space extraction made now, with the float64 brute force."""
    ext, core = addon.operators.extract, addon.core
    mesh = ext.scene_mesh(bpy.context.evaluated_depsgraph_get())
    return mesh, core.build(mesh, "brute").trace(o, d)


def test_a_frame_where_nothing_moved_keeps_the_session_and_its_structures(fresh, addon, monkeypatch):
    scene, wave, mover, empty = _scene()
    wave.modifiers.clear()  # nothing deforms; only an Empty moves
    scene.frame_set(1)
    session = addon.operators.session
    o, d = _rays()
    first = addon.api.cast(o, d, structure="grid")
    s1 = session.get(bpy.context.evaluated_depsgraph_get())
    reads = _reads(addon, monkeypatch)
    scene.frame_set(7)
    again = addon.api.cast(o, d, structure="grid")
    s7 = session.get(bpy.context.evaluated_depsgraph_get())
    assert s7 is s1, "a frame that moved only an Empty started a new session"
    assert reads == [], f"meshes read again: {reads}"
    assert np.array_equal(first.t, again.t) and np.array_equal(first.triangle, again.triangle)
    assert s7.summary["frame"] == 7


def test_a_changed_frame_reads_again_only_the_mesh_that_changed(fresh, addon, monkeypatch):
    scene, wave, mover, empty = _scene()
    o, d = _rays()
    addon.api.cast(o, d, structure="grid")
    reads = _reads(addon, monkeypatch)
    scene.frame_set(5)
    r = addon.api.cast(o, d, structure="grid")
    assert reads == ["Wave"], f"a frame where only the wave deformed read {reads}"
    mesh, ref = _fresh_flat(addon, o, d)
    assert np.array_equal(r.hit, ref.hit), "hits differ from a fresh extraction"
    assert np.allclose(r.t[ref.hit], ref.t[ref.hit], rtol=1e-5, atol=1e-5)
    assert np.array_equal(r.triangle, ref.triangle), "triangle numbering differs from a fresh extraction"
    reads.clear()
    mover.location.x += 1.5  # moved rigidly, nothing deforms at this frame
    r = addon.api.cast(o, d, structure="grid")
    assert "Mover" not in reads, f"a rigid move read the moved mesh again: {reads}"
    mesh, ref = _fresh_flat(addon, o, d)
    assert np.array_equal(r.hit, ref.hit) and np.allclose(r.t[ref.hit], ref.t[ref.hit], rtol=1e-5, atol=1e-5)


def test_meshes_no_session_uses_are_forgotten(fresh, addon):
    scene, wave, mover, empty = _scene()
    session = addon.operators.session
    o, d = _rays()
    for frame in range(1, 8):
        scene.frame_set(frame)
        addon.api.cast(o, d, structure="grid")
    live = {g.key for s in session.SESSIONS.values() for g in s.layout.groups}
    assert set(session.MESHES) == live, "the mesh cache keeps meshes of past frames"
    assert len(session.MESHES) == 4


def test_a_later_frame_inherits_the_plan_instead_of_planning_again(fresh, addon):
    scene, wave, mover, empty = _scene()
    o, d = _rays()
    first = addon.api.cast(o, d)
    scene.frame_set(9)
    later = addon.api.cast(o, d)
    assert later.plan is first.plan, "a frame that deformed one mesh planned again"
    mesh, ref = _fresh_flat(addon, o, d)
    assert np.array_equal(later.hit, ref.hit)


def _placements():
    """Linked duplicates of one mesh under a mirror, a non-uniform scale, a shear (a
    parent's scale under a child's rotation) and a collection instance; two materials."""
    scene = bpy.context.scene
    red, blue = bpy.data.materials.new("Red"), bpy.data.materials.new("Blue")
    base = add_cube("Base", 1.0, (0.0, 0.0, 0.0))
    base.data.materials.append(red)
    base.data.materials.append(blue)
    base.data.polygons[2].material_index = 1
    obs = [base]
    for name, loc, scale, rot in (("Mirror", (3.0, 0.0, 0.0), (-1.0, 1.0, 1.0), (0.0, 0.0, 0.3)),
                                  ("Squash", (-3.0, 0.0, 0.0), (2.0, 0.5, 1.0), (0.2, 0.0, 0.0)),
                                  ("Tall", (0.0, 3.0, 0.0), (1.0, 1.0, 3.0), (0.0, 0.4, 0.0))):
        ob = bpy.data.objects.new(name, base.data)
        ob.location, ob.scale, ob.rotation_euler = loc, scale, rot
        scene.collection.objects.link(ob)
        obs.append(ob)
    parent = bpy.data.objects.new("Parent", None)
    scene.collection.objects.link(parent)
    parent.scale = (1.0, 2.5, 1.0)
    sheared = bpy.data.objects.new("Sheared", base.data)
    scene.collection.objects.link(sheared)
    sheared.parent = parent
    sheared.location, sheared.rotation_euler = (0.0, -1.5, 0.0), (0.0, 0.0, 0.7)
    coll = bpy.data.collections.new("Props")
    prop = add_cube("Prop", 0.8)
    scene.collection.objects.unlink(prop)
    coll.objects.link(prop)
    inst = bpy.data.objects.new("Props.0", None)
    inst.instance_type, inst.instance_collection = "COLLECTION", coll
    inst.location = (0.0, -4.0, 0.5)
    scene.collection.objects.link(inst)
    add_plane("Ground", 20.0, z=-2.0)
    bpy.context.view_layer.update()
    return obs


@pytest.mark.parametrize("movers", ["flat", "two-level"])
@pytest.mark.parametrize("moved", ["one", "all"])
@pytest.mark.parametrize("kind", ["grid", "bvh", "embree"])
def test_two_level_hits_give_every_field_of_a_fresh_flat_extraction(fresh, addon, kind, moved, movers):
    """After a change (the session traces two levels) every field equals the flat reference:
    the float64 brute force over a fresh world-space extraction, with its per-triangle
    tables (normals from the world triangle, so the inverse transpose and mirrors are checked)."""
    if kind == "embree" and not addon.core.embree_available():
        pytest.skip("embreex is not installed here")
    obs = _placements()
    session, ext, core = addon.operators.session, addon.operators.extract, addon.core
    rng = np.random.default_rng(3)
    o = np.stack([rng.uniform(-6, 6, 3000), rng.uniform(-6, 6, 3000), np.full(3000, 8.0)], axis=1)
    d = np.stack([rng.uniform(-0.4, 0.4, 3000), rng.uniform(-0.4, 0.4, 3000), -np.ones(3000)], axis=1)
    addon.api.cast(o, d, structure=kind, materials=True)  # the first session traces flat
    # a change: the next session traces the still placements flat and the moved ones on two levels
    for ob in (obs[1:2] if moved == "one" else bpy.context.scene.objects):
        if ob.parent is None:
            ob.location.x += 0.25
    # the movers are rebuilt flat when they have fewer triangles than the session's first call has
    # rays: a first call of 5 rays places them on two levels, which the next call keeps
    if movers == "two-level":
        addon.api.cast(o[:5], d[:5], structure=kind, materials=True)
    r = addon.api.cast(o, d, structure=kind, materials=True)
    dg = bpy.context.evaluated_depsgraph_get()
    s = session.get(dg)
    tracer = s.tracer(kind, **({"density": float(bpy.context.scene.hybrid_raycast.grid_density)}
                               if kind == "grid" else {}))
    assert s.changed and s.still.sum() == (s.still.size - 1 if moved == "one" else 0)
    assert isinstance(tracer, core.Split), tracer
    assert (tracer.moving is not None) == (movers == "two-level"), tracer
    assert len(tracer.soups) == (moved == "one") + (movers == "flat"), tracer
    forms = [p["form"] for p in r.scene["parts"]]
    assert forms == ["flat"] * len(tracer.soups) + (["two levels"] if movers == "two-level" else []), r.scene
    assert all(p["why"] for p in r.scene["parts"])
    mesh = ext.scene_mesh(dg, attributes=("material",))
    ref = core.build(mesh, "brute").trace(o, d)
    assert np.array_equal(r.hit, ref.hit), f"hit differs on {np.flatnonzero(r.hit != ref.hit)[:10]}"
    h = ref.hit
    assert np.allclose(r.t[h], ref.t[h], rtol=1e-5, atol=1e-5)
    same = r.triangle == ref.triangle
    assert same.mean() > 0.995, f"{(~same).sum()} rays hit another triangle (ties at shared edges may differ)"
    k = ref.triangle[h & same]
    inst = mesh.instances
    assert np.array_equal(r.object_index[h & same], inst.instance_object[mesh.instance_index[k]])
    assert np.array_equal(r.instance_index[h & same], mesh.instance_index[k])
    assert np.array_equal(r.polygon_index[h & same], mesh.polygon_index[k])
    tv = mesh.tri_vertices[k].astype(np.float64)
    n = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    assert np.abs(r.normals[h & same] - n).max() < 1e-4, "world normals differ from the flat triangles'"
    assert np.allclose(r.u[h & same], ref.u[h & same], atol=1e-4) and np.allclose(r.v[h & same], ref.v[h & same], atol=1e-4)
    names = np.array([m.name for m in inst.materials] + [""], object)  # -1 (no material) picks ""
    ours = np.append(r.material_names, "")[r.material_index[h & same]]
    assert np.array_equal(ours, names[inst.triangle_material[k]]), "materials differ from the flat extraction's"
    assert np.allclose(r.instance_matrices, inst.matrices)


def test_movers_no_ray_passes_near_go_on_two_levels_whatever_the_ray_count(fresh, addon):
    """The rebuild-or-two-levels line counts the rays that pass near the moved objects: 3,000
    rays pointing up, away from everything, leave the movers on two levels; the same number
    aimed at the scene rebuilds them flat (fewer triangles than rays near them)."""
    obs = _placements()
    session, core = addon.operators.session, addon.core
    rng = np.random.default_rng(5)
    o = np.stack([rng.uniform(-6, 6, 3000), rng.uniform(-6, 6, 3000), np.full(3000, 8.0)], axis=1)
    down = np.stack([rng.uniform(-0.4, 0.4, 3000), rng.uniform(-0.4, 0.4, 3000), -np.ones(3000)], axis=1)
    addon.api.cast(o, down, structure="bvh")
    forms = {}
    for name, d in (("up", down * [1.0, 1.0, -1.0]), ("down", down)):
        obs[1].location.x += 0.25  # a change: a new session decides again
        r = addon.api.cast(o, d, structure="bvh")
        tracer = session.get(bpy.context.evaluated_depsgraph_get()).tracer("bvh")
        assert isinstance(tracer, core.Split), tracer
        forms[name] = tracer.moving is not None
        assert name == "down" or not r.hit.any()
    assert forms == {"up": True, "down": False}, forms


def test_a_deforming_mesh_is_rebuilt_flat_beside_a_moved_one_on_two_levels(fresh, addon):
    """A mesh read afresh (the wave deforms every frame) is built whatever its form, so it
    is rebuilt flat; a moved mesh kept from before stays on two levels when no ray passes
    near it; the hits equal a fresh flat extraction's."""
    scene, wave, mover, empty = _scene()
    session, core = addon.operators.session, addon.core
    o, d = _rays(3000)
    addon.api.cast(o, d, structure="bvh")
    scene.frame_set(5)  # the wave deforms
    mover.location.x += 0.5
    up = addon.api.cast(o, -d, structure="bvh")
    tracer = session.get(bpy.context.evaluated_depsgraph_get()).tracer("bvh")
    assert isinstance(tracer, core.Split) and tracer.moving is not None and tracer.moving.instance_count == 1
    assert len(tracer.soups) == 2, tracer  # the still placements, then the wave rebuilt
    whys = [p["why"] for p in up.scene["parts"]]
    assert "afresh" in whys[1] and "two levels" == up.scene["parts"][2]["form"], up.scene["parts"]
    r = addon.api.cast(o, d, structure="bvh")  # the same session: its structures as they are
    mesh, ref = _fresh_flat(addon, o, d)
    assert np.array_equal(r.hit, ref.hit) and np.allclose(r.t[r.hit], ref.t[ref.hit], rtol=1e-5, atol=1e-5)


def test_the_displacement_between_two_instants_is_the_largest_vertex_move(fresh, addon):
    """``Layout.displacement``: the same mesh moved (one product by M1 - M0) and a mesh
    that deforms (each end placed) both give the largest move of any vertex, as the world
    vertices of two flat extractions give it."""
    scene, wave, mover, empty = _scene()
    ext = addon.operators.extract
    cache = {}

    def state():
        dg = bpy.context.evaluated_depsgraph_get()
        return ext.scene_layout(dg, cache=cache)

    a = state()
    w0 = a.flat().vertices.astype(np.float64)
    mover.location.x += 0.7
    mover.rotation_euler.z += 0.3
    scene.frame_set(6)  # and the wave deforms
    b = state()
    w1 = b.flat().vertices.astype(np.float64)
    want = float(np.sqrt(((w1 - w0) ** 2).sum(axis=1).max()))
    assert a.displacement(b) == pytest.approx(want, rel=1e-6, abs=1e-6)
    assert a.displacement(a) == 0.0


def test_nan_vertices_in_one_object_leave_out_its_bad_triangles_with_one_warning(fresh, addon):
    from blender_scenes import make_nan

    add_cube("Fine", 1.0, (0.0, 0.0, 0.0))
    broken = add_cube("Broken", 1.0, (3.0, 0.0, 0.0))
    make_nan(broken)  # vertex 0: the three faces around it lose their triangles that use it
    bpy.context.view_layer.update()
    o = np.array([[0.0, 0.0, 5.0], [3.0, 0.0, 5.0], [3.0, 0.0, -5.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    with pytest.warns(RuntimeWarning, match=r"'Broken': \d+ triangles"):
        r = addon.api.cast(o, d)
    assert r.hit[0] and r.object_names[r.object_index[0]] == "Fine"
    assert r.hit[1] and r.object_names[r.object_index[1]] == "Broken", "the broken cube's good top face is traced"
    assert np.isclose(r.t[1], 4.5)
    with pytest.raises(addon.operators.jobs.InvalidGeometry, match="'Broken'"):
        addon.api.cast(o, d, strict=True)
    mesh = addon.operators.extract.scene_layout(bpy.context.evaluated_depsgraph_get())
    assert mesh.left_out and mesh.left_out[0][0] == ["Broken"] and 0 < mesh.left_out[0][1] < 12


def test_heavy_instancing_is_traced_on_two_levels_from_the_first_call(fresh, addon):
    """100 collection instances of one cube: the flat soup would hold 100 copies, so the first
    call already places one structure per mesh; every hit equals the flat brute force."""
    scene = bpy.context.scene
    coll = bpy.data.collections.new("Props")
    cube = add_cube("Cell", 0.8)
    scene.collection.objects.unlink(cube)
    coll.objects.link(cube)
    rng = np.random.default_rng(5)
    for i in range(100):
        e = bpy.data.objects.new(f"I{i}", None)
        e.instance_type, e.instance_collection = "COLLECTION", coll
        e.location = (*rng.uniform(-10, 10, 2), 0.0)
        e.rotation_euler = (0.0, 0.0, rng.uniform(0, 3))
        scene.collection.objects.link(e)
    bpy.context.view_layer.update()
    o = np.stack([rng.uniform(-10, 10, 2000), rng.uniform(-10, 10, 2000), np.full(2000, 5.0)], axis=1)
    d = np.array([0.05, 0.02, -1.0])
    addon.api.cast(o[:100], d)  # fewer rays than triangles: nothing is rebuilt flat, and the next call keeps it
    r = addon.api.cast(o, d)
    s = addon.operators.session.get(bpy.context.evaluated_depsgraph_get())
    assert s.instanced and not s.changed and "instanced" in r.scene, r.scene
    assert [p["form"] for p in r.scene["parts"]] == ["two levels"], r.scene
    assert s.layout._flat is None, "the flat soup was assembled"
    mesh = addon.operators.extract.scene_mesh(bpy.context.evaluated_depsgraph_get())
    ref = addon.core.build(mesh, "brute").trace(o, np.broadcast_to(d, o.shape))
    assert np.array_equal(r.hit, ref.hit) and np.allclose(r.t[ref.hit], ref.t[ref.hit], rtol=1e-5, atol=1e-5)
    other = np.flatnonzero(r.triangle != ref.triangle)
    # ties: a ray down a quad's diagonal, or onto the coplanar tops of two overlapping cubes, whose
    # t rounds differently in each instance's space; our triangle is hit there too, at the same t
    for i in other:
        a, b, c = mesh.tri_vertices[r.triangle[i]].astype(np.float64)
        p = o[i] + float(ref.t[i]) * d  # the reference's hit point, on our triangle too
        n = np.cross(b - a, c - a)
        area2 = np.linalg.norm(n)
        assert abs(np.dot(p - a, n)) / area2 < 1e-4, f"ray {i}: our triangle is not in the hit's plane"
        w = [np.dot(np.cross(y - x, p - x), n) / area2 ** 2 for x, y in ((b, c), (c, a), (a, b))]
        assert min(w) > -1e-4, f"ray {i}: the hit point is outside our triangle (barycentrics {w})"


def _assert_like_fresh_flat(addon, o, d, what):
    """Every hit of the session's cast equals a fresh flat extraction traced by brute force."""
    r = addon.api.cast(o, d, structure="bvh")
    mesh, ref = _fresh_flat(addon, o, np.broadcast_to(d, o.shape))
    assert np.array_equal(r.hit, ref.hit), f"{what}: hit differs on rays {np.flatnonzero(r.hit != ref.hit)[:10]}"
    h = ref.hit
    assert np.allclose(r.t[h], ref.t[h], rtol=1e-5, atol=1e-5), f"{what}: t differs"
    same = r.triangle[h] == ref.triangle[h]
    assert same.mean() > 0.99, f"{what}: {(~same).sum()} rays on another triangle"
    k = ref.triangle[h][same]
    assert np.array_equal(r.object_index[h][same], mesh.instances.instance_object[mesh.instance_index[k]]), what
    return r


def test_shared_meshes_swapped_data_and_new_instances_are_seen_at_the_next_call(fresh, addon):
    scene = bpy.context.scene
    add_plane("Ground", 20.0, z=-1.0)
    a = add_cube("A", 1.0, (-2.0, 0.0, 0.0))
    b = bpy.data.objects.new("B", a.data)  # a linked duplicate: one mesh, two objects
    b.location = (2.0, 0.0, 0.0)
    scene.collection.objects.link(b)
    other = add_cube("Other", 1.6, (0.0, 5.0, 0.0))
    bpy.context.view_layer.update()
    rng = np.random.default_rng(9)
    o = np.stack([rng.uniform(-4, 4, 1500), rng.uniform(-2, 7, 1500), np.full(1500, 6.0)], axis=1)
    d = np.array([0.0, 0.0, -1.0])
    _assert_like_fresh_flat(addon, o, d, "first call")
    b.location.x += 0.5  # one of two placements of a shared mesh moved
    _assert_like_fresh_flat(addon, o, d, "one instance moved")
    co = np.empty(len(a.data.vertices) * 3, np.float32)
    a.data.vertices.foreach_get("co", co)
    co[2::3] *= 1.8  # the shared mesh edited: both objects grow
    a.data.vertices.foreach_set("co", co)
    a.data.update()
    _assert_like_fresh_flat(addon, o, d, "shared mesh edited")
    b.data = other.data  # an object's data swapped
    _assert_like_fresh_flat(addon, o, d, "data swapped")
    coll = bpy.data.collections.new("Props")
    prop = add_cube("Prop", 0.7)
    scene.collection.objects.unlink(prop)
    coll.objects.link(prop)
    for i in range(3):  # the instance count changes
        e = bpy.data.objects.new(f"Props.{i}", None)
        e.instance_type, e.instance_collection = "COLLECTION", coll
        e.location = (-3.0 + 3.0 * i, 2.5, 0.0)
        scene.collection.objects.link(e)
        r = _assert_like_fresh_flat(addon, o, d, f"{i + 1} collection instances")
    hit_instances = set(r.instance_index[r.hit & (r.object_names[np.maximum(r.object_index, 0)] != "Ground")])
    assert len(hit_instances) >= 5, f"the new instances are not hit: {hit_instances}"


def test_the_analysis_json_says_how_the_scene_is_traced(fresh, addon):
    import json

    scene, wave, mover, empty = _scene()
    assert bpy.ops.hybrid_raycast.analyze() == {"FINISHED"}
    rec = json.loads(scene.hybrid_raycast.last_analysis_json)
    parts = rec["scene_structures"]["parts"]
    assert rec["scene_structures"]["placements"] == 4 and parts and all(p["why"] for p in parts), rec["scene_structures"]


def _scatter_and_wave(addon):
    """A static scatter of small triangles (where the numpy BVH beats the grid per ray) and a
    waving grid beside it (read afresh every frame); numpy structures only."""
    from blender_scenes import add_mesh

    scene = bpy.context.scene
    scene.hybrid_raycast.candidates = {"BVH"}
    m = addon.core.scenes.scatter(8000)
    lo, hi = m.bounds()
    add_mesh("Scatter", (m.vertices - lo) * (10.0 / float((hi - lo).max())) - 5.0, m.triangles.tolist())
    wave = add_plane("Wave", 4.0, z=0.0, location=(-3.0, 0.0, 0.0), subdivisions=16)
    wave.modifiers.new("w", "WAVE")
    scene.frame_set(1)
    return scene


def _parts(result):
    """(the still soup's choice, the part read afresh's choice) of a cast's scene description."""
    parts = [p for p in result.scene["parts"] if "choice" in p]
    still = [p["choice"] for p in parts if p["choice"]["what"] == "the placements that stayed put"]
    fresh = [p["choice"] for p in parts if p["choice"]["what"] == "rebuilt this call"]
    return still[0], fresh[0]


def test_each_part_chooses_its_structure_over_its_life_by_the_ski_rental_rule(fresh, addon):
    scene = _scatter_and_wave(addon)
    o, d = _rays(4_000, seed=3)
    addon.api.cast(o, d)  # the first call plans over the flat scene
    seen, switched = [], None
    for frame in range(2, 40):
        scene.frame_set(frame)
        r = addon.api.cast(o, d)
        still, part = _parts(r)
        seen.append(still)
        # the still soup expects as many rays again as it has served: the rays of each frame since the change
        assert still["rays_expected"] == pytest.approx(4_000 * (frame - 1))
        # the wave lives one frame: the rays passing near it in this one call, at the least total
        assert 0 < part["rays_expected"] < 4_000
        assert part["kind"] == min(part["totals"], key=lambda k: (part["totals"][k], k != "grid"))
        if switched is None and still["kind"] == "bvh":
            switched = frame
        if frame == 2 or frame == switched:  # the parts answer as a flat extraction of the scene now
            _mesh, ref = _fresh_flat(addon, o, d)
            assert np.array_equal(r.hit, ref.triangle >= 0)
            assert np.allclose(r.t[r.hit], ref.t[r.hit], rtol=1e-5, atol=1e-5)
        if switched is not None and frame > switched + 1:
            break
    assert switched is not None, f"the still soup never left the grid: {seen[-1]}"
    assert all(c["kind"] == "bvh" for c in seen[switched - 2:]), "a built BVH costs nothing more to keep"
    before = seen[switched - 3]  # the frame before the switch, the grid built already
    assert before["kind"] == "grid" and "grid" in before["built_already"]
    assert before["rays_expected"] <= before["break_even"] < seen[switched - 2]["rays_expected"]
    assert before["totals"]["grid"] <= before["totals"]["bvh"]


def test_a_job_that_says_its_calls_gives_the_lasting_parts_their_structure_at_once(fresh, addon):
    scene = _scatter_and_wave(addon)
    session = addon.operators.session
    o, d = _rays(4_000, seed=3)
    addon.api.cast(o, d)
    scene.frame_set(2)
    with session.expecting(200):
        r = addon.api.cast(o, d)
    still, part = _parts(r)
    assert still["kind"] == "bvh" and still["rays_expected"] == 200 * 4_000
    assert "the job's 200 calls" in still["life"]
    assert 0 < part["rays_expected"] < 4_000, "a part rebuilt every frame is chosen for its one frame"
    assert session.JOB[0] is None, "the hint ends with the job"
    # the panel draws the same parts
    from hybrid_raycast.ui.panel import part_lines

    lines = [t for t, _ in part_lines(addon.settings.PARTS[scene.name])]
    assert any(t.startswith("BVH, flat: 1 placements, 8,000 triangles") for t in lines), lines
    assert any("BVH: 800k rays over its life" in t for t in lines), lines


def test_a_hits_only_cast_gives_the_full_casts_fields_at_the_hits(fresh, addon):
    """The scan's cast (``hits_``: per-hit fields for the hits only) against the full cast,
    flat and on two levels, with a mirrored mover (its u and v trade places) and materials."""
    scene, wave, _mover, _empty = _scene()
    wave.modifiers.clear()
    big = add_plane("Big", 3.0, z=0.5, location=(0.0, 0.0, 0.0), subdivisions=20)
    big.scale.x = -1.0
    for frame, x in ((1, 0.0), (20, 2.0)):
        big.location.x = x
        big.keyframe_insert("location", frame=frame)
    query, session = addon.operators.query, addon.operators.session
    o, d = _rays(300, seed=5)
    for frame in (1, 2):
        scene.frame_set(frame)
        full = addon.api.cast(o, d, structure="bvh", materials=True)
        part = query.cast(o, d, structure="bvh", materials=True, points_=False, hits_=True)
        h = np.flatnonzero(full.hit)
        assert part.points is None and len(h) > 50
        for f in ("t", "hit", "triangle", "u", "v"):
            assert np.array_equal(getattr(part, f), getattr(full, f)), f
        for f in ("object_index", "instance_index", "polygon_index", "normals", "material_index"):
            assert np.array_equal(getattr(part, f), getattr(full, f)[h]), f
    forms = [p["form"] for p in session.get(bpy.context.evaluated_depsgraph_get()).describe()["parts"]]
    assert "two levels" in forms, forms
