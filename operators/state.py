"""Session state: has the scene changed since the analysis, and the extracted-scene cache.

Stale results
-------------
``on_depsgraph_update`` (a persistent ``depsgraph_update_post`` handler, also run on
``frame_change_post``) counts, per scene, the updates that can change the extracted
triangles, and sets ``scene.hybrid_raycast.geometry_changed`` when the scene has results.
Counted as a change:
- an Object update with new geometry or a new transform, except cameras, lights, light
  probes, speakers and armatures (an armature's deformed meshes report their own update);
- a Collection update with geometry or transform (objects added, removed, linked,
  collections hidden or excluded for render);
- a Scene update that changed which objects are visible (``hide_set``, hiding
  collections in the viewport), or which are selected when the analysis was made with
  "Selected Only": checked with a fingerprint of the visible (selected) objects, only for
  scenes analysed in this session.
Not counted: the add-on's own writes (results, pass images, and the AO colour attribute,
which ``own_updates`` excludes while it is written), selection without "Selected Only",
cameras and lights.  Settings that change the answer (expected rays, candidates, sample
rays, grid density, selected-only) are compared by ``HybridRaycastSettings.stale``
itself.

The cache
---------
``CACHE[scene pointer]`` keeps the last extracted mesh, its grid and any structure built
over it (``SceneCache``), with the change counter it was made at and the extraction
settings.  ``cached(scene, key)`` returns it only while nothing changed, so the trace
operator and ``api.cast`` reuse the triangles and structures between calls on an
unchanged scene and rebuild them after any counted change.  Callers must evaluate the
depsgraph first (``context.evaluated_depsgraph_get()``) so pending updates have been
counted.  Loading a file clears everything.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import bpy
from bpy.app.handlers import persistent

#: scene pointer -> number of counted changes in this session
GENERATION: dict[int, int] = {}
#: scene pointer -> SceneCache
CACHE: dict[int, "SceneCache"] = {}
#: scene pointer -> (selected_only, fingerprint of the visible objects) at the last analysis
VISIBILITY: dict[int, tuple] = {}
#: pointers of IDs the add-on itself is writing (their updates are not changes)
OWN_UPDATES: set[int] = set()

_NOT_GEOMETRY = {"CAMERA", "LIGHT", "LIGHT_PROBE", "LIGHTPROBE", "SPEAKER", "ARMATURE"}


@dataclass
class SceneCache:
    """One scene's extraction and the structures built over it."""

    generation: int
    key: tuple  # (selected_only, grid_density)
    mesh: object
    summary: dict
    grid: object = None
    plan: object = None  # the analysis' plan, when the analysis made this cache
    structures: dict = field(default_factory=dict)  # kind -> Accel


def scene_key(scene) -> int:
    return scene.original.as_pointer() if getattr(scene, "original", None) is not None else scene.as_pointer()


def generation(scene) -> int:
    return GENERATION.get(scene_key(scene), 0)


def cached(scene, key) -> SceneCache | None:
    c = CACHE.get(scene_key(scene))
    if c is not None and c.generation == generation(scene) and c.key == tuple(key):
        return c
    return None


def store(scene, key, mesh, summary, grid=None, generation_at=None) -> SceneCache:
    gen = generation(scene) if generation_at is None else generation_at
    c = SceneCache(gen, tuple(key), mesh, summary, grid)
    CACHE[scene_key(scene)] = c
    return c


def visibility_fingerprint(scene, view_layer, selected_only: bool) -> int:
    out = []
    for ob in scene.objects:
        try:
            vis = ob.visible_get(view_layer=view_layer)
        except (RuntimeError, TypeError):
            vis = ob.visible_get()
        if vis and (not selected_only or ob.select_get(view_layer=view_layer)):
            out.append(ob.as_pointer())
    return hash(tuple(out))


def remember_visibility(scene, view_layer, selected_only: bool):
    VISIBILITY[scene_key(scene)] = (selected_only, visibility_fingerprint(scene, view_layer, selected_only))


def mark_changed(scene):
    k = scene_key(scene)
    GENERATION[k] = GENERATION.get(k, 0) + 1
    props = getattr(scene, "hybrid_raycast", None)
    if props is not None and props.has_results and not props.geometry_changed:
        props.geometry_changed = True


def _counts(update) -> bool:
    idb = update.id
    if isinstance(idb, bpy.types.Object):
        if idb.type in _NOT_GEOMETRY:
            return False
        return update.is_updated_geometry or update.is_updated_transform
    if isinstance(idb, bpy.types.Collection):
        return update.is_updated_geometry or update.is_updated_transform
    return False


def _pointer(idb) -> int:
    orig = getattr(idb, "original", None)
    return (orig if orig is not None else idb).as_pointer()


@persistent
def on_depsgraph_update(scene, depsgraph):
    changed = False
    scene_updated = False
    for u in depsgraph.updates:
        if isinstance(u.id, bpy.types.Scene):
            scene_updated = True
            continue
        if OWN_UPDATES and _pointer(u.id) in OWN_UPDATES:
            continue
        if _counts(u):
            changed = True
            break
    if not changed and scene_updated:
        seen = VISIBILITY.get(scene_key(scene))
        if seen is not None:
            fp = visibility_fingerprint(scene, depsgraph.view_layer, seen[0])
            if fp != seen[1]:
                VISIBILITY[scene_key(scene)] = (seen[0], fp)
                changed = True
    if changed:
        mark_changed(scene)


@persistent
def on_load_post(*_args):
    clear()


def clear():
    GENERATION.clear()
    CACHE.clear()
    VISIBILITY.clear()
    OWN_UPDATES.clear()


_HANDLERS = (
    ("depsgraph_update_post", on_depsgraph_update),
    ("frame_change_post", on_depsgraph_update),
    ("load_post", on_load_post),
)


def register():
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn not in lst:
            lst.append(fn)


def unregister():
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        # match by name too: a reloaded module brings new function objects
        for h in [h for h in lst if h is fn or (getattr(h, "__name__", "") == fn.__name__
                                               and getattr(h, "__module__", "") == fn.__module__)]:
            lst.remove(h)
    clear()
