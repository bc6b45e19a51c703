"""Startup script for the GUI check (``blender file.blend --python gui_startup.py -- WORK``).

Enables the installed extension, opens the 3D View sidebar on the "Hybrid RT" tab, and
sets the calibration to the full (slow) scale for the cancel check, writes ``gui_layout.json`` (window and sidebar geometry, UI scale) so run.sh can click
Analyze with xdotool.  A timer then writes ``gui_status.json`` every half second with the
scene's results, so run.sh knows when the click has produced a decision.
"""

import json
import sys
from pathlib import Path

import addon_utils
import bpy

WORK = Path(sys.argv[sys.argv.index("--") + 1])
MODULE = "bl_ext.user_default.hybrid_raycast"

addon_utils.enable(MODULE, default_set=True)
bpy.context.preferences.view.show_splash = False


def _view3d():
    win = bpy.context.window_manager.windows[0]
    areas = [a for a in win.screen.areas if a.type == "VIEW_3D"]
    return win, max(areas, key=lambda a: a.width * a.height)


def setup():
    win, area = _view3d()
    area.spaces.active.show_region_ui = True
    region = next(r for r in area.regions if r.type == "UI")
    try:
        region.active_panel_category = "Hybrid RT"
    except (AttributeError, TypeError) as e:  # before 4.2
        print("cannot set the sidebar tab:", e)
    area.tag_redraw()
    # the full calibration takes long enough for run.sh to cancel it with Esc
    bpy.context.scene.hybrid_raycast.calibration_scale = "default"
    bpy.app.timers.register(write_layout, first_interval=1.0)
    return None


def write_layout():
    win, area = _view3d()
    region = next(r for r in area.regions if r.type == "UI")
    layout = {
        "window": {"x": win.x, "y": win.y, "width": win.width, "height": win.height},
        "area": {"x": area.x, "y": area.y, "width": area.width, "height": area.height},
        "sidebar": {"x": region.x, "y": region.y, "width": region.width, "height": region.height},
        "category": getattr(region, "active_panel_category", None),
        "ui_scale": bpy.context.preferences.system.ui_scale,
        "pixel_size": bpy.context.preferences.system.pixel_size,
    }
    (WORK / "gui_layout.json").write_text(json.dumps(layout, indent=1))
    print("GUI layout", layout, flush=True)
    return None


def write_status():
    p = bpy.context.scene.hybrid_raycast
    try:
        win, area = _view3d()
        region = next(r for r in area.regions if r.type == "UI")
        category = getattr(region, "active_panel_category", None)
    except (StopIteration, ValueError, ReferenceError):
        category = None
    settings = sys.modules.get(MODULE + ".settings")
    status = {"category": category, "running": bool(settings and settings.RUNNING), "has_results": p.has_results, "decision": p.decision, "triangles": p.triangle_count,
              "break_even": None if p.break_even_infinite else p.break_even_rays, "stale": p.stale}
    (WORK / "gui_status.json").write_text(json.dumps(status))
    return 0.5


bpy.app.timers.register(setup, first_interval=0.5)
bpy.app.timers.register(write_status, first_interval=1.0)
