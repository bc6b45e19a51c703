"""The script API's point queries (api.closest, inside, signed_distance, count_hits) on an
evaluated scene with moved, rotated, scaled and instanced objects, against Blender's own
BVHTree.find_nearest over the evaluated meshes in world space."""

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, add_plane, addon, fresh  # noqa: E402,F401

pytestmark = pytest.mark.blender


def scene():
    """A rotated, uniformly scaled cube; a moved cube linked twice (a linked duplicate); a plane."""
    a = add_cube("A", 2.0, (0.0, 0.0, 0.0))
    a.rotation_euler = (0.3, 0.2, 0.1)
    a.scale = (1.5, 1.5, 1.5)
    b = add_cube("B", 1.0, (4.0, 0.0, 0.0))
    c = bpy.data.objects.new("B.linked", b.data)
    c.location = (-4.0, 1.0, 0.5)
    bpy.context.scene.collection.objects.link(c)
    add_plane("Ground", 20.0, z=0.0, location=(0.0, 0.0, -3.0), subdivisions=4)
    bpy.context.view_layer.update()


def blender_nearest(points):
    """Blender's own answer: one world-space BVHTree over every evaluated mesh, a Python loop."""
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    dg = bpy.context.evaluated_depsgraph_get()
    verts, polys = [], []
    for ob in bpy.context.scene.objects:
        if ob.type != "MESH":
            continue
        ev = ob.evaluated_get(dg)
        me = ev.to_mesh()
        base = len(verts)
        verts += [ev.matrix_world @ v.co for v in me.vertices]
        polys += [[base + i for i in p.vertices] for p in me.polygons]
        ev.to_mesh_clear()
    tree = BVHTree.FromPolygons(verts, polys, all_triangles=False)
    out = [tree.find_nearest(Vector(p)) for p in points]
    return np.array([o[3] for o in out]), np.array([list(o[0]) for o in out])


def test_closest_agrees_with_blenders_find_nearest_and_has_every_field(fresh, addon):
    scene()
    api = addon.api
    pts = np.random.default_rng(0).uniform([-6, -3, -4], [6, 3, 3], size=(400, 3))
    c = api.closest(pts)
    dist, near = blender_nearest(pts)
    assert c.found.all() and c.structure in ("grid", "bvh")
    assert np.allclose(c.distance, dist, rtol=1e-5, atol=1e-5)
    assert np.allclose(c.points, near, atol=1e-4)
    names = c.object_names[c.object_index]
    assert set(names) <= {"A", "B", "B.linked", "Ground"} and len(set(names)) == 4
    assert np.allclose(np.linalg.norm(c.normals, axis=1), 1.0, atol=1e-5)
    m = c.instance_matrices[c.instance_index]
    assert m.shape == (400, 4, 4) and (c.polygon_index >= 0).all() and (c.triangle >= 0).all()
    one = api.closest(pts[0])
    assert one.distance.shape == (1,) and one.distance[0] == c.distance[0]


def test_closest_follows_the_scene_as_it_is_now_and_max_distance_misses(fresh, addon):
    scene()
    api = addon.api
    p = np.array([[4.0, 0.0, 2.0]])
    before = api.closest(p)
    assert before.distance[0] == pytest.approx(1.5, abs=1e-5) and before.object_names[before.object_index[0]] == "B"
    bpy.data.objects["B"].location.z = 1.0  # its top face from z = 0.5 to 1.5
    bpy.context.view_layer.update()
    assert api.closest(p).distance[0] == pytest.approx(0.5, abs=1e-5), "a moved object must be seen"
    far = api.closest(p, max_distance=0.4)
    assert not far.found[0] and far.distance[0] == math.inf and far.object_index[0] == -1
    assert np.isnan(far.points[0]).all() and np.isnan(far.normals[0]).all()


def test_inside_signed_distance_and_count_hits(fresh, addon):
    scene()
    api = addon.api
    pts = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [-4.0, 1.0, 0.5], [0.0, 0.0, 2.9], [10.0, 0.0, 0.0]])
    assert list(api.inside(pts)) == [True, True, True, False, False]
    sd = api.signed_distance(pts)
    assert (sd[:3] < 0).all() and (sd[3:] > 0).all()
    assert sd[1] == pytest.approx(-0.5, abs=1e-5)
    # down through B (two faces) onto the ground; and along x through every cube
    o = np.array([[4.0, 0.0, 5.0], [-10.0, 0.0, 0.0]])
    d = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    assert list(api.count_hits(o, d)) == [3, 4]
    assert list(api.count_hits(o, d, tmax=5.0)) == [1, 0]  # B's top only; short of A


def test_bad_points_are_errors_naming_the_argument(fresh, addon):
    scene()
    api = addon.api
    with pytest.raises(ValueError, match="points has 1 rows with NaN"):
        api.closest(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(ValueError, match="points must have shape"):
        api.inside(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="max_distance must be positive"):
        api.closest(np.zeros((1, 3)), max_distance=0.0)
    with pytest.raises(TypeError, match="points must hold real numbers"):
        api.signed_distance(np.array([["a", "b", "c"]]))


def test_closest_decides_between_grid_and_bvh_and_every_structure_answers_the_same(fresh, addon):
    """'auto' answers a sample on the grid and lets the decision for point queries pick the
    structure for the rest; a named structure answers all; the answers are the same."""
    scene()
    api = addon.api
    pts = np.random.default_rng(4).uniform([-6, -3, -4], [6, 3, 3], size=(3000, 3))
    auto = api.closest(pts)
    assert auto.structure in ("grid", "bvh") and (auto.break_even > 0 or math.isinf(auto.break_even))
    for kind in ("grid", "bvh"):
        got = api.closest(pts, structure=kind)
        assert got.structure == kind and math.isnan(got.break_even)
        assert np.array_equal(got.triangle, auto.triangle) and np.array_equal(got.distance, auto.distance)
    # the sidebar's Closest Points lines: the decision of that first call
    from hybrid_raycast.ui.panel import point_lines

    lines = [t for t, _ in point_lines(addon.settings.POINTS[bpy.context.scene.name])]
    assert lines[0].startswith(("Grid for 3,000 points", "BVH for 3,000 points")) and "Grid sample: 256 points" in lines
    assert any(t.startswith("BVH beats the grid ") for t in lines) and lines[-1].startswith("(least estimated total")
    # the session's BVH is built now: it answers without a sample
    again = api.closest(pts[:10])
    assert again.structure == "bvh"
    assert point_lines(addon.settings.POINTS[bpy.context.scene.name])[-1][0] == "(the session's BVH is built)"
    with pytest.raises(ValueError, match="structure"):
        api.closest(pts, structure="octree")


def test_closest_after_casts_of_a_changed_scene_uses_the_session_as_it_is(fresh, addon):
    """Casts of a scene that changed between calls leave two-level structures in the session;
    a closest-point query then still decides on the flat ones and answers as Blender does."""
    scene()
    api = addon.api
    d = np.random.default_rng(1).normal(size=(2000, 3))
    api.cast((0.0, -8.0, 0.5), d)
    bpy.data.objects["B"].location.x += 0.5
    bpy.context.view_layer.update()
    api.cast((0.0, -8.0, 0.5), d)
    session = addon.operators.session
    assert any(len(k) == 3 for s in session.SESSIONS.values() for k in s.structures), "no two-level structure"
    pts = np.random.default_rng(5).uniform([-6, -3, -4], [6, 3, 3], size=(500, 3))
    c = api.closest(pts)
    dist, _ = blender_nearest(pts)
    assert np.allclose(c.distance, dist, rtol=1e-5, atol=1e-5)
