"""Intel Embree (through embreex) behind the same Accel interface, kind 'embree'.

embreex is optional: this module imports it only when a structure is built, and
``embree_available()`` says whether that will work.  What embreex 4.4 offers, and what
this wrapper does about it:

- ``rtcore_scene.EmbreeScene(robust=True)`` sets Embree's RTC_SCENE_FLAG_ROBUST
  (watertight traversal and intersection, at some speed: robust=False traces faster, at
  Open3D's speed, but lets more of the rays from inside a closed mesh leak than the 5%
  bound allows, which robust mode keeps; BENCHMARKS.md, "Tried and not kept").  Open3D uses no
  scene flags, and also one ``rtcIntersect1`` per ray (no packets).
- ``scene.run(origins_f32, dirs_f32, dists=None, query='INTERSECT', output=None)``
  traces one ray at a time (``rtcIntersect1``), but its loop over the rays runs inside
  ``with nogil`` (embreex ``embreex/rtcore_scene.pyx``, ``EmbreeScene.run``; checked in
  embreex 4.4.0.post1's source), so chunks on a thread pool trace in parallel.  Every
  per-call state (the ``RTCRayHit``, the output arrays) is local to ``run``; the one
  shared flag is ``is_committed``, set by the first call, which ``_build`` makes before
  any concurrent use.  ``dists`` is the per-ray tfar (default 1e37; a passed
  array is overwritten with the hit distances, so we pass a copy).  With ``output=1``
  it returns a dict of float32 ``u``, ``v``, ``tfar``, ``Ng`` (M, 3) and int32
  ``primID``, ``geomID`` (-1 on a miss).  ``query='OCCLUDED'`` without ``output``
  returns int32, -1 where nothing is hit (with ``output`` the dict is garbage).
- There is no tnear: embreex always traces from 0 and Embree counts a hit at
  exactly t = tnear, while our convention is tmin < t.  A ray with tmin <= 0 is traced
  as given over [0, tmax] (the fast path: no copy, no float64); only when such a ray hits
  at exactly t = 0 is it traced again as below.  For tmin > 0 we move the
  origin to ``o + tmin * d`` (in float64, rounded to float32, so the ray the structure
  sees differs from the caller's by up to an ulp of the origin) and trace over
  (0, tmax - tmin]; a hit at exactly the start (t' = 0) is traced again from a start a
  few ulps further on (at most ``_RESTARTS`` times; after that the ray reports a miss).
  Both Embree's tfar and ours are inclusive.  A negative tmin is treated as 0: Embree
  cannot report hits behind the origin.
- The scene commits (builds its BVH) on the first ``run``; ``_build`` runs one dummy
  ray so that ``build_time`` includes Embree's build, as the cost model needs.
- What embreex does not expose (``embreex/rtcore_scene.pxd``, ``rtcore.pyx``): the
  scene's build quality (``rtcSetSceneBuildQuality``; Embree's default, MEDIUM, is
  used, as in Open3D), any device config (``rtcNewDevice(NULL)``: Embree's own build
  threads are all hardware threads), scene flags other than ROBUST and packet or stream
  queries.  Its ``mesh_construction.TriangleMesh`` copies the arrays into Embree's
  buffers element by element through untyped (Python-level) indexing
  (``_build_from_indices``): on a large mesh several times as long as Embree's own BVH
  build, and most of the build's scatter.  So the geometry is filled through Embree's C
  API instead (``_DirectFill``: ctypes on the Embree embreex's own calls reach, two
  numpy copies into the buffers of ``rtcSetNewGeometryBuffer``, a small part of the
  build; BENCHMARKS.md, "Trace speed: engine table"), on the
  scene embreex made, whose handle it reads from the scene object (the layout is
  checked, and Embree must confirm the handle, before anything is written).
  ``TriangleMesh`` remains the fallback when that check fails (another embreex layout,
  no library file found); ``stats()['fill']`` says which one built the structure.

Triangles that are degenerate (zero area in float64, ``TriangleMesh.valid``) are not
given to Embree, and Embree's primID is mapped back to the mesh's triangle index.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import sys

import numpy as np

from .accel import Accel
from .hits import Hits
from .intersect import Rays, prepare_rays

F32 = np.float32
#: how often a hit at exactly the (moved) origin is re-traced from a little further on
_RESTARTS = 4


def embree_available() -> bool:
    """True when embreex can be imported (without importing it)."""
    try:
        return importlib.util.find_spec("embreex") is not None
    except (ImportError, ValueError):
        return False


#: (system, machine) pairs and Python versions embreex 4.4.0.post1 has wheels for (PyPI's file
#: list; the manifest bundles the linux-x64 and windows-x64 ones, for Blender's Pythons).
_WHEEL_PLATFORMS = {("linux", "x86_64"): "Linux x64", ("windows", "amd64"): "Windows x64"}
_WHEEL_PYTHONS = ((3, 11), (3, 13))
_SYSTEM_NAMES = {"darwin": "macOS", "linux": "Linux", "windows": "Windows"}
_MACHINE_NAMES = {"x86_64": "x64", "amd64": "x64", "arm64": "arm64", "aarch64": "arm64"}


def embree_unavailable_reason(system: str | None = None, machine: str | None = None,
                              python: tuple[int, int] | None = None) -> str | None:
    """Why the 'embree' structure cannot be built here, in words for the user; None when it can.

    ``system``, ``machine`` and ``python`` default to this interpreter's (``platform.system()``,
    ``platform.machine()``, ``sys.version_info[:2]``).
    """
    if embree_available():
        return None
    import platform
    import sys

    system = (system or platform.system()).lower()
    machine = (machine or platform.machine()).lower()
    python = tuple(python or sys.version_info[:2])
    if (system, machine) not in _WHEEL_PLATFORMS:
        where = f"{_SYSTEM_NAMES.get(system, system)} {_MACHINE_NAMES.get(machine, machine)}"
        return f"embreex has no wheel for {where}"
    if python not in _WHEEL_PYTHONS:
        return f"embreex has no wheel for Python {python[0]}.{python[1]}"
    return "embreex is not installed"


def _import_embreex():
    try:
        from embreex import mesh_construction, rtcore, rtcore_scene
    except ImportError as e:  # ModuleNotFoundError, or a broken binary wheel
        raise RuntimeError(
            f"embreex is not installed: the 'embree' structure needs it ({e}); "
            "use kind 'grid', 'bvh' or 'brute', or install embreex"
        ) from e
    return rtcore, rtcore_scene, mesh_construction


class EmbreeAccel(Accel):
    """Embree 4 through embreex.

    Config: ``robust`` (default True): RTC_SCENE_FLAG_ROBUST.  ``threads`` (default: the
    machine's cores, ``accel.default_threads()``): chunks of ``chunk_size`` (default 2**17)
    rays traced concurrently, each call releasing the GIL inside embreex's ray loop.
    ``direct_fill`` (default True): fill the geometry through Embree's C API when
    ``_DirectFill`` can; False always uses embreex's ``TriangleMesh`` (same hits, slower).
    """

    kind = "embree"
    uses_shear = False
    #: rays per chunk: twice the base class's, since each chunk has a fixed cost beyond
    #: embreex's ray loop (the five fresh output arrays of ``EmbreeScene.run``, the
    #: validation, the copy into the output block) that held back 2-thread traces of
    #: coherent camera rays at 65,536; 8 chunks per 1M rays still keep both threads busy
    #: when the cost is uneven along the image (sky rows vs object rows); docs/bench_engines.md
    chunk_size = 1 << 17

    def __init__(self, mesh, *, robust: bool = True, threads: int | None = None, direct_fill: bool = True, **kw):
        self.robust = bool(robust)
        self.direct_fill = bool(direct_fill)
        super().__init__(mesh, threads=threads, **kw)

    def _point_index(self):
        from .bvh import point_index_of  # a BVH for the point queries, built on first use

        return point_index_of(self)

    def _build(self):
        rtcore, rtcore_scene, mesh_construction = _import_embreex()
        valid = self.mesh.valid
        self.prim_to_triangle = np.flatnonzero(valid).astype(np.int32)
        # None when every triangle is valid: Embree's primID is the triangle index
        self._remap = None if self.prim_to_triangle.size == valid.size else self.prim_to_triangle
        self.scene = None
        self.fill = None
        if self.prim_to_triangle.size == 0:
            return
        device = rtcore.EmbreeDevice()  # what EmbreeScene() makes itself; cheap next to a build
        self.scene = rtcore_scene.EmbreeScene(device, robust=self.robust)
        triangles = self.mesh.triangles if self._remap is None else self.mesh.triangles[self._remap]
        direct = self.direct_fill and _DirectFill.get()
        if direct and direct.fill(self.scene, device, self.mesh.vertices, triangles):
            self.fill = "direct"
        else:
            mesh_construction.TriangleMesh(
                self.scene, np.ascontiguousarray(self.mesh.vertices, F32), np.ascontiguousarray(triangles, np.int32)
            )
            self.fill = "embreex"
        # force the commit (Embree's BVH build) now, so build_time measures it and no two
        # threads' first run() commit at once
        one = np.zeros((1, 3), F32)
        self.scene.run(one, one + F32(1.0), dists=np.zeros(1, F32))

    # -- the batch: validated chunk by chunk on the pool, written into one output -----------
    def trace(self, origins, directions, tmin=0.0, tmax=np.inf) -> Hits:
        """``Accel.trace`` (same hits, same errors), except that each chunk's rays are
        validated inside its pool task and its hits written into one preallocated output:
        embreex leaves so little work per ray that a serial validation of the whole batch
        and a serial concatenation are a visible share of a threaded trace.

        The four arrays of the Hits are rows of one (4, M) block: numpy asks Linux for huge
        pages for an allocation of 4 MiB or more (``madvise(MADV_HUGEPAGE)`` in numpy's
        ``alloc.c``; ``np.core.multiarray._get_madvise_hugepage()`` says whether it is on),
        which four separate (M,) arrays of 1M rays each just miss, so the output costs a few
        page faults instead of one per 4 KiB.  Keeping one of the arrays
        keeps the whole block alive."""
        batch = self._batch(origins, directions, tmin, tmax)
        if batch is None:
            return super().trace(origins, directions, tmin, tmax)
        m, prepare = batch
        block = np.empty((4, m), F32)
        out = Hits(block[0], block[1].view(np.int32), block[2], block[3])

        def chunk(a, b):
            view = Hits(out.t[a:b], out.triangle[a:b], out.u[a:b], out.v[a:b])
            h = self._trace_rays(prepare(a, b), view)
            if h is not view:
                view.t[:], view.triangle[:], view.u[:], view.v[:] = h.t, h.triangle, h.u, h.v

        self._each_chunk(chunk, m, origins, directions, tmin, tmax)
        return out

    def occluded(self, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
        """``Accel.occluded``, chunked as ``trace``."""
        batch = self._batch(origins, directions, tmin, tmax)
        if batch is None:
            return super().occluded(origins, directions, tmin, tmax)
        m, prepare = batch
        out = np.empty(m, bool)

        def chunk(a, b):
            out[a:b] = self._occluded_rays(prepare(a, b))

        self._each_chunk(chunk, m, origins, directions, tmin, tmax)
        return out

    def _batch(self, origins, directions, tmin, tmax):
        """(M, prepare) where ``prepare(a, b)`` is ``prepare_rays`` (no shear) of rays a..b;
        None when the whole-batch path must answer: no scene, no rays, or arguments whose
        shapes ``prepare_rays`` reshapes or refuses (a single (3,) ray, mismatched shapes)."""
        if self.scene is None:
            return None
        o, d, lo, hi = np.asarray(origins), np.asarray(directions), np.asarray(tmin), np.asarray(tmax)
        if o.ndim != 2 or o.shape[1:] != (3,) or d.shape != o.shape or len(o) == 0:
            return None
        m = len(o)
        if any(x.ndim > 1 or (x.ndim == 1 and x.shape != (m,)) for x in (lo, hi)):
            return None

        def prepare(a, b):
            return prepare_rays(o[a:b], d[a:b], lo if lo.ndim == 0 else lo[a:b], hi if hi.ndim == 0 else hi[a:b],
                                shear=False)

        return m, prepare

    def _each_chunk(self, fn, m, *args):
        """``fn(a, b)`` for every chunk of ``Accel._chunk_bounds``, on the pool when there are
        several.  Validity is per ray, so a chunk's ValueError means the whole batch is
        invalid: ``prepare_rays`` then names the bad rays by their index in the batch, as
        ``Accel.trace`` would."""
        try:
            self._in_pool(lambda ab: fn(*ab), self._chunk_bounds(m))
        except ValueError:
            prepare_rays(*args, shear=False)
            raise

    # -- embreex calls ------------------------------------------------------------------
    def _run(self, origins, directions, tfar, query):
        """One embreex call; origins/directions (P, 3) float32, tfar (P,) float32."""
        o = np.ascontiguousarray(origins, dtype=F32)
        d = np.ascontiguousarray(directions, dtype=F32)
        dists = np.array(tfar, dtype=F32)  # a copy: embreex writes the hit distances into it
        if query == "OCCLUDED":
            return self.scene.run(o, d, dists=dists, query="OCCLUDED")
        return self.scene.run(o, d, dists=dists, output=1)

    def _triangles(self, prim):
        return prim if self._remap is None else self._remap[prim]

    def _moved(self, rays: Rays, idx, s):
        """Origins moved to o + s d (float64, rounded to float32), directions, tfar = tmax - s."""
        o = rays.origins[idx].astype(np.float64) + s[:, None] * rays.directions[idx].astype(np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            tfar = rays.tmax[idx].astype(np.float64) - s
        return o.astype(F32), rays.directions[idx], tfar.astype(F32)

    def _restart_param(self, rays: Rays, idx, s):
        """A start a few float32 ulps of the origin further along the ray than ``s``."""
        o = np.abs(rays.origins[idx]).max(axis=1).astype(np.float64)
        d = np.abs(rays.directions[idx]).max(axis=1).astype(np.float64)
        step = np.maximum(o / d, 1e-30) * 2.0 ** -21
        return np.maximum(s * (1 + 2.0 ** -21), s + step)

    def _hits_from_origin(self, rays: Rays, out: Hits | None = None):
        """Every ray as given over [0, tmax], when all have tmin <= 0 and tmax >= 0: Hits
        (written into ``out`` when given), and the indices of the rays whose nearest hit is at
        exactly t = 0 (None if there are none)."""
        r = self._run(rays.origins, rays.directions, rays.tmax, "INTERSECT")
        prim, tfar = r["primID"], r["tfar"]
        if out is None:
            out = Hits(*(np.empty(len(prim), x) for x in (F32, np.int32, F32, F32)))
        miss = prim < 0
        at_zero = None
        zero = np.less_equal(tfar, 0)  # a miss keeps tfar = tmax, which may be 0
        if zero.any():
            zero &= ~miss
            if zero.any():
                at_zero = np.flatnonzero(zero)
                miss |= zero
        # embreex's primID is already -1 on a miss, u and v are whatever the previous ray left
        # (embreex rtcore_scene.pyx, EmbreeScene.run: one RTCRayHit reused for every ray)
        np.copyto(out.t, tfar)
        np.copyto(out.t, F32(np.inf), where=miss)
        if self._remap is None and at_zero is None:
            np.copyto(out.triangle, prim)
        else:
            np.copyto(out.triangle, np.where(miss, np.int32(-1), self._triangles(prim)))
        for field in ("u", "v"):
            a = getattr(out, field)
            np.copyto(a, r[field])
            np.copyto(a, F32(0), where=miss)
        return out, at_zero

    def _trace_from_origin(self, rays: Rays, idx, out: Hits):
        """Rays ``idx`` as given over [0, tmax] into ``out``; returns the indices of those
        whose nearest hit is at exactly t = 0 (to be traced again)."""
        o, d, tmax = rays.origins[idx], rays.directions[idx], rays.tmax[idx]
        live = tmax >= 0
        if not live.all():
            idx, o, d, tmax = idx[live], o[live], d[live], tmax[live]
        r = self._run(o, d, tmax, "INTERSECT")
        prim, tfar = r["primID"], r["tfar"]
        hit = prim >= 0
        good = hit & (tfar > 0)
        g = idx[good]
        out.t[g] = tfar[good]
        out.triangle[g] = self._triangles(prim[good])
        out.u[g] = r["u"][good]
        out.v[g] = r["v"][good]
        return idx[hit & ~good]

    def _trace_rays(self, rays: Rays, out: Hits | None = None) -> Hits:
        """Hits of ``rays``: written into ``out`` (and returned) on the common path when it
        is given, else new arrays; callers copy when the returned Hits is not ``out``."""
        m = len(rays)
        if self.scene is None:
            return Hits.empty(m)
        fresh = rays.tmin <= 0  # a negative tmin only widens the range: Embree starts at 0
        if fresh.all() and (rays.tmax >= 0).all():  # the common case: no scatter, no float64
            out, at_zero = self._hits_from_origin(rays, out)
            if at_zero is None:
                return out
            todo = np.empty(0, np.intp)
        else:
            out = Hits.empty(m)
            at_zero = self._trace_from_origin(rays, np.flatnonzero(fresh), out)
            todo = np.flatnonzero(~fresh)
        s = rays.tmin[todo].astype(np.float64)
        # the rays that hit at exactly their origin join the moved rays after their first
        # pass, so that every ray gets at most _RESTARTS traces after its first
        late, s_late = at_zero, self._restart_param(rays, at_zero, np.zeros(at_zero.size))
        for it in range(_RESTARTS + 1):
            if it == 1 and late.size:
                todo, s = np.concatenate([todo, late]), np.concatenate([s, s_late])
            if todo.size == 0:
                if it == 0 and late.size:
                    continue
                break
            o, d, tfar = self._moved(rays, todo, s)
            live = tfar >= 0
            idx, s = todo[live], s[live]
            r = self._run(o[live], d[live], tfar[live], "INTERSECT")
            prim = r["primID"]
            hit = prim >= 0
            at_start = hit & (r["tfar"] <= 0)
            # rays that hit exactly at their start: the convention excludes t = tmin
            good = hit & ~at_start
            g = idx[good]
            t = (s[good] + r["tfar"][good].astype(np.float64)).astype(F32)
            out.t[g] = np.minimum(t, rays.tmax[g])  # rounding of s + t' must not pass tmax
            out.triangle[g] = self._triangles(prim[good])
            out.u[g] = r["u"][good]
            out.v[g] = r["v"][good]
            todo = idx[at_start]
            s = self._restart_param(rays, todo, s[at_start])
        return out

    def _occluded_rays(self, rays: Rays) -> np.ndarray:
        m = len(rays)
        hit = np.zeros(m, bool)
        if self.scene is None:
            return hit
        fresh = rays.tmin <= 0
        s = np.zeros(m)
        o, d, tfar = rays.origins, rays.directions, rays.tmax
        if not fresh.all():  # only the rays with tmin > 0 are moved
            moved = np.flatnonzero(~fresh)
            s[moved] = rays.tmin[moved]
            o, tfar = o.copy(), tfar.copy()
            o[moved], _, tfar[moved] = self._moved(rays, moved, s[moved])
        live = tfar >= 0
        if live.all():
            occ = np.flatnonzero(self._run(o, d, tfar, "OCCLUDED") != -1)
        else:
            live = np.flatnonzero(live)
            occ = live[self._run(o[live], d[live], tfar[live], "OCCLUDED") != -1]
        # Embree also counts a hit at exactly the start (t = tmin, which we exclude):
        # ask again from a few ulps further on, and settle the rest with a nearest-hit trace
        s2 = self._restart_param(rays, occ, s[occ])
        o2, d2, tfar2 = self._moved(rays, occ, s2)
        live2 = tfar2 >= 0
        sure = np.zeros(occ.size, bool)
        sure[live2] = self._run(o2[live2], d2[live2], tfar2[live2], "OCCLUDED") != -1
        hit[occ[sure]] = True
        unsure = occ[~sure]
        if unsure.size:
            hit[unsure] = self._trace_rays(rays.subset(unsure)).hit
        return hit

    def stats(self) -> dict:
        st = super().stats()
        st.update(robust=self.robust, embree_triangles=int(self.prim_to_triangle.size), fill=self.fill)
        return st


class _DirectFill:
    """A scene's triangle geometry filled through Embree's C API (ctypes), not embreex's loop.

    embreex keeps the scene's ``RTCScene`` in a private attribute of ``EmbreeScene`` and the
    ``RTCDevice`` in one of ``EmbreeDevice``.  Cython lays a cdef class out as a C struct
    after the object header, in declaration order (``rtcore_scene.pxd``: ``scene_i``,
    ``is_committed``, ``device``; ``rtcore.pxd``: ``device``), so with no vtable the handles
    sit at fixed offsets.  Before it writes anything, ``fill`` checks that layout three ways:
    both classes have the struct's size, the scene's ``device`` slot holds the very
    EmbreeDevice passed to it, and Embree's ``rtcGetSceneDevice`` on the scene handle
    returns the device handle.  If any check fails it returns False and the caller uses
    ``TriangleMesh``; an Embree error after the checks is raised.

    The library is the one embreex's calls reach (``library``): an Embree the program
    itself exports (Debian's Blender), else the libembree4 file shipped beside embreex
    (``embreex.libs`` on Linux and Windows, ``.dylibs`` on macOS), whose path, loaded again,
    gives the library already loaded.
    """

    _instance: "_DirectFill | None | bool" = False  # False: not looked for yet
    #: RTCGeometryType, RTCBufferType and RTCFormat values (embree4/rtcore_geometry.h,
    #: rtcore_buffer.h, rtcore_common.h)
    TRIANGLE, INDEX, VERTEX, UINT3, FLOAT3 = 0, 0, 1, 0x5003, 0x9003
    _HEAD = object.__basicsize__  # the object header before a cdef class's fields
    _PTR = ctypes.sizeof(ctypes.c_void_p)
    #: EmbreeScene: header, RTCScene scene_i, int is_committed (padded), EmbreeDevice device
    SCENE_SIZE, SCENE_DEVICE = _HEAD + 3 * _PTR, _HEAD + 2 * _PTR
    DEVICE_SIZE = _HEAD + _PTR  # EmbreeDevice: header, RTCDevice device
    _ERRORS = {2: "invalid argument", 3: "invalid operation", 4: "out of memory"}

    def __init__(self, lib):
        vp, c = ctypes.c_void_p, ctypes
        self.lib = lib
        for name, res, args in (
            ("rtcGetSceneDevice", vp, [vp]),
            ("rtcReleaseDevice", None, [vp]),
            ("rtcGetDeviceError", c.c_int, [vp]),
            ("rtcNewGeometry", vp, [vp, c.c_int]),
            ("rtcSetNewGeometryBuffer", vp, [vp, c.c_int, c.c_uint, c.c_int, c.c_size_t, c.c_size_t]),
            ("rtcCommitGeometry", None, [vp]),
            ("rtcAttachGeometry", c.c_uint, [vp, vp]),
            ("rtcReleaseGeometry", None, [vp]),
        ):
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = res, args

    @classmethod
    def get(cls) -> "_DirectFill | None":
        """The one instance, or None when the library or the expected layout is not there."""
        if cls._instance is False:
            cls._instance = None
            try:
                lib = cls.library()
                if lib is not None:
                    cls._instance = cls(lib)
            except (OSError, AttributeError):  # not loadable, or a symbol missing
                pass
        return cls._instance

    @classmethod
    def library(cls):
        """The Embree that embreex's own calls reach (a ctypes library), or None.

        On Linux a library's undefined symbols bind to the first definition in the global
        scope (the program and what it loaded with RTLD_GLOBAL) before its own dependencies.
        Debian's Blender links the system libembree4 for Cycles, so there embreex's calls go
        to that one, not to the copy in its wheel; a device made by one must not be handed to
        the other (rtcNewGeometry of the wheel's copy on such a device crashed Blender
        4.3.2).  So the global scope is asked first, the wheel's file after; Windows and
        macOS bind each import to the library it was linked with, the wheel's."""
        if sys.platform.startswith("linux"):
            scope = ctypes.CDLL(None)
            if hasattr(scope, "rtcNewGeometry"):
                return scope
        path = cls.library_path()
        return None if path is None else ctypes.CDLL(path)

    @staticmethod
    def library_path() -> str | None:
        """The libembree4 file embreex's extensions load, when exactly one is found."""
        spec = importlib.util.find_spec("embreex")
        if spec is None or not spec.submodule_search_locations:
            return None
        pkg = list(spec.submodule_search_locations)[0]
        found = []
        for folder in (os.path.join(os.path.dirname(pkg), "embreex.libs"), os.path.join(pkg, ".dylibs"), pkg):
            if os.path.isdir(folder):
                found += [os.path.join(folder, f) for f in sorted(os.listdir(folder)) if "embree4" in f]
        if len(found) != 1:
            return None
        if sys.platform.startswith("linux"):  # the file must be the one already mapped
            try:
                with open("/proc/self/maps") as maps:
                    if os.path.realpath(found[0]) not in maps.read():
                        return None
            except OSError:
                return None
        return found[0]

    def handles(self, scene, device):
        """(RTCScene, RTCDevice) of an embreex scene and the device it was made with, or None
        when the layout is not the one described in the class docstring."""
        rtcore, rtcore_scene, _ = _import_embreex()
        if sys.implementation.name != "cpython":  # id() is an object's address only in CPython
            return None
        if (type(scene) is not rtcore_scene.EmbreeScene or type(device) is not rtcore.EmbreeDevice
                or type(scene).__basicsize__ != self.SCENE_SIZE or type(device).__basicsize__ != self.DEVICE_SIZE):
            return None
        address = ctypes.c_void_p.from_address
        if address(id(scene) + self.SCENE_DEVICE).value != id(device):
            return None
        scene_h, device_h = address(id(scene) + self._HEAD).value, address(id(device) + self._HEAD).value
        if not scene_h or not device_h:
            return None
        owner = self.lib.rtcGetSceneDevice(scene_h)  # adds a reference to the device
        if owner:
            self.lib.rtcReleaseDevice(owner)
        return (scene_h, device_h) if owner == device_h else None

    def fill(self, scene, device, vertices, triangles) -> bool:
        """Attach one triangle geometry of ``vertices`` (V, 3) and ``triangles`` (T, 3) to
        ``scene``, to be built on its next ``run``; False (nothing written) when ``handles``
        refuses."""
        h = self.handles(scene, device)
        if h is None:
            return False
        scene_h, device_h = h
        lib = self.lib
        geometry = lib.rtcNewGeometry(device_h, self.TRIANGLE)
        self._check(device_h, geometry)
        try:
            for kind, fmt, item, data in ((self.VERTEX, self.FLOAT3, ctypes.c_float, vertices),
                                          (self.INDEX, self.UINT3, ctypes.c_uint32, triangles)):
                n = len(data)
                buf = lib.rtcSetNewGeometryBuffer(geometry, kind, 0, fmt, 3 * ctypes.sizeof(item), n)
                self._check(device_h, buf)
                # the values convert on the copy: float64 -> float32 rounds as astype does,
                # int32 -> uint32 keeps the (non-negative) indices
                np.copyto(np.ctypeslib.as_array((item * (3 * n)).from_address(buf)).reshape(n, 3), data,
                          casting="unsafe")
            lib.rtcCommitGeometry(geometry)
            lib.rtcAttachGeometry(scene_h, geometry)
            self._check(device_h)
        finally:
            lib.rtcReleaseGeometry(geometry)  # the scene keeps its own reference
        scene.is_committed = 0  # embreex's run commits (rebuilds) only when this is 0
        return True

    def _check(self, device_h, result=True):
        """Raise Embree's pending error on ``device_h``, or an unknown one when ``result``
        (a handle or pointer a call returned) is NULL."""
        code = self.lib.rtcGetDeviceError(device_h)
        if code or not result:
            what = self._ERRORS.get(code, f"error {code}")
            raise (MemoryError if code == 4 else RuntimeError)(f"Embree could not take the triangles: {what}")
