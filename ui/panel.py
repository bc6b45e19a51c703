"""The 3D View sidebar tab "Hybrid RT": draws scene.hybrid_raycast and calls operators."""

import bpy


class VIEW3D_PT_hybrid_raycast(bpy.types.Panel):
    bl_label = "Hybrid Ray Cast"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Hybrid RT"

    def draw(self, context):
        layout = self.layout
        props = context.scene.hybrid_raycast
        col = layout.column()
        col.prop(props, "selected_only")
        col.prop(props, "expected_rays")
        col.operator("hybrid_raycast.scene_summary", icon="MESH_DATA")
        if props.has_summary:
            box = layout.box()
            box.label(text=f"{props.triangle_count:,} triangles", icon="MESH_DATA")
            box.label(text=f"{props.object_count:,} objects ({props.instance_count:,} instances)", icon="OBJECT_DATA")
            lo, hi = props.bounds_min, props.bounds_max
            box.label(text="Size {:.3g} x {:.3g} x {:.3g}".format(*(h - l for l, h in zip(lo, hi))))
            box.label(text=f"Extracted in {props.extraction_time * 1e3:.0f} ms", icon="TIME")
