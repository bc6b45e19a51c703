"""HYBRID_RAYCAST_OT_scene_summary: extract the evaluated scene and store its summary."""

import time

import bpy

from .extract import NoGeometryError, scene_mesh, scene_summary


def store_summary(props, summary: dict):
    props.triangle_count = summary["triangles"]
    props.object_count = summary["objects"]
    props.instance_count = summary["instances"]
    props.extraction_time = summary["extraction_seconds"]
    props.bounds_min, props.bounds_max = summary["bounds"]
    props.has_summary = True


class HYBRID_RAYCAST_OT_scene_summary(bpy.types.Operator):
    """Extract the evaluated triangles of the scene and show how many, where and how fast"""

    bl_idname = "hybrid_raycast.scene_summary"
    bl_label = "Summarise Scene"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        props = context.scene.hybrid_raycast
        depsgraph = context.evaluated_depsgraph_get()
        t0 = time.perf_counter()
        try:
            mesh = scene_mesh(depsgraph, selected_only=props.selected_only)
        except NoGeometryError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        summary = scene_summary(depsgraph, mesh, time.perf_counter() - t0)
        store_summary(props, summary)
        self.report({"INFO"}, f"{summary['triangles']:,} triangles from {summary['objects']} objects in {summary['extraction_seconds'] * 1e3:.0f} ms")
        return {"FINISHED"}
