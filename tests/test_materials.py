"""Materials per hit (extraction, ``cast(materials=True)``) and their LiDAR optics
(``operators.materials``).

The material of a hit is checked against Blender's own answer: ``scene.ray_cast``'s
polygon, its ``material_index`` and the evaluated object's ``material_slots`` (Blender's
render rule on an evaluated object).  Optics are checked against values set on the nodes.
"""

from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, addon, fresh  # noqa: E402,F401

pytestmark = pytest.mark.blender

# add_cube's faces: -z, +z, -y, +x, +y, -x; a ray from outside at each face's centre
FACE_DIRS = np.array([(0, 0, -1), (0, 0, 1), (0, -1, 0), (1, 0, 0), (0, 1, 0), (-1, 0, 0)], np.float64)


def material(name, color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5, transmission=0.0, alpha=1.0):
    m = bpy.data.materials.new(name)
    if m.node_tree is None or bpy.app.version < (5, 0, 0):  # before 5.0 a new material has no nodes in use
        m.use_nodes = True
    p = m.node_tree.nodes["Principled BSDF"]
    p.inputs["Base Color"].default_value = (*color, 1.0)
    p.inputs["Metallic"].default_value = metallic
    p.inputs["Roughness"].default_value = roughness
    p.inputs["Transmission Weight"].default_value = transmission
    p.inputs["Alpha"].default_value = alpha
    return m


def face_rays(location, size=2.0):
    """(origins, directions): one ray per face of a cube at ``location``, from 3 units out."""
    c = np.asarray(location, np.float64)
    return c + FACE_DIRS * (size / 2 + 3.0), -FACE_DIRS


def blender_materials(origins, directions):
    """Per ray, the name of the material Blender renders the hit polygon with (None: none)."""
    from mathutils import Vector

    dg = bpy.context.evaluated_depsgraph_get()
    out = []
    for o, d in zip(origins, directions):
        ok, _loc, _n, face, ob, _m = bpy.context.scene.ray_cast(dg, Vector(o.tolist()), Vector(d.tolist()))
        assert ok, f"Blender's ray_cast from {o} missed"
        slots = ob.material_slots
        if not len(slots):
            out.append(None)
            continue
        idx = min(max(ob.data.polygons[face].material_index, 0), len(slots) - 1)  # Blender clamps
        m = slots[idx].material
        out.append(m.name if m is not None else None)
    return out


def hit_names(r):
    return [r.material_names[i] if i >= 0 else None for i in r.material_index]


def two_material_cube(name="Cube", location=(0.0, 0.0, 0.0)):
    """A cube whose -z, +z, -y faces use slot 0 ('A') and +x, +y, -x slot 1 ('B')."""
    a = bpy.data.materials.get("A") or material("A", (0.2, 0.4, 0.6))
    b = bpy.data.materials.get("B") or material("B", (0.9, 0.9, 0.9))
    ob = add_cube(name, 2.0, location)
    ob.data.materials.append(a)
    ob.data.materials.append(b)
    ob.data.polygons.foreach_set("material_index", np.array([0, 0, 0, 1, 1, 1], np.int32))
    ob.data.update()
    return ob


def test_each_face_reports_the_material_of_its_slot(fresh, addon):
    two_material_cube()
    bpy.context.view_layer.update()
    o, d = face_rays((0.0, 0.0, 0.0))
    r = addon.api.cast(o, d, materials=True)
    assert r.hit.all()
    got, want = hit_names(r), blender_materials(o, d)
    assert got == want == ["A", "A", "A", "B", "B", "B"], f"faces: ours {got}, Blender's {want}"
    assert all(isinstance(m, bpy.types.Material) for m in r.materials)
    assert r.material_index.dtype == np.int32


def test_object_linked_slot_and_linked_duplicates_keep_each_objects_material(fresh, addon):
    """One mesh, three placements: the data's materials, a linked duplicate whose slot 0 is
    object-linked to 'C', and a collection instance of that duplicate."""
    cube = two_material_cube("Cube")
    dup = bpy.data.objects.new("Dup", cube.data)
    dup.location = (10.0, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(dup)
    dup.material_slots[0].link = "OBJECT"
    dup.material_slots[0].material = material("C", (0.1, 0.1, 0.1))
    coll = bpy.data.collections.new("Src")
    coll.objects.link(dup)
    inst = bpy.data.objects.new("Inst", None)
    inst.instance_type, inst.instance_collection, inst.location = "COLLECTION", coll, (0.0, 10.0, 0.0)
    bpy.context.scene.collection.objects.link(inst)
    bpy.context.view_layer.update()
    for where, want in (((0.0, 0.0, 0.0), ["A"] * 3 + ["B"] * 3), ((10.0, 0.0, 0.0), ["C"] * 3 + ["B"] * 3),
                        ((10.0, 10.0, 0.0), ["C"] * 3 + ["B"] * 3)):
        o, d = face_rays(where)
        r = addon.api.cast(o, d, materials=True)
        got = hit_names(r)
        assert got == want, f"cube at {where}: {got}, expected {want}"
        assert got == blender_materials(o, d), f"cube at {where}: Blender renders {blender_materials(o, d)}"
    mats = addon.api.cast(*face_rays((0.0, 0.0, 0.0)), materials=True).materials
    assert sorted(m.name for m in mats) == ["A", "B", "C"], "each material once, none unused"


def test_slot_past_the_end_takes_the_last_slot_and_no_slots_give_none(fresh, addon):
    ob = two_material_cube()
    ob.data.polygons.foreach_set("material_index", np.array([7, 0, 0, 1, 1, 1], np.int32))
    ob.data.update()
    add_cube("Bare", 2.0, (0.0, 10.0, 0.0))
    bpy.context.view_layer.update()
    o, d = face_rays((0.0, 0.0, 0.0))
    r = addon.api.cast(o[:1], d[:1], materials=True)
    assert hit_names(r) == ["B"] == blender_materials(o[:1], d[:1]), "index 7 of 2 slots renders slot 1"
    o, d = face_rays((0.0, 10.0, 0.0))
    r = addon.api.cast(np.vstack([o, [[100.0, 100.0, 100.0]]]), np.vstack([d, [[0.0, 0.0, 1.0]]]), materials=True)
    assert (r.material_index == -1).all(), f"no slots and a miss: {r.material_index}"


def test_a_changed_slot_material_is_seen_by_the_next_cast(fresh, addon):
    ob = two_material_cube()
    bpy.context.view_layer.update()
    o, d = face_rays((0.0, 0.0, 0.0))
    assert addon.api.cast(o, d).material_index is None  # the session exists without materials
    assert hit_names(addon.api.cast(o, d, materials=True))[:3] == ["A"] * 3
    ob.material_slots[0].link = "OBJECT"
    ob.material_slots[0].material = material("D")
    bpy.context.view_layer.update()
    assert hit_names(addon.api.cast(o, d, materials=True)) == ["D"] * 3 + ["B"] * 3


def test_cast_without_materials_leaves_the_fields_none(fresh, addon):
    two_material_cube()
    bpy.context.view_layer.update()
    r = addon.api.cast(*face_rays((0.0, 0.0, 0.0)))
    assert r.material_index is None and r.materials is None and r.material_names is None
    assert "material_index" not in r.as_dict()
    r = addon.api.cast(*face_rays((0.0, 0.0, 0.0)), materials=True)
    assert list(r.as_dict()["material_names"][r.as_dict()["material_index"]]) == ["A"] * 3 + ["B"] * 3


# -- optics ---------------------------------------------------------------------------------

def optics_module(addon):
    import importlib

    return importlib.import_module(addon.__name__ + ".operators.materials")


def test_principled_inputs_give_reflectivity_transmission_and_mirror(fresh, addon):
    mats = [material("Paint", (0.2, 0.4, 0.6)), material("Glass", transmission=1.0),
            material("Chrome", metallic=1.0, roughness=0.05), material("Brushed", metallic=1.0, roughness=0.5),
            material("Leaf", alpha=0.25)]
    opt = optics_module(addon).optics(mats)
    np.testing.assert_allclose(opt.reflectivity[0], 0.4, atol=1e-6, err_msg="mean of (0.2, 0.4, 0.6)")
    assert opt.transmission.tolist() == [0.0, 1.0, 0.0, 0.0, 0.75], f"transmission {opt.transmission}"
    assert opt.mirror.tolist() == [False, False, True, False, False], f"mirror {opt.mirror}"
    assert opt.metallic[2] == 1.0 and np.isclose(opt.roughness[2], 0.05)
    for a in (opt.reflectivity, opt.metallic, opt.roughness, opt.transmission):
        assert a.dtype == np.float32 and a.shape == (5,)


def test_a_linked_base_colour_or_no_principled_falls_back_to_the_viewport_colour(fresh, addon):
    tex = material("Textured", (0.9, 0.9, 0.9))
    tex.diffuse_color = (0.1, 0.2, 0.3, 1.0)
    img = tex.node_tree.nodes.new("ShaderNodeTexImage")
    tex.node_tree.links.new(img.outputs["Color"], tex.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    emit = bpy.data.materials.new("Emitter")
    if emit.node_tree is None or bpy.app.version < (5, 0, 0):
        emit.use_nodes = True
    nt = emit.node_tree
    nt.nodes.remove(nt.nodes["Principled BSDF"])
    e = nt.nodes.new("ShaderNodeEmission")
    nt.links.new(e.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    emit.diffuse_color, emit.metallic, emit.roughness = (0.3, 0.3, 0.6, 0.5), 0.9, 0.1
    mixed = material("Mixed", (0.5, 0.5, 0.5), metallic=1.0, roughness=0.0)  # Principled behind a Mix Shader
    nt = mixed.node_tree
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(nt.nodes["Principled BSDF"].outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    opt = optics_module(addon).optics([tex, emit, mixed])
    np.testing.assert_allclose(opt.reflectivity, [0.2, 0.4, 0.5], atol=1e-6)
    np.testing.assert_allclose(opt.transmission, [0.0, 0.5, 0.0], atol=1e-6, err_msg="no Principled: 1 - alpha")
    assert opt.mirror.tolist() == [False, True, True]


def test_reflectivity_properties_override_and_no_material_reflects_fully(fresh, addon):
    paint = material("Paint", (0.2, 0.4, 0.6))
    marked = material("Marked", (0.2, 0.4, 0.6))
    marked["hybrid_raycast_reflectivity"] = 0.9
    obs = [add_cube("Plain", 1.0), add_cube("Sign", 1.0, (5.0, 0.0, 0.0))]
    obs[1]["hybrid_raycast_reflectivity"] = 0.05
    opt = optics_module(addon).optics([paint, marked], obs)
    assert np.isclose(opt.reflectivity[1], 0.9)
    assert np.isnan(opt.object_reflectivity[0]) and np.isclose(opt.object_reflectivity[1], 0.05)
    refl, trans, mirror = opt.per_hit(np.array([0, 1, -1, 0, -1], np.int32), np.array([0, 0, 0, 1, -1], np.int32))
    np.testing.assert_allclose(refl, [0.4, 0.9, 1.0, 0.05, 1.0], atol=1e-6,
                               err_msg="material, material override, no material, object override, miss")
    assert trans.tolist() == [0.0] * 5 and not mirror.any()
    assert refl.dtype == trans.dtype == np.float32 and mirror.dtype == bool


@pytest.mark.parametrize("value", ["shiny", 1.5, -0.1, float("nan"), True])
def test_a_bad_reflectivity_property_raises_naming_it(fresh, addon, value):
    m = material("Odd")
    m["hybrid_raycast_reflectivity"] = value
    with pytest.raises(ValueError, match="material 'Odd'.*hybrid_raycast_reflectivity"):
        optics_module(addon).optics([m])
    ob = add_cube("OddObject", 1.0)
    ob["hybrid_raycast_reflectivity"] = value
    with pytest.raises(ValueError, match="object 'OddObject'.*hybrid_raycast_reflectivity"):
        optics_module(addon).optics([], [ob])


def test_per_hit_optics_of_a_cast(fresh, addon):
    """End to end: cast with materials, then per-hit optics from the result's tables."""
    two_material_cube()
    glass = add_cube("Window", 2.0, (0.0, 10.0, 0.0))
    glass.data.materials.append(material("Glass", transmission=1.0))
    glass["hybrid_raycast_reflectivity"] = 0.07
    add_cube("Bare", 2.0, (0.0, 20.0, 0.0))
    bpy.context.view_layer.update()
    rays = [face_rays(c) for c in ((0.0, 0.0, 0.0), (0.0, 10.0, 0.0), (0.0, 20.0, 0.0))]
    o, d = np.vstack([r[0] for r in rays]), np.vstack([r[1] for r in rays])
    r = addon.api.cast(o, d, materials=True)
    opt = optics_module(addon).optics(r.materials, r.objects)
    refl, trans, _ = opt.per_hit(r.material_index, r.object_index)
    want = [0.4] * 3 + [0.9] * 3 + [0.07] * 6 + [1.0] * 6
    np.testing.assert_allclose(refl, want, atol=1e-6, err_msg=f"hits on {r.object_names[r.object_index]}")
    assert trans.tolist() == [0.0] * 6 + [1.0] * 6 + [0.0] * 6


def test_geometry_nodes_instances_and_set_material_render_their_materials(fresh, addon):
    """An Object Info "As Instance" instance keeps the instanced object's object-linked
    material; a realized mesh with Set Material gets the node's material (both as Cycles
    renders them, checked with bpy 5.0.1)."""
    src = two_material_cube("Src", (0.0, 0.0, -50.0))
    src.material_slots[0].link = "OBJECT"
    src.material_slots[0].material = material("C")
    for name, realize, x in (("AsInstance", False, 10.0), ("Realized", True, 20.0)):
        ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
        ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        point = ng.nodes.new("GeometryNodeMeshLine")
        point.inputs["Count"].default_value = 1
        info = ng.nodes.new("GeometryNodeObjectInfo")
        info.inputs["Object"].default_value = src
        info.inputs["As Instance"].default_value = True
        on_points = ng.nodes.new("GeometryNodeInstanceOnPoints")
        ng.links.new(point.outputs["Mesh"], on_points.inputs["Points"])
        ng.links.new(info.outputs["Geometry"], on_points.inputs["Instance"])
        last = on_points.outputs["Instances"]
        if realize:
            real = ng.nodes.new("GeometryNodeRealizeInstances")
            setm = ng.nodes.new("GeometryNodeSetMaterial")
            setm.inputs["Material"].default_value = material("FromNodes")
            ng.links.new(last, real.inputs[0])
            ng.links.new(real.outputs[0], setm.inputs["Geometry"])
            last = setm.outputs[0]
        ng.links.new(last, ng.nodes.new("NodeGroupOutput").inputs["Geometry"])
        host = bpy.data.objects.new(name, bpy.data.meshes.new(name))
        host.location = (x, 0.0, 0.0)  # Object Info's 'Original' space: Src's geometry at the host
        bpy.context.scene.collection.objects.link(host)
        host.modifiers.new("GN", "NODES").node_group = ng
    bpy.context.view_layer.update()
    r = addon.api.cast(*face_rays((10.0, 0.0, 0.0)), materials=True)
    assert hit_names(r) == ["C"] * 3 + ["B"] * 3, f"as-instance: {hit_names(r)}"
    r = addon.api.cast(*face_rays((20.0, 0.0, 0.0)), materials=True)
    assert hit_names(r) == ["FromNodes"] * 6, f"realized with Set Material: {hit_names(r)}"
