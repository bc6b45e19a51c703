"""The script API's queries (``api.cast``, ``api.occluded``, ``api.cast_all``): checked
arguments, the session of the depsgraph's scene, the chunked trace, and the per-hit fields
assembled from the evaluated data.  ``api`` re-exports them; the sensor scans
(``operators.scan``) trace through them too, so nothing in ``operators`` imports ``api``."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import core, settings
from ..core.accel import LOCKSTEP_CHUNK

__all__ = ["CastResult", "AllHits", "cast", "occluded", "cast_all", "STRUCTURES"]

STRUCTURES = ("auto", "grid", "bvh", "embree")
#: rays per chunk: bounds the working memory of a cast (about 0.3 KiB a ray in flight).  One
#: chunk of the numpy structures (``core.accel.LOCKSTEP_CHUNK``): each chunk ends in steps over
#: the rays still in flight, so a smaller chunk costs more per ray, and calibration measures
#: the same batch (``core.decide.measurements.RAYS_PER_SCENE``)
CHUNK = LOCKSTEP_CHUNK


@dataclass
class CastResult:
    """The nearest hit of every ray; per ray (M,) unless said otherwise.

    t: float32 distance in units of the direction (inf on a miss)
    hit: bool
    points: (M, 3) float64 world hit points (NaN on a miss)
    normals: (M, 3) float32 world-space unit geometric normal of the hit triangle, turned
        by the inverse transpose of its instance's matrix (NaN on a miss).  The same as
        ``scene.ray_cast``'s except under non-uniform scale, where Blender's are wrong: it
        turns normals by the matrix itself
    smooth_normals: with ``smooth=True``, (M, 3) float32 normals interpolated from the
        evaluated mesh's corner normals (NaN on a miss); else None
    uv: with ``uv=True``, (M, 2) float32 coordinates in the active UV map (NaN on a miss
        or without a UV map); else None
    material_index: with ``materials=True``, (M,) int32 index into ``materials`` of the
        material the hit triangle renders with (object-linked slots honoured per object;
        ``operators.extract`` module doc), -1 on a miss or where it has none; else None
    materials: with ``materials=True``, object array of the original ``bpy.types.Material``s
        of the scene's triangles (no None; ``operators.materials.optics`` reads their LiDAR
        parameters); material_names: their names; else None
    objects: object array of the hit-able original ``bpy.types.Object``s (an instanced
        object for collection/vertex/particle instances, the instancer for geometry-nodes
        instances, as ``scene.ray_cast`` reports them); object_names: their names
    object_index: int32 index into ``objects`` (-1 on a miss: mask with ``hit`` first)
    instance_index: int32 index into ``instance_matrices`` (-1 on a miss)
    instance_matrices: (I, 4, 4) float64 world matrix of every instance (``ray_cast``'s matrix)
    polygon_index: int32 polygon of the evaluated mesh (-1 on a miss)
    triangle: int32 index into the extracted triangles (-1 on a miss)
    u, v: float32 barycentrics: point = (1-u-v) v0 + u v1 + v v2 (0 on a miss)
    structure: 'grid', 'bvh' or 'embree', the structure that traced (the last chunk's)
    plan: the session's ``core.Plan`` (break-even, timings, notes), None if never planned
    """

    t: np.ndarray
    hit: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    objects: np.ndarray
    object_names: np.ndarray
    object_index: np.ndarray
    instance_index: np.ndarray
    instance_matrices: np.ndarray
    polygon_index: np.ndarray
    triangle: np.ndarray
    u: np.ndarray
    v: np.ndarray
    structure: str
    smooth_normals: np.ndarray | None = None
    uv: np.ndarray | None = None
    material_index: np.ndarray | None = None
    materials: np.ndarray | None = None
    material_names: np.ndarray | None = None
    plan: object = field(repr=False, default=None)
    #: how the scene was traced: its parts (flat or two levels), what each holds and why
    #: (``session.Session.describe``)
    scene: dict = field(repr=False, default_factory=dict)

    def __len__(self):
        return len(self.t)

    def as_dict(self) -> dict:
        """The plain arrays (no bpy references); the material fields when they were asked."""
        keys = ("t", "hit", "points", "normals", "object_names", "object_index", "instance_index", "polygon_index",
                "triangle", "u", "v", "structure")
        out = {k: getattr(self, k) for k in keys}
        if self.material_index is not None:
            out["material_index"], out["material_names"] = self.material_index, self.material_names
        return out


@dataclass
class AllHits:
    """Every hit of every ray, flat, sorted by ray then t (``cast_all``).

    ray: int64 ray index; t: float32; triangle, object_index, instance_index,
    polygon_index: int32; points: (H, 3) float64; normals: (H, 3) float32;
    objects / object_names / instance_matrices as in ``CastResult``; count: (M,) hits per ray.
    """

    ray: np.ndarray
    t: np.ndarray
    triangle: np.ndarray
    object_index: np.ndarray
    instance_index: np.ndarray
    polygon_index: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    count: np.ndarray
    objects: np.ndarray
    object_names: np.ndarray
    instance_matrices: np.ndarray
    structure: str

    def __len__(self):
        return len(self.t)


# -- input ---------------------------------------------------------------------------------

def _vectors(x, name) -> np.ndarray:
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name} must be an array of 3-vectors: {e}") from None
    if a.dtype == object:
        try:
            a = np.asarray(x, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"{name} must hold real numbers, got {type(x).__name__} of objects") from None
    if np.issubdtype(a.dtype, np.complexfloating):
        raise TypeError(f"{name} must hold real numbers, got complex dtype {a.dtype}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise TypeError(f"{name} must hold real numbers, got dtype {a.dtype}")
    if a.ndim == 1 and a.shape == (3,):
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (M, 3) or (3,), got {a.shape}")
    return a


def _check_finite(a, name, zero=False):
    """Checked as the rays will be traced: rounded to float32, chunk by chunk (no copy of
    the whole input)."""
    for s in range(0, len(a), CHUNK):
        c = a[s:s + CHUNK]
        if c.dtype != np.float32:
            with np.errstate(over="ignore", invalid="ignore"):  # overflow to inf is reported below
                c = c.astype(np.float32)
        if not np.isfinite(c).all():
            w = np.flatnonzero(~np.isfinite(c).all(axis=1)) + s
            raise ValueError(f"{name}: rays with NaN or infinite values (or overflowing float32), first at ray {w[:5].tolist()}")
        if zero and not c.all():  # some component is zero: is a whole row zero? (by columns: a
            # row-wise reduce over 3 columns costs several times more)
            nz = (c[:, 0] != 0) | (c[:, 1] != 0) | (c[:, 2] != 0)
            if not nz.all():
                w = np.flatnonzero(~nz) + s
                raise ValueError(f"{name}: rays with a zero-length direction, first at ray {w[:5].tolist()}")


def _bound(x, m, name):
    try:
        a = np.asarray(x)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number or an (M,) array, got {type(x).__name__}") from None
    if np.issubdtype(a.dtype, np.complexfloating) or not (np.issubdtype(a.dtype, np.floating)
                                                          or np.issubdtype(a.dtype, np.integer)):
        raise TypeError(f"{name} must be real, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if a.ndim not in (0, 1) or (a.ndim == 1 and a.shape != (m,)):
        raise ValueError(f"{name} must be a scalar or shape ({m},), got {a.shape}")
    if np.isnan(a).any():
        raise ValueError(f"{name} contains NaN")
    return a


def _rays(origins, directions, tmin, tmax):
    """Validated (origins, directions, tmin, tmax, M); one origin or one direction is
    broadcast against many (as a read-only view: no copy)."""
    o = _vectors(origins, "origins")
    d = _vectors(directions, "directions")
    if len(o) != len(d):
        if len(o) == 1:
            o = np.broadcast_to(o, d.shape)
        elif len(d) == 1:
            d = np.broadcast_to(d, o.shape)
        else:
            raise ValueError(f"origins {o.shape} and directions {d.shape}: give as many of each, or one of either")
    m = len(o)
    _check_finite(o[:1] if o.strides[0] == 0 else o, "origins")
    _check_finite(d[:1] if d.strides[0] == 0 else d, "directions", zero=True)
    lo, hi = _bound(tmin, m, "tmin"), _bound(tmax, m, "tmax")
    if (lo > hi).any():
        w = np.flatnonzero(np.broadcast_to(lo > hi, (m,)))
        raise ValueError(f"tmin > tmax on {w.size} rays, first at ray {w[:5].tolist()}")
    return o, d, lo, hi, m


def _positive_int(x, name, allow_none=True):
    if x is None and allow_none:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, np.integer, float, np.floating)):
        raise TypeError(f"{name} must be a positive whole number, got {type(x).__name__}")
    if not np.isfinite(x) or x <= 0 or int(x) != x:
        raise ValueError(f"{name} must be a positive whole number, got {x!r}")
    return int(x)


class _Call:
    """What every query shares: checked arguments, the session, the decision inputs."""

    def __init__(self, origins, directions, tmin, tmax, *, depsgraph, expected_rays, selected_only, samples,
                 structure, attributes=(), strict=False, session_=None):
        import bpy

        from . import session
        from .analyze import candidate_kinds
        from .calibrate import load_calibration

        self.o, self.d, self.tmin, self.tmax, self.m = _rays(origins, directions, tmin, tmax)
        if structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {', '.join(STRUCTURES)}, got {structure!r}")
        if structure == "embree" and not core.embree_available():
            raise ValueError("structure='embree' needs embreex, which cannot be imported here")
        self.structure = structure
        samples = _positive_int(samples, "samples")
        if expected_rays is not None:
            try:
                budget = float(expected_rays)
            except (TypeError, ValueError):
                raise TypeError(f"expected_rays must be a number, got {type(expected_rays).__name__}") from None
            if not (budget > 0 and np.isfinite(budget)):
                raise ValueError(f"expected_rays must be positive and finite, got {expected_rays!r}")
        else:
            budget = float(max(self.m, 1))
        self.budget = budget
        if depsgraph is None:
            depsgraph = bpy.context.evaluated_depsgraph_get()
        else:
            session.check_depsgraph(depsgraph)
            depsgraph.update()
        props = depsgraph.scene.hybrid_raycast
        # session_: a session made elsewhere for this depsgraph's scene (session.swept: a rigid sweep)
        self.session = session_ if session_ is not None else session.get(
            depsgraph, props, selected_only=bool(selected_only), attributes=attributes, strict=bool(strict))
        s = self.session
        self.samples = samples or props.sample_rays
        self.grid_config = {"density": float(props.grid_density)}
        if s.chosen is None and structure == "auto":
            self.kinds, _ = candidate_kinds(props)
            self.calibration = load_calibration()[0]
        else:
            self.kinds, self.calibration = s.kinds, s.calibration

    def chunks(self, progress):
        """(start, stop) of each chunk, with progress after each; the window manager's
        progress bar when there is a GUI."""
        import bpy

        wm = None
        if self.m > CHUNK and not bpy.app.background:
            wm = getattr(bpy.context, "window_manager", None)
        if wm is not None:
            wm.progress_begin(0, self.m)
        try:
            for a in range(0, self.m, CHUNK):
                b = min(self.m, a + CHUNK)
                yield a, b
                if progress is not None:
                    progress(b, self.m)
                if wm is not None:
                    wm.progress_update(b)
        finally:
            if wm is not None:
                wm.progress_end()

    def rays(self, a, b):
        def bound(x):
            return x if x.ndim == 0 else x[a:b]

        # a chunk of the caller's arrays: float32 copies of the chunk only; a broadcast row
        # stays one (the structures see one origin, and fill their float32 rows by columns)
        o, d = (np.broadcast_to(np.asarray(x[:1], np.float32), (b - a, 3)) if x.strides[0] == 0 else
                np.ascontiguousarray(x[a:b], np.float32) for x in (self.o, self.d))
        return o, d, bound(self.tmin), bound(self.tmax)

    def query(self, rays, any_hit=False, flat=True, slot=None):
        return self.session.query(*rays, any_hit=any_hit, structure=self.structure, budget=self.budget,
                                  kinds=self.kinds, calibration=self.calibration, samples=self.samples,
                                  grid_config=self.grid_config, flat=flat, slot=slot)


def _interpolate(corners, tri, u, v):
    """Barycentric interpolation of per-corner data (T, 3, k) at hits."""
    c = corners[tri].astype(np.float64)
    w0 = (1.0 - u - v).astype(np.float64)
    return w0[:, None] * c[:, 0] + u[:, None].astype(np.float64) * c[:, 1] + v[:, None].astype(np.float64) * c[:, 2]


def _cast_hits(call, s, objects, names, inst, kind, materials, mats, mat_names, slot_, progress) -> CastResult:
    """``cast(hits_=True)``: t and hit per ray, the per-hit fields for the hits only."""
    m = call.m
    t = np.empty(m, np.float32)
    tri = np.empty(m, np.int32)
    u = np.empty(m, np.float32)
    v = np.empty(m, np.float32)
    cols = [[] for _ in range(5)]  # object, instance, polygon, normal, material
    tables = None
    for a, b in call.chunks(progress):
        h, kind = call.query(call.rays(a, b), flat=False, slot=None if slot_ is None else slot_[a:b])
        k = h.triangle
        t[a:b], tri[a:b], u[a:b], v[a:b] = h.t, k, h.u, h.v
        if isinstance(h, core.InstanceHits):
            got, (o_h, i_h, p_h, n_h, u_h, v_h) = s.decode(h, hits_only=True)
            u[got + a], v[got + a] = u_h, v_h  # a mirrored instance's u and v trade places
            got_cols = (o_h, i_h, p_h, n_h) + ((s.decode_materials(h, hits_only=True),) if materials else ())
        else:
            if tables is None:
                tables = s.per_triangle() + ((s.material_tables()[1],) if materials else ())
            kg = k[k >= 0]
            got_cols = tuple(np.take(table, kg, axis=0) for table in tables)
        for col, x in zip(cols, got_cols):
            col.append(x)
    if not cols[0]:  # no rays
        cols = [[np.zeros(0, np.int32)]] * 3 + [[np.zeros((0, 3), np.float32)], [np.zeros(0, np.int32)]]
    obj, ins, poly, normals, mat_index = (c[0] if len(c) == 1 else np.concatenate(c) if c else None for c in cols)
    return CastResult(t=t, hit=tri >= 0, points=None, normals=normals.astype(np.float32, copy=False),
                      objects=objects, object_names=names, object_index=obj.astype(np.int32, copy=False),
                      instance_index=ins.astype(np.int32, copy=False), instance_matrices=inst.matrices,
                      polygon_index=poly.astype(np.int32, copy=False), triangle=tri, u=u, v=v, structure=kind,
                      smooth_normals=None, uv=None,
                      material_index=mat_index.astype(np.int32, copy=False) if materials else None,
                      materials=mats, material_names=mat_names, plan=s.plan, scene=s.describe())


def _corner_data(inst, tri, u, v, smooth: bool, uv: bool):
    """(smooth normals (M, 3), UVs (M, 2)), float32, interpolated from the evaluated meshes'
    corners at (tri, u, v), NaN where tri is -1; None for what was not asked."""
    got = tri >= 0
    kh, uh, vh = tri[got], u[got], v[got]
    normals = coords = None
    if smooth:
        normals = np.full((len(tri), 3), np.nan, np.float32)
        sn = _interpolate(inst.corner_normals, kh, uh, vh)
        with np.errstate(invalid="ignore", divide="ignore"):
            normals[got] = sn / np.linalg.norm(sn, axis=1, keepdims=True)
    if uv:
        coords = np.full((len(tri), 2), np.nan, np.float32)
        coords[got] = _interpolate(inst.corner_uvs, kh, uh, vh)
    return normals, coords


# -- the queries -----------------------------------------------------------------------------

def cast(origins, directions, expected_rays=None, *, depsgraph=None, tmin=0.0, tmax=np.inf,
         selected_only: bool = False, samples: int | None = None, structure: str = "auto",
         smooth: bool = False, uv: bool = False, materials: bool = False, progress=None,
         strict: bool = False, session_=None, slot_=None, points_=True, hits_=False) -> CastResult:
    """The nearest hit of every ray ``origins + t directions`` in the evaluated scene.

    origins, directions: (M, 3) or (3,) arrays, lists or tuples, world space; one origin
        (or one direction) is used for every ray of the other.
    expected_rays: the ray budget the first cast of a session plans for (default M).
    depsgraph: an evaluated ``bpy.types.Depsgraph`` (default the context's), e.g.
        ``view_layer.depsgraph`` for another view layer.
    tmin, tmax: scalars or (M,) arrays; hits count for tmin < t <= tmax.
    selected_only: only the selected objects.  samples: sample rays the plan times
        (default the scene's setting).  structure: 'auto', 'grid', 'bvh' or 'embree'.
    smooth, uv: also return interpolated corner normals / active-UV-map coordinates.
    materials: also return each hit's material (``material_index``, ``materials``,
        ``material_names``); the first such cast of a session reads the meshes' slots once.
    progress: called as progress(rays_done, rays_total) after each chunk.
    session_: internal (the sensor sweep): trace with this ``session.Session`` instead of the
        depsgraph's; slot_: (M,) each ray's instant for a sweep's session (``session.swept``);
        points_=False: no ``points`` (None; a scan makes its own from its ranges);
        hits_=True (with ``points_=False``, without ``smooth`` or ``uv``): ``normals``,
        ``object_index``, ``instance_index``, ``polygon_index`` and ``material_index`` for
        the hits only, in ray order (``np.flatnonzero(hit)``), neither filled for the misses
        nor gathered back by the caller.
    strict: raise InvalidGeometry when an object has NaN or infinite vertex coordinates;
        by default its bad triangles are left out with one ``RuntimeWarning`` naming the
        object and the count, and the rest is traced (as ``scene.ray_cast`` does).
    Raises TypeError/ValueError naming the argument for bad input, and the operators'
    NoGeometry / InvalidGeometry (``operators.jobs``) for a scene without usable triangles.
    """
    attributes = (("normal",) if smooth else ()) + (("uv",) if uv else ()) + (("material",) if materials else ())
    call = _Call(origins, directions, tmin, tmax, depsgraph=depsgraph, expected_rays=expected_rays,
                 selected_only=selected_only, samples=samples, structure=structure, attributes=attributes,
                 strict=strict, session_=session_)
    s, m = call.session, call.m
    objects, names = s.tables()
    inst = s.mesh.instances if (smooth or uv) else s.layout.instances
    t = np.empty(m, np.float32)
    tri = np.empty(m, np.int32)
    u = np.empty(m, np.float32)
    v = np.empty(m, np.float32)
    points = np.empty((m, 3), np.float64) if points_ else None
    normals = np.empty((m, 3), np.float32)
    obj = np.empty(m, np.int32)
    ins = np.empty(m, np.int32)
    poly = np.empty(m, np.int32)
    smooth_n = np.empty((m, 3), np.float32) if smooth else None
    uvs = np.empty((m, 2), np.float32) if uv else None
    mat_index = mats = mat_names = None
    two_level = not (smooth or uv)  # per-corner data lives in the flat mesh's tables
    if materials:
        if two_level:
            found = s.layout.material_pool()[0]
            mats = np.empty(len(found), object)
            mats[:] = found
        else:
            mats = s.material_tables()[0]
        mat_names = np.empty(len(mats), object)
        mat_names[:] = [mt.name for mt in mats]  # read now: a rename is no geometry change
        mat_index = np.empty(m, np.int32)
    kind = call.structure if call.structure != "auto" else (s.chosen or "grid")
    tables = None
    if hits_:
        if smooth or uv or points_:
            raise ValueError("hits_ gives no points, smooth normals or UVs")
        return _cast_hits(call, s, objects, names, inst, kind, materials, mats, mat_names, slot_, progress)
    for a, b in call.chunks(progress):
        rays = call.rays(a, b)
        h, kind = call.query(rays, flat=not two_level, slot=None if slot_ is None else slot_[a:b])
        k = h.triangle  # -1 on a miss picks the tables' miss row
        t[a:b], tri[a:b] = h.t, k
        if isinstance(h, core.InstanceHits):
            obj[a:b], ins[a:b], poly[a:b], normals[a:b], u[a:b], v[a:b] = s.decode(h)
            if materials:
                mat_index[a:b] = s.decode_materials(h)
        else:
            if tables is None:
                tables = s.per_triangle() + ((s.material_tables()[1],) if materials else ())
            u[a:b], v[a:b] = h.u, h.v
            outs = (obj, ins, poly, normals) + ((mat_index,) if materials else ())
            got = np.flatnonzero(k >= 0)
            if got.size * 2 < len(k):
                # most rays miss (a sensor's sky): the misses take the tables' miss row as one
                # fill, and only the hits gather from the large per-triangle tables
                kg, at = k[got], got + a
                for table, out in zip(tables, outs):
                    if out.ndim == 2:  # by columns: a broadcast of one row of 3 fills several times slower
                        for c in range(out.shape[1]):
                            out[a:b, c] = table[-1, c]
                    else:
                        out[a:b] = table[-1]
                    out[at] = np.take(table, kg, axis=0)
            else:
                for table, out in zip(tables, outs):
                    np.take(table, k, axis=0, out=out[a:b])
        if points_:
            tt = np.where(k >= 0, h.t, np.float32(np.nan)).astype(np.float64)
            np.multiply(tt[:, None], rays[1].astype(np.float64), out=points[a:b])  # one dtype: a mixed one loops slower
            points[a:b] += rays[0]
        if smooth or uv:
            sn, uvk = _corner_data(inst, k, h.u, h.v, smooth, uv)
            if smooth:
                smooth_n[a:b] = sn
            if uv:
                uvs[a:b] = uvk
    return CastResult(t=t, hit=tri >= 0, points=points, normals=normals, objects=objects, object_names=names,
                      object_index=obj, instance_index=ins, instance_matrices=inst.matrices, polygon_index=poly,
                      triangle=tri, u=u, v=v, structure=kind, smooth_normals=smooth_n, uv=uvs,
                      material_index=mat_index, materials=mats, material_names=mat_names, plan=s.plan,
                      scene=s.describe())


def occluded(origins, directions, *, tmin=0.0, tmax=np.inf, depsgraph=None, expected_rays=None,
             selected_only: bool = False, samples: int | None = None, structure: str = "auto",
             progress=None, strict: bool = False) -> np.ndarray:
    """(M,) bool: True where any triangle is hit with tmin < t <= tmax (line of sight,
    shadows: stops at the first hit found).  Arguments as ``cast``."""
    call = _Call(origins, directions, tmin, tmax, depsgraph=depsgraph, expected_rays=expected_rays,
                 selected_only=selected_only, samples=samples, structure=structure, strict=strict)
    out = np.empty(call.m, bool)
    for a, b in call.chunks(progress):
        out[a:b] = call.query(call.rays(a, b), any_hit=True, flat=False)[0]
    return out


def cast_all(origins, directions, *, max_hits: int = 16, tmin=0.0, tmax=np.inf, depsgraph=None,
             selected_only: bool = False, structure: str = "auto", progress=None, strict: bool = False) -> AllHits:
    """Every hit along each ray, nearest first, at most ``max_hits`` per ray, as flat
    arrays sorted by ray then t (``AllHits``).  Hits at one point (a shared edge or vertex)
    count once (``core.all_hits``).  Traces with the session's structure ('auto': the one
    its casts use, or the grid before any; planning needs a nearest-hit cast)."""
    max_hits = _positive_int(max_hits, "max_hits", allow_none=False)
    call = _Call(origins, directions, tmin, tmax, depsgraph=depsgraph, expected_rays=None,
                 selected_only=selected_only, samples=None, structure=structure, strict=strict)
    s = call.session
    kind = call.structure if call.structure != "auto" else (s.chosen or "grid")
    acc = s.structure(kind, **(call.grid_config if kind == "grid" else {}))
    parts = []
    for a, b in call.chunks(progress):
        o, d, lo, hi = call.rays(a, b)
        ray, t, tri, u, v = core.all_hits(acc, o, d, lo, hi, max_hits=max_hits)
        parts.append((ray + a, t, tri, o[ray], d[ray]))
    if parts:
        ray, t, tri, o, d = (np.concatenate(c) for c in zip(*parts))
    else:
        ray, t, tri, o, d = (np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.int32),
                             np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    objects, names = s.tables()
    inst, mesh = s.mesh.instances, s.mesh
    points = o.astype(np.float64) + t.astype(np.float64)[:, None] * d.astype(np.float64)
    return AllHits(ray=ray, t=t, triangle=tri, object_index=inst.instance_object[mesh.instance_index[tri]],
                   instance_index=mesh.instance_index[tri], polygon_index=mesh.polygon_index[tri], points=points,
                   normals=s.triangle_normals[tri], count=np.bincount(ray, minlength=call.m).astype(np.int32),
                   objects=objects, object_names=names, instance_matrices=inst.matrices, structure=kind)


# -- point queries ----------------------------------------------------------------------------

@dataclass
class ClosestResult:
    """The closest surface point of every query point; per point (M,) unless said otherwise.

    distance: float64 Euclidean distance (inf where nothing is within ``max_distance``)
    found: bool (False: nothing within ``max_distance``, or an empty scene)
    points: (M, 3) float64 world closest points (NaN where not found)
    normals: (M, 3) float32 world unit geometric normal of the closest triangle, as
        ``CastResult.normals`` (the inverse transpose under non-uniform scale; NaN where not found)
    objects, object_names, object_index, instance_index, instance_matrices, polygon_index,
        triangle, u, v: as ``CastResult``'s (-1 / 0 where not found)
    smooth_normals, uv: with ``smooth=True`` / ``uv=True``, as ``CastResult``'s; else None
    structure: the structure that answered the points ('grid' or 'bvh' as the decision for
        point queries chose, or the one named; 'embree' searches a BVH built beside it).  When
        the decision keeps the grid, points too far from every triangle for its rings still go
        to a BVH (``core.decide.points.REACH``; the panel counts them)
    break_even: the points from which the BVH beats the grid, as the decision estimated them
        (inf: never; NaN: no decision was made, a structure was named or the BVH was built)
    """

    distance: np.ndarray
    found: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    objects: np.ndarray
    object_names: np.ndarray
    object_index: np.ndarray
    instance_index: np.ndarray
    instance_matrices: np.ndarray
    polygon_index: np.ndarray
    triangle: np.ndarray
    u: np.ndarray
    v: np.ndarray
    structure: str
    smooth_normals: np.ndarray | None = None
    uv: np.ndarray | None = None
    break_even: float = float("nan")


def _points(points) -> np.ndarray:
    """(M, 3) float64 finite points (a (3,) point is one row), or TypeError/ValueError
    naming ``points``."""
    return core.proximity.check_points(_vectors(points, "points"))


def _point_session(depsgraph, selected_only, attributes=(), tree=True):
    """(session, its BVH for the tree queries, or the scene's props without ``tree``)."""
    import bpy

    from . import session

    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    else:
        session.check_depsgraph(depsgraph)
        depsgraph.update()
    props = depsgraph.scene.hybrid_raycast
    s = session.get(depsgraph, props, selected_only=bool(selected_only), attributes=attributes)
    return s, (s.structure("bvh") if tree else props)


def _check_point_structure(structure):
    if structure not in STRUCTURES:
        raise ValueError(f"structure must be one of {', '.join(STRUCTURES)}, got {structure!r}")
    if structure == "embree" and not core.embree_available():
        raise ValueError("structure='embree' needs embreex, which cannot be imported here")


def _session_closest(s, p, md, structure: str, grid_config: dict, calibration=None):
    """(``core.proximity.Nearest``, the kind that answered, ``core.decide.points.PointPlan`` or
    None) for checked points ``p`` on session ``s``.

    A named structure answers every point.  'auto': a BVH the session has built answers
    (nothing is cheaper to own, and the grid is at best as fast per point); else the grid
    (built if need be) answers an evenly spaced sample of the points, whose work counts give
    the paper's decision for the rest (``core.decide.points.decide``: the least estimated
    total, the grid's build sunk), and the structure it picks answers them.  The plan is kept
    as ``s.point_plan``."""
    flat = {key[0]: acc for key, acc in s.structures.items() if key[0] in STRUCTURES}  # not two-level ones
    if structure != "auto":
        acc = flat.get(structure) or s.structure(structure, **(grid_config if structure == "grid" else {}))
        return acc.closest(p, md), structure, None
    if "bvh" in flat:
        got, kind = flat["bvh"].closest(p, md), "bvh"
        plan = core.decide.points.PointPlan("bvh", {}, {}, float("nan"), 0, "the session's BVH is built")
    else:
        if calibration is None:
            from .calibrate import load_calibration

            calibration = load_calibration()[0]
        grid = flat.get("grid") or s.structure("grid", **grid_config)
        got, kind, plan = core.decide.points.closest_planned(p, md, calibration.point_model(), grid,
                                                             lambda: s.structure("bvh"), s.mesh.triangle_count)
    s.point_plan = plan
    settings.POINTS[s._summary.get("scene", "")] = dict(plan.to_dict(), points=len(p), triangles=s.mesh.triangle_count)
    return got, kind, plan


def closest(points, *, max_distance=np.inf, depsgraph=None, selected_only: bool = False, smooth: bool = False,
            uv: bool = False, structure: str = "auto") -> ClosestResult:
    """The closest point of the evaluated scene's surface to each of ``points`` (M, 3) or (3,),
    world space, with every per-hit field of ``cast`` plus ``distance`` (``ClosestResult``).

    max_distance: inclusive; a point with nothing that near gets distance inf (found False).
    The search is exact in float64 (an exact tie to the lowest triangle index) over the same
    session (extracted triangles, instances) as ``cast``, whichever structure answers.
    structure: 'auto' (the paper's decision for point queries, ``_session_closest``), or
    'grid', 'bvh', 'embree' (its point queries search a BVH built beside it on first use).
    Raises TypeError/ValueError naming the argument, NoGeometry / InvalidGeometry for a scene
    without usable triangles."""
    p = _points(points)
    md = core.proximity.check_max_distance(max_distance)
    _check_point_structure(structure)
    attributes = (("normal",) if smooth else ()) + (("uv",) if uv else ())
    s, props = _point_session(depsgraph, selected_only, attributes, tree=False)
    n, kind, plan = _session_closest(s, p, md, structure, {"density": float(props.grid_density)}, s.calibration)
    objects, names = s.tables()
    inst = s.mesh.instances
    tri_obj, tri_ins, tri_poly, tri_normals = s.per_triangle()
    k = n.triangle
    found = k >= 0
    smooth_n, uvs = _corner_data(inst, k, n.u, n.v, smooth, uv)
    return ClosestResult(distance=n.distance, found=found, points=n.points, normals=tri_normals[k], objects=objects,
                         object_names=names, object_index=tri_obj[k], instance_index=tri_ins[k],
                         instance_matrices=inst.matrices, polygon_index=tri_poly[k], triangle=k, u=n.u, v=n.v,
                         structure=kind, smooth_normals=smooth_n, uv=uvs,
                         break_even=plan.break_even if plan is not None else float("nan"))


def inside(points, *, depsgraph=None, selected_only: bool = False) -> np.ndarray:
    """(M,) bool: each point's generalized winding number over the evaluated scene is above
    0.5 (``core.Accel.inside``): right on open meshes, meshes with holes, self-intersecting
    meshes and overlapping shells, where ray parity is not."""
    p = _points(points)
    _, acc = _point_session(depsgraph, selected_only)
    return acc.inside(p)


def signed_distance(points, *, depsgraph=None, selected_only: bool = False) -> np.ndarray:
    """(M,) float64 distance to the evaluated scene's surface, negative ``inside``."""
    p = _points(points)
    _, acc = _point_session(depsgraph, selected_only)
    return acc.signed_distance(p)


def count_hits(origins, directions, *, tmin=0.0, tmax=np.inf, depsgraph=None, selected_only: bool = False) -> np.ndarray:
    """(M,) int32 distinct hits along each ray with tmin < t <= tmax (a shared edge counts once,
    as ``cast_all`` counts them), without keeping them."""
    o, d, lo, hi, _ = _rays(origins, directions, tmin, tmax)
    _, acc = _point_session(depsgraph, selected_only)
    return acc.count_hits(o, d, lo, hi)


__all__ += ["ClosestResult", "closest", "inside", "signed_distance", "count_hits"]
