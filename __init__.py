"""Hybrid Ray Cast: grid or BVH for the rays you are about to shoot (Blender extension).

Layout: ``core/`` computes (pure numpy), ``operators/`` bridges Blender and core,
``ui/`` only draws and calls; ``settings.py`` (``scene.hybrid_raycast``) and ``budget.py``
are what operators and ui share; ``api.cast`` is the script interface.  ``register()``
walks one tuple of classes, then adds the scene property, the change handlers, the
plot's preview collection and the ``-c hybrid_raycast`` command-line command.
"""

import bpy

from . import api, operators, settings, ui  # noqa: F401  (api: reachable as <package>.api)
from .operators import cli, state
from .settings import HybridRaycastSettings
from .ui import plot

classes = (
    HybridRaycastSettings,
    *operators.classes,
    *ui.classes,
)

_cli_handle = None


def register():
    global _cli_handle
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.hybrid_raycast = bpy.props.PointerProperty(type=HybridRaycastSettings)
    state.register()
    plot.register()
    if _cli_handle is None and hasattr(bpy.utils, "register_cli_command"):
        _cli_handle = bpy.utils.register_cli_command(cli.COMMAND, cli.handler)


def unregister():
    global _cli_handle
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    plot.unregister()
    state.unregister()
    if hasattr(bpy.types.Scene, "hybrid_raycast"):
        del bpy.types.Scene.hybrid_raycast
    for cls in reversed(classes):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)
