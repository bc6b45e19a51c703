"""Install a built zip into Blender-as-a-module as a user would, use it, then uninstall it.

Run in a fresh process with BLENDER_USER_RESOURCES pointing at an empty folder:
    python tests/install_roundtrip.py ZIP
Prints one JSON line with what it observed; exits non-zero on the first failure.

embreex installed in this Python's own environment (the test venv) is hidden: the add-on
sees embreex only if the package brought its wheel, as on a user's Blender, so what the
installed add-on offers (Embree or not) is the package's doing.
"""

import importlib.machinery
import json
import os
import site
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scripts"))
from _bpy_exit import exit_past_bpy  # noqa: E402

HIDDEN = {os.path.realpath(p) for p in site.getsitepackages()}


class _EmbreexOnlyFromExtensions:
    """Finds embreex on sys.path without this environment's site-packages, or not at all."""

    @staticmethod
    def find_spec(name, path=None, target=None):
        if name != "embreex":
            return None
        search = [p for p in sys.path if os.path.realpath(p or ".") not in HIDDEN]
        spec = importlib.machinery.PathFinder.find_spec(name, search)
        if spec is None:
            raise ModuleNotFoundError("No module named 'embreex' (outside the test environment)", name=name)
        return spec


sys.meta_path.insert(0, _EmbreexOnlyFromExtensions)

import bpy  # noqa: E402  (bpy first: it puts Blender's modules on sys.path)

import addon_utils  # noqa: E402

zip_path = sys.argv[1]
seen = {}
repos = {r.module: i for i, r in enumerate(bpy.context.preferences.extensions.repos)}
res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
seen["install"] = sorted(res)
module = "bl_ext.user_default.hybrid_raycast"
seen["enabled_after_install"] = module in {a.module for a in bpy.context.preferences.addons}
seen["operator_registered"] = hasattr(bpy.types, "HYBRID_RAYCAST_OT_scene_summary")
seen["scene_property"] = hasattr(bpy.types.Scene, "hybrid_raycast")
seen["panel_registered"] = hasattr(bpy.types, "VIEW3D_PT_hybrid_raycast")
# The installed add-on works: the demo-free summary on the default cube.
bpy.ops.wm.read_homefile(use_empty=False)
seen["summary_result"] = sorted(bpy.ops.hybrid_raycast.scene_summary())
seen["triangles_default_cube"] = bpy.context.scene.hybrid_raycast.triangle_count
# What it offers: Embree only where the package's own embreex wheel was installed.
embree = sys.modules[module + ".core.embree"]
seen["embree_available"] = embree.embree_available()
seen["embree_unavailable"] = embree.embree_unavailable_reason()
if seen["embree_available"]:
    import embreex

    seen["embreex_from"] = os.path.relpath(os.path.realpath(embreex.__file__),
                                           os.path.realpath(os.environ["BLENDER_USER_RESOURCES"])).split(os.sep)[0]
props = bpy.context.scene.hybrid_raycast
props.candidates = {"BVH", "EMBREE"}
props.ray_budget = "CUSTOM"
props.custom_rays = 1e6
seen["analyze_result"] = sorted(bpy.ops.hybrid_raycast.analyze())
record = json.loads(props.last_analysis_json)
seen["candidates_weighed"] = sorted(record["structures"])
seen["record_embree_unavailable"] = record.get("embree_unavailable")
seen["panel_embree_unavailable"] = props.embree_unavailable
seen["notes"] = props.notes
# Twice off and on again through Blender's own add-on machinery.
for _ in range(2):
    addon_utils.disable(module, default_set=True)
    addon_utils.enable(module, default_set=True)
seen["enabled_after_toggle"] = hasattr(bpy.types.Scene, "hybrid_raycast")
res = bpy.ops.extensions.package_uninstall(repo_index=repos["user_default"], pkg_id="hybrid_raycast")
seen["uninstall"] = sorted(res)
seen["enabled_after_uninstall"] = module in {a.module for a in bpy.context.preferences.addons}
seen["operator_after_uninstall"] = hasattr(bpy.types, "HYBRID_RAYCAST_OT_scene_summary")
seen["scene_property_after_uninstall"] = hasattr(bpy.types.Scene, "hybrid_raycast")
print("ROUNDTRIP " + json.dumps(seen))
exit_past_bpy(0)
