"""Checks run inside a real `blender -b` (Blender 4.3.2, Python 3.13) with the zip installed.

Exits non-zero (through --python-exit-code) on the first failed check; prints one line per check.
"""

import json
import sys
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


# --factory-startup ignores the user preferences, so enable the installed extension here.
addon_utils.enable(MODULE, default_set=True)
check("extension enabled", MODULE in {a.module for a in bpy.context.preferences.addons})
check("scene settings registered", hasattr(bpy.types.Scene, "hybrid_raycast"))

pkg = sys.modules[MODULE]
try:
    import embreex  # noqa: F401

    embree = True
except ImportError as exc:
    embree = False
    print("embreex not importable:", exc)
check("bundled embreex wheel importable (cp313)", embree)

bpy.ops.wm.read_homefile(use_empty=False)
res = bpy.ops.hybrid_raycast.scene_summary()
check("summary operator finishes on the default cube", res == {"FINISHED"}, str(res))
check("default cube has 12 triangles", bpy.context.scene.hybrid_raycast.triangle_count == 12,
      str(bpy.context.scene.hybrid_raycast.triangle_count))

import numpy as np  # noqa: E402

core = pkg.core
mesh = core.TriangleMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
for kind in ("brute", "grid", "bvh") + (("embree",) if embree else ()):
    try:
        hits = core.build(mesh, kind).trace(np.array([[0.2, 0.2, 1.0]]), np.array([[0.0, 0.0, -1.0]]))
    except ModuleNotFoundError as exc:  # a structure that is not written yet
        print(f"skip {kind}: {exc}")
        continue
    check(f"{kind} traces under numpy {np.__version__}", hits.triangle[0] == 0 and abs(hits.t[0] - 1.0) < 1e-6,
          f"t={hits.t[0]} tri={hits.triangle[0]}")

addon_utils.disable(MODULE, default_set=True)
check("extension disabled cleanly", not hasattr(bpy.types.Scene, "hybrid_raycast"))
(WORK / "real_blender_checks.json").write_text(json.dumps(results, indent=2))
print(f"{len(results)} passed, 0 failed")
