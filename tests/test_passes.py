"""Camera passes, the AO bake and the plot, against independent references:
Blender's own ``Scene.ray_cast``, core brute force, and Blender's PNG reader."""

import json
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_camera, add_cube, add_plane, addon, fresh, props, simple_scene  # noqa: E402,F401

pytestmark = pytest.mark.blender


def pixels(name):
    img = bpy.data.images[name]
    w, h = img.size
    a = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(a)
    return a.reshape(h, w, 4)[::-1]  # top row first, like the rays


def rays_of(scene):
    from hybrid_raycast.operators.passes import camera_workload

    return camera_workload(scene, bpy.context.evaluated_depsgraph_get())


@pytest.mark.parametrize("ortho", [False, True])
def test_camera_rays_match_blenders_own_ray_cast(fresh, ortho):
    simple_scene(resolution=(41, 31))
    if ortho:
        cam = bpy.data.objects["Camera"]
        cam.data.type = "ORTHO"
        cam.data.ortho_scale = 6.0
    scene = bpy.context.scene
    dg = bpy.context.evaluated_depsgraph_get()
    r = rays_of(scene)
    assert r["origins"].shape == (41 * 31, 3)
    from mathutils import Vector

    mismatches = []
    for idx in range(0, 41 * 31, 37):
        o, d = Vector(r["origins"][idx].tolist()), Vector(r["directions"][idx].tolist())
        ok, loc, _n, _f, ob, _m = scene.ray_cast(dg, o, d)
        t_blender = (loc - o).length if ok else math.inf
        from hybrid_raycast.api import cast

        res = cast(r["origins"][idx:idx + 1], r["directions"][idx:idx + 1])
        t_mine = float(res.t[0])
        if ok != bool(res.hit[0]) or (ok and abs(t_mine - t_blender) > 1e-4 * max(1.0, t_blender)):
            mismatches.append((idx, ok, t_blender, bool(res.hit[0]), t_mine))
        elif ok and res.object_names[res.object_index[0]] != ob.name:
            mismatches.append((idx, ob.name, res.object_names[res.object_index[0]]))
    assert not mismatches, f"(pixel, blender hit, t, ours hit, t): {mismatches[:5]}"


def test_centre_pixel_looks_along_the_camera_axis(fresh):
    simple_scene(resolution=(41, 31))
    r = rays_of(bpy.context.scene)
    centre = r["directions"][15 * 41 + 20]
    assert np.allclose(centre, [0, 1, 0], atol=1e-6), f"centre ray {centre}, camera looks along +Y"
    assert r["directions"][0][2] > 0 and r["directions"][0][0] < 0, "the first pixel is the top-left one"


def test_camera_passes_match_brute_force(fresh, addon):
    simple_scene(resolution=(64, 48))
    assert bpy.ops.hybrid_raycast.trace(workload="CAMERA") == {"FINISHED"}
    from hybrid_raycast.operators.analyze import extract
    from hybrid_raycast.operators.passes import DEPTH, NORMAL, OBJECT_ID, object_id_colors

    scene = bpy.context.scene
    mesh, _ = extract(bpy.context.evaluated_depsgraph_get())
    r = rays_of(scene)
    ref = addon.core.build(mesh, "brute").trace(r["origins"], r["directions"], r["tmin"], r["tmax"])
    depth, normal, oid = pixels(DEPTH), pixels(NORMAL), pixels(OBJECT_ID)
    hit = ref.hit.reshape(48, 64)
    assert np.array_equal(depth[..., 3] > 0.5, hit), f"{int((hit != (depth[..., 3] > 0.5)).sum())} pixels differ in hit/miss"
    img = bpy.data.images[DEPTH]
    near, far = img["near"], img["far"]
    z_ref = (ref.t * r["cos"]).reshape(48, 64)[hit]
    z_img = far - depth[..., 0][hit] * (far - near)
    assert np.allclose(z_img, z_ref, rtol=1e-5, atol=1e-5 * far), f"depth differs by up to {np.abs(z_img - z_ref).max()}"
    # the cube's front face points at the camera (-Y); the ground's normal is +Z
    names = json.loads(bpy.data.images[OBJECT_ID]["object_names"])
    tri_obj = mesh.object_index[ref.triangle.reshape(48, 64)]
    n = normal[..., :3] * 2 - 1
    cube_px = hit & (tri_obj == names.index("Cube"))
    ground_px = hit & (tri_obj == names.index("Ground"))
    assert cube_px.any() and ground_px.any()
    assert np.allclose(n[cube_px], [0, -1, 0], atol=1e-5), "the cube's visible face should face -Y"
    assert np.allclose(n[ground_px], [0, 0, 1], atol=1e-5), "the ground faces +Z"
    colors = object_id_colors(len(names))
    assert np.allclose(oid[hit][:, :3], colors[tri_obj[hit]]), "object-id colours differ from object_id_colors"
    assert props().trace_workload == "CAMERA" and props().trace_rays == 64 * 48


def test_pass_images_are_float_non_color_and_savable(fresh, tmp_path):
    simple_scene(resolution=(32, 24))
    bpy.ops.hybrid_raycast.trace(workload="CAMERA")
    from hybrid_raycast.operators.passes import DEPTH, save_image

    img = bpy.data.images[DEPTH]
    assert img.is_float and tuple(img.size) == (32, 24)
    out = save_image(img, tmp_path / "depth.png")
    back = bpy.data.images.load(out)
    assert tuple(back.size) == (32, 24)


def test_camera_less_scene_says_so_and_writes_nothing(fresh):
    add_cube("Cube")
    with pytest.raises(RuntimeError, match="no camera"):
        bpy.ops.hybrid_raycast.trace(workload="CAMERA")
    assert not [i for i in bpy.data.images if i.name.startswith("HRC ")]


def test_panoramic_camera_is_refused(fresh):
    simple_scene()
    bpy.data.objects["Camera"].data.type = "PANO"
    with pytest.raises(RuntimeError, match="only perspective and orthographic"):
        bpy.ops.hybrid_raycast.trace(workload="CAMERA")


def test_ao_of_an_open_plane_is_one_and_under_a_roof_is_zero(fresh):
    floor = add_plane("Floor", 2.0, subdivisions=3)
    add_plane("Roof", 200.0, z=0.0, location=(0.0, 0.0, 0.5))
    add_plane("Open", 2.0, subdivisions=2, location=(0.0, 0.0, 10.0))
    props().ao_samples = 32
    view_layer = bpy.context.view_layer
    view_layer.objects.active = floor
    assert bpy.ops.hybrid_raycast.trace(workload="AO") == {"FINISHED"}
    view_layer.objects.active = bpy.data.objects["Open"]
    assert bpy.ops.hybrid_raycast.trace(workload="AO") == {"FINISHED"}
    for name, expected in (("Floor", 0.0), ("Open", 1.0)):
        me = bpy.data.objects[name].data
        attr = me.color_attributes["HRC AO"]
        assert attr.data_type == "FLOAT_COLOR" and attr.domain == "POINT"
        c = np.empty(len(me.vertices) * 4, np.float32)
        attr.data.foreach_get("color", c)
        ao = c.reshape(-1, 4)[:, 0]
        assert np.allclose(ao, expected), f"{name}: AO {ao} should all be {expected}"
        assert me.color_attributes.active_color.name == "HRC AO"


def test_ao_bake_is_undoable_data(fresh):
    """The bake only touches the mesh's attributes (undoable in Object Mode)."""
    simple_scene()
    bpy.context.view_layer.objects.active = bpy.data.objects["Cube"]
    bpy.ops.hybrid_raycast.trace(workload="AO")
    me = bpy.data.objects["Cube"].data
    assert "HRC AO" in me.color_attributes
    # a second bake replaces the attribute instead of adding another
    bpy.ops.hybrid_raycast.trace(workload="AO")
    assert [a.name for a in me.color_attributes].count("HRC AO") == 1


def test_ao_without_a_mesh_says_so(fresh):
    simple_scene()
    bpy.context.view_layer.objects.active = bpy.data.objects["Camera"]
    for ob in bpy.context.view_layer.objects:
        ob.select_set(False)
    with pytest.raises(RuntimeError, match="no mesh to bake"):
        bpy.ops.hybrid_raycast.trace(workload="AO")


def test_plot_has_the_curves_the_interval_and_the_break_even_marker(addon, tmp_path):
    from hybrid_raycast.core import plot

    f = {"grid_per_ray": 1e-6, "candidates": {"bvh": (0.1, 1e-7)}, "expected_rays": 1e7,
         "break_even": 0.1 / (1e-6 - 1e-7), "break_even_low": 5e4, "break_even_high": 3e5}
    img = plot.plot_rgba(f, 300, 240)
    assert img.shape == (240, 300, 4) and np.isfinite(img).all()
    rgb = img[..., :3]
    for kind in ("grid", "bvh"):
        n = int(np.all(np.isclose(rgb, plot.COLORS[kind]), axis=-1).sum())
        assert n > 100, f"the {kind} curve has only {n} pixels"
    band = int(np.all(np.isclose(rgb, (0.2, 0.2, 0.26)), axis=-1).sum())
    assert band > 500, "the break-even interval is not shaded"
    path = plot.write_png(tmp_path / "plot.png", img)
    back = bpy.data.images.load(path)
    b = np.empty(300 * 240 * 4, np.float32)
    back.pixels.foreach_get(b)
    b = b.reshape(240, 300, 4)[::-1]
    assert np.abs(b - np.round(np.clip(img, 0, 1) * 255) / 255).max() < 1e-3, "the PNG does not read back as written"


def test_plot_with_an_infinite_break_even_has_no_marker_and_no_band(addon):
    from hybrid_raycast.core import plot

    f = {"grid_per_ray": 1e-7, "candidates": {"bvh": (0.1, 1e-6)}, "expected_rays": 1e6,
         "break_even": None, "break_even_low": None, "break_even_high": None}
    img = plot.plot_rgba(f, 200, 200)
    assert not np.all(np.isclose(img[..., :3], (0.2, 0.2, 0.26)), axis=-1).any()
