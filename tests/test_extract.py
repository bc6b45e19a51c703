"""operators/extract.py: the scene Blender would render, as world-space triangles.

Every check compares against an independent reference: Blender's own evaluated meshes
read per face with bmesh and transformed with mathutils, Blender's ``Scene.ray_cast``,
or analytic values of known primitives.
"""

from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402
from mathutils import Matrix, Vector  # noqa: E402
from mathutils.geometry import area_tri  # noqa: E402

from hybrid_raycast.operators import extract  # noqa: E402

pytestmark = pytest.mark.blender

SRC_CUBE = 2.0  # edge of the collection-instanced cube
GN_CUBE = 0.5  # edge of the cube placed by geometry nodes
GN_COUNT = 5
CI_SCALES = [(1.0, 2.0, 3.0), (2.0, 1.0, 0.5), (-1.0, 1.5, 1.0)]


# -- scene building --------------------------------------------------------------------

def _cube_mesh(name, size):
    me = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=size)
    bm.to_mesh(me)
    bm.free()
    return me


def _link(name, data, location=(0.0, 0.0, 0.0), collection=None):
    ob = bpy.data.objects.new(name, data)
    ob.location = location
    (collection or bpy.context.scene.collection).objects.link(ob)
    return ob


def _scatter_tree(instance_object, count):
    """Mesh Line (count points, 2 apart on x) -> Instance on Points of Object Info(object)."""
    ng = bpy.data.node_groups.new("Scatter", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    line = ng.nodes.new("GeometryNodeMeshLine")
    line.inputs["Count"].default_value = count
    line.inputs["Offset"].default_value = (2.0, 0.0, 0.0)
    info = ng.nodes.new("GeometryNodeObjectInfo")
    info.inputs["Object"].default_value = instance_object
    on_points = ng.nodes.new("GeometryNodeInstanceOnPoints")
    out = ng.nodes.new("NodeGroupOutput")
    ng.links.new(line.outputs["Mesh"], on_points.inputs["Points"])
    ng.links.new(info.outputs["Geometry"], on_points.inputs["Instance"])
    ng.links.new(on_points.outputs["Instances"], out.inputs["Geometry"])
    return ng


def build_scene():
    """The test scene. Visible: Subdiv, CI0..CI2 (collection instances of SrcCube, one
    mirrored), GNCube (the object geometry nodes instance, visible itself too), GNHost
    (five instances of GNCube), Text. Hidden in every way: the rest (names start with Hid
    or InRenderOff)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    vl = bpy.context.view_layer

    sub = _link("Subdiv", _cube_mesh("SubdivMesh", 2.0), (0.0, 0.0, 0.0))
    mod = sub.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = 2
    sub.rotation_euler = (0.3, 0.2, 0.1)

    src = bpy.data.collections.new("Src")
    scene.collection.children.link(src)
    _link("SrcCube", _cube_mesh("SrcCubeMesh", SRC_CUBE), collection=src)
    # hide_render inside an instanced collection: Blender's viewport depsgraph still lists it
    _link("HidInCollection", _cube_mesh("HidInCollectionMesh", 1.0), (0.0, 5.0, 0.0), collection=src).hide_render = True
    vl.layer_collection.children["Src"].exclude = True  # seen only through its instances
    for i, s in enumerate(CI_SCALES):
        e = _link(f"CI{i}", None, (10.0 + 6.0 * i, 1.0, -2.0))
        e.instance_type = "COLLECTION"
        e.instance_collection = src
        e.scale = s
        e.rotation_euler = (0.0, 0.0, 0.25 * i)

    gn_cube = _link("GNCube", _cube_mesh("GNCubeMesh", GN_CUBE), (0.0, -50.0, 0.0))
    host = _link("GNHost", bpy.data.meshes.new("HostMesh"), (0.0, 10.0, 0.0))
    host.modifiers.new("Scatter", "NODES").node_group = _scatter_tree(gn_cube, GN_COUNT)

    text = bpy.data.curves.new("TextCurve", "FONT")
    text.body = "Hi"
    _link("Text", text, (0.0, 20.0, 1.0))

    for name, how in [("HidSet", "set"), ("HidViewport", "viewport"), ("HidRender", "render")]:
        ob = _link(name, _cube_mesh(name + "Mesh", 1.0), (0.0, -20.0, 0.0))
        _hide(ob, how)
    for name, how in [("HidInstSet", "set"), ("HidInstViewport", "viewport"), ("HidInstRender", "render")]:
        e = _link(name, None, (0.0, -30.0, 0.0))
        e.instance_type = "COLLECTION"
        e.instance_collection = src
        _hide(e, how)
    off = bpy.data.collections.new("RenderOff")
    scene.collection.children.link(off)
    off.hide_render = True
    _link("InRenderOffCollection", _cube_mesh("OffMesh", 1.0), (0.0, -40.0, 0.0), collection=off)
    return bpy.context.evaluated_depsgraph_get()


def _hide(ob, how):
    if how == "set":
        ob.hide_set(True)
    elif how == "viewport":
        ob.hide_viewport = True
    else:
        ob.hide_render = True


VISIBLE = {"Subdiv", "CI0/SrcCube", "CI1/SrcCube", "CI2/SrcCube", "GNCube", "GNHost/GNCubeMesh", "Text"}


# -- independent references ---------------------------------------------------------------

def _reference(ob, depsgraph, matrices):
    """(triangles, area, lo, hi) of an object's evaluated mesh placed at each matrix,
    computed face by face with bmesh and mathutils (a copy made by new_from_object)."""
    ob_eval = ob.evaluated_get(depsgraph)
    me = bpy.data.meshes.new_from_object(ob_eval, depsgraph=depsgraph)
    try:
        tris, area, pts = 0, 0.0, []
        for m in matrices:
            bm = bmesh.new()
            bm.from_mesh(me)
            bm.transform(m)
            tris += sum(len(f.verts) - 2 for f in bm.faces)
            # non-planar quads: the area of the surface a renderer sees is that of
            # BMesh's own triangulation (a code path apart from Mesh.loop_triangles)
            area += sum(area_tri(*(loop.vert.co for loop in lt)) for lt in bm.calc_loop_triangles())
            pts += [tuple(v.co) for f in bm.faces for v in f.verts]
            bm.free()
    finally:
        bpy.data.meshes.remove(me)
    pts = np.array(pts)
    return tris, area, pts.min(axis=0), pts.max(axis=0)


def _scene_reference(depsgraph):
    objs = bpy.data.objects
    src = objs["SrcCube"]
    gn_cube = objs["GNCube"]
    host = objs["GNHost"]
    gn_mats = [Matrix.Translation(host.location + Vector((2.0 * i, 0.0, 0.0))) for i in range(GN_COUNT)]
    return {
        "Subdiv": _reference(objs["Subdiv"], depsgraph, [objs["Subdiv"].matrix_world]),
        **{f"CI{i}/SrcCube": _reference(src, depsgraph, [objs[f"CI{i}"].matrix_world @ src.matrix_world])
           for i in range(3)},
        "GNCube": _reference(gn_cube, depsgraph, [gn_cube.matrix_world]),
        "GNHost/GNCubeMesh": _reference(gn_cube, depsgraph, gn_mats),
        "Text": _reference(objs["Text"], depsgraph, [objs["Text"].matrix_world]),
    }


def _part(mesh, name):
    """(triangle indices, (n, 3, 3) float64 corners) of one entry of object_names."""
    i = mesh.object_names.index(name)
    sel = np.flatnonzero(mesh.object_index == i)
    return sel, mesh.vertices[mesh.triangles[sel]].astype(np.float64)


def _signed_volume(corners):
    return float(np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6.0)


def _nearest_hit(mesh, origin, direction):
    """Index of the nearest triangle a ray hits, float64 Moller-Trumbore over all triangles."""
    tv = mesh.vertices[mesh.triangles].astype(np.float64)
    o, d = np.asarray(origin, float), np.asarray(direction, float)
    e1, e2 = tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - tv[:, 0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(ok, t, np.inf)
    k = int(np.argmin(t))
    return (k, float(t[k])) if np.isfinite(t[k]) else (-1, np.inf)


# -- tests -----------------------------------------------------------------------------------

def test_extracts_exactly_the_visible_render_enabled_sources():
    mesh = extract.scene_mesh(build_scene())
    assert set(mesh.object_names) == VISIBLE, f"extracted {sorted(mesh.object_names)}, expected {sorted(VISIBLE)}"
    for name in mesh.object_names:
        assert "Hid" not in name and "InRenderOff" not in name, f"hidden object {name} was extracted"
    # nothing from where the hidden objects stand (y = -20, -30, -40)
    near_hidden = (mesh.tri_vertices[:, :, 1] < -15) & (mesh.tri_vertices[:, :, 1] > -45)
    assert not near_hidden.any(), "triangles found where only hidden objects are"


def test_triangles_area_and_bounds_match_blenders_evaluated_meshes_per_source():
    depsgraph = build_scene()
    mesh = extract.scene_mesh(depsgraph)
    ref = _scene_reference(depsgraph)
    for name, (n, area, lo, hi) in ref.items():
        sel, corners = _part(mesh, name)
        assert len(sel) == n, f"{name}: {len(sel)} triangles, Blender's evaluated mesh has {n}"
        got_area = float(0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                                              axis=1).sum())
        assert got_area == pytest.approx(area, rel=1e-5), f"{name}: area {got_area} != reference {area}"
        pts = corners.reshape(-1, 3)
        np.testing.assert_allclose(pts.min(axis=0), lo, atol=1e-4, err_msg=f"{name}: lower bound")
        np.testing.assert_allclose(pts.max(axis=0), hi, atol=1e-4, err_msg=f"{name}: upper bound")
    total_tris = sum(r[0] for r in ref.values())
    assert mesh.triangle_count == total_tris
    assert mesh.surface_area() == pytest.approx(sum(r[1] for r in ref.values()), rel=1e-5)
    lo, hi = mesh.bounds()
    np.testing.assert_allclose(lo, np.min([r[2] for r in ref.values()], axis=0), atol=1e-4)
    np.testing.assert_allclose(hi, np.max([r[3] for r in ref.values()], axis=0), atol=1e-4)


def test_known_primitives_have_their_analytic_counts_and_areas():
    mesh = extract.scene_mesh(build_scene())
    assert (mesh.object_index == mesh.object_names.index("Subdiv")).sum() == 6 * 16 * 2  # level 2: 16 quads a face
    for i, s in enumerate(CI_SCALES):
        sel, corners = _part(mesh, f"CI{i}/SrcCube")
        assert len(sel) == 12
        sx, sy, sz = (abs(c) * SRC_CUBE for c in s)
        area = 2 * (sx * sy + sy * sz + sx * sz)
        got = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
        assert got == pytest.approx(area, rel=1e-5), f"CI{i}: area {got}, a {sx}x{sy}x{sz} box has {area}"
    sel, corners = _part(mesh, "GNHost/GNCubeMesh")
    assert len(sel) == 12 * GN_COUNT
    h = GN_CUBE / 2
    np.testing.assert_allclose(corners.reshape(-1, 3).min(axis=0), (-h, 10 - h, -h), atol=1e-6)
    np.testing.assert_allclose(corners.reshape(-1, 3).max(axis=0), (2 * (GN_COUNT - 1) + h, 10 + h, h), atol=1e-6)
    info = mesh.source_info
    assert info.instances[mesh.object_names.index("GNHost/GNCubeMesh")] == GN_COUNT
    assert info.instancer[mesh.object_names.index("CI2/SrcCube")] == "CI2"
    assert info.source[mesh.object_names.index("CI2/SrcCube")] == "SrcCube"


def test_text_curve_surface_and_metaball_are_counted_once():
    """Blender lists each of them twice in object_instances (their own entry and a MESH
    instance whose parent is the object); the extractor must count their triangles once."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.object.text_add(location=(0, 0, 0))
    bpy.ops.curve.primitive_bezier_circle_add(location=(5, 0, 0))
    bpy.context.object.data.bevel_depth = 0.2
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(location=(10, 0, 0))
    bpy.ops.object.metaball_add(location=(15, 0, 0))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    doubled = [i.object.name for i in depsgraph.object_instances if i.is_instance and i.object.type == "MESH"]
    assert len(doubled) == 4, f"the pitfall this guards against is no longer there: {doubled}"
    mesh = extract.scene_mesh(depsgraph)
    assert sorted(mesh.object_names) == sorted(o.name for o in bpy.data.objects)
    for ob in bpy.data.objects:
        n, area, lo, hi = _reference(ob, depsgraph, [ob.matrix_world])
        got = int((mesh.object_index == mesh.object_names.index(ob.name)).sum())
        assert n > 0 and got == n, f"{ob.name} ({ob.type}): {got} triangles extracted, its evaluated mesh has {n}"


def test_mirrored_instances_keep_outward_winding():
    """A closed cube keeps a positive signed volume (normals outward) under every
    placement, including the mirrored one (det < 0); the volume is |det| x the cube's."""
    mesh = extract.scene_mesh(build_scene())
    for i, s in enumerate(CI_SCALES):
        _, corners = _part(mesh, f"CI{i}/SrcCube")
        vol = _signed_volume(corners)
        expect = abs(np.prod(s)) * SRC_CUBE ** 3
        assert vol == pytest.approx(expect, rel=1e-5), f"CI{i} (scale {s}): signed volume {vol}, expected +{expect}"
    _, corners = _part(mesh, "GNHost/GNCubeMesh")
    assert _signed_volume(corners) == pytest.approx(GN_COUNT * GN_CUBE ** 3, rel=1e-5)
    _, corners = _part(mesh, "Subdiv")
    assert _signed_volume(corners) > 0


def test_selected_only_keeps_selected_objects_and_instances_of_selected_instancers():
    depsgraph = build_scene()
    for ob in bpy.data.objects:
        if ob.visible_get():  # objects hidden or in excluded collections cannot be (de)selected
            ob.select_set(False)
    bpy.data.objects["Subdiv"].select_set(True)
    bpy.data.objects["CI2"].select_set(True)
    bpy.data.objects["GNHost"].select_set(True)
    mesh = extract.scene_mesh(depsgraph, selected_only=True)
    assert set(mesh.object_names) == {"Subdiv", "CI2/SrcCube", "GNHost/GNCubeMesh"}
    assert mesh.triangle_count == 192 + 12 + 12 * GN_COUNT
    # selecting the instanced object itself does not select its instances
    for ob in bpy.data.objects:
        if ob.visible_get():
            ob.select_set(False)
    bpy.data.objects["GNCube"].select_set(True)
    mesh = extract.scene_mesh(depsgraph, selected_only=True)
    assert mesh.object_names == ["GNCube"]


def test_selected_only_with_nothing_selected_is_a_clear_error():
    depsgraph = build_scene()
    for ob in bpy.data.objects:
        if ob.visible_get():
            ob.select_set(False)
    with pytest.raises(extract.NoGeometryError, match="selected"):
        extract.scene_mesh(depsgraph, selected_only=True)


def test_empty_scene_is_a_clear_error():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with pytest.raises(extract.NoGeometryError) as err:
        extract.scene_mesh(bpy.context.evaluated_depsgraph_get())
    assert "no objects" in str(err.value) and "\n" not in str(err.value)
    assert isinstance(err.value, ValueError)


def test_scene_without_geometry_is_a_clear_error():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    _link("Camera", bpy.data.cameras.new("Camera"), (0, -5, 0))
    _link("Light", bpy.data.lights.new("Light", "POINT"), (0, 0, 5))
    _link("Empty", None)
    with pytest.raises(extract.NoGeometryError) as err:
        extract.scene_mesh(bpy.context.evaluated_depsgraph_get())
    msg = str(err.value)
    assert "triangles" in msg and scene.name in msg and "\n" not in msg


def test_polygon_and_object_index_of_a_hit_match_blenders_scene_ray_cast():
    depsgraph = build_scene()
    mesh = extract.scene_mesh(depsgraph)
    scene = bpy.context.scene
    objs = bpy.data.objects
    rays = [  # (origin, direction, the source it should hit)
        ((0.05, 0.07, 10.0), (0.0, 0.0, -1.0), "Subdiv"),
        ((-6.0, 0.3, 0.2), (1.0, 0.01, 0.02), "Subdiv"),
        ((objs["CI1"].location.x + 0.3, 10.0 - 9.3, 10.0), (0.0, 0.0, -1.0), "CI1/SrcCube"),
        ((objs["CI2"].location.x + 0.2, 1.3, 10.0), (0.0, 0.0, -1.0), "CI2/SrcCube"),
        ((objs["CI2"].location.x - 0.3, 0.6, -10.0), (0.01, 0.0, 1.0), "CI2/SrcCube"),
        ((objs["CI2"].location.x + 10.0, 1.2, -1.7), (-1.0, 0.0, 0.0), "CI2/SrcCube"),
        ((4.1, 10.1, 5.0), (0.0, 0.0, -1.0), "GNHost/GNCubeMesh"),
    ]
    for origin, direction, expect in rays:
        hit, location, normal, polygon, ob, matrix = scene.ray_cast(depsgraph, Vector(origin), Vector(direction))
        assert hit, f"Blender's ray from {origin} missed (test set-up)"
        k, t = _nearest_hit(mesh, origin, direction)
        assert k >= 0, f"ray from {origin} hit Blender's {ob.name} but no extracted triangle"
        got = mesh.object_names[mesh.object_index[k]]
        # Blender names the instanced object, or for geometry-nodes instances the host
        assert ob.name in expect.split("/"), f"test set-up: Blender's ray hit {ob.name}, not {expect}"
        assert got == expect, f"ray from {origin}: hit {got}, expected {expect}"
        assert mesh.polygon_index[k] == polygon, (
            f"ray from {origin} into {expect}: polygon {mesh.polygon_index[k]}, Blender's ray_cast says {polygon}")
        where = np.asarray(origin) + t * np.asarray(direction)
        np.testing.assert_allclose(where, location, atol=1e-4, err_msg=f"hit point of the ray from {origin}")


def test_each_triangle_lies_on_the_polygon_its_index_names():
    """Every triangle's corners are corners of polygon ``polygon_index`` of its source's
    evaluated mesh (placed in world space)."""
    depsgraph = build_scene()
    mesh = extract.scene_mesh(depsgraph)
    objs = bpy.data.objects
    for name, ob, m in [("Subdiv", objs["Subdiv"], objs["Subdiv"].matrix_world),
                        ("CI2/SrcCube", objs["SrcCube"], objs["CI2"].matrix_world)]:
        me = ob.evaluated_get(depsgraph).data
        sel, corners = _part(mesh, name)
        for k, tri in zip(sel, corners):
            poly = me.polygons[int(mesh.polygon_index[k])]
            pc = np.array([tuple(m @ me.vertices[v].co) for v in poly.vertices])
            d = np.linalg.norm(tri[:, None, :] - pc[None], axis=2).min(axis=1)
            assert d.max() < 1e-4, f"{name}: triangle {k} is not on polygon {poly.index}"


def test_triangulation_matches_blenders_loop_triangles_for_quads_concave_quads_and_ngons():
    """The numpy quad rule (and the fallback to loop_triangles) give Blender's triangles."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    verts = [(0, 0, 0), (2, 1, 0), (0, 2, 0), (0.5, 1, 0),  # a dart: the 0-2 diagonal lies outside
             (3, 0, 0), (4, 0, 0), (4, 1, 1), (3, 1, 0),  # a non-planar quad
             (5, 0, 0), (6, 0, 0), (6, 1, 0),  # a triangle
             (7, 0, 0), (8, 0, 0), (8.5, 1, 0), (7.5, 2, 0), (7, 1, 0),  # a pentagon
             (0, 0, 3), (0, 2, 3.5), (0, 0, 4), (-2, 1, 3.5)]  # a fold Blender's two tests split differently
    faces = [(0, 1, 2, 3), (4, 5, 6, 7), (8, 9, 10)]
    meshes = {"Shapes": faces, "Ngon": faces + [(11, 12, 13, 14, 15)], "Fold": faces + [(16, 17, 18, 19)]}
    fast = {"Shapes": True, "Grid": True, "Ngon": False, "Fold": False}
    for name, f in meshes.items():
        me = bpy.data.meshes.new(name)
        me.from_pydata(verts, [], f)
        _link(name, me)
    grid = bpy.data.meshes.new("Grid")
    bm = bmesh.new()
    bmesh.ops.create_grid(bm, x_segments=20, y_segments=20, size=1.0)
    rng = np.random.default_rng(1)
    for v in bm.verts:
        v.co.z += rng.normal() * 0.02  # gently non-planar quads (stronger noise folds some)
    bm.to_mesh(grid)
    bm.free()
    _link("Grid", grid)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for name, used_fast in fast.items():
        m_eval = bpy.data.objects[name].evaluated_get(depsgraph).data
        co, tris, poly = extract.mesh_triangles(m_eval)
        n = len(m_eval.loop_triangles)
        ref = np.empty(n * 3, np.int32)
        m_eval.loop_triangles.foreach_get("vertices", ref)
        ref_poly = np.array([t.polygon_index for t in m_eval.loop_triangles])
        np.testing.assert_array_equal(tris, ref.reshape(n, 3), err_msg=f"{name}: triangles differ from Blender's")
        np.testing.assert_array_equal(poly, ref_poly, err_msg=f"{name}: polygon indices differ")
        np.testing.assert_array_equal(co, np.array([tuple(v.co) for v in m_eval.vertices], np.float32))
        if name != "Ngon":  # which path was taken: the numpy rule, or Blender's loop_triangles
            got_fast = extract._tris_and_quads(m_eval, co, poly, np.bincount(poly)) is not None
            assert got_fast == used_fast, f"{name}: numpy quad rule used: {got_fast}, expected {used_fast}"


def test_particle_instances_and_emitter_are_extracted():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    piece = _link("Piece", _cube_mesh("PieceMesh", 0.2), (0.0, 0.0, -30.0))
    emitter = _link("Emitter", _cube_mesh("EmitterMesh", 2.0))
    psys = emitter.modifiers.new("Particles", "PARTICLE_SYSTEM").particle_system
    psys.settings.count = 7
    psys.settings.frame_start = psys.settings.frame_end = 1
    psys.settings.render_type = "OBJECT"
    psys.settings.instance_object = piece
    scene.frame_set(1)
    mesh = extract.scene_mesh(bpy.context.evaluated_depsgraph_get())
    counts = dict(zip(mesh.object_names, mesh.source_info.instances))
    assert counts == {"Emitter": 1, "Emitter/Piece": 7, "Piece": 1}, counts
    emitter.show_instancer_for_render = False
    mesh = extract.scene_mesh(bpy.context.evaluated_depsgraph_get())
    assert "Emitter" not in mesh.object_names and "Emitter/Piece" in mesh.object_names


def test_summary_and_progress():
    depsgraph = build_scene()
    seen = []
    mesh = extract.scene_mesh(depsgraph, progress=seen.append)
    assert seen and seen[-1] == 1.0 and all(0.0 <= f <= 1.0 for f in seen) and seen == sorted(seen)
    s = extract.scene_summary(depsgraph, mesh, 0.25)
    assert s["triangles"] == mesh.triangle_count
    assert s["objects"] == 7  # Subdiv, CI0, CI1, CI2, GNCube, GNHost, Text
    assert s["instances"] == 3 + GN_COUNT
    assert s["extraction_seconds"] == 0.25
    lo, hi = mesh.bounds()
    assert s["bounds"] == [lo.tolist(), hi.tolist()]
