"""Script API: cast rays into the evaluated scene with the structure the plan picks.

    from bl_ext.user_default.hybrid_raycast import api      # installed extension
    r = api.cast(origins, directions)                       # (M, 3) arrays, world space
    r.t, r.hit, r.object_names[r.object_index[r.hit]], r.points

``cast`` extracts the evaluated, visible, render-enabled triangles of the scene (as the
Analyze operator does), plans for ``expected_rays`` (default: the number of rays given)
by timing up to K of the given rays through the uniform grid, builds the chosen
structure and traces.  The extracted triangles, the grid and every structure built are
cached per scene and reused by the next call, by the Trace operator and vice versa,
until the scene changes (``operators/state.py`` says what counts as a change; the cache
lives for the Blender session and is cleared when a file is loaded).  Pass a
``depsgraph`` to cast into another scene or view layer than the context's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import core

__all__ = ["CastResult", "cast"]


@dataclass
class CastResult:
    """The nearest hit of every ray; per ray unless said otherwise.

    t: float32 distance in units of the direction (inf on a miss)
    hit: bool
    triangle: int32 index into the extracted mesh (-1 on a miss)
    object_index: int32 index into ``object_names`` (-1 on a miss)
    object_names: list of the extracted sources (see ``operators/extract.py`` for naming)
    polygon_index: int32 polygon of that source's evaluated mesh (-1 on a miss)
    u, v: float32 barycentrics: point = (1-u-v) v0 + u v1 + v v2 (0 on a miss)
    points: (M, 3) float64 world hit points (NaN on a miss)
    structure: 'grid', 'bvh' or 'embree', the structure that traced
    plan: the ``core.Plan`` that chose it (break-even, timings, notes)
    """

    t: np.ndarray
    hit: np.ndarray
    triangle: np.ndarray
    object_index: np.ndarray
    object_names: list
    polygon_index: np.ndarray
    u: np.ndarray
    v: np.ndarray
    points: np.ndarray
    structure: str
    plan: object = field(repr=False, default=None)

    def __len__(self):
        return len(self.t)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("t", "hit", "triangle", "object_index", "object_names",
                                               "polygon_index", "u", "v", "points", "structure")}


def cast(origins, directions, expected_rays=None, *, depsgraph=None, tmin=0.0, tmax=np.inf,
         selected_only: bool = False, samples: int | None = None) -> CastResult:
    """Trace ``origins`` + t ``directions`` (both (M, 3), world space) into the evaluated scene.

    expected_rays: the budget the decision is made for (default M; pass the total when
        you will call ``cast`` many times with small batches).
    depsgraph: an evaluated depsgraph (default: the context's, evaluated now).
    tmin, tmax: scalars or (M,) arrays; hits count for tmin < t <= tmax.
    selected_only: only the selected objects, as the sidebar setting.
    samples: sample rays timed through the grid (default the scene's setting).
    Raises ValueError for malformed rays or a zero/negative ray budget, and the
    operators' NoGeometry / InvalidGeometry (``operators.jobs``) for a scene without
    usable triangles.
    """
    import bpy

    from .operators import state
    from .operators.analyze import candidate_kinds, extract
    from .operators.calibrate import load_calibration

    o = np.asarray(origins, np.float32)
    d = np.asarray(directions, np.float32)
    if o.ndim != 2 or o.shape[1:] != (3,) or d.shape != o.shape:
        raise ValueError(f"origins and directions must both have shape (M, 3), got {o.shape} and {d.shape}")
    m = len(o)
    budget = float(m if expected_rays is None else expected_rays)
    if m and not budget > 0:
        raise ValueError(f"expected_rays must be positive, got {expected_rays!r}")
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    scene = depsgraph.scene
    props = scene.hybrid_raycast
    key = (bool(selected_only), round(float(props.grid_density), 6))
    cache = state.cached(scene, key)
    if cache is None:
        gen_at = state.generation(scene)
        mesh, summary = extract(depsgraph, selected_only=selected_only)
        cache = state.store(scene, key, mesh, summary, generation_at=gen_at)
    mesh = cache.mesh
    if m == 0:
        hits = core.Hits.empty(0)
        plan, kind = None, "grid"
    else:
        kinds, _ = candidate_kinds(props)
        cal, _, _ = load_calibration()
        plan = core.plan(mesh, budget, cal, rays=(o, d, tmin, tmax), samples=samples or props.sample_rays,
                         grid=cache.grid, grid_config={"density": props.grid_density}, kinds=kinds)
        cache.grid = plan.grid
        kind = plan.chosen
        if kind != "grid":
            if kind not in cache.structures:
                cache.structures[kind] = core.build(mesh, kind, **plan.configs.get(kind, {}))
            plan.structure = cache.structures[kind]
        hits = plan.trace(o, d, tmin, tmax)
    hit = hits.hit
    tri = hits.triangle
    obj = np.full(m, -1, np.int32)
    poly = np.full(m, -1, np.int32)
    if mesh.object_index is not None:
        obj[hit] = mesh.object_index[tri[hit]]
    if mesh.polygon_index is not None:
        poly[hit] = mesh.polygon_index[tri[hit]]
    return CastResult(t=hits.t, hit=hit, triangle=tri, object_index=obj, object_names=list(mesh.object_names),
                      polygon_index=poly, u=hits.u, v=hits.v, points=hits.points(o, d), structure=kind, plan=plan)
