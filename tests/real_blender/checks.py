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
    hits = core.build(mesh, kind).trace(np.array([[0.2, 0.2, 1.0]]), np.array([[0.0, 0.0, -1.0]]))
    check(f"{kind} traces a one-triangle mesh under numpy {np.__version__}",
          hits.triangle[0] == 0 and abs(hits.t[0] - 1.0) < 1e-6,
          f"t={hits.t[0]} tri={hits.triangle[0]} in {time.perf_counter() - t0:.3f} s")

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
check("grid estimate is the sample time times this machine's batch ratio (0 < ratio <= 1.5)",
      0 < props.grid_sample_ratio <= 1.5
      and abs(props.grid_sample_ratio - plan["grid_sample_ratio"]) <= 1e-6 * plan["grid_sample_ratio"],
      f"ratio {props.grid_sample_ratio} vs {plan['grid_sample_ratio']}")
check("grid per ray = sample x ratio",
      abs(props.grid_per_ray - plan["grid_sample_per_ray"] * plan["grid_sample_ratio"]) <= 1e-5 * props.grid_per_ray,
      f"{props.grid_per_ray} vs {plan['grid_sample_per_ray']} x {plan['grid_sample_ratio']}")
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
