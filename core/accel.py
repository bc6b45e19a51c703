"""The one interface every structure implements (``build(mesh, kind)`` is in factory.py).

Every structure answers the two questions of pbrt's accelerators: the nearest hit
(``trace``) and whether anything is hit at all (``occluded``).  This base class owns
what they share: validating and preparing rays, bounded chunks so memory stays flat
as the ray count grows, and an optional thread pool (numpy releases the GIL inside most
ufuncs, so threads overlap on several cores): one chunk per thread, or, for the lockstep
tracers (``shares_chunks``), all threads inside each chunk, drawing rays from one
``RaySupply``.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .hits import Hits
from . import proximity
from .intersect import Rays, prepare_rays, shear_rays
from .mesh import TriangleMesh

#: fewest rays per chunk when a batch is split to give every thread a chunk.  The lockstep
#: loops' last steps run on a handful of rays, where each numpy call is mostly Python
#: overhead under the GIL, so two threads on two small chunks contend instead of overlapping:
#: split into small chunks, a plan's sample took longer on two threads than on one; from
#: this size on the split no longer loses (BENCHMARKS.md, "Measurement protocol and model
#: terms" and "Tried and not kept")
MIN_SPLIT = 1 << 16

#: rays per chunk of the lockstep tracers (the numpy BVH and grid, ``chunk_size``).  Each
#: chunk ends in steps over the rays still in flight, so a cast pays that once per chunk:
#: api.cast traces in chunks of this size and the calibration times batches of it
#: (decide/measurements.py, RAYS_PER_SCENE), so its constants are what a large cast pays
LOCKSTEP_CHUNK = 1 << 20


#: (process id, threads) -> the kept pool of that size (``Accel._in_pool``); made on first use
_POOLS: dict = {}
_POOLS_LOCK = threading.Lock()
#: set in a kept pool's threads while they run a task
_IN_POOL = threading.local()


def _pool(threads: int) -> ThreadPoolExecutor:
    """The kept pool of ``threads`` threads of this process (a forked child makes its own:
    the parent's threads do not survive a fork)."""
    key = (os.getpid(), threads)
    with _POOLS_LOCK:
        pool = _POOLS.get(key)
        if pool is None:
            pool = _POOLS[key] = ThreadPoolExecutor(threads, thread_name_prefix=f"hrc-{threads}")
        return pool


def _pool_task(fn):
    def run(x):
        _IN_POOL.busy = True
        try:
            return fn(x)
        finally:
            _IN_POOL.busy = False
    return run


def default_threads() -> int:
    return max(1, min(8, os.cpu_count() or 1))


def even_parts(m: int, n: int) -> list[slice]:
    """``range(m)`` cut into ``n`` consecutive slices whose sizes differ by at most one."""
    return [slice(m * i // n, m * (i + 1) // n) for i in range(n)]


class RaySupply:
    """The rays of one chunk handed out in consecutive slices to the threads tracing it
    together (``Accel.shares_chunks``): every thread refills its lockstep pool from here as
    its rays finish, so all threads stay busy until the chunk runs out and finish together,
    instead of one thread tracing alone while the other's fixed half is done."""

    def __init__(self, m: int):
        self.m = m
        self.next = 0
        self._lock = threading.Lock()

    @property
    def left(self) -> bool:
        return self.next < self.m

    def take(self, k: int) -> slice:
        """The next at most ``k`` rays (an empty slice once the chunk is handed out)."""
        with self._lock:
            a = self.next
            self.next = min(self.m, a + max(0, int(k)))
            return slice(a, self.next)


class Accel:
    """Base of every structure. Subclasses implement ``_build`` and ``_trace_rays``."""

    kind = "?"
    #: rays per chunk: bounds the per-chunk working set
    chunk_size = 1 << 16
    #: whether ``_trace_rays`` needs the Woop shear of core/intersect.py (Embree does not)
    uses_shear = True
    #: True: ``_trace_rays``/``_occluded_rays`` trace a whole chunk on all threads at once,
    #: drawing rays from one ``RaySupply`` (``_shared``); False: one chunk per thread
    shares_chunks = False

    def __init__(self, mesh: TriangleMesh, *, threads: int | None = None, chunk_size: int | None = None):
        if not isinstance(mesh, TriangleMesh):
            raise TypeError(f"build() needs a core.TriangleMesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self.threads = default_threads() if threads is None else max(1, int(threads))
        if chunk_size is not None:
            self.chunk_size = max(1, int(chunk_size))
        t0 = time.perf_counter()
        self._build()
        self.build_time = time.perf_counter() - t0

    # -- what subclasses provide ---------------------------------------------------
    def _build(self):
        raise NotImplementedError

    def _trace_rays(self, rays: Rays) -> Hits:
        raise NotImplementedError

    def _occluded_rays(self, rays: Rays) -> np.ndarray:
        """Any-hit; structures override it to stop at the first hit."""
        return self._trace_rays(rays).hit

    # -- the public interface --------------------------------------------------------
    def trace(self, origins, directions, tmin=0.0, tmax=np.inf) -> Hits:
        """Nearest hit per ray with tmin < t <= tmax; an exact tie in t goes to the lowest
        triangle index; both faces are hit (the hit convention, ../shared/DESIGN.md)."""
        rays = prepare_rays(origins, directions, tmin, tmax, shear=False)
        m = len(rays)
        if m == 0 or self.mesh.triangle_count == 0:
            return Hits.empty(m)
        parts = self._map_chunks(self._trace_rays, rays)
        return Hits(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t", "triangle", "u", "v")))

    def occluded(self, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
        """(M,) bool: True where some triangle is hit with tmin < t <= tmax."""
        rays = prepare_rays(origins, directions, tmin, tmax, shear=False)
        m = len(rays)
        if m == 0 or self.mesh.triangle_count == 0:
            return np.zeros(m, bool)
        return np.concatenate(self._map_chunks(self._occluded_rays, rays))

    def _chunk_bounds(self, m: int) -> list[tuple[int, int]]:
        """At most ``chunk_size`` rays a chunk, the sizes equal within one ray.  With one chunk
        per thread (not ``shares_chunks``) the count is a multiple of ``threads`` (when each
        chunk keeps ``MIN_SPLIT`` rays: a small batch is not worth a thread pool), so that no
        thread is left alone with the last chunk."""
        n = -(-m // self.chunk_size)
        if self.threads > 1 and n % self.threads and not self.shares_chunks:
            n = max(n, min(-(-n // self.threads) * self.threads, m // MIN_SPLIT))
        return [(p.start, p.stop) for p in even_parts(m, n)]

    def _map_chunks(self, fn, rays: Rays):
        chunks = [rays.subset(slice(a, b)) for a, b in self._chunk_bounds(len(rays))]
        if self.shares_chunks:  # the threads work inside each chunk (``_shared``)
            return [fn(self._sheared(c) if self.uses_shear else c) for c in chunks]
        if self.uses_shear and rays.shear is None:
            # the Woop shear is computed inside each chunk's task, so on the thread pool too
            def fn(chunk, fn=fn):
                return fn(shear_rays(chunk))
        return self._in_pool(fn, chunks)

    def _workers(self, m: int) -> int:
        """Threads for one chunk of ``m`` rays: each keeps at least ``MIN_SPLIT`` of them."""
        return max(1, min(self.threads, m // MIN_SPLIT))

    def _sheared(self, rays: Rays) -> Rays:
        """``shear_rays`` of a chunk, its parts on the pool."""
        if rays.shear is not None:
            return rays
        n = self._workers(len(rays))
        if n == 1:
            return shear_rays(rays)
        parts = self._in_pool(shear_rays, [rays.subset(p) for p in even_parts(len(rays), n)])
        return Rays(rays.origins, rays.directions, rays.tmin, rays.tmax,
                    *(np.concatenate([getattr(p, f) for p in parts]) for f in ("kx", "ky", "kz", "shear")))

    def _shared(self, work, m: int) -> list:
        """``work(supply)`` on ``_workers(m)`` threads sharing one ``RaySupply(m)``."""
        supply = RaySupply(m)
        return self._in_pool(lambda _: work(supply), range(self._workers(m)))

    def _finished(self, best, rays: Rays, tri_vertices) -> Hits:
        """``best.finish`` (a ``NearestHits`` over the chunk ``rays``), its parts on the pool."""
        m = len(rays)
        n = self._workers(m)
        if n == 1:
            return best.finish(rays, tri_vertices)
        parts = self._in_pool(lambda sl: best.part(sl).finish(rays.subset(sl), tri_vertices), even_parts(m, n))
        return Hits(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t", "triangle", "u", "v")))

    def _in_pool(self, fn, items) -> list:
        """[fn(x) for x in items], on a pool of ``threads`` threads when there are several
        (the process's pool of that size, kept: starting threads for every call cost as much
        as a small trace; a call from one of its own threads runs inline, so work nested in
        a pool task cannot wait on the pool it occupies)."""
        if self.threads <= 1 or len(items) <= 1 or getattr(_IN_POOL, "busy", False):
            return [fn(x) for x in items]
        return list(_pool(self.threads).map(_pool_task(fn), items))

    # -- point queries (core/proximity.py) ------------------------------------------------
    def _point_parts(self, m: int) -> list[slice]:
        """The points cut into one part per thread, each of at least ``MIN_SPLIT``."""
        return even_parts(m, max(1, min(self.threads, m // MIN_SPLIT)))

    def _point_index(self):
        """The ``proximity.TreeIndex`` the point queries search: a BVH's own arrays; the
        structures without a tree build a BVH over the same mesh on first use."""
        raise NotImplementedError

    def _closest_search(self):
        """fn(points, max_distance) -> ``proximity.Nearest``: the closest-point search this
        structure runs, its index made before any thread shares it (the tree's branch and
        bound; the grid searches its own cells)."""
        index = self._point_index()
        return lambda p, md: proximity.closest_tree(index, p, md)

    def closest(self, points, max_distance=np.inf) -> proximity.Nearest:
        """The closest point on the surface to each of ``points`` (M, 3): ``distance``,
        ``triangle``, ``points``, ``u``, ``v`` (``proximity.Nearest``); a point with nothing
        within ``max_distance`` (inclusive) gets distance inf and triangle -1.  Exact in
        float64; a tie goes to the lowest triangle index."""
        search = self._closest_search()
        p = proximity.check_points(points)
        parts = self._point_parts(len(p))
        if len(parts) == 1:
            return search(p, max_distance)
        return proximity.Nearest.concat(self._in_pool(lambda sl: search(p[sl], max_distance), parts))

    def winding_number(self, points, accuracy: float = proximity.ACCURACY) -> np.ndarray:
        """(M,) float64 generalized winding number of each point (1 inside a closed mesh, 0
        outside, fractional near holes), by the tree's far-field sum (``accuracy``: Barill
        et al.'s beta; ``proximity.winding_number_tree``)."""
        index = self._point_index()
        p = proximity.check_points(points)
        parts = self._point_parts(len(p))
        if len(parts) == 1:
            return proximity.winding_number_tree(index, p, accuracy)
        index.dipoles()  # made once, before the threads share it
        return np.concatenate(self._in_pool(lambda sl: proximity.winding_number_tree(index, p[sl], accuracy), parts))

    def inside(self, points, accuracy: float = proximity.ACCURACY) -> np.ndarray:
        """(M,) bool: winding number above 0.5, which holds on open meshes, meshes with
        holes, self-intersecting meshes and overlapping shells."""
        return self.winding_number(points, accuracy) > 0.5

    def signed_distance(self, points, accuracy: float = proximity.ACCURACY) -> np.ndarray:
        """(M,) float64 distance to the surface, negative inside (``inside``); inf for every
        point of an empty mesh."""
        d = self.closest(points).distance
        return np.where(self.inside(points, accuracy), -d, d)

    def count_hits(self, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
        """(M,) int32 distinct hits along each ray with tmin < t <= tmax (hits of one ray at
        the same point, a shared edge, count once; as ``core.all_hits`` counts them), without
        keeping them."""
        return proximity.count_hits_tree(self._point_index(), origins, directions, tmin, tmax)

    def stats(self) -> dict:
        return {"kind": self.kind, "triangles": self.mesh.triangle_count, "build_time_s": self.build_time}

    def __repr__(self):
        return f"<{type(self).__name__} {self.mesh.triangle_count} triangles, built in {self.build_time * 1e3:.1f} ms>"

