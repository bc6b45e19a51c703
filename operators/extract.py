"""Blender scene -> ``core.TriangleMesh``: the evaluated, visible, render-enabled triangles.

What is extracted
-----------------
Every entry of ``depsgraph.object_instances`` whose (evaluated) object is a MESH, so
modifiers and geometry nodes are applied, and collection, vertex/face, particle and
geometry-nodes instances come with their instance matrices. Curves, text, surfaces and
metaballs are *not* read from their own entry: Blender (checked on 5.0.1) lists the
evaluated mesh of every such object a second time, as a MESH instance whose parent is the
object itself, so reading both (e.g. ``to_mesh()`` on the FONT entry plus the instance)
would count their triangles twice. Only MESH entries are read, which counts each once.
Curves (hair), point clouds and volumes have no triangles and are skipped.

Visibility: an entry is kept when its *root* object (the object itself, or for an
instance the top-level instancer, ``inst.parent``) is visible in the viewport of the view
layer (``visible_get``: not ``hide_set``, not ``hide_viewport``, collection and layer
collection not hidden) **and** enabled for render (not ``hide_render``, and reachable
through collections that are neither excluded nor ``hide_render``). Instances of a hidden
instancer are therefore left out too. An instanced object with ``hide_render`` is left
out as well (Blender's viewport depsgraph still lists it). An instancer's own geometry is
left out where Blender would not render it (``show_instancer_for_render`` off, or the
depsgraph's ``show_self`` off). Modifier levels are the depsgraph's: the viewport one
for ``evaluated_depsgraph_get()`` (e.g. Subdivision Surface ``levels``, not
``render_levels``).

Names (``TriangleMesh.object_names``), one entry per source of geometry, unique:
- an object's own geometry: the object's name (``"Cube"``; also ``"Text"`` for the mesh
  of a text, curve, surface or metaball object);
- an instanced object (collection, vertex/face or particle instancing):
  ``"Instancer/Instanced"``, e.g. ``"CollectionEmpty/Tree"``; the instancer is the
  top-level one for nested instances;
- geometry-nodes instances: ``"Instancer/MeshData"``, the evaluated mesh datablock's name
  (for an Object Info instance that is the instanced object's mesh name).
An entry is one (source, evaluated mesh) pair, so ``polygon_index`` is always a polygon
of one mesh; where one source brings several meshes (an instanced object that has
geometry-nodes instances of its own, two generated meshes both named "Mesh"), the later
entries get " #<entry>" appended to keep names unique.
``mesh.source_info`` (a ``SourceInfo``) holds, per entry, the instancer, the source,
the number of instances and of triangles.

Instances: every placement of a mesh is one instance; ``mesh.instance_index`` gives each
triangle's, and ``mesh.instances`` (an ``InstanceTable``) each instance's world matrix and
the original object a ray hit on it reports (``scene.ray_cast``'s object: the object itself,
the instanced object, or a geometry-nodes instancer), filled with the same batched writes as
the other per-triangle arrays.  Corner normals and UVs are read only when asked
(``attributes``), since they cost a read per mesh and 60 bytes per triangle.

Materials (``attributes`` 'material', read only when asked): each triangle gets the
material Blender renders it with.  A mesh's face ``material_index`` is read once per
evaluated mesh; slot -> material is resolved per *kind of placement* (per distinct
(instancer, instanced object, mesh)), from the evaluated object the depsgraph lists it with
(``inst.object.material_slots``).  On an evaluated object a slot's ``material`` is
Blender's render rule, ``BKE_object_material_get_eval`` (blenkernel material.cc, through
``rna_MaterialSlot_material_get``): an object-linked slot's material, or the data's when
that is empty.  This holds for an object's own geometry, for objects placed by
collection/vertex/particle instancing or by an Object Info node "As Instance" (their
object-linked materials apply), and for geometry-nodes meshes (the depsgraph's
temporary object carries the generated mesh's materials, e.g. from Set Material); all
checked against Cycles renders with bpy 5.0.1.  So two objects sharing one mesh (a
linked duplicate) with different object-linked materials each keep theirs, although the
mesh is read once.  A slot index past the last slot takes the last slot, as Blender renders
it (the same function's clamp; checked with Cycles); a mesh without slots, or an empty
slot, gives no material (-1).  ``mesh.instances.materials`` lists the original
``bpy.types.Material``s hit-able, ``triangle_material`` indexes it per triangle.

Not handled: ``hide_render`` on an *intermediate* instancer of nested instances (only the
top-level instancer and the instanced object itself are checked; the depsgraph's
iteration does not expose the chain), per-ray visibility (``visible_camera`` ...),
holdout and indirect-only collections, and hair curves, point clouds and volumes; for
materials, the view layer's ``material_override`` and materials of meshes in edit mode
(read from the evaluated mesh, not the edit-mode cage).

Speed: no Python loop per vertex or triangle. The Python loop is per depsgraph instance
(a dict look-up and two appends, three with materials, after the first placement of a
kind); each evaluated mesh is read once with ``foreach_get`` into numpy, keyed by its
pointer (the depsgraph owns its
meshes while we iterate, and we create no temporaries such as ``to_mesh()``, so a pointer
names one mesh for the whole walk); all placements' matrices come from one
``object_instances.foreach_get('matrix_world')`` (an instance's data is only valid
during its iteration step, hence indices rather than kept references); each mesh is
transformed by all its placements in one batched float32 matmul into a preallocated
output. Triangles of triangle/quad meshes are built in numpy (see ``mesh_triangles``),
faster than ``loop_triangles.foreach_get``.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.mesh import TriangleMesh, place, unit_normals

__all__ = ["InstanceTable", "Layout", "MeshRead", "NoGeometryError", "SourceInfo", "mesh_key", "scene_layout",
           "scene_mesh", "scene_summary", "mesh_triangles"]

_INT_MAX = 2147483647
_PROGRESS_EVERY = 0.1  # seconds between progress calls


class NoGeometryError(ValueError):
    """The scene (or the selection) has no visible, render-enabled triangles."""


@dataclass
class SourceInfo:
    """Per entry of ``object_names``: where its triangles come from."""

    instancer: list = field(default_factory=list)  # top-level instancer name, or None (own geometry)
    source: list = field(default_factory=list)  # instanced object or mesh name, or None
    instances: list = field(default_factory=list)  # placements of this source
    triangles: list = field(default_factory=list)  # triangles it contributes
    root_objects: int = 0  # distinct top-level objects contributing triangles
    meshes_read: int = 0  # distinct evaluated meshes read (each once, however often placed)
    seconds: float = 0.0
    walk_length: int = 0  # entries of depsgraph.object_instances the extraction walked


# -- reading one evaluated mesh -------------------------------------------------------

def mesh_triangles(me) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions (V,3) float32, triangles (T,3) int32, polygon (T,) int32) of a Mesh.

    The triangles are Blender's loop triangles (``corner_tris``), in Blender's order.
    For meshes of triangles and quads they are computed here from raw arrays (faster
    than ``loop_triangles.foreach_get``) with the rule of Blender's
    ``mesh_tessellate.cc``: a quad is cut on its 0-2 diagonal unless that diagonal lies
    outside it, then on 1-3. Blender decides that with one of two tests, depending on
    whether the mesh's face normals were cached when it tessellated; both are evaluated
    here, and a mesh with a quad on which they disagree or which is too close to call in
    float32 is read from ``loop_triangles`` instead, so the result is always Blender's.
    """
    return _mesh_triangles(me)[:3]


def _mesh_triangles(me):
    """``mesh_triangles`` plus each triangle's three corners (T,3) int32 (the loop
    indices, for corner normals and UVs)."""
    nv = len(me.vertices)
    co = np.empty(nv * 3, np.float32)
    me.attributes["position"].data.foreach_get("vector", co)
    co = co.reshape(nv, 3)
    nt = len(me.loop_triangles)
    if nt == 0:
        return co, np.empty((0, 3), np.int32), np.empty(0, np.int32), np.empty((0, 3), np.int32)
    poly = np.empty(nt, np.int32)
    me.loop_triangle_polygons.foreach_get("value", poly)
    npoly = len(me.polygons)
    # triangles per polygon from the triangle->polygon map; a polygon of n corners has n-2
    per_poly = np.bincount(poly, minlength=npoly)
    got = None
    if per_poly.size and per_poly.max() <= 2 and per_poly.min() >= 1 and ".corner_vert" in me.attributes:
        got = _tris_and_quads(me, co, poly, per_poly, corners=True)
    if got is None:  # n-gons, or a quad too close to call
        loops = np.empty(nt * 3, np.int32)
        me.loop_triangles.foreach_get("loops", loops)
        loops = loops.reshape(nt, 3)
        got = _corner_verts(me)[loops], loops
    return co, got[0], poly, got[1]


def _corner_verts(me) -> np.ndarray:
    n = len(me.loops)
    cv = np.empty(n, np.int32)
    if ".corner_vert" in me.attributes:
        me.attributes[".corner_vert"].data.foreach_get("value", cv)  # raw copy, fast
    else:
        me.loops.foreach_get("vertex_index", cv)
    return cv


def _tris_and_quads(me, co, poly, per_poly, corners=False):
    """Blender's loop triangles of a mesh with only triangles and quads, in numpy;
    None when a quad's split cannot be decided for certain.  With ``corners``:
    (triangles, their corners)."""
    cv = _corner_verts(me)
    start = np.zeros(len(per_poly), np.int32)
    np.cumsum(per_poly[:-1] + 2, out=start[1:])  # first corner of each polygon
    second = np.zeros(len(poly), np.int8)
    second[1:] = poly[1:] == poly[:-1]  # the second triangle of a quad
    s = start[poly]
    # corners of each triangle within its polygon: (0, 1, 2), or (0, 2, 3) for a quad's second
    loops = np.empty((len(poly), 3), np.int32)
    loops[:, 0] = s
    np.add(s, 1 + second, out=loops[:, 1])
    np.add(s, 2 + second, out=loops[:, 2])
    qa = np.flatnonzero(second[1:]).astype(np.int32)  # first triangle of each quad
    if qa.size:
        qc = np.take(cv, s[qa, None] + np.arange(4, dtype=np.int32))
        qv = np.take(co, qc, axis=0)  # (Q, 4, 3) quad corners; np.take beats fancy indexing
        flip = _quad_flips(qv)
        if flip is None:
            return None
        if flip.any():
            qa = qa[flip]
            loops[qa] = s[qa, None] + _QUAD_FLIPPED[0]
            loops[qa + 1] = s[qa, None] + _QUAD_FLIPPED[1]
    tris = np.take(cv, loops)
    return (tris, loops) if corners else tris


# Blender's other split of a quad, when the 0-2 diagonal lies outside: (0, 1, 3), (1, 2, 3)
_QUAD_FLIPPED = np.array([[0, 1, 3], [1, 2, 3]], np.int32)


def _quad_flips(qv):
    """Per quad, whether Blender cuts it on the 1-3 diagonal; None if unsure for any.

    Blender's two tests (BLI math_geom.cc), evaluated in float32 like Blender:
    - is_quad_flip_v3_first_third_fast: flip when v2 and v4 lie on the same side of the
      0-2 diagonal, ``((v2-v1) x (v3-v1)) . ((v4-v1) x (v3-v1)) > 0``;
    - ..._with_normal, n = normalize((v1-v3) x (v2-v4)), t = (v3-v1) x n: flip when
      ``v4.t >= v1.t or v2.t <= v1.t`` (the sign test is scale-free, so n is not normalized).
    A quad is unsure when the tests disagree, its diagonals are nearly parallel, or a
    compared quantity is within ~100 float32 roundings of its threshold (operation order or
    fused multiply-adds in Blender's build could round it the other way).
    """
    x1, y1, z1 = (np.ascontiguousarray(qv[:, 0, k]) for k in range(3))
    ax, ay, az = (qv[:, 1, k] - w for k, w in enumerate((x1, y1, z1)))  # v2 - v1
    bx, by, bz = (qv[:, 2, k] - w for k, w in enumerate((x1, y1, z1)))  # v3 - v1
    cx, cy, cz = (qv[:, 3, k] - w for k, w in enumerate((x1, y1, z1)))  # v4 - v1
    sa, sb, sc = (abs(u) + abs(v) + abs(w) for u, v, w in ((ax, ay, az), (bx, by, bz), (cx, cy, cz)))
    eps = np.float32(1e-5)
    # normal-less test
    pa = (ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx)  # (v2-v1) x (v3-v1)
    pc = (cy * bz - cz * by, cz * bx - cx * bz, cx * by - cy * bx)  # (v4-v1) x (v3-v1)
    dot = pa[0] * pc[0] + pa[1] * pc[1] + pa[2] * pc[2]
    flip = dot > 0
    unsure = abs(dot) <= eps * sa * sb * sb * sc
    # normal test: n ~ (v1-v3) x (v2-v4) = -(v3-v1) x ((v2-v1) - (v4-v1))
    dx, dy, dz = ax - cx, ay - cy, az - cz
    nx, ny, nz = dy * bz - dz * by, dz * bx - dx * bz, dx * by - dy * bx
    sd = abs(dx) + abs(dy) + abs(dz)
    sn = abs(nx) + abs(ny) + abs(nz)
    unsure |= sn <= np.float32(1e-3) * sb * sd  # diagonals nearly parallel: n is unreliable
    tx, ty, tz = by * nz - bz * ny, bz * nx - bx * nz, bx * ny - by * nx  # (v3-v1) x n
    e4 = cx * tx + cy * ty + cz * tz  # (v4 - v1) . t
    e2 = ax * tx + ay * ty + az * tz  # (v2 - v1) . t
    flip_n = (e4 >= 0) | (e2 <= 0)
    # Blender forms v.t - v1.t from absolute positions: its rounding grows with |v| |t|
    s1 = abs(x1) + abs(y1) + abs(z1)
    st = abs(tx) + abs(ty) + abs(tz)
    unsure |= abs(e4) <= eps * (s1 + sc + s1) * st
    unsure |= abs(e2) <= eps * (s1 + sa + s1) * st
    unsure |= flip != flip_n
    unsure |= ~np.isfinite(dot + e4 + e2)
    return None if unsure.any() else flip


def _cross(a, b):
    """Row-wise cross product, float32 in and out (np.cross is slower on (N, 3))."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


# -- visibility -------------------------------------------------------------------------

def _render_enabled_objects(view_layer) -> set:
    """Pointers of objects reachable through collections that are neither excluded from
    the view layer nor disabled for render, and that are not hide_render themselves."""
    keep = set()
    stack = [view_layer.layer_collection]
    while stack:
        lc = stack.pop()
        if lc.exclude or lc.collection.hide_render:
            continue
        for ob in lc.collection.objects:
            if not ob.hide_render:
                keep.add(ob.as_pointer())
        stack.extend(lc.children)
    return keep


@dataclass
class InstanceTable:
    """Per placement (instance) of the extraction, and the objects a ray can hit.

    objects: the hit-able original ``bpy.types.Object``s, each once: an object's own
        geometry gives the object, an instanced object (collection, vertex/face, particle
        instancing) the instanced object, geometry-nodes instances their instancer, as
        ``scene.ray_cast`` reports them.
    entry_object: (entries,) int32, per entry of ``object_names`` its index in ``objects``.
    matrices: (I, 4, 4) float64 world matrices (row-major, like ``matrix_world``).
    instance_object: (I,) int32 index into ``objects``.
    corner_normals: (T, 3, 3) float32 world-space corner normals of each triangle, and
    corner_uvs: (T, 3, 2) float32 active-UV-map coordinates (NaN without one), when asked.
    materials: the original ``bpy.types.Material``s some triangle renders with, each once
        (no None), and
    triangle_material: (T,) int32 index into ``materials`` per triangle (-1: no material),
        when 'material' is asked (module doc: how slots are resolved).
    """

    objects: list
    entry_object: np.ndarray
    matrices: np.ndarray
    instance_object: np.ndarray
    corner_normals: np.ndarray | None = None
    corner_uvs: np.ndarray | None = None
    materials: list | None = None
    triangle_material: np.ndarray | None = None


class _Group:
    """One evaluated mesh and every placement of it (positions in the instance iteration)."""

    __slots__ = ("co", "tris", "poly", "where", "entries", "matrices", "normals", "uvs", "slots", "slot_tables",
                 "slot_table_of", "table_of", "key", "read", "fresh")

    def __init__(self, co, tris, poly, corners, me=None, attributes=(), read=None):
        self.key = None  # the mesh's identity across calls (``mesh_key``), when cached
        self.read = read
        #: read from the evaluated mesh in this call, not found kept from an earlier one (new,
        #: edited or deforming): a structure built over it serves no earlier or later frame
        self.fresh = read is None
        if read is not None:  # the same evaluated mesh as a call before: its arrays, not read again
            self.co, self.tris, self.poly, self.normals, self.uvs, self.slots = read.arrays
            self._placements()
            return
        self.co, self.tris, self.poly = co, tris, poly
        # per triangle corner: normals (T,3,3) and UVs (T,3,2) read now (the mesh of a
        # geometry-nodes instance lives only during its iteration step), only when asked
        self.normals = self.uvs = None
        if "normal" in attributes and len(tris):
            n = np.empty(len(me.loops) * 3, np.float32)
            me.corner_normals.foreach_get("vector", n)
            self.normals = n.reshape(-1, 3)[corners]
        if "uv" in attributes and len(tris):
            layer = me.uv_layers.active
            if layer is not None:
                uv = np.empty(len(me.loops) * 2, np.float32)
                layer.data.foreach_get("uv", uv)
                self.uvs = uv.reshape(-1, 2)[corners]
            else:
                self.uvs = np.full((len(tris), 3, 2), np.nan, np.float32)
        # per triangle its polygon's material slot (T,) int32; slot -> material is resolved
        # per kind of placement (``slot_table``), as object-linked slots differ between objects
        self.slots = _polygon_materials(me)[poly] if "material" in attributes else None
        self._placements()

    def _placements(self):
        self.slot_tables = []  # distinct slot -> original material tuples of this mesh's placements
        self.table_of = {}  # material pointers of a slot table -> its index in slot_tables
        self.slot_table_of = []  # per placement, its index in slot_tables
        self.where = []  # index of each placement in depsgraph.object_instances
        self.entries = []  # its entry in object_names
        self.matrices = None  # (k, 4, 4) float32, column-major rows: m[:, :3, :3] is R^T

    def slot_table(self, ob, me) -> int:
        """Index in ``slot_tables`` of the materials ``ob`` (an evaluated object, as the
        depsgraph lists it with this mesh) renders slot by slot: its ``material_slots``
        (Blender's render rule on an evaluated object, module doc), then any further slots
        of the evaluated mesh."""
        mats = [s.material for s in ob.material_slots]
        if len(me.materials) > len(mats):
            mats += list(me.materials)[len(mats):]
        mats = tuple(m.original if m is not None else None for m in mats)
        key = tuple(m.as_pointer() if m is not None else 0 for m in mats)
        i = self.table_of.get(key)
        if i is None:
            i = self.table_of[key] = len(self.slot_tables)
            self.slot_tables.append(mats)
        return i


class MeshRead:
    """One evaluated mesh's object-space arrays, kept across calls under its ``mesh_key``
    (the session's cache): co (V, 3), tris (T, 3), poly (T,), and when read, corner normals,
    corner UVs and per-triangle material slots.  Read-only: every scene using it shares it."""

    __slots__ = ("key", "arrays", "attributes", "_local", "normals", "finite")

    def __init__(self, key, group: "_Group", attributes):
        self.key = key
        self.arrays = (group.co, group.tris, group.poly, group.normals, group.uvs, group.slots)
        for a in self.arrays:
            if a is not None:
                a.flags.writeable = False
        self.attributes = frozenset(attributes)
        self._local = None
        self.normals = None  # (T, 3) unit object-space normals, made on first use (_local_normals)
        self.finite = False  # every vertex checked finite (_leave_out_non_finite)

    def local_mesh(self) -> TriangleMesh:
        """The mesh in its own object space (a two-level scene's bottom level builds on it)."""
        if self._local is None:
            co, tris, poly = self.arrays[:3]
            self._local = TriangleMesh(co, tris, None, poly)
        return self._local


def mesh_key(me, owner, edits) -> tuple:
    """What names an evaluated mesh's content across calls: its ``session_uid`` (bpy 5.0
    gives an evaluated mesh a new one when it is evaluated again; module doc of
    operators/session.py), or where that is 0 (bpy 5.3 gives evaluated meshes none, checked
    with 5.3.0) the evaluated mesh's address and its owner object's ``session_uid`` (a new
    object, even at a reused address, is another); then the geometry updates seen on the
    owner (``edits``: bpy 5.3 updates some evaluated meshes in place) and its sizes."""
    uid = me.session_uid
    ident = (uid,) if uid else ("address", me.as_pointer(), owner.session_uid)
    return ident + (edits.get(owner.as_pointer(), 0) if edits else 0, len(me.vertices), len(me.loop_triangles))


def _polygon_materials(me) -> np.ndarray:
    """(polygons,) int32 material slot index of each polygon (0 where the mesh has no
    ``material_index`` attribute, as Blender reads it)."""
    mi = np.zeros(len(me.polygons), np.int32)
    a = me.attributes.get("material_index")
    if a is not None and a.domain == "FACE" and a.data_type == "INT":
        a.data.foreach_get("value", mi)  # raw copy; polygons.foreach_get goes through RNA per face
    elif a is not None:
        me.polygons.foreach_get("material_index", mi)
    return mi


def _slot_materials(slots, table, found: list, index: dict) -> np.ndarray:
    """(T,) int32 index into ``found`` of each triangle's material under one slot ->
    material ``table`` (-1: an empty slot, or a table without slots); materials new to
    ``found`` are appended (``index``: pointer -> position).  A slot past the last takes the
    last, as Blender renders it (``BKE_object_material_get_eval`` clamps the index)."""
    if not table:
        return np.full(len(slots), -1, np.int32)
    lut = np.full(len(table), -1, np.int32)
    for s, m in enumerate(table):  # a loop per slot, not per triangle
        if m is not None:
            p = m.as_pointer()
            if p not in index:
                index[p] = len(found)
                found.append(m)
            lut[s] = index[p]
    return lut[np.clip(slots, 0, len(table) - 1)]


# -- extraction ------------------------------------------------------------------------

def scene_mesh(depsgraph, *, selected_only: bool = False, view_layer=None, progress=None,
               attributes=()) -> TriangleMesh:
    """World-space triangles of what the depsgraph's scene renders (see module doc).

    The mesh carries ``instance_index`` (per triangle, its placement) and
    ``mesh.instances`` (an ``InstanceTable``: the objects and the placements' matrices).

    depsgraph: an evaluated depsgraph (``context.evaluated_depsgraph_get()``).
    selected_only: only selected objects, and instances whose instancer is selected.
    view_layer: for visibility and selection; the depsgraph's view layer by default.
    progress: called with a fraction 0..1 now and then (at most every 0.1 s), and with 1.0
        at the end.
    attributes: also read 'normal' (corner normals) and/or 'uv' (the active UV map) of
        every triangle corner, and/or 'material' (each triangle's material), into
        ``mesh.instances`` (costs a read per mesh and memory).
    Triangles with a NaN or infinite corner are left out (``scene_layout(...).left_out``
    says whose); a ValueError when every triangle has one.
    Raises NoGeometryError when nothing visible has a triangle.
    """
    return scene_layout(depsgraph, selected_only=selected_only, view_layer=view_layer, progress=progress,
                        attributes=attributes).flat(progress)


def scene_layout(depsgraph, *, selected_only: bool = False, view_layer=None, progress=None, attributes=(),
                 cache=None, edits=None) -> "Layout":
    """The evaluated scene as meshes and their placements (``Layout``), arguments as
    ``scene_mesh``; ``cache`` (mesh key -> ``MeshRead``) keeps meshes across calls, so a
    mesh whose key has not changed is not read again; ``edits``: per original object
    pointer, the geometry updates seen (part of the key).  ``layout.flat()`` is
    ``scene_mesh``'s world-space mesh."""
    t0 = time.perf_counter()
    vl = view_layer if view_layer is not None else depsgraph.view_layer
    attributes = tuple(attributes)
    groups, names, info, entry_obj = _collect(depsgraph, vl, selected_only, progress, attributes, cache, edits)
    if not groups:
        scene = depsgraph.scene.name
        if not len(depsgraph.scene.objects):
            raise NoGeometryError(f"scene '{scene}' has no objects")
        what = "selected, " if selected_only else ""
        raise NoGeometryError(
            f"no {what}visible, render-enabled object in scene '{scene}' (view layer '{vl.name}') has triangles"
        )
    left_out = _leave_out_non_finite(groups, names)
    groups = [g for g in groups if len(g.tris)]
    if not groups:
        raise ValueError("every triangle has a NaN or infinite vertex coordinate")
    info.seconds = time.perf_counter() - t0
    layout = Layout(groups, names, entry_obj, info, attributes)
    layout.left_out = left_out
    return layout


def _leave_out_non_finite(groups, names) -> list:
    """Leave out the triangles with a NaN or infinite corner (a modifier or geometry nodes
    can make them), as Blender's ``scene.ray_cast`` does: [(source names, triangles left
    out over every placement)] of the meshes that had any.  Such a mesh is not kept for
    later calls in this form: its group loses its cache key."""
    out = []
    for g in groups:
        if g.read is not None and g.read.finite:
            continue
        ok = np.isfinite(g.co).all(axis=1)
        if ok.all():
            if g.read is not None:
                g.read.finite = True  # checked once for every call that reuses the read
            continue
        keep = ok[g.tris].all(axis=1)
        g.co = np.where(ok[:, None], g.co, np.float32(0.0))  # no triangle uses them any more
        g.tris, g.poly = g.tris[keep], g.poly[keep]
        g.normals = g.normals[keep] if g.normals is not None else None
        g.uvs = g.uvs[keep] if g.uvs is not None else None
        g.slots = g.slots[keep] if g.slots is not None else None
        g.read, g.key = None, None
        sources = sorted({names[e] for e in g.entries})
        out.append((sources, int((~keep).sum()) * len(g.where)))
    return out


#: the groups' mesh keys -> (poly pool, normal pool, group starts) of ``Layout.pools``, for the
#: last few sets of meshes (the layouts of a scene whose objects move share them)
_POOLS: dict = {}


#: the same for ``Layout.material_pool``, keyed by the meshes and their slot tables' materials
_MATERIAL_POOLS: dict = {}


def forget():
    """Drop what layouts share between calls (``session.clear`` on a file load)."""
    _POOLS.clear()
    _MATERIAL_POOLS.clear()


class Layout:
    """One extraction as unique meshes (``groups``, each in object space) and placements.

    Per placement (I, in the order of the flat mesh's instances: group by group):
    ``placement_group`` (I,) int32, ``matrices`` (I, 4, 4) float64 world (row-major),
    ``tri_base`` (I,) int64 the flat index of its first triangle (so flat triangle =
    tri_base[i] + local), ``instances`` (an ``InstanceTable`` without per-triangle arrays).
    ``flat()`` assembles the world-space ``TriangleMesh`` (what ``scene_mesh`` returns),
    once; a two-level scene traces without it.
    """

    def __init__(self, groups, names, entry_obj, info, attributes):
        self.groups, self.names, self.entry_obj, self.info = groups, names, entry_obj, info
        self.attributes = tuple(attributes)
        counts = np.array([len(g.where) for g in groups], np.int64)
        sizes = np.array([len(g.tris) for g in groups], np.int64)
        self.placement_group = np.repeat(np.arange(len(groups), dtype=np.int32), counts)
        starts = np.concatenate([[0], np.cumsum(counts * sizes)[:-1]]).astype(np.int64)
        within = np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
        self.tri_base = np.repeat(starts, counts) + within * np.repeat(sizes, counts)
        self.triangle_count = int((counts * sizes).sum())
        self.matrices = (np.concatenate([g.matrices for g in groups]).transpose(0, 2, 1).astype(np.float64)
                         if groups else np.zeros((0, 4, 4)))
        entries = np.concatenate([np.asarray(g.entries, np.int32) for g in groups]) if groups else np.zeros(0, np.int32)
        objects, entry_object = _hit_objects(names, entry_obj)
        self.instances = InstanceTable(objects, entry_object, self.matrices, entry_object[entries])
        self._flat = self._pools = self._materials = None
        #: [(source names, triangles left out)] of meshes with NaN or infinite vertices
        self.left_out = []
        #: (I,) each placement's entry in depsgraph.object_instances, for ``read_matrices``
        self.where = np.concatenate([np.asarray(g.where, np.int64) for g in groups]) if groups \
            else np.zeros(0, np.int64)
        self.derived = False  # a copy with other matrices (``with_matrices``): it has no flat mesh
        self.tiles = 1  # how many times over the placements are listed (``tiled``)

    def with_matrices(self, matrices) -> "Layout":
        """The same meshes and placements, placed by ``matrices`` (I, 4, 4) world: what a
        scene whose objects only moved rigidly looks like at another time.  It traces on
        two levels; it has no flat mesh (its groups keep the first placement's matrices)."""
        out = copy.copy(self)
        out.matrices = np.asarray(matrices, np.float64)
        out.instances = dataclasses.replace(self.instances, matrices=out.matrices)
        out._flat = out._pools = None
        out.derived = True
        return out

    def tiled(self, matrices) -> "Layout":
        """The placements K times over, copy k placed by ``matrices[k]`` ((K, I, 4, 4)
        world): placement k * I + i is placement i at instant k of a sweep.  For naming and
        decoding hits (``pools``, ``material_pool``, ``instances``); it has no flat mesh."""
        m = np.asarray(matrices, np.float64)
        k = len(m)
        out = self.with_matrices(m.reshape(-1, 4, 4))
        out.placement_group = np.tile(self.placement_group, k)
        out.tri_base = np.tile(self.tri_base, k)
        out.where = np.tile(self.where, k)
        out.instances = dataclasses.replace(out.instances, instance_object=np.tile(self.instances.instance_object, k))
        out._materials = None
        out.tiles = self.tiles * k
        return out

    def read_matrices(self, depsgraph):
        """(I, 4, 4) float64 world matrices of this layout's placements in ``depsgraph`` as
        evaluated now, read in one ``foreach_get``; None when its instance walk has another
        length (something was added, removed or re-instanced: extract again)."""
        count = len(depsgraph.object_instances)
        if count != self.info.walk_length:
            return None
        flat = np.empty(count * 16, np.float32)
        try:
            depsgraph.object_instances.foreach_get("matrix_world", flat)
        except (RuntimeError, TypeError, ValueError):
            return None
        return flat.reshape(count, 4, 4)[self.where].transpose(0, 2, 1).astype(np.float64)

    def flat(self, progress=None) -> TriangleMesh:
        if self.derived:
            raise RuntimeError("a layout with moved placements (Layout.with_matrices) has no flat mesh")
        if self._flat is None:
            mesh = _assemble(self.groups, self.names, progress, self.entry_obj, self.attributes)
            mesh.source_info = self.info
            self._flat = mesh
        if progress is not None:
            progress(1.0)
        return self._flat

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) float32 world box of the placed vertices, computed as ``flat()`` places
        them (float32, the same products), so it equals the flat mesh's bounds; a group with
        many placements takes its transformed object-space box instead (a looser box, not
        worth a pass over every placed vertex)."""
        if self._flat is not None:
            return self._flat.bounds()
        lo = np.full(3, np.inf, np.float32)
        hi = np.full(3, -np.inf, np.float32)
        for gi, g in enumerate(self.groups):
            # column-major rows in float32, as _assemble reads them (this layout's matrices)
            co, m = g.co, self.matrices[self.placement_group == gi].transpose(0, 2, 1).astype(np.float32)
            if not len(co) or not len(m):
                continue
            mask = np.zeros(len(co), bool)
            mask[g.tris] = True
            used = co if mask.all() else co[mask]
            if len(used) * len(m) > (1 << 22):
                c = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float32)
                glo, ghi = used.min(axis=0), used.max(axis=0)
                used = np.where(c == 0, glo, ghi).astype(np.float32)
            w = (used[None] @ m[:, :3, :3] + m[:, None, 3, :3]).reshape(-1, 3)
            lo = np.minimum(lo, np.array([w[:, k].min() for k in range(3)], np.float32))
            hi = np.maximum(hi, np.array([w[:, k].max() for k in range(3)], np.float32))
        if not np.isfinite(lo).all():
            return np.zeros(3, np.float32), np.zeros(3, np.float32)
        return lo, hi

    def soup(self, placements) -> tuple:
        """(world-space ``TriangleMesh``, global (Ts,) int64, instance (Ts,) int32, local
        (Ts,) int32) of the given placements' triangles, laid out and rounded as ``flat()``
        lays them (float32 products, mirrored corners swapped), in increasing global order."""
        placements = np.sort(np.asarray(placements, np.int64))
        if not len(placements):
            return None
        # the placements in global order are runs of one group each (the flat order: group by group)
        groups = self.placement_group[placements]
        cuts = np.flatnonzero(np.diff(groups)) + 1
        verts, tris = [], []
        v0 = 0
        for run in np.split(placements, cuts):
            g = self.groups[self.placement_group[run[0]]]
            cm = self.matrices[run].transpose(0, 2, 1).astype(np.float32)  # as _assemble reads them
            w, t, _ = place(g.co, g.tris, cm, v0 + len(g.co) * np.arange(len(run)))
            verts.append(w.reshape(-1, 3))
            tris.append(t.reshape(-1, 3))
            v0 += len(run) * len(g.co)
        n = np.array([len(self.groups[gi].tris) for gi in groups.tolist()], np.int64)
        start = np.repeat(np.cumsum(n) - n, n)
        within = np.arange(int(n.sum()), dtype=np.int64) - start
        mesh = TriangleMesh(np.concatenate(verts), np.concatenate(tris))
        return (mesh, np.repeat(self.tri_base[placements], n) + within, np.repeat(placements, n).astype(np.int32),
                within.astype(np.int32))

    def pools(self):
        """What a hit on (placement, local triangle) needs without the flat mesh, made once:
        (poly_pool (sum T,) int32 the groups' polygon indices end to end, normal_pool
        (sum T, 3) float32 their unit object-space geometric normals, placement_base (I,)
        int64 where each placement's group starts in them, inverse (I, 3, 3) float64
        inverse of each placement's linear part, mirrored (I,) bool: det < 0)."""
        if self._pools is None:
            keys = tuple(g.key for g in self.groups)
            kept = _POOLS.get(keys) if None not in keys else None
            if kept is None:  # the same meshes as a layout before (a frame that moved things): theirs
                sizes = np.array([len(g.tris) for g in self.groups], np.int64)
                start = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
                poly = np.concatenate([g.poly for g in self.groups]) if self.groups else np.zeros(0, np.int32)
                normal = np.concatenate([_local_normals(g) for g in self.groups]) if self.groups \
                    else np.zeros((0, 3), np.float32)
                kept = (poly.astype(np.int32), normal, start)
                if None not in keys:
                    _POOLS[keys] = kept
                    while len(_POOLS) > 4:
                        _POOLS.pop(next(iter(_POOLS)))
            poly, normal, start = kept
            a = self.matrices[:, :3, :3]
            with np.errstate(all="ignore"):
                det = np.linalg.det(a)
                inv = np.linalg.inv(np.where((det != 0)[:, None, None], a, np.eye(3)))
            self._pools = (poly.astype(np.int32), normal, start[self.placement_group], inv, det < 0)
        return self._pools

    def material_pool(self):
        """(materials some triangle renders with, pool (sum over groups and slot tables,) int32
        of per-triangle material indices, placement_base (I,) int64 where each placement's
        group-and-table run starts), for hits without the flat mesh; as ``flat()`` resolves them."""
        if self._materials is None:
            # the same meshes under the same slot tables as a layout before: its pool
            keys = tuple((g.key, tuple(tuple((m.as_pointer(), m.session_uid) if m is not None else 0 for m in tab)
                                       for tab in g.slot_tables)) for g in self.groups)
            cacheable = all(k[0] is not None for k in keys)
            kept = _MATERIAL_POOLS.get(keys) if cacheable else None
            if kept is None:
                found, found_at, runs, base_of, n = [], {}, [], {}, 0
                for gi, g in enumerate(self.groups):
                    for ti, tab in enumerate(g.slot_tables):
                        runs.append(_slot_materials(g.slots, tab, found, found_at))
                        base_of[(gi, ti)] = n
                        n += len(g.tris)
                pool = np.concatenate(runs) if runs else np.zeros(0, np.int32)
                used = np.bincount(pool + 1, minlength=len(found) + 1)[1:] > 0
                remap = np.full(len(found) + 1, -1, np.int32)
                remap[:-1][used] = np.arange(int(used.sum()), dtype=np.int32)
                kept = ([m for m, u in zip(found, used) if u], remap[pool], base_of)
                if cacheable:
                    _MATERIAL_POOLS[keys] = kept
                    while len(_MATERIAL_POOLS) > 4:
                        _MATERIAL_POOLS.pop(next(iter(_MATERIAL_POOLS)))
            materials, pool, base_of = kept
            tables = np.tile(np.concatenate([np.asarray(g.slot_table_of, np.int64) for g in self.groups]), self.tiles) \
                if self.groups else np.zeros(0, np.int64)
            base = np.array([base_of.get((int(gi), int(ti)), 0) for gi, ti in zip(self.placement_group, tables)],
                            np.int64) if len(tables) == len(self.placement_group) else np.zeros(0, np.int64)
            self._materials = (materials, pool, base)
        return self._materials

    def rigid_to(self, other: "Layout") -> bool:
        """Whether ``other`` (the same scene at another time) has the same placements of the
        same meshes (kept, by key), in the same instance walk: only their matrices can differ."""
        return (len(self.placement_group) == len(other.placement_group)
                and self.info.walk_length == other.info.walk_length
                and np.array_equal(self.tri_base, other.tri_base) and np.array_equal(self.where, other.where)
                and all(a.key is not None and a.key == b.key for a, b in zip(
                    (self.groups[g] for g in self.placement_group.tolist()),
                    (other.groups[g] for g in other.placement_group.tolist()))))

    def displacement(self, other: "Layout") -> float:
        """The largest distance any vertex moves from this layout to ``other`` (the same
        scene at another time): 0 for a placement with the same mesh and matrix, the
        transformed vertices' difference otherwise; inf when the placements or the meshes'
        vertex counts differ (the topology changed)."""
        if len(self.placement_group) != len(other.placement_group) or \
                not np.array_equal(self.tri_base, other.tri_base):
            return float("inf")
        worst = 0.0
        for i in range(len(self.placement_group)):
            g0, g1 = self.groups[self.placement_group[i]], other.groups[other.placement_group[i]]
            m0, m1 = self.matrices[i], other.matrices[i]
            if g0.key is not None and g0.key == g1.key and np.array_equal(m0, m1):
                continue
            if len(g0.co) != len(g1.co):
                return float("inf")
            if not len(g0.co):
                continue
            if g0.key is not None and g0.key == g1.key:  # the same mesh moved: (M1 - M0) p, one product
                diff = g0.co.astype(np.float64) @ (m1[:3, :3] - m0[:3, :3]).T + (m1[:3, 3] - m0[:3, 3])
            else:
                diff = (g1.co.astype(np.float64) @ m1[:3, :3].T + m1[:3, 3]) - \
                    (g0.co.astype(np.float64) @ m0[:3, :3].T + m0[:3, 3])
            # squared lengths by a product: numpy's reduction over rows of 3 costs several times more
            worst = max(worst, float(np.sqrt((np.square(diff) @ np.ones(3)).max())))
        return worst

    @property
    def object_names(self):
        return self.names

    @property
    def source_info(self):
        return self.info

    @property
    def vertex_count(self) -> int:
        return int(sum(len(g.co) * len(g.where) for g in self.groups))


def _local_normals(g) -> np.ndarray:
    """(T, 3) float32 unit geometric normals of a group's triangles in object space
    (``core.mesh.unit_normals``), kept with its cached read."""
    if g.read is not None and g.read.normals is not None:
        return g.read.normals
    n = unit_normals(g.co[g.tris])
    if g.read is not None:
        n.flags.writeable = False
        g.read.normals = n
    return n


def _hit_objects(names, entry_obj):
    """(the hit-able objects, each once; per entry its index among them)."""
    objects, slot, entry_object = [], {}, np.empty(len(names), np.int32)
    for e, ob in enumerate(entry_obj if entry_obj is not None else [None] * len(names)):
        key = ob.as_pointer() if ob is not None else -1 - e
        if key not in slot:
            slot[key] = len(objects)
            objects.append(ob)
        entry_object[e] = slot[key]
    return objects, entry_object


def _collect(depsgraph, vl, selected_only, progress, attributes=(), cache=None, edits=None):
    """Walk ``object_instances`` once: decide per (instancer, source, mesh), read each kept
    mesh once (or take it from ``cache``: mesh key -> ``MeshRead``, when its key is there
    with every attribute asked), note where each placement is; then fetch all matrices in
    one foreach_get."""
    render_ok = _render_enabled_objects(vl)
    n_objects = max(1, len(depsgraph.objects))
    next_report = time.perf_counter() + _PROGRESS_EVERY
    roots: dict[int, bool] = {}  # root pointer -> kept
    decided: dict[tuple, tuple | None] = {}  # (parent, instanced, mesh) pointers -> (group, entry)
    groups: dict[int, _Group] = {}  # evaluated mesh pointer -> group
    entry_of: dict[tuple, int] = {}  # (root, source kind, source, mesh) pointers -> entry
    names: list[str] = []
    entry_obj: list = []  # per entry, the original object a ray hit reports
    taken: set[str] = set()
    want_materials = "material" in attributes
    info = SourceInfo()
    seen_roots = 0
    n = -1

    def root_kept(root) -> bool:
        ptr = root.as_pointer()
        kept = roots.get(ptr)
        if kept is None:
            kept = (
                ptr in render_ok
                and root.visible_get(view_layer=vl)
                and (not selected_only or root.select_get(view_layer=vl))
            )
            roots[ptr] = kept
        return kept

    def decide(inst, ob, me):
        """The (group, entry, slot table) of a new kind of placement, or None to leave it out."""
        if inst.is_instance:
            root = inst.parent.original  # the top-level instancer, also for nested instances
            if not root_kept(root):
                return None
            src = inst.instance_object
            src_orig = src.original if src is not None else root
            if src_orig != root:  # an object placed by collection/vertex/face/particle instancing
                if src_orig.hide_render:
                    return None
                # the mesh too: an instanced object can bring several (its own, its GN instances)
                key = (root.as_pointer(), "object", src_orig.as_pointer(), me.as_pointer())
                label = (root.name, src_orig.name)
                hit_ob = src_orig
            elif inst.persistent_id[1] == _INT_MAX:  # the object's own geometry (curve, text...)
                key, label = (root.as_pointer(), "self", 0, me.as_pointer()), (None, None)
                hit_ob = root
            else:  # geometry-nodes instances: named by the mesh datablock
                key = (root.as_pointer(), "mesh", 0, me.as_pointer())
                label = (root.name, me.name)
                hit_ob = root
        else:
            root = ob.original
            if not root_kept(root) or (root.is_instancer and not root.show_instancer_for_render):
                return None
            key, label = (root.as_pointer(), "self", 0, me.as_pointer()), (None, None)
            hit_ob = root
        if not len(me.loop_triangles):
            return None
        # The depsgraph owns its evaluated meshes while we iterate and we create no
        # temporaries (no to_mesh), so a mesh pointer names one mesh for the whole walk.
        group = groups.get(me.as_pointer())
        if group is None:
            mkey = mesh_key(me, ob.original, edits) if cache is not None else None
            read = cache.get(mkey) if mkey is not None else None
            if read is not None and read.attributes >= set(attributes):
                group = _Group(None, None, None, None, read=read)
            else:
                group = _Group(*_mesh_triangles(me), me=me, attributes=attributes)
                if mkey is not None:
                    group.read = cache[mkey] = MeshRead(mkey, group, attributes)
            group.key = mkey
            groups[me.as_pointer()] = group
        # slot -> material per kind of placement: objects sharing this mesh can differ
        table = group.slot_table(ob, me) if want_materials else -1
        entry = entry_of.get(key)
        if entry is None:
            entry = entry_of[key] = len(names)
            name = root.name if label[0] is None else f"{label[0]}/{label[1]}"
            if name in taken:  # two sources with one name (e.g. two meshes named "Mesh")
                name = f"{name} #{entry}"
            names.append(name)
            entry_obj.append(hit_ob)
            taken.add(name)
            info.instancer.append(label[0])
            info.source.append(label[1])
        return group, entry, table

    for n, inst in enumerate(depsgraph.object_instances):
        ob = inst.object
        if ob.type != "MESH":
            if progress is not None and not inst.is_instance:
                seen_roots += 1
                if time.perf_counter() >= next_report:
                    progress(0.5 * min(1.0, seen_roots / n_objects))
                    next_report = time.perf_counter() + _PROGRESS_EVERY
            continue
        me = ob.data
        parent, src = inst.parent, inst.instance_object
        key = (parent.as_pointer() if parent is not None else ob.original.as_pointer(),
               src.as_pointer() if src is not None else 0, me.as_pointer())
        if key in decided:
            hit = decided[key]
        else:
            hit = decided[key] = decide(inst, ob, me)
            if progress is not None and not inst.is_instance:
                seen_roots += 1
                if time.perf_counter() >= next_report:
                    progress(0.5 * min(1.0, seen_roots / n_objects))
                    next_report = time.perf_counter() + _PROGRESS_EVERY
        if hit is not None:
            hit[0].where.append(n)
            hit[0].entries.append(hit[1])
            if want_materials:
                hit[0].slot_table_of.append(hit[2])

    kept = [g for g in groups.values() if g.where]
    if kept:
        _fetch_matrices(depsgraph, n + 1, kept)
        # placements the depsgraph would not draw (show_self off: e.g. a hidden emitter)
        show = np.empty(n + 1, bool)
        depsgraph.object_instances.foreach_get("show_self", show)
        for g in kept:
            ok = show[g.where]
            if not ok.all():
                g.where = np.asarray(g.where)[ok].tolist()
                g.entries = np.asarray(g.entries)[ok].tolist()
                g.matrices = g.matrices[ok]
                if want_materials:
                    g.slot_table_of = np.asarray(g.slot_table_of)[ok].tolist()
        kept = [g for g in kept if g.where]
    counts = np.zeros(len(names), np.int64)
    tris = np.zeros(len(names), np.int64)
    for g in kept:
        c = np.bincount(np.asarray(g.entries, np.int64), minlength=len(names))
        counts += c
        tris += c * len(g.tris)
    live = np.flatnonzero(counts)
    if len(live) < len(names):  # entries whose every placement was dropped: renumber
        remap = np.full(len(names), -1, np.int64)
        remap[live] = np.arange(len(live))
        for g in kept:
            g.entries = remap[np.asarray(g.entries, np.int64)].tolist()
        names = [names[i] for i in live]
        entry_obj = [entry_obj[i] for i in live]
        info.instancer = [info.instancer[i] for i in live]
        info.source = [info.source[i] for i in live]
        roots_of = [k[0] for k, e in sorted(entry_of.items(), key=lambda kv: kv[1])]
        entry_roots = {roots_of[i] for i in live}
    else:
        entry_roots = {k[0] for k in entry_of}
    info.instances = counts[live].tolist()
    info.triangles = tris[live].tolist()
    info.root_objects = len(entry_roots)
    info.meshes_read = len(groups)
    info.walk_length = n + 1  # entries of depsgraph.object_instances walked (Layout.read_matrices)
    if progress is not None:
        progress(0.5)
    return kept, names, info, entry_obj


def _fetch_matrices(depsgraph, count, groups):
    """Every placement's world matrix, from one foreach_get over all instances (a matrix
    read per instance in Python costs about ten times more). The instance data is only
    valid during iteration, hence the index bookkeeping rather than kept references."""
    try:
        flat = np.empty(count * 16, np.float32)
        depsgraph.object_instances.foreach_get("matrix_world", flat)
        flat = flat.reshape(count, 4, 4)
    except (RuntimeError, TypeError, ValueError):  # the walk changed length: read one by one
        want = {i for g in groups for i in g.where}
        flat = np.zeros((count, 4, 4), np.float32)
        for i, inst in enumerate(depsgraph.object_instances):
            if i in want:
                flat[i] = np.array(inst.matrix_world, np.float32).T
    for g in groups:
        g.matrices = flat[g.where]


def _assemble(groups, names, progress=None, entry_obj=None, attributes=()) -> TriangleMesh:
    """Transform every group by all its matrices at once and concatenate."""
    nv = sum(len(g.co) * len(g.where) for g in groups)
    nt = sum(len(g.tris) * len(g.where) for g in groups)
    ni = sum(len(g.where) for g in groups)
    if nv > np.iinfo(np.int32).max:
        raise ValueError(f"the scene has {nv} vertices, more than int32 triangle indices can address")
    vertices = np.empty((nv, 3), np.float32)
    triangles = np.empty((nt, 3), np.int32)
    object_index = np.empty(nt, np.int32)
    polygon_index = np.empty(nt, np.int32)
    instance_index = np.empty(nt, np.int32)
    matrices = np.empty((ni, 4, 4), np.float64)
    instance_entry = np.empty(ni, np.int32)
    normals = np.empty((nt, 3, 3), np.float32) if "normal" in attributes else None
    uvs = np.empty((nt, 3, 2), np.float32) if "uv" in attributes else None
    tri_mat = np.empty(nt, np.int32) if "material" in attributes else None
    found, found_at = [], {}  # distinct original materials, pointer -> index
    v0 = f0 = i0 = 0
    next_report = time.perf_counter() + _PROGRESS_EVERY
    for g in groups:
        k, V, T = len(g.where), len(g.co), len(g.tris)
        m = g.matrices  # column-major: m[:, :3, :3] is R transposed, m[:, 3, :3] the translation
        # all k placements in one batched matmul (float32 throughout), mirrored ones' corners swapped
        _, _, neg = place(g.co, g.tris, m, v0 + V * np.arange(k), out_vertices=vertices[v0:v0 + k * V].reshape(k, V, 3),
                          out_triangles=triangles[f0:f0 + k * T].reshape(k, T, 3))
        object_index[f0:f0 + k * T].reshape(k, T)[:] = np.asarray(g.entries, np.int32)[:, None]
        polygon_index[f0:f0 + k * T].reshape(k, T)[:] = g.poly
        instance_index[f0:f0 + k * T].reshape(k, T)[:] = np.arange(i0, i0 + k, dtype=np.int32)[:, None]
        matrices[i0:i0 + k] = m.transpose(0, 2, 1)
        instance_entry[i0:i0 + k] = g.entries
        if normals is not None:
            out_n = normals[f0:f0 + k * T].reshape(k, T, 3, 3)
            # normals transform by the inverse transpose: n_world = n @ R^-1 = n @ inv(m)^T
            inv_t = np.linalg.inv(m[:, :3, :3].astype(np.float64)).transpose(0, 2, 1).astype(np.float32)
            np.matmul(g.normals[None].reshape(1, T * 3, 3), inv_t, out=out_n.reshape(k, T * 3, 3))
            out_n /= np.maximum(np.linalg.norm(out_n, axis=-1, keepdims=True), np.float32(1e-30))
            if neg.any():
                out_n[neg] = out_n[neg][:, :, [0, 2, 1]]
        if uvs is not None:
            out_uv = uvs[f0:f0 + k * T].reshape(k, T, 3, 2)
            out_uv[:] = g.uvs
            if neg.any():
                out_uv[neg] = out_uv[neg][:, :, [0, 2, 1]]
        if tri_mat is not None:  # (tables, T) per distinct slot table, then a row per placement
            per_table = np.stack([_slot_materials(g.slots, tab, found, found_at) for tab in g.slot_tables])
            np.take(per_table, np.asarray(g.slot_table_of, np.intp), axis=0,
                    out=tri_mat[f0:f0 + k * T].reshape(k, T))
        v0 += k * V
        f0 += k * T
        i0 += k
        if progress is not None and time.perf_counter() >= next_report:
            progress(0.5 + 0.5 * f0 / nt)
            next_report = time.perf_counter() + _PROGRESS_EVERY
    mesh = TriangleMesh(vertices, triangles, object_index, polygon_index, names, instance_index=instance_index)
    objects, entry_object = _hit_objects(names, entry_obj)
    mesh.instances = InstanceTable(objects, entry_object, matrices, entry_object[instance_entry], normals, uvs)
    if tri_mat is not None:
        # keep the materials some triangle renders with (a slot no polygon uses is left out)
        used = np.bincount(tri_mat + 1, minlength=len(found) + 1)[1:] > 0
        remap = np.full(len(found) + 1, -1, np.int32)  # the last row maps -1 to -1
        remap[:-1][used] = np.arange(int(used.sum()), dtype=np.int32)
        mesh.instances.materials = [m for m, u in zip(found, used) if u]
        mesh.instances.triangle_material = remap[tri_mat]
    return mesh


# -- summary ----------------------------------------------------------------------------

def scene_summary(depsgraph, mesh: TriangleMesh, elapsed: float, bounds: bool = True) -> dict:
    """A small dict for reports and the UI: what was extracted and how long it took.

    objects: top-level objects that contributed triangles (an instancer counts once);
    sources: entries of ``object_names``; instances: placements made by instancing
    (collection, particle, geometry nodes), not counting objects' own geometry;
    bounds: [lo, hi] of the triangles' vertices (left out with ``bounds=False``: a pass
    over every placed vertex, which the session makes only when asked);
    extraction_seconds: ``elapsed``.
    """
    info = getattr(mesh, "source_info", None)
    if info is not None:
        objects = info.root_objects
        instances = int(sum(n for n, who in zip(info.instances, info.instancer) if who is not None))
    else:
        objects, instances = len(mesh.object_names), 0
    return {
        "scene": depsgraph.scene.name,
        "view_layer": depsgraph.view_layer.name,
        "frame": depsgraph.scene.frame_current,
        "objects": int(objects),
        "sources": len(mesh.object_names),
        "instances": instances,
        "triangles": mesh.triangle_count,
        "vertices": int(mesh.vertex_count if hasattr(mesh, "vertex_count") else len(mesh.vertices)),
        "extraction_seconds": float(elapsed),
    } | ({"bounds": [x.tolist() for x in mesh.bounds()]} if bounds else {})
