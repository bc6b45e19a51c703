"""Checks run inside a real `blender -b` (Blender 4.3.2, Python 3.13, numpy 2.x) with the zip installed.

Exits non-zero (through --python-exit-code) on the first failed check; prints one line per
check.  Also saves the .blend files the CLI checks (check_cli.py) run on:
demo.blend, empty.blend (only an empty), nan.blend (a mesh with NaN coordinates),
nocamera.blend (a cube, no camera).
"""

import json
import math
import sys
import time
from pathlib import Path

import addon_utils
import bpy

WORK = Path(sys.argv[sys.argv.index("--") + 1])
MODULE = "bl_ext.user_default.hybrid_raycast"
results = {}


def check(name, ok, detail=""):
    results[name] = bool(ok)
    print(f"{'ok  ' if ok else 'FAIL'} {name} {detail}", flush=True)
    if not ok:
        (WORK / "real_blender_checks.json").write_text(json.dumps(results, indent=2))
        raise SystemExit(f"check failed: {name} {detail}")


def raises(fn, words):
    try:
        fn()
    except RuntimeError as e:
        return words in str(e), str(e).strip()
    return False, "no error"


# --factory-startup ignores the user preferences, so enable the installed extension here.
addon_utils.enable(MODULE, default_set=True)
check("extension enabled", MODULE in {a.module for a in bpy.context.preferences.addons})
check("scene settings registered", hasattr(bpy.types.Scene, "hybrid_raycast"))
for op in ("analyze", "trace", "calibrate", "scene_summary"):
    check(f"operator hybrid_raycast.{op} registered", hasattr(bpy.ops.hybrid_raycast, op))

pkg = sys.modules[MODULE]
try:
    import embreex  # noqa: F401

    embree = True
except ImportError as exc:
    embree = False
    print("embreex not importable:", exc)
check("bundled embreex wheel importable (cp313)", embree)

import numpy as np  # noqa: E402

core = pkg.core
mesh = core.TriangleMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
for kind in ("brute", "grid", "bvh") + (("embree",) if embree else ()):
    t0 = time.perf_counter()
    accel = core.build(mesh, kind)
    hits = accel.trace(np.array([[0.2, 0.2, 1.0]]), np.array([[0.0, 0.0, -1.0]]))
    check(f"{kind} traces a one-triangle mesh under numpy {np.__version__}",
          hits.triangle[0] == 0 and abs(hits.t[0] - 1.0) < 1e-6,
          f"t={hits.t[0]} tri={hits.triangle[0]} in {time.perf_counter() - t0:.3f} s")
if embree:  # the bundled wheel's libembree4 found beside it, the geometry filled through it
    check("embree fills its geometry through Embree's C API (not embreex's copy loop)",
          accel.stats()["fill"] == "direct", str(accel.stats()))

# -- the calibration lives in the extension's user folder ------------------------------------
cal_path = pkg.operators.calibrate.calibration_path()
user_dir = Path(bpy.utils.extension_path_user(MODULE, path="", create=True))
check("calibration path is in the extension's user folder", cal_path.parent == user_dir, str(cal_path))
res = bpy.ops.hybrid_raycast.calibrate(scale="tiny")
check("calibrate (tiny) finishes and saves", res == {"FINISHED"} and cal_path.is_file(), str(res))

# -- operators on the default cube --------------------------------------------------------------
bpy.ops.wm.read_homefile(use_empty=False)
scene = bpy.context.scene
props = scene.hybrid_raycast
res = bpy.ops.hybrid_raycast.scene_summary()
check("summary operator finishes on the default cube", res == {"FINISHED"}, str(res))
check("default cube has 12 triangles", props.triangle_count == 12, str(props.triangle_count))
props.expected_rays = 1e6
props.candidates = {"BVH"}
res = bpy.ops.hybrid_raycast.analyze()
check("analyze on the cube, a surface, at 1M rays: the BVH within the slack of the grid, no grid built",
      res == {"FINISHED"} and not props.grid_built and props.decision == "BVH" and props.settled_slack > 0
      and props.samples_traced == 0, f"{res}, grid built {props.grid_built}, {props.decision}, {props.settled_slack}")
# the cube's faces with vertices of their own: a soup, which only a sample judges (the measured
# path; with Embree the calibration may still settle it alone: below)
cube = bpy.data.objects["Cube"]
soup = bpy.data.meshes.new("Cube soup")
soup.from_pydata([tuple(cube.data.vertices[i].co) for p in cube.data.polygons for i in p.vertices], [],
                 [list(range(4 * j, 4 * j + 4)) for j in range(len(cube.data.polygons))])
cube.data = soup
res = bpy.ops.hybrid_raycast.analyze()
check("analyze finishes", res == {"FINISHED"}, str(res))
check("analyze decides", props.decision in {"GRID", "BVH", "EMBREE"}, props.decision)
check("analyze used this machine's calibration", props.calibration_source == "measured", props.calibration_source)
be = math.inf if props.break_even_infinite else props.break_even_rays
check("decision follows the break-even", (props.decision == "GRID") == (props.analyzed_rays <= be * (1 + 1e-6)),
      f"{props.decision}, R={props.analyzed_rays}, R*={be}")
record = json.loads(props.last_analysis_json)
check("stored JSON matches the properties", record["decision"] == props.decision and record["summary"]["triangles"] == 12)
plan = record["plan"]
# with the count models the ratio is the grid's estimate over its sample's own time per ray: on a
# 12-triangle cube right after a tiny calibration it moves with the machine's speed between the
# two, so the bound is plausibility, not precision
check("grid estimate is the sample time times this machine's batch ratio (0 < ratio <= 3)",
      0 < props.grid_sample_ratio <= 3
      and abs(props.grid_sample_ratio - plan["grid_sample_ratio"]) <= 1e-6 * plan["grid_sample_ratio"],
      f"ratio {props.grid_sample_ratio} vs {plan['grid_sample_ratio']}")
check("grid per ray = sample x ratio",
      abs(props.grid_per_ray - plan["grid_sample_per_ray"] * plan["grid_sample_ratio"]) <= 1e-5 * props.grid_per_ray,
      f"{props.grid_per_ray} vs {plan['grid_sample_per_ray']} x {plan['grid_sample_ratio']}")
props.candidates = {"BVH", "EMBREE"}
res = bpy.ops.hybrid_raycast.analyze()
plan = json.loads(props.last_analysis_json)["plan"]
check("with Embree: a grid measured, or Embree settled by the calibration without one",
      res == {"FINISHED"} and (props.grid_built and props.samples_traced > 0
                               or (not props.grid_built and props.decision == "EMBREE" and props.samples_traced == 0
                                   and plan["grid_built"] is False)),
      f"{res}, grid built {props.grid_built}, {props.decision}, samples {props.samples_traced}")
check("results fresh after analyze", not props.stale, props.stale_reason)
bpy.data.objects["Camera"].location.x += 1
bpy.context.evaluated_depsgraph_get()
check("moving the camera keeps results fresh", not props.stale, props.stale_reason)
bpy.data.objects["Cube"].location.x += 1
bpy.context.evaluated_depsgraph_get()
check("moving the cube makes results stale", props.stale, props.stale_reason)

scene.render.resolution_x, scene.render.resolution_y = 64, 48
res = bpy.ops.hybrid_raycast.trace(workload="CAMERA")
check("camera passes finish", res == {"FINISHED"}, str(res))
img = bpy.data.images.get("HRC Depth")
check("depth image written", img is not None and tuple(img.size) == (64, 48) and img.is_float)
px = np.empty(64 * 48 * 4, np.float32)
img.pixels.foreach_get(px)
check("depth image has hits and misses", 0 < (px[3::4] > 0.5).sum() < 64 * 48, f"{(px[3::4] > 0.5).sum()} hits")
bpy.context.view_layer.objects.active = bpy.data.objects["Cube"]
res = bpy.ops.hybrid_raycast.trace(workload="AO")
check("AO bake finishes", res == {"FINISHED"} and "HRC AO" in bpy.data.objects["Cube"].data.color_attributes, str(res))

# -- the script API against Blender's own ray cast -----------------------------------------------
from mathutils import Vector  # noqa: E402

dg = bpy.context.evaluated_depsgraph_get()
rng = np.random.default_rng(1)
o = np.tile([[1.0, -6.0, 0.3]], (40, 1)).astype(np.float32)
d = (np.array([0.0, 1.0, 0.0]) + rng.normal(0, 0.2, (40, 3))).astype(np.float32)
r = pkg.api.cast(o, d)
agree = 0
for i in range(40):
    ok, loc, _n, face, ob, _m = scene.ray_cast(dg, Vector(o[i].tolist()), Vector(d[i].tolist()))
    if ok == bool(r.hit[i]) and (not ok or (np.allclose(r.points[i], loc[:], atol=1e-4) and r.polygon_index[i] == face)):
        agree += 1
check("api.cast agrees with Scene.ray_cast", agree == 40, f"{agree}/40 rays, structure {r.structure}")

# -- the session is never stale: every field of api.cast equals Scene.ray_cast after each change ----
def ring_rays(seed, m=200):
    g = np.random.default_rng(seed)
    a = g.uniform(0, 2 * np.pi, m)
    o = np.stack([9 * np.cos(a), 9 * np.sin(a), g.uniform(-0.8, 2.5, m)], axis=1)
    tgt = np.stack([g.uniform(-3, 3, m), g.uniform(-3, 3, m), g.uniform(-1.2, 1.5, m)], axis=1)
    return o, tgt - o


def like_ray_cast(name, seed, depsgraph=None):
    o, d = ring_rays(seed)
    r = pkg.api.cast(o, d, depsgraph=depsgraph)  # the API first, as a script does
    g = depsgraph if depsgraph is not None else bpy.context.evaluated_depsgraph_get()
    bad = []
    for i in range(len(o)):
        ok, loc, n, face, ob, mat = g.scene.ray_cast(g, Vector(o[i]), Vector(d[i]))
        if ok != bool(r.hit[i]):
            bad.append((i, "hit", ok))
            continue
        if not ok:
            continue
        same_point = np.allclose(r.points[i], loc[:], atol=2e-4)
        fields = (np.allclose(r.normals[i], n[:], atol=2e-5) and r.polygon_index[i] == face
                  and r.objects[r.object_index[i]] == ob.original
                  and np.allclose(r.instance_matrices[r.instance_index[i]], np.array(mat), atol=1e-5))
        if not same_point or not (fields or np.linalg.norm(np.asarray(loc) - r.points[i]) < 1e-5):
            bad.append((i, ob.name, r.object_names[r.object_index[i]]))
    check(f"api.cast == Scene.ray_cast, every field: {name}", not bad, f"{len(bad)}/{len(o)} differ {bad[:3]}")
    return r


def hit_names(r):
    return set(r.object_names[r.object_index[r.hit]])


bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable(MODULE, default_set=True)
scene = bpy.context.scene
vl = bpy.context.view_layer
bpy.ops.mesh.primitive_plane_add(size=12, location=(0, 0, -1))
bpy.ops.mesh.primitive_cube_add(size=1.5, location=(1.5, 0, 0))
cube = bpy.context.object
col = bpy.data.collections.new("Col")
scene.collection.children.link(col)
bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, location=(-1.5, 1.0, 0.3))
ball = bpy.context.object
for c in list(ball.users_collection):
    c.objects.unlink(ball)
col.objects.link(ball)
bpy.ops.mesh.primitive_cone_add(radius1=0.4, depth=0.8)
cone = bpy.context.object
src = bpy.data.collections.new("Src")
scene.collection.objects.unlink(cone)
src.objects.link(cone)
for i, x in enumerate((-2.5, 2.5)):
    e = bpy.data.objects.new(f"Inst{i}", None)
    e.instance_type, e.instance_collection = "COLLECTION", src
    e.location, e.rotation_euler = (x, -2.0, 0.0), (0.0, 0.0, 0.3 * (i + 1))
    scene.collection.objects.link(e)
vl.update()
like_ray_cast("first cast", 0)
cube.location.x += 0.7
like_ray_cast("object moved", 1)
mod = cube.modifiers.new("Bevel", "BEVEL")
mod.width = 0.1
like_ray_cast("modifier added", 2)
mod.width = 0.3
like_ray_cast("modifier changed", 3)
ball.hide_set(True)
check("hide_set(True) hides the ball", "Sphere" not in hit_names(like_ray_cast("hide_set(True)", 4)))
ball.hide_set(False)
check("hide_set(False) shows the ball", "Sphere" in hit_names(like_ray_cast("hide_set(False)", 4)))
lc = vl.layer_collection.children["Col"]
lc.hide_viewport = True
check("eye icon hides the ball", "Sphere" not in hit_names(like_ray_cast("collection eye icon off", 5)))
lc.hide_viewport = False
lc.exclude = True
check("exclude hides the ball", "Sphere" not in hit_names(like_ray_cast("collection excluded", 5)))
lc.exclude = False
like_ray_cast("collection back", 6)
bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 2.5, 0))
extra = bpy.context.object
extra.name = "Extra"
check("an added object is hit", "Extra" in hit_names(like_ray_cast("object added", 7)))
bpy.data.objects.remove(extra)
check("a removed object is not", "Extra" not in hit_names(like_ray_cast("object removed", 7)))
other = scene.view_layers.new("Other")
other.layer_collection.children["Col"].exclude = True
other.update()
check("another view layer's depsgraph has its own geometry",
      "Sphere" not in hit_names(like_ray_cast("other view layer", 8, depsgraph=other.depsgraph)))
like_ray_cast("first view layer again", 8)
cube.keyframe_insert("location", frame=1)
cube.location.z += 1.0
cube.keyframe_insert("location", frame=10)
scene.frame_set(1)
like_ray_cast("frame 1", 9)
scene.frame_set(10)
like_ray_cast("frame_set(10)", 9)
early_failures = []


def early_handler(scene, depsgraph):
    try:
        like_ray_cast(f"frame_change_post handler before ours, frame {scene.frame_current}", 10, depsgraph=depsgraph)
    except SystemExit as e:
        early_failures.append(str(e))


bpy.app.handlers.frame_change_post.insert(0, early_handler)
scene.frame_set(1)
scene.frame_set(10)
bpy.app.handlers.frame_change_post.remove(early_handler)
check("a handler registered before ours sees the current frame", not early_failures, str(early_failures[:1]))
at = cube.matrix_world.translation
r = pkg.api.cast((at.x, at.y - 9.0, at.z), (0, 1, 0))
check("a single ray as tuples", len(r) == 1 and bool(r.hit[0]), str(r.t))
occ = pkg.api.occluded(*ring_rays(11), structure="bvh")
check("occluded is any hit", np.array_equal(occ, pkg.api.cast(*ring_rays(11), structure="bvh").hit))
allh = pkg.api.cast_all(*ring_rays(12), max_hits=8)
near = pkg.api.cast(*ring_rays(12))
check("cast_all sorted by ray then t, every hit ray in it",
      np.all(np.diff(allh.ray) >= 0) and np.array_equal(np.unique(allh.ray), np.flatnonzero(near.hit))
      and len(allh) >= near.hit.sum(), f"{len(allh)} hits on {near.hit.sum()} rays")
for bad_call, word in ((lambda: pkg.api.cast([[0, 0, 0j]], [[0, 1, 0]]), "origins"),
                       (lambda: pkg.api.cast([[0, 0, 0]], [[0, 1, 0]], samples=0), "samples"),
                       (lambda: pkg.api.cast([[0, 0, 0]], [[0, 1, 0]], depsgraph=scene), "depsgraph")):
    try:
        bad_call()
        check(f"bad {word} raises", False)
    except (TypeError, ValueError) as e:
        check(f"bad {word} raises a clear error", word in str(e), str(e))

# -- failures say why ---------------------------------------------------------------------------
bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable(MODULE, default_set=True)
ok, msg = raises(lambda: bpy.ops.hybrid_raycast.analyze(), "no geometry")
check("empty scene: no geometry", ok, msg)
ok, msg = raises(lambda: bpy.ops.hybrid_raycast.trace(workload="CAMERA"), "no camera")
check("camera-less scene: no camera", ok, msg)

# -- the .blend files for the CLI checks -----------------------------------------------------------
from bl_ext.user_default.hybrid_raycast.operators.demo_scene import build_demo_scene  # noqa: E402

build_demo_scene()
addon_utils.enable(MODULE, default_set=True)
bpy.ops.wm.save_as_mainfile(filepath=str(WORK / "demo.blend"))
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.context.scene.collection.objects.link(bpy.data.objects.new("Empty", None))
bpy.ops.wm.save_as_mainfile(filepath=str(WORK / "empty.blend"))
bpy.ops.wm.read_homefile(use_empty=False)
cube = bpy.data.objects["Cube"]
co = np.empty(len(cube.data.vertices) * 3, np.float32)
cube.data.vertices.foreach_get("co", co)
co[:3] = np.nan
cube.data.vertices.foreach_set("co", co)
cube.data.update()
bpy.ops.wm.save_as_mainfile(filepath=str(WORK / "nan.blend"))
bpy.ops.wm.read_homefile(use_empty=False)
bpy.data.objects.remove(bpy.data.objects["Camera"])
bpy.ops.wm.save_as_mainfile(filepath=str(WORK / "nocamera.blend"))
check("CLI test files saved", all((WORK / f"{n}.blend").is_file() for n in ("demo", "empty", "nan", "nocamera")))

# reading files in a --factory-startup session resets the preferences: enable once more to test disabling
addon_utils.enable(MODULE, default_set=True)
check("extension enabled again", hasattr(bpy.types.Scene, "hybrid_raycast"))
handlers = bpy.app.handlers.depsgraph_update_post
check("stale handler installed", any(getattr(h, "__module__", "").startswith(MODULE) for h in handlers))
addon_utils.disable(MODULE, default_set=True)
check("handlers removed on disable", not any(getattr(h, "__module__", "").startswith(MODULE) for h in handlers))
check("extension disabled cleanly", not hasattr(bpy.types.Scene, "hybrid_raycast"))
(WORK / "real_blender_checks.json").write_text(json.dumps(results, indent=2))
print(f"{len(results)} passed, 0 failed")
