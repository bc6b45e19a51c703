"""Scene settings and results: ``scene.hybrid_raycast``."""

import bpy
from bpy.props import BoolProperty, FloatProperty, FloatVectorProperty, IntProperty


class HybridRaycastSettings(bpy.types.PropertyGroup):
    # -- settings ------------------------------------------------------------------
    selected_only: BoolProperty(
        name="Selected Only",
        description="Extract only the selected objects (and instances whose instancer is selected)",
        default=False,
    )
    expected_rays: FloatProperty(
        name="Expected Rays",
        description="How many rays you are about to shoot; decides whether a BVH pays for its build",
        default=1.0e6,
        min=0.0,
        soft_max=1.0e10,
        precision=0,
        step=100000,
    )
    # -- results of the last extraction (read-only in the UI) -----------------------
    triangle_count: IntProperty(name="Triangles", description="Triangles extracted from the evaluated scene", min=0)
    object_count: IntProperty(name="Objects", description="Objects and instances that contributed triangles", min=0)
    instance_count: IntProperty(name="Instances", description="Instances among the contributing objects", min=0)
    extraction_time: FloatProperty(
        name="Extraction Time", description="Wall time of the last extraction", unit="TIME_ABSOLUTE", min=0.0, precision=3
    )
    bounds_min: FloatVectorProperty(name="Bounds Min", description="World-space minimum corner", subtype="XYZ", unit="LENGTH", size=3)
    bounds_max: FloatVectorProperty(name="Bounds Max", description="World-space maximum corner", subtype="XYZ", unit="LENGTH", size=3)
    has_summary: BoolProperty(name="Has Summary", description="An extraction has run in this scene", default=False)
