"""Hybrid Ray Cast: grid or BVH for the rays you are about to shoot (Blender extension).

Layout: ``core/`` computes (pure numpy), ``operators/`` bridges Blender and core,
``ui/`` only draws and calls.  ``register()`` walks one tuple of classes.
"""

import bpy

from . import operators, ui
from .ui.properties import HybridRaycastSettings

classes = (
    HybridRaycastSettings,
    *operators.classes,
    *ui.classes,
)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.hybrid_raycast = bpy.props.PointerProperty(type=HybridRaycastSettings)


def unregister():
    if hasattr(bpy.types.Scene, "hybrid_raycast"):
        del bpy.types.Scene.hybrid_raycast
    for cls in reversed(classes):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)
