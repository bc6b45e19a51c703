"""Tracing on a Dask cluster: the scene as a file the workers read, the rays as dask arrays.

``trace(path, origins, directions)`` takes (M, 3) dask arrays chunked by rows and returns
dask arrays ``t``, ``triangle``, ``u``, ``v``, ``object_index`` chunked like them.  Each
block is traced by a task that asks its worker process for the structure: the first task
on a worker reads the scene file (``core.save_mesh``, ``core.meshio.save_scene``) and
builds it, every later task reuses it.  The cache is keyed by the file's path, the SHA-256 of its bytes as the client
saw them (a worker that reads different bytes fails instead of tracing another scene;
node-local copies with other modification times still hit), the kind and its options.

An instanced scene file (version 2, ``core.meshio.save_scene``) is traced in two levels:
the worker builds one bottom level per unique mesh, keyed by the mesh's content digest,
the kind and its options, and places them with ``core.TwoLevel`` (the top level, per
file).  A bottom lives in the worker's cache while some cached scene uses it, so a later
frame whose meshes are unchanged (only matrices moved) builds its top level alone;
``worker_stats`` counts bottom builds and reuses.  The results are the flat scene's: the
global triangle (``tri_base + local``), its object, and u, v as the flat mesh's corners
give them (a mirrored instance's corners are swapped there, so its u and v are swapped
here), within float32 rounding of a flat trace (the ray is carried into object space).
``closest`` on such a file builds the flat mesh's structure.

``kind="auto"`` decides once, on the client, for the whole array: ``core.plan`` with the
caller's calibration or the shipped one, the expected rays defaulting to the array's
length, then every worker builds the chosen kind.  Each worker builds its own structure,
so W workers pay W builds; pass ``expected_rays=M / W`` to weigh that.

Fault tolerance is Dask's: a block is a pure function of its rays and the scene file, so
when a worker dies the scheduler recomputes its blocks elsewhere and the answers are the
same.  A missing or foreign scene file is reported on the client before any task runs.

``closest(path, points)`` answers point queries the same way: (M, 3) dask points in, dask
arrays ``distance``, ``triangle``, ``u``, ``v``, ``object_index`` and ``points`` out, each
block searched by its worker's cached structure (``Accel.closest``).

dask is imported when a function here is called; without it they raise ImportError
saying what to install (``pip install hybrid_raycast[dask]``).
"""

from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .factory import KINDS, build
from .meshio import INSTANCED_VERSION, check_scene, file_digest, read_scene
from .twolevel import TwoLevel

#: one traced ray; a block of rays becomes one structured array, the public arrays are its fields
RESULT_DTYPE = np.dtype([("t", np.float32), ("triangle", np.int32), ("u", np.float32), ("v", np.float32),
                         ("object_index", np.int32)])
FIELDS = RESULT_DTYPE.names
#: structures one worker process keeps, least recently used dropped first: trace_frames'
#: tasks go roughly frame by frame, so a few bound the memory without rebuilding (an
#: instanced scene's bottom levels are kept while one of these uses them)
CACHE_SIZE = 4


def _dask_array():
    try:
        import dask.array as da
    except ImportError as e:
        raise ImportError("core.distributed needs dask: pip install 'hybrid_raycast[dask]' "
                          f"(dask[array] and distributed); {e}") from None
    return da


@dataclass(frozen=True)
class SceneRef:
    """A scene file as the tasks name it: the absolute path, the SHA-256 the client read and
    its format version (2: instanced, traced in two levels)."""

    path: str
    digest: str
    version: int = 1

    @classmethod
    def of(cls, path) -> "SceneRef":
        """Check ``path`` on the client: FileNotFoundError or core.SceneFileError naming it."""
        p = Path(path).expanduser().absolute()
        version = check_scene(p)
        return cls(str(p), file_digest(p), version)

    @property
    def instanced(self) -> bool:
        return self.version >= INSTANCED_VERSION

    def label(self) -> str:
        return f"{Path(self.path).name}@{self.digest[:12]}"


# -- the worker side -----------------------------------------------------------------------------

class _Instanced:
    """A version-2 scene on a worker: a ``TwoLevel`` over shared bottoms, and per instance
    its object and whether it is mirrored (the flat mesh swapped its corners)."""

    kind = "twolevel"

    def __init__(self, top: TwoLevel, instance_object, mirrored, build_time: float):
        if top.triangle_dtype != np.int32:
            raise ValueError(f"the scene has more global triangles than int32 results can number "
                             f"({top.triangle_count:,})")
        self.top, self.instance_object, self.mirrored, self.build_time = top, instance_object, mirrored, build_time

    def trace(self, origins, directions, tmin, tmax):
        hits = self.top.trace(origins, directions, tmin, tmax)
        swap = hits.instance >= 0
        swap[swap] = self.mirrored[hits.instance[swap]]
        hits.u[swap], hits.v[swap] = hits.v[swap], hits.u[swap].copy()
        return hits

    def object_index(self, hits) -> np.ndarray:
        obj = np.full(len(hits.triangle), -1, np.int32)
        found = hits.instance >= 0
        obj[found] = self.instance_object[hits.instance[found]]
        return obj


class _StructureCache:
    """Structures built in this process, keyed by (path, digest, kind, options, two levels);
    at most ``size`` kept.  Builds of one key are serialised, so threads of a worker build
    once.  Bottom levels of instanced scenes, keyed by (mesh digest, kind, options), live
    while a cached scene uses them (or a build in progress holds them: ``pins``)."""

    def __init__(self, size: int):
        self.size = size
        self.lock = threading.Lock()
        self.entries: OrderedDict = OrderedDict()
        self.uses: dict = {}  # entry key -> the bottom keys it uses
        self.bottoms: dict = {}  # (mesh digest, kind, config) -> structure
        self.pins: Counter = Counter()
        self.building: dict = {}
        self.builds: Counter = Counter()
        self.blocks: Counter = Counter()
        self.bottom_builds: Counter = Counter()
        self.bottom_reuses: Counter = Counter()
        #: seconds per (scene label, kind): building, tracing (wall), tracing (this thread's CPU)
        self.seconds: dict = {"build": Counter(), "trace": Counter(), "trace_cpu": Counter()}

    def _cached(self, key):
        with self.lock:
            acc = self.entries.get(key)
            if acc is not None:
                self.entries.move_to_end(key)
            return acc

    def get(self, scene: SceneRef, kind: str, config: tuple, two_level: bool = False):
        """The structure of ``scene``: a ``_Instanced`` when ``two_level`` and the file is
        instanced, else one ``build`` over its (flat) mesh."""
        two_level = two_level and scene.instanced
        key = (scene.path, scene.digest, kind, config, two_level)
        acc = self._cached(key)
        if acc is not None:
            return acc
        with self.lock:
            key_lock = self.building.setdefault(key, threading.Lock())
        with key_lock:
            acc = self._cached(key)
            if acc is None:
                f = read_scene(scene.path, expect_digest=scene.digest)
                used = []
                try:
                    if two_level:
                        acc = self._two_level(f.instances, scene, kind, config, used)
                    else:
                        acc = build(f.mesh, kind, **dict(config))
                    with self.lock:
                        self.entries[key] = acc
                        self.uses[key] = tuple(used)
                        self.builds[(scene.label(), kind)] += 1
                        self.seconds["build"][(scene.label(), kind)] += acc.build_time
                        while len(self.entries) > self.size:
                            old, _ = self.entries.popitem(last=False)
                            self.uses.pop(old, None)
                finally:
                    with self.lock:
                        self.pins.subtract(used)
                        self._drop_unused_bottoms()
                        self.building.pop(key, None)
        return acc

    def _two_level(self, inst, scene: SceneRef, kind: str, config: tuple, used: list) -> _Instanced:
        """The top level over this file's instances, each bottom taken from the cache or
        built (and pinned in ``used`` until the scene is cached)."""
        t0 = time.perf_counter()
        label = (scene.label(), kind)
        bottoms = []
        for mesh, digest in zip(inst.meshes, inst.digests):
            bkey = (digest, kind, config)
            acc = self._take_bottom(bkey, label, used)
            if acc is None:
                with self.lock:
                    bottom_lock = self.building.setdefault(("bottom",) + bkey, threading.Lock())
                with bottom_lock:
                    acc = self._take_bottom(bkey, label, used)
                    if acc is None:
                        try:
                            acc = build(mesh, kind, **dict(config))
                            with self.lock:
                                self.bottoms[bkey] = acc
                                self.pins[bkey] += 1
                                used.append(bkey)
                                self.bottom_builds[label] += 1
                        finally:
                            with self.lock:
                                self.building.pop(("bottom",) + bkey, None)
            bottoms.append(acc)
        top = TwoLevel(bottoms, inst.instance_mesh, inst.matrices, inst.tri_base)
        return _Instanced(top, inst.instance_object, inst.mirrored, time.perf_counter() - t0)

    def _take_bottom(self, bkey, label, used: list):
        with self.lock:
            acc = self.bottoms.get(bkey)
            if acc is not None:
                self.pins[bkey] += 1
                used.append(bkey)
                self.bottom_reuses[label] += 1
            return acc

    def _drop_unused_bottoms(self):
        """Under the lock: forget the bottoms no cached scene uses and no build holds."""
        keep = {b for bs in self.uses.values() for b in bs} | {b for b, n in self.pins.items() if n > 0}
        for b in [b for b in self.bottoms if b not in keep]:
            del self.bottoms[b]
        self.pins = Counter({b: n for b, n in self.pins.items() if n > 0})

    def traced(self, scene: SceneRef, kind: str, wall: float, cpu: float):
        key = (scene.label(), kind)
        with self.lock:
            self.blocks[key] += 1
            self.seconds["trace"][key] += wall
            self.seconds["trace_cpu"][key] += cpu

    def stats(self) -> dict:
        def named(counter):
            return {f"{s}:{k}": n for (s, k), n in counter.items()}

        with self.lock:
            return {"builds": named(self.builds), "blocks": named(self.blocks),
                    "bottom_builds": named(self.bottom_builds), "bottom_reuses": named(self.bottom_reuses),
                    **{f"{what}_s": named(c) for what, c in self.seconds.items()},
                    "cached": [f"{Path(p).name}@{d[:12]}:{k}" for p, d, k, _, _ in self.entries],
                    "bottoms_cached": [f"{d[:12]}:{k}" for d, k, _ in self.bottoms]}

    def clear(self):
        with self.lock:
            self.entries.clear()
            self.uses.clear()
            self.bottoms.clear()
            self.pins.clear()
            for c in (self.builds, self.blocks, self.bottom_builds, self.bottom_reuses, *self.seconds.values()):
                c.clear()


_CACHE = _StructureCache(CACHE_SIZE)


def worker_stats() -> dict:
    """This process's structure cache, per '<file>@<digest>:<kind>': builds, traced blocks,
    seconds spent building (build_s), tracing (trace_s) and this worker thread's CPU seconds
    while tracing (trace_cpu_s: below trace_s when the machine is oversubscribed), what is
    cached; for instanced files also the bottom levels the file's top level built
    (bottom_builds) and took from the cache (bottom_reuses), and the bottoms cached
    ('<mesh digest>:<kind>').  On a cluster: ``client.run(core.distributed.worker_stats)``."""
    return _CACHE.stats()


def clear_worker_cache() -> None:
    """Drop this process's structures and counters (``client.run(...)`` frees the workers)."""
    _CACHE.clear()


def _trace_block(origins, directions, tmin, tmax, *, scene: SceneRef, kind: str, config: tuple):
    acc, hits = _timed(scene, kind, config, lambda acc: acc.trace(origins, directions, tmin, tmax), two_level=True)
    out = np.empty(len(hits), RESULT_DTYPE)
    out["t"], out["triangle"], out["u"], out["v"] = hits.t, hits.triangle, hits.u, hits.v
    out["object_index"] = acc.object_index(hits) if isinstance(acc, _Instanced) else _object_index(acc, hits.triangle)
    return out


def _timed(scene: SceneRef, kind: str, config: tuple, query, two_level: bool = False):
    """(the worker's cached structure, ``query(structure)``), its time added to the worker's stats."""
    acc = _CACHE.get(scene, kind, config, two_level)
    wall, cpu = time.perf_counter(), time.thread_time()
    result = query(acc)
    _CACHE.traced(scene, kind, time.perf_counter() - wall, time.thread_time() - cpu)
    return acc, result


def _object_index(acc, triangle) -> np.ndarray:
    """int32 index into the scene file's object names per triangle (-1 for -1, or no names)."""
    obj = np.full(len(triangle), -1, np.int32)
    if acc.mesh.object_index is not None:
        found = triangle >= 0
        obj[found] = acc.mesh.object_index[triangle[found]]
    return obj


# -- the client side -----------------------------------------------------------------------------

@dataclass
class DistributedHits:
    """Dask arrays, one entry per ray, chunked like the rays (nothing is computed yet).

    t: float32 (inf on a miss); triangle: int32 (-1 on a miss); u, v: float32 barycentrics;
    object_index: int32 into the scene file's object names (-1 on a miss).
    kind: the structure the workers build; plan: the ``core.Plan`` when kind was 'auto'.
    """

    t: object
    triangle: object
    u: object
    v: object
    object_index: object
    kind: str
    scene: SceneRef
    plan: object = field(default=None, repr=False)

    @property
    def hit(self):
        return self.triangle >= 0

    def compute(self, **kwargs) -> dict:
        """Every field as a numpy array, in one pass over the graph (each block traced once)."""
        import dask

        values = dask.compute(*(getattr(self, f) for f in FIELDS), **kwargs)
        return dict(zip(FIELDS, values))


def _as_rows(x, name: str, da):
    if not isinstance(x, da.Array):
        raise TypeError(f"{name} must be a dask array (dask.array.from_array(x, chunks=(rows, 3))), "
                        f"got {type(x).__name__}")
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name} must have shape (M, 3), got {x.shape}")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise ValueError(f"{name} must be real numbers, got dtype {x.dtype}")
    return x


def _ray_bound(x, name: str, m: int, rows, da):
    """A scalar stays a literal of every task; a per-ray array is chunked like the rays."""
    if np.ndim(x) == 0 and not isinstance(x, da.Array):
        return float(x), None
    if np.shape(x) != (m,):
        raise ValueError(f"{name} must be a scalar or have shape ({m},), got {np.shape(x)}")
    if not isinstance(x, da.Array):
        x = da.from_array(np.asarray(x), chunks=(rows,))
    return x.rechunk((rows,)), "i"


def _config_key(kind: str, configs: dict | None, threads: int) -> tuple:
    """The build options of ``kind`` as a hashable, sorted tuple (part of the cache key)."""
    merged = {"threads": int(threads), **((configs or {}).get(kind) or {})}
    return tuple(sorted(merged.items()))


def _choose(scene: SceneRef, m: int, expected_rays, calibration, configs: dict | None):
    """(kind, Plan): core.plan over the scene, once, on the client, for ``expected_rays``
    (default ``m``, the rays given).  No rays and no budget: the grid, unplanned."""
    from .decide import Calibration, load_or_default
    from .plan import plan

    if expected_rays is None:
        if m == 0:
            return "grid", None
        expected_rays = m
    cal = calibration if isinstance(calibration, Calibration) else load_or_default(calibration)[0]
    mesh = read_scene(scene.path, expect_digest=scene.digest).mesh
    p = plan(mesh, expected_rays, cal, grid_config=(configs or {}).get("grid"), configs=configs)
    return p.chosen, p


def _check_kind(kind):
    if kind != "auto" and kind not in KINDS:
        raise ValueError(f"kind must be 'auto' or one of {', '.join(KINDS)}, got {kind!r}")


def _trace_scene(scene: SceneRef, origins, directions, kind: str, tmin, tmax, config: tuple, plan, da):
    rows = origins.chunks[0]
    m = origins.shape[0]
    origins = origins.rechunk((rows, 3))
    directions = directions.rechunk((rows, 3))
    lo, lo_ix = _ray_bound(tmin, "tmin", m, rows, da)
    hi, hi_ix = _ray_bound(tmax, "tmax", m, rows, da)
    records = da.blockwise(
        _trace_block, "i", origins, "ij", directions, "ij", lo, lo_ix, hi, hi_ix,
        dtype=RESULT_DTYPE, concatenate=True, scene=scene, kind=kind, config=config,
        name=f"hybrid-raycast-{kind}-" + _token(scene, kind, config, origins, directions, lo, hi),
    )
    return DistributedHits(*(records[f] for f in FIELDS), kind=kind, scene=scene, plan=plan)


def _token(*parts) -> str:
    from dask.base import tokenize

    return tokenize(*parts)


def trace(path, origins, directions, *, kind: str = "auto", tmin=0.0, tmax=np.inf, expected_rays=None,
          calibration=None, configs: dict | None = None, threads: int = 1) -> DistributedHits:
    """Trace rays into the scene file ``path`` on the Dask cluster of the current client.

    origins, directions: (M, 3) dask arrays chunked by rows (one task per block of rows;
        columns are merged into one chunk, directions rechunked like origins).
    kind: 'auto' (decide once here, see the module notes), or 'grid', 'bvh', 'embree', 'brute'.
    tmin, tmax: scalars, or (M,) arrays; hits count for tmin < t <= tmax.
    expected_rays: the ray budget of the 'auto' decision (default M).
    calibration: a core.Calibration, a calibration file path, or None for the shipped defaults.
    configs: build options per kind, {kind: options} as ``core.plan`` takes them ('grid' for
        the grid); threads: per structure (default 1: Dask runs one task per worker thread).
    Raises FileNotFoundError / core.SceneFileError naming the file, here, when ``path`` is
    missing or not a scene file; TypeError/ValueError for malformed arguments.
    """
    da = _dask_array()
    _check_kind(kind)
    origins = _as_rows(origins, "origins", da)
    directions = _as_rows(directions, "directions", da)
    if directions.shape != origins.shape:
        raise ValueError(f"origins and directions must have the same shape, got {origins.shape} and {directions.shape}")
    scene = SceneRef.of(path)
    plan = None
    if kind == "auto":
        kind, plan = _choose(scene, origins.shape[0], expected_rays, calibration, configs)
    return _trace_scene(scene, origins, directions, kind, tmin, tmax, _config_key(kind, configs, threads), plan, da)


def trace_frames(paths, origins_list, directions_list, *, kind: str = "auto", tmin: float = 0.0,
                 tmax: float = np.inf, expected_rays=None, calibration=None, configs: dict | None = None,
                 threads: int = 1) -> list[DistributedHits]:
    """One ``trace`` per frame: scene file ``paths[i]`` with rays ``origins_list[i]``,
    ``directions_list[i]``; the graphs are independent, so ``dask.compute`` over all of them
    keeps every worker busy.

    Every file is checked here first (a missing one is named before any task runs).
    kind='auto' decides once, on the first frame, for its ray count (or ``expected_rays``,
    the rays one frame's structure answers): the frames of one animation are alike, and
    planning each would build a grid per frame on the client.  tmin, tmax: scalars.
    """
    da = _dask_array()
    _check_kind(kind)
    paths, origins_list, directions_list = list(paths), list(origins_list), list(directions_list)
    if not (len(paths) == len(origins_list) == len(directions_list)):
        raise ValueError(f"paths, origins_list and directions_list must have one entry per frame, got "
                         f"{len(paths)}, {len(origins_list)} and {len(directions_list)}")
    if np.ndim(tmin) or np.ndim(tmax):
        raise ValueError("trace_frames takes scalar tmin and tmax (use trace() per frame for per-ray bounds)")
    scenes = [SceneRef.of(p) for p in paths]
    rays = []
    for i, (o, d) in enumerate(zip(origins_list, directions_list)):
        o, d = _as_rows(o, f"origins_list[{i}]", da), _as_rows(d, f"directions_list[{i}]", da)
        if o.shape != d.shape:
            raise ValueError(f"frame {i}: origins and directions must have the same shape, got {o.shape} and {d.shape}")
        rays.append((o, d))
    if not scenes:
        return []
    plan = None
    if kind == "auto":
        kind, plan = _choose(scenes[0], rays[0][0].shape[0], expected_rays, calibration, configs)
    key = _config_key(kind, configs, threads)
    return [_trace_scene(s, o, d, kind, tmin, tmax, key, plan, da) for s, (o, d) in zip(scenes, rays)]


# -- point queries ---------------------------------------------------------------------------------

NEAREST_DTYPE = np.dtype([("distance", np.float64), ("triangle", np.int32), ("u", np.float32), ("v", np.float32),
                          ("object_index", np.int32), ("x", np.float64), ("y", np.float64), ("z", np.float64)])
NEAREST_FIELDS = ("distance", "triangle", "u", "v", "object_index")


def _closest_block(points, *, scene: SceneRef, kind: str, config: tuple, max_distance: float):
    acc, near = _timed(scene, kind, config, lambda acc: acc.closest(points, max_distance))
    out = np.empty(len(near), NEAREST_DTYPE)
    out["distance"], out["triangle"], out["u"], out["v"] = near.distance, near.triangle, near.u, near.v
    out["x"], out["y"], out["z"] = near.points[:, 0], near.points[:, 1], near.points[:, 2]
    out["object_index"] = _object_index(acc, near.triangle)
    return out


@dataclass
class DistributedNearest:
    """Dask arrays, one entry per point, chunked like the points (nothing is computed yet).

    distance: float64 (inf where nothing is within max_distance); triangle: int32 (-1 there);
    u, v: float32 barycentrics; object_index: int32 into the scene file's object names (-1
    there); points: (M, 3) float64 the closest points (NaN there).  kind: the structure the
    workers build."""

    distance: object
    triangle: object
    u: object
    v: object
    object_index: object
    points: object
    kind: str
    scene: SceneRef

    @property
    def found(self):
        return self.triangle >= 0

    def compute(self, **kwargs) -> dict:
        """Every field as a numpy array, in one pass over the graph (each block searched once)."""
        import dask

        names = NEAREST_FIELDS + ("points",)
        values = dask.compute(*(getattr(self, f) for f in names), **kwargs)
        return dict(zip(names, values))


def closest(path, points, *, max_distance=np.inf, kind: str = "bvh", configs: dict | None = None,
            threads: int = 1) -> DistributedNearest:
    """The closest surface point of the scene file ``path`` to each of ``points`` (an (M, 3)
    dask array chunked by rows), on the Dask cluster of the current client, as dask arrays.

    kind: the structure each worker builds and keeps ('bvh' default; 'grid' searches its
    own cells, 'embree' a BVH it builds on first use; 'brute' the float64 reference); max_distance:
    inclusive, positive (inf: no limit); configs, threads: as ``trace``.  Raises
    FileNotFoundError / core.SceneFileError naming the file, TypeError/ValueError for
    malformed arguments, here, before any task runs."""
    from .proximity import check_max_distance

    da = _dask_array()
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    points = _as_rows(points, "points", da)
    md = check_max_distance(max_distance)
    scene = SceneRef.of(path)
    config = _config_key(kind, configs, threads)
    rows = points.chunks[0]
    points = points.rechunk((rows, 3))
    records = da.blockwise(
        _closest_block, "i", points, "ij", dtype=NEAREST_DTYPE, concatenate=True, scene=scene, kind=kind,
        config=config, max_distance=md, name=f"hybrid-raycast-closest-{kind}-" + _token(scene, kind, config, points, md),
    )
    xyz = da.stack([records["x"], records["y"], records["z"]], axis=1)
    return DistributedNearest(*(records[f] for f in NEAREST_FIELDS), points=xyz, kind=kind, scene=scene)

