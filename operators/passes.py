"""What tracing gives the user: camera passes as images, and an ambient-occlusion bake.

Camera passes (``camera_workload`` + ``pass_images`` + ``write_images``)
    One ray per pixel centre of the active camera at the render resolution (times the
    percentage), through the camera's own frame (``Camera.view_frame``: sensor fit,
    shift and aspect as Blender renders them), perspective or orthographic; the clip
    range limits the rays along the view axis.  Three float RGBA Image datablocks,
    colour space Non-Color, rows bottom-up as Blender stores them:

    - "HRC Depth": view-axis depth (Blender's Z-pass convention) mapped for viewing:
      ``1 - (z - near) / (far - near)``, so the nearest hit is white and the farthest
      hit black; misses are 0 with alpha 0.  The image's custom properties ``near``
      and ``far`` (scene units) undo the mapping: ``z = far - v * (far - near)``.
    - "HRC Normal": the hit triangle's geometric world-space normal, facing the
      camera, as ``0.5 * n + 0.5``; misses 0 with alpha 0.
    - "HRC Object ID": a distinct colour per source object (golden-ratio hues);
      misses 0 with alpha 0.  ``image["object_names"]`` (JSON) lists the sources in
      index order; ``object_id_colors`` gives each index's colour.

    They show in the Image Editor and save as PNG or EXR like any image.

Ambient occlusion (``ao_workload`` + ``write_ao``)
    From every vertex of the target mesh, ``samples`` cosine-weighted hemisphere rays
    around its normal, traced as any-hit (occlusion) queries against the whole evaluated
    scene; the vertex's value is the unoccluded fraction.  Vertices are the evaluated
    mesh's when it has the original's vertex count (deforming modifiers) or when only
    subdivision modifiers change it (subdivision lists the original vertices' limit
    positions first, in order: checked on Blender 5.0), else the original's (a note
    says so).  Rays start ``1e-4`` of the scene's diagonal off the
    surface along the normal.  The result is a FLOAT_COLOR attribute on the POINT domain
    (grey, alpha 1), made the active colour attribute; writing it is undoable.
"""

from __future__ import annotations

import json

import bpy
import numpy as np

from .. import core
from .jobs import BadInput, NothingToTrace

DEPTH, NORMAL, OBJECT_ID = "HRC Depth", "HRC Normal", "HRC Object ID"
_PHI = 0.6180339887498949
_SUBDIVISION = {"SUBSURF", "MULTIRES"}


# -- camera rays ---------------------------------------------------------------------------

def _matrix(m) -> np.ndarray:
    return np.array([list(row) for row in m], np.float64)


def camera_workload(scene, depsgraph, camera=None) -> dict:
    """Rays through every pixel of the active camera: origins, directions (unit), tmin,
    tmax (per ray, from the clip range), cos to the view axis, width, height."""
    cam = camera if camera is not None else scene.camera
    if cam is None:
        raise NothingToTrace(f"no camera: scene '{scene.name}' has no active camera (set one in the Scene properties)")
    if cam.type != "CAMERA":
        raise NothingToTrace(f"no camera: the scene camera '{cam.name}' is a {cam.type.lower()}, not a camera")
    data = cam.data
    if data.type not in {"PERSP", "ORTHO"}:
        raise BadInput(f"camera '{cam.name}' is {data.type.lower()}: only perspective and orthographic cameras are supported")
    r = scene.render
    pct = r.resolution_percentage / 100.0
    width, height = max(1, int(r.resolution_x * pct)), max(1, int(r.resolution_y * pct))
    ev = cam.evaluated_get(depsgraph)
    frame = np.array([tuple(v) for v in ev.data.view_frame(scene=scene)], np.float64)  # tr, br, bl, tl
    right, top = frame[0, 0], frame[0, 1]
    left, bottom = frame[2, 0], frame[2, 1]
    z = frame[0, 2]
    px = left + (np.arange(width) + 0.5) / width * (right - left)
    py = top - (np.arange(height) + 0.5) / height * (top - bottom)  # top row first
    X, Y = np.meshgrid(px, py)
    M = _matrix(ev.matrix_world)
    R, t = M[:3, :3], M[:3, 3]
    fwd = R @ np.array([0.0, 0.0, -1.0])
    fwd /= np.linalg.norm(fwd)
    n = width * height
    if data.type == "PERSP":
        local = np.stack([X.ravel(), Y.ravel(), np.full(n, z)], axis=1)
        d = local @ R.T
        o = np.broadcast_to(t, (n, 3))
    else:
        local = np.stack([X.ravel(), Y.ravel(), np.zeros(n)], axis=1)
        o = local @ R.T + t
        d = np.broadcast_to(fwd, (n, 3))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    cos = np.clip(d @ fwd, 1e-6, None)
    tmin = (data.clip_start / cos).astype(np.float32)
    tmax = (data.clip_end / cos).astype(np.float32)
    return {"origins": np.ascontiguousarray(o, np.float32), "directions": d.astype(np.float32), "tmin": tmin,
            "tmax": tmax, "cos": cos.astype(np.float32), "width": width, "height": height, "camera": cam.name}


# -- camera passes ---------------------------------------------------------------------------

def object_id_colors(count: int) -> np.ndarray:
    """(count, 3) float32: a distinct, bright colour per object index (golden-ratio hues)."""
    h = (np.arange(count) * _PHI + 0.1) % 1.0
    s, v = 0.65, 0.95
    i = np.floor(h * 6).astype(int) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, tt = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    table = np.stack([
        np.stack([np.full_like(f, v), tt, np.full_like(f, p)], 1),
        np.stack([q, np.full_like(f, v), np.full_like(f, p)], 1),
        np.stack([np.full_like(f, p), np.full_like(f, v), tt], 1),
        np.stack([np.full_like(f, p), q, np.full_like(f, v)], 1),
        np.stack([tt, np.full_like(f, p), np.full_like(f, v)], 1),
        np.stack([np.full_like(f, v), np.full_like(f, p), q], 1),
    ], 0)
    return table[i, np.arange(count)].astype(np.float32)


def pass_images(mesh, hits, rays: dict) -> dict:
    """{name: (height, width, 4) float32 RGBA, top row first} and the depth range."""
    w, h = rays["width"], rays["height"]
    hit = hits.hit
    rgba_depth = np.zeros((w * h, 4), np.float32)
    rgba_normal = np.zeros((w * h, 4), np.float32)
    rgba_id = np.zeros((w * h, 4), np.float32)
    near = far = 0.0
    if hit.any():
        z = hits.t[hit].astype(np.float64) * rays["cos"][hit]
        near, far = float(z.min()), float(z.max())
        span = far - near if far > near else 1.0
        v = 1.0 - (z - near) / span
        rgba_depth[hit, :3] = v[:, None]
        tv = mesh.tri_vertices[hits.triangle[hit]].astype(np.float64)
        nrm = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        facing = (nrm * rays["directions"][hit]).sum(axis=1) > 0
        nrm[facing] *= -1
        rgba_normal[hit, :3] = 0.5 * nrm + 0.5
        if mesh.object_index is not None:
            colors = object_id_colors(max(len(mesh.object_names), 1))
            rgba_id[hit, :3] = colors[mesh.object_index[hits.triangle[hit]]]
    for a in (rgba_depth, rgba_normal, rgba_id):
        a[hit, 3] = 1.0
    shape = (h, w, 4)
    return {DEPTH: rgba_depth.reshape(shape), NORMAL: rgba_normal.reshape(shape), OBJECT_ID: rgba_id.reshape(shape),
            "near": near, "far": far}


def write_image(name: str, rgba: np.ndarray):
    """Create or refresh a float RGBA Image datablock (Non-Color) from a top-first array."""
    h, w = rgba.shape[:2]
    img = bpy.data.images.get(name)
    if img is not None and (tuple(img.size) != (w, h) or not img.is_float or img.source != "GENERATED"):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    try:
        img.colorspace_settings.name = "Non-Color"
    except TypeError:  # a build without that colour space name
        pass
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], np.float32).ravel())
    img.update()
    return img


def write_pass_images(mesh, passes: dict) -> list:
    imgs = []
    for name in (DEPTH, NORMAL, OBJECT_ID):
        imgs.append(write_image(name, passes[name]))
    imgs[0]["near"], imgs[0]["far"] = passes["near"], passes["far"]
    imgs[2]["object_names"] = json.dumps(list(mesh.object_names))
    return imgs


def save_image(img, path) -> str:
    """Save an Image datablock as PNG at ``path`` (8 bits per channel, RGBA)."""
    img.filepath_raw = str(path)
    img.file_format = "PNG"
    img.save()
    return str(path)


# -- ambient occlusion --------------------------------------------------------------------------

def ao_target(scene, view_layer, name: str | None = None, what: str = "the AO bake"):
    """The mesh object to bake: ``name``, else the active object, else the first selected mesh
    (``what``: the bake, for the messages)."""
    if name:
        ob = scene.objects.get(name)
        if ob is None:
            raise NothingToTrace(f"no mesh to bake: scene '{scene.name}' has no object named '{name}'")
    else:
        ob = view_layer.objects.active if view_layer is not None else None
        if ob is None or ob.type != "MESH":
            sel = [o for o in (view_layer.objects if view_layer is not None else scene.objects)
                   if o.type == "MESH" and o.select_get(view_layer=view_layer)]
            ob = sel[0] if sel else ob
    if ob is None:
        raise NothingToTrace("no mesh to bake: make a mesh object active")
    if ob.type != "MESH":
        raise NothingToTrace(f"no mesh to bake: '{ob.name}' is a {ob.type.lower()}, not a mesh")
    if ob.mode == "EDIT":
        raise BadInput(f"{what} needs Object Mode: leave Edit Mode on '{ob.name}' first")
    if len(ob.data.vertices) == 0:
        raise NothingToTrace(f"no mesh to bake: '{ob.name}' has no vertices")
    return ob


def _vertex_normals(me) -> np.ndarray:
    n = np.empty(len(me.vertices) * 3, np.float32)
    if hasattr(me, "vertex_normals"):
        me.vertex_normals.foreach_get("vector", n)
    else:  # before 3.5
        me.vertices.foreach_get("normal", n)
    return n.reshape(-1, 3)


def bake_vertices(ob, depsgraph, what: str = "bake"):
    """(world positions (V, 3), world vertex normals (V, 3), not normalised; a note or None)
    of ``ob``'s original vertices, float64, where a bake writes its per-vertex values:
    the evaluated positions when its modifiers only deform it (or subdivide it, whose first
    vertices are the originals' limit positions), else the original ones with a note."""
    ev = ob.evaluated_get(depsgraph)
    me_eval, me = ev.data, ob.data
    V = len(me.vertices)
    note = None
    if me_eval is not None and len(me_eval.vertices) == V:
        src = me_eval  # deforming modifiers only: the evaluated vertices are the original ones, moved
    elif (me_eval is not None and len(me_eval.vertices) > V and ob.modifiers
          and all(m.type in _SUBDIVISION for m in ob.modifiers if m.show_viewport)):
        # subdivision puts each original vertex's limit position first, in the original order
        src = me_eval
    else:
        src = me
        if me_eval is not None:
            note = (f"'{ob.name}': its modifiers change the vertex count ({V} -> {len(me_eval.vertices)}); "
                    f"{what} at the original vertices, which may lie off the evaluated surface")
    co = np.empty(len(src.vertices) * 3, np.float32)
    src.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)[:V].astype(np.float64)
    if not np.isfinite(co).all():
        raise BadInput(f"'{ob.name}' has NaN or infinite vertex coordinates: nothing to {what} from")
    nrm = _vertex_normals(src)[:V].astype(np.float64)
    M = _matrix(ev.matrix_world)
    A, t = M[:3, :3], M[:3, 3]
    try:
        nw = nrm @ np.linalg.inv(A)  # normals transform by the inverse transpose
    except np.linalg.LinAlgError:
        raise BadInput(f"'{ob.name}' has a degenerate (zero-scale) transform: nothing to {what} from") from None
    return co @ A.T + t, nw, note


def ao_workload(ob, depsgraph, samples: int, distance: float, scene_diagonal: float, seed: int = 0) -> dict:
    """Hemisphere rays from every vertex of ``ob`` (see the module doc)."""
    p, nw, note = bake_vertices(ob, depsgraph, "bake")
    length = np.linalg.norm(nw, axis=1)
    bad = ~(length > 0) | ~np.isfinite(length)
    nw[bad] = (0.0, 0.0, 1.0)  # loose vertices: an arbitrary hemisphere
    nw[~bad] /= length[~bad, None]
    eps = 1e-4 * max(scene_diagonal, 1e-6)
    o, d = core.hemisphere_rays(p + eps * nw, nw, int(samples), seed=seed)
    tmax = float(distance) if distance and distance > 0 else np.inf
    return {"origins": o, "directions": d, "tmin": np.float32(eps), "tmax": tmax, "vertices": len(p),
            "samples": int(samples), "object": ob.name, "note": note}


def write_ao(ob, occluded: np.ndarray, samples: int, attribute: str):
    """Store 1 - occluded fraction per vertex as a FLOAT_COLOR POINT attribute (undoable)."""
    me = ob.data
    ao = 1.0 - occluded.reshape(-1, samples).mean(axis=1)
    if len(ao) != len(me.vertices):
        raise BadInput(f"'{ob.name}' changed while baking ({len(me.vertices)} vertices now, {len(ao)} baked)")
    rgba = np.empty((len(ao), 4), np.float32)
    rgba[:, :3] = ao[:, None]
    rgba[:, 3] = 1.0
    attr = me.color_attributes.get(attribute)
    if attr is not None and (attr.data_type != "FLOAT_COLOR" or attr.domain != "POINT"):
        me.color_attributes.remove(attr)
        attr = None
    if attr is None:
        other = me.attributes.get(attribute)
        if other is not None:
            me.attributes.remove(other)
        attr = me.color_attributes.new(attribute, "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", rgba.ravel())
    me.color_attributes.active_color = attr
    me.update()
    return attr, ao
