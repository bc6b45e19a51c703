"""The sidebar's "Scan" panel (Hybrid RT tab): the active object's sensor settings and the Scan button.

Draws ``object.hybrid_raycast_sensor`` (``operators/scan.py``) and calls
``hybrid_raycast.scan``; nothing here computes.
"""

import bpy

from .. import settings


class VIEW3D_PT_hybrid_raycast_scan(bpy.types.Panel):
    bl_label = "Scan"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Hybrid RT"

    def draw(self, context):
        layout = self.layout
        ob = context.active_object
        if ob is None or not hasattr(ob, "hybrid_raycast_sensor"):
            layout.label(text="Select an object to scan from", icon="INFO")
            return
        s = ob.hybrid_raycast_sensor
        layout.use_property_split = True
        layout.use_property_decorate = False
        layout.label(text=f"Sensor: {ob.name}", icon="OUTLINER_OB_LIGHTPROBE" if ob.type == "EMPTY" else "OBJECT_DATA")
        layout.prop(s, "preset")
        layout.prop(s, "kind")
        col = layout.column(align=True)
        if s.kind == "ROTATING":
            col.prop(s, "channels")
            col.prop(s, "fov_up")
            col.prop(s, "fov_down")
            col.prop(s, "elevations")
            col.prop(s, "azimuth_steps")
            col.prop(s, "rotation_rate")
            col.label(text=f"{s.channels * s.azimuth_steps:,} rays per frame, {360.0 / s.azimuth_steps:.3g} deg steps")
        elif s.kind == "AREA":
            col.prop(s, "h_fov")
            col.prop(s, "v_fov")
            col.prop(s, "h_steps")
            col.prop(s, "v_steps")
            col.prop(s, "frame_rate")
            col.label(text=f"{s.h_steps * s.v_steps:,} rays per frame")
        else:
            if ob.type != "CAMERA":
                col.label(text="A depth camera must be a camera object", icon="ERROR")
            col.prop(s, "width")
            col.prop(s, "height")
        col = layout.column(align=True)
        col.prop(s, "range_min")
        col.prop(s, "range_max")
        col = layout.column(align=True)
        col.prop(s, "noise_sigma")
        col.prop(s, "seed")
        col.prop(s, "reference_range")
        col.prop(s, "drop_below")
        col = layout.column(align=True)
        col.prop(s, "motion")
        if s.motion == "SWEEP":
            col.prop(s, "sweep_tolerance")
            col.prop(s, "sweep_blocks")
        col = layout.column(align=True)
        col.prop(s, "returns")
        col.prop(s, "beam_divergence")
        col.prop(s, "beam_samples")
        col.prop(s, "range_resolution")
        col.prop(s, "use_materials")
        if s.use_materials:
            col.prop(s, "max_bounces")
        col = layout.column(align=True)
        col.prop(s, "use_atmosphere")
        if s.use_atmosphere:
            col.prop(s, "visibility")
        col.prop(s, "false_return_rate")
        if s.false_return_rate > 0:
            col.prop(s, "false_return_range")
            col.prop(s, "false_return_intensity")
        col.prop(s, "dropoff_general_rate")
        col.prop(s, "dropoff_zero_intensity")
        col.prop(s, "dropoff_intensity_limit")
        col = layout.column(align=True)
        col.prop(s, "directory")
        col.prop(s, "file_format")
        col.prop(s, "space")
        col.prop(s, "use_scene_range")
        if not s.use_scene_range:
            col.prop(s, "frame_start")
            col.prop(s, "frame_end")
        running = settings.RUNNING
        if running and running.get("label") == "Hybrid RT scan":
            box = layout.box()
            text = running.get("text", "")
            if hasattr(box, "progress"):
                box.progress(factor=float(running.get("fraction", 0.0)), type="BAR", text=text)
            else:
                box.label(text=text, icon="TIME")
            box.label(text="Esc stops between frames", icon="CANCEL")
        row = layout.row()
        row.scale_y = 1.5
        row.operator("hybrid_raycast.scan", icon="OUTLINER_DATA_POINTCLOUD")


classes = (VIEW3D_PT_hybrid_raycast_scan,)
