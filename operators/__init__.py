"""The bridge between Blender and core: extraction and the operators."""

from .summary import HYBRID_RAYCAST_OT_scene_summary

classes = (HYBRID_RAYCAST_OT_scene_summary,)
