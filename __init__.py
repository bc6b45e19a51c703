"""Hybrid Ray Cast: grid or BVH for the rays you are about to shoot (Blender extension).

Layout: ``core/`` computes (pure numpy), ``operators/`` bridges Blender and core,
``ui/`` only draws and calls; ``settings.py`` (``scene.hybrid_raycast``) and ``budget.py``
are what operators and ui share; ``api.cast`` is the script interface.  ``register()``
walks one tuple of classes, then adds the scene property, the change handlers, the
plot's preview collection and the ``-c hybrid_raycast`` command-line command.

Importing the package needs no Blender: ``pip install .`` gives ``hybrid_raycast.core``
in any Python with numpy (on Dask workers, for instance).  The Blender parts
(``operators``, ``settings``, ``ui``, ``classes``) are imported when ``register()`` runs or when they
are first asked for, so bpy is imported only then.
"""

import importlib

from . import api  # noqa: F401  (reachable as <package>.api; bpy is imported when api.cast runs)

_cli_handle = None
_BLENDER_PARTS = ("operators", "settings", "ui")


def _classes():
    """The one tuple of classes register() walks (imports the Blender parts, so bpy)."""
    global classes
    from . import operators, ui
    from .operators import scan
    from .settings import HybridRaycastSettings
    from .ui import scan_panel

    classes = (HybridRaycastSettings, *operators.classes, *ui.classes, *scan.classes, *scan_panel.classes)
    return classes


def __getattr__(name):
    # PEP 562: the Blender parts on first use, so a plain `import hybrid_raycast` never imports bpy
    if name in _BLENDER_PARTS:
        return importlib.import_module(f".{name}", __name__)
    if name == "classes":
        return _classes()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def register():
    import bpy

    from .operators import cli, scan, session
    from .settings import HybridRaycastSettings
    from .ui import plot

    global _cli_handle
    for cls in _classes():
        bpy.utils.register_class(cls)
    bpy.types.Scene.hybrid_raycast = bpy.props.PointerProperty(type=HybridRaycastSettings)
    scan.register_properties()
    session.register()
    plot.register()
    if _cli_handle is None and hasattr(bpy.utils, "register_cli_command"):
        _cli_handle = bpy.utils.register_cli_command(cli.COMMAND, cli.handler)


def unregister():
    import bpy

    from .operators import scan, session
    from .ui import plot

    global _cli_handle
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    plot.unregister()
    session.unregister()
    scan.unregister_properties()
    if hasattr(bpy.types.Scene, "hybrid_raycast"):
        del bpy.types.Scene.hybrid_raycast
    for cls in reversed(_classes()):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)
