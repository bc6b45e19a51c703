"""Fixtures and small scenes shared by the Blender front-end tests (bpy module, background).

Import the fixtures into a test module by name (``from blender_scenes import addon, fresh``).
``addon`` registers the add-on for one test module and unregisters it afterwards (so
test_register still starts from a clean slate); ``fresh`` gives an empty file and points
the calibration at a temporary path that does not exist yet.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from conftest import load_addon  # noqa: E402


@pytest.fixture(scope="module")
def addon():
    pkg = load_addon()
    pkg.register()
    yield pkg
    pkg.unregister()


@pytest.fixture
def fresh(addon, tmp_path, monkeypatch):
    """An empty file, the add-on registered, the calibration file at tmp_path (absent)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    monkeypatch.setattr(addon.operators.calibrate, "CALIBRATION_PATH", str(tmp_path / "calibration.json"))
    scene = bpy.context.scene
    scene.hybrid_raycast.ray_budget = "CUSTOM"
    scene.hybrid_raycast.custom_rays = 1.0e6
    scene.hybrid_raycast.sample_rays = 2048
    yield scene


def run_cli(addon, *argv):
    """The add-on's -c hybrid_raycast handler as Blender calls it, its stdout and stderr captured:
    (exit code, stdout text, stderr text)."""
    out, err = io.StringIO(), io.StringIO()
    code = addon.operators.cli.main(list(argv), stdout=out, stderr=err)
    return code, out.getvalue(), err.getvalue()


def add_mesh(name, vertices, faces, location=(0.0, 0.0, 0.0), scene=None):
    scene = scene or bpy.context.scene
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(map(float, v)) for v in vertices], [], [tuple(f) for f in faces])
    me.update()
    ob = bpy.data.objects.new(name, me)
    ob.location = location
    scene.collection.objects.link(ob)
    return ob


def add_plane(name, size=2.0, z=0.0, location=(0.0, 0.0, 0.0), subdivisions=1):
    n = subdivisions + 1
    xs = np.linspace(-size / 2, size / 2, n)
    verts = [(x, y, z) for y in xs for x in xs]
    faces = [(j * n + i, j * n + i + 1, (j + 1) * n + i + 1, (j + 1) * n + i) for j in range(n - 1) for i in range(n - 1)]
    return add_mesh(name, verts, faces, location)


def add_cube(name, size=2.0, location=(0.0, 0.0, 0.0)):
    h = size / 2
    v = [(-h, -h, -h), (h, -h, -h), (h, h, -h), (-h, h, -h), (-h, -h, h), (h, -h, h), (h, h, h), (-h, h, h)]
    f = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    return add_mesh(name, v, f, location)


def unweld(ob):
    """Give every face of ``ob`` vertices of its own, in place of shared ones: the same
    triangles, but a soup, not a surface (``TriangleMesh.is_surface``), so the calibration
    alone settles only a structure that beats the grid on all its scenes and Analyze
    measures the grid against the numpy BVH."""
    me = ob.data
    verts, faces = [], []
    for poly in me.polygons:
        faces.append(list(range(len(verts), len(verts) + len(poly.vertices))))
        verts += [tuple(me.vertices[i].co) for i in poly.vertices]
    soup = bpy.data.meshes.new(me.name + " soup")
    soup.from_pydata(verts, [], faces)
    soup.update()
    ob.data = soup
    bpy.context.view_layer.update()
    return ob


def add_camera(location=(0.0, -8.0, 0.0), rotation=(math.radians(90), 0.0, 0.0), ortho=False, scene=None):
    scene = scene or bpy.context.scene
    data = bpy.data.cameras.new("Camera")
    if ortho:
        data.type = "ORTHO"
        data.ortho_scale = 6.0
    cam = bpy.data.objects.new("Camera", data)
    cam.location = location
    cam.rotation_euler = rotation
    scene.collection.objects.link(cam)
    scene.camera = cam
    return cam


def simple_scene(resolution=(81, 61)):
    """A cube in front of a camera on a ground plane: 12 + 2 triangles, a camera, a light."""
    add_cube("Cube", 2.0, (0.0, 0.0, 0.0))
    add_plane("Ground", 20.0, z=0.0, location=(0.0, 0.0, -1.0))
    add_camera()
    light = bpy.data.objects.new("Light", bpy.data.lights.new("Light", "POINT"))
    bpy.context.scene.collection.objects.link(light)
    r = bpy.context.scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = resolution[0], resolution[1], 100
    bpy.context.view_layer.update()
    return bpy.context.scene


def props():
    return bpy.context.scene.hybrid_raycast


def make_nan(ob):
    co = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", co)
    co[:3] = np.nan
    ob.data.vertices.foreach_set("co", co)
    ob.data.update()
