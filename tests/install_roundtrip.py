"""Install the built zip into Blender-as-a-module as a user would, then uninstall it.

Run in a fresh process with BLENDER_USER_RESOURCES pointing at an empty folder:
    python tests/install_roundtrip.py ZIP
Prints one JSON line with what it observed; exits non-zero on the first failure.
"""

import json
import sys

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
