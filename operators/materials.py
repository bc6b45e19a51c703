"""Blender materials -> the optical parameters a LiDAR scan needs per hit (``Optics``).

``optics(materials, objects)`` reads each material once: from the Principled BSDF that
feeds its active Material Output's Surface (linked directly, else the first found walking
upstream from it, e.g. through a Mix Shader), its 'Base Color', 'Metallic', 'Roughness',
transmission ('Transmission Weight' in Blender 4.x/5.x, 'Transmission' before 4.0) and
'Alpha' inputs, looked up by name (checked with bpy 5.0.1; these names are 4.2's too).
Without nodes or without a connected Principled BSDF: the material's viewport values
(``diffuse_color``, ``metallic``, ``roughness``), transmission 0, alpha
``diffuse_color[3]``.  The active output is the one Cycles renders
(``get_output_node('CYCLES')``: target All or Cycles).

Reflectivity is an approximation: the mean of the linear base colour's R, G and B, a
visible-light albedo standing in for the near-infrared (905 nm) one, which Blender does
not know.  Transmission is reported beside it, not folded in.  A float custom property
``hybrid_raycast_reflectivity`` (0-1) on a material replaces its reflectivity; on an
object it replaces the reflectivity of every hit on that object (material or not).

Not handled: textures and other links into a socket (a linked Base Color, Metallic or
Roughness falls back to the material's viewport value, a linked transmission or alpha to
the socket's own default value), node groups (not entered), other shaders (Diffuse,
Glossy, Glass ... count as no Principled BSDF), and Mix Shader weights (the first
Principled BSDF found is taken alone).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import bpy
import numpy as np

__all__ = ["Optics", "optics", "REFLECTIVITY_PROPERTY", "MIRROR_METALLIC", "MIRROR_ROUGHNESS"]

#: custom property (float 0-1) on a material or an object that sets its reflectivity
REFLECTIVITY_PROPERTY = "hybrid_raycast_reflectivity"
#: a material is mirror-like when metallic >= MIRROR_METALLIC and roughness <= MIRROR_ROUGHNESS:
#: this add-on's choice (a specular reflector that a LiDAR return would follow), not a
#: physical constant or a Blender setting
MIRROR_METALLIC = 0.5
MIRROR_ROUGHNESS = 0.2

# socket names, newest first: Blender 4.0 renamed 'Transmission' to 'Transmission Weight'
_TRANSMISSION = ("Transmission Weight", "Transmission")


@dataclass
class Optics:
    """Per material (K,) and per object (N,) LiDAR parameters, in the order given to ``optics``.

    reflectivity: float32, the mean linear base colour clipped to [0, 1] (an approximation
        of the near-infrared albedo) or the material's ``hybrid_raycast_reflectivity``
    metallic, roughness: float32 0-1, the Principled BSDF's (or the material's own)
    transmission: float32 0-1, max(transmission weight, 1 - alpha)
    mirror: bool, metallic >= MIRROR_METALLIC and roughness <= MIRROR_ROUGHNESS
    object_reflectivity: float32, each object's ``hybrid_raycast_reflectivity`` (NaN where unset)
    """

    reflectivity: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray
    transmission: np.ndarray
    mirror: np.ndarray
    object_reflectivity: np.ndarray

    def per_hit(self, material_index, object_index=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(reflectivity float32, transmission float32, mirror bool), each (M,), for hits
        with ``material_index`` (-1: none) and ``object_index`` (-1: none; both as in
        ``CastResult``).  No material: reflectivity 1, transmission 0, not a mirror.  An
        object's reflectivity wins over its material's."""
        mi = np.asarray(material_index, np.intp)
        k = len(self.reflectivity)
        if mi.size and (mi.min() < -1 or mi.max() >= k):
            raise ValueError(f"material_index must lie in [-1, {k}), got values from {mi.min()} to {mi.max()}")
        # one extra row for "no material", picked by index -1
        refl = np.append(self.reflectivity, np.float32(1.0))[mi]
        trans = np.append(self.transmission, np.float32(0.0))[mi]
        mirror = np.append(self.mirror, False)[mi]
        if object_index is not None and len(self.object_reflectivity):
            oi = np.asarray(object_index, np.intp)
            if oi.shape != mi.shape:
                raise ValueError(f"object_index {oi.shape} and material_index {mi.shape} must have one shape")
            n = len(self.object_reflectivity)
            if oi.size and (oi.min() < -1 or oi.max() >= n):
                raise ValueError(f"object_index must lie in [-1, {n}), got values from {oi.min()} to {oi.max()}")
            over = np.append(self.object_reflectivity, np.float32(np.nan))[oi]
            set_ = ~np.isnan(over)
            refl[set_] = over[set_]
        return refl, trans, mirror


def optics(materials, objects=None) -> Optics:
    """The ``Optics`` of ``materials`` (a sequence of ``bpy.types.Material``, e.g.
    ``CastResult.materials``), each read once, and the reflectivity overrides of
    ``objects`` (e.g. ``CastResult.objects``; None entries allowed).  Raises TypeError for
    a non-material and ValueError naming the material or object and the property for a
    ``hybrid_raycast_reflectivity`` that is not a number in [0, 1]."""
    materials = list(materials)
    k = len(materials)
    refl, metal, rough, trans = (np.empty(k, np.float32) for _ in range(4))
    for i, mat in enumerate(materials):  # a loop per material: K is small
        if not isinstance(mat, bpy.types.Material):
            raise TypeError(f"materials[{i}] must be a bpy.types.Material, got {type(mat).__name__}")
        color, metal[i], rough[i], weight, alpha = _read(mat)
        over = _override(mat, f"material '{mat.name}'")
        refl[i] = over if over is not None else float(np.mean(color[:3]))
        trans[i] = min(1.0, max(0.0, weight, 1.0 - alpha))
    objects = [] if objects is None else list(objects)
    obj_refl = np.full(len(objects), np.nan, np.float32)
    for j, ob in enumerate(objects):
        if ob is not None:
            over = _override(ob, f"object '{ob.name}'")
            if over is not None:
                obj_refl[j] = over
    np.clip(metal, 0.0, 1.0, out=metal)
    np.clip(rough, 0.0, 1.0, out=rough)
    np.clip(refl, 0.0, 1.0, out=refl)
    mirror = (metal >= MIRROR_METALLIC) & (rough <= MIRROR_ROUGHNESS)
    return Optics(refl, metal, rough, trans, mirror, obj_refl)


def _override(idb, what: str) -> float | None:
    """The ID's ``hybrid_raycast_reflectivity``, None where unset; ValueError if not a number in [0, 1]."""
    v = idb.get(REFLECTIVITY_PROPERTY)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0.0 <= v <= 1.0:
        raise ValueError(f"{what}: custom property '{REFLECTIVITY_PROPERTY}' must be a number in [0, 1], got {v!r}")
    return float(v)


def _read(mat):
    """(linear base colour RGBA, metallic, roughness, transmission weight, alpha) of a material."""
    own = (tuple(mat.diffuse_color), float(mat.metallic), float(mat.roughness))
    bsdf = _principled(mat)
    if bsdf is None:
        return own[0], own[1], own[2], 0.0, float(own[0][3])
    color = _value(bsdf, ("Base Color",), own[0], own[0])
    metallic = _value(bsdf, ("Metallic",), own[1], own[1])
    roughness = _value(bsdf, ("Roughness",), own[2], own[2])
    weight = _value(bsdf, _TRANSMISSION, 0.0)
    alpha = _value(bsdf, ("Alpha",), 1.0)
    return tuple(color), float(metallic), float(roughness), float(weight), float(alpha)


def _value(node, names, missing, linked=None):
    """The default value of the first input of ``node`` named one of ``names`` (``missing``
    without one); ``linked`` when given and that input is linked (a texture, a math node)."""
    for name in names:
        sock = node.inputs.get(name)
        if sock is not None:
            if linked is not None and sock.is_linked:
                return linked
            v = sock.default_value
            return tuple(v) if hasattr(v, "__len__") else v
    return missing


def _principled(mat):
    """The Principled BSDF node feeding the active Material Output's Surface, or None."""
    tree = mat.node_tree
    if tree is None or (bpy.app.version < (5, 0, 0) and not mat.use_nodes):  # 5.0: always nodes
        return None
    # the output Cycles renders (target All or Cycles), else any output marked active
    out = tree.get_output_node("CYCLES")
    if out is None:
        out = next((n for n in tree.nodes if n.type == "OUTPUT_MATERIAL" and n.is_active_output), None)
    surface = out.inputs.get("Surface") if out is not None else None
    if surface is None:
        return None
    # breadth first up the links into Surface: the direct one, else the first found
    seen, todo = set(), [surface]
    while todo:
        nxt = []
        for sock in todo:
            for link in sock.links:
                if not link.is_valid or link.is_muted:
                    continue
                node = link.from_node
                if node.type == "BSDF_PRINCIPLED" and not node.mute:
                    return node
                if node.as_pointer() not in seen:
                    seen.add(node.as_pointer())
                    nxt.extend(s for s in node.inputs if s.is_linked)
        todo = nxt
    return None
