"""The sidebar's time-versus-rays picture: ``core.plot``'s raster in an image preview.

``panel_preview`` puts the raster into an image preview (``bpy.utils.previews``) that the
panel shows with ``template_icon``; it is redrawn only when the figures change.
"""

from __future__ import annotations

import numpy as np

from ..core.plot import plot_rgba

PREVIEW_SIZE = 256
_previews = None
_drawn: dict = {}


def register():
    global _previews
    import bpy.utils.previews

    _previews = bpy.utils.previews.new()
    _drawn.clear()


def unregister():
    global _previews
    import bpy.utils.previews

    if _previews is not None:
        bpy.utils.previews.remove(_previews)
    _previews = None
    _drawn.clear()


def panel_preview(scene_name: str, f: dict):
    """The icon id of the preview showing ``f`` for this scene (drawn when ``f`` changed);
    0 when previews are unavailable."""
    if _previews is None or f is None:
        return 0
    name = f"plot {scene_name}"
    key = repr(sorted(f.items()))
    pv = _previews.get(name) or _previews.new(name)
    if _drawn.get(name) != key:
        rgba = plot_rgba(f, PREVIEW_SIZE, PREVIEW_SIZE)
        flat = np.ascontiguousarray(rgba[::-1]).ravel()
        pv.image_size = (PREVIEW_SIZE, PREVIEW_SIZE)
        pv.image_pixels_float.foreach_set(flat)
        small = plot_rgba({**f, "decision": None}, 32, 32, scale=1)
        pv.icon_size = (32, 32)
        pv.icon_pixels_float.foreach_set(np.ascontiguousarray(small[::-1]).ravel())
        _drawn[name] = key
    return pv.icon_id
