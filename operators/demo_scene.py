"""The built-in demo scene: a small set that exercises every extraction path.

A ground plane, a subdivided Suzanne, three collection instances of a torus with
non-uniform scale, a text object, a camera and a sun.  Built with the data API and
primitive operators so it works in a background (``-b``) session.
"""

import math

import bpy


def build_demo_scene(*, subdivision_levels: int = 2) -> bpy.types.Scene:
    """Replace the current file's contents with the demo scene and return the scene."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.name = "Hybrid Ray Cast demo"

    bpy.ops.mesh.primitive_plane_add(size=20.0, location=(0.0, 0.0, 0.0))
    bpy.context.object.name = "Ground"

    bpy.ops.mesh.primitive_monkey_add(size=2.0, location=(0.0, 0.0, 1.2), rotation=(0.0, 0.0, math.radians(-20)))
    monkey = bpy.context.object
    monkey.name = "Suzanne"
    mod = monkey.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = subdivision_levels

    # A torus in its own (excluded-from-view) collection, instanced three times.
    ring_coll = bpy.data.collections.new("Ring")
    scene.collection.children.link(ring_coll)
    bpy.ops.mesh.primitive_torus_add(major_radius=0.8, minor_radius=0.25)
    torus = bpy.context.object
    torus.name = "Torus"
    for c in list(torus.users_collection):
        c.objects.unlink(torus)
    ring_coll.objects.link(torus)
    bpy.context.view_layer.layer_collection.children[ring_coll.name].exclude = True
    for i, (x, sx, sz) in enumerate(((-4.0, 1.0, 1.0), (4.0, 1.5, 0.5), (0.0, 0.7, 2.0))):
        inst = bpy.data.objects.new(f"Ring instance {i + 1}", None)
        inst.instance_type = "COLLECTION"
        inst.instance_collection = ring_coll
        inst.location = (x, 4.0, 0.6)
        inst.scale = (sx, 1.0, sz)
        scene.collection.objects.link(inst)

    curve = bpy.data.curves.new("Title", "FONT")
    curve.body = "Hybrid RT"
    curve.extrude = 0.05
    text = bpy.data.objects.new("Title", curve)
    text.location = (-2.5, -3.0, 0.01)
    scene.collection.objects.link(text)

    cam_data = bpy.data.cameras.new("Camera")
    cam = bpy.data.objects.new("Camera", cam_data)
    cam.location = (0.0, -11.0, 5.5)
    cam.rotation_euler = (math.radians(65), 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.rotation_euler = (math.radians(40), math.radians(20), 0.0)
    scene.collection.objects.link(sun)

    scene.render.resolution_x = 640
    scene.render.resolution_y = 360
    scene.render.resolution_percentage = 100
    bpy.context.view_layer.update()
    return scene
