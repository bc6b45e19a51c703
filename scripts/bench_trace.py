"""Benchmark the tracers: build time, rays/s, peak memory and error against float64.

    .venv/bin/python scripts/bench_trace.py                       # 10k, 100k, 1M; 100k rays; 5 repeats
    .venv/bin/python scripts/bench_trace.py --sizes 10k --rays 10000 --repeats 2
    .venv/bin/python scripts/bench_trace.py --sizes 1m --memory-check   # + 10M rays through grid and BVH
    .venv/bin/python scripts/bench_trace.py --engines                   # the engine table (make bench-trace)
    .venv/bin/python scripts/bench_trace.py --scale 10m                 # Suzanne instanced 10x: build, trace, peak memory
    .venv/bin/python scripts/bench_trace.py --engines --scenes suzanne10m --build-repeats 1 --repeats 3 --numpy-rays 524288
                                                      # the engine table at 10M triangles, with peak memory

The engine table (``--engines``): on 3 icospheres (983,040 triangles) and Suzanne at
level 5 (1,007,616), 1M random rays and about 1M camera rays, raw embreex (a thread
pool over 64k-ray chunks, and one thread), ``core.build(mesh, 'embree')`` with its
defaults, with threads=1 and with robust=False (Open3D's scene flags), the numpy BVH and
grid (on the pool and on 1 thread), Blender's BVHTree loop (on a strided subset) and
Open3D's ``RaycastingScene.cast_rays``, which runs in its own venv (``.venv-open3d``;
scripts/bench_open3d.py) on the same rays saved to a temporary directory.  Columns:
build s, Mrays/s, ratios to raw embreex and to Open3D, hit %, and the share of rays that
hit the same triangle as raw embreex.

The per-size table (the default):

Scenes are Blender's Suzanne under a Subdivision Surface modifier, at the level whose
triangle count is nearest (in log scale) to each requested size: level 2 = 15,744,
level 3 = 62,976, level 4 = 251,904, level 5 = 1,007,616 triangles.  Two ray batches
per scene: the paper's (origins uniform in the scene box padded by 1%, directions
uniform on the sphere; ``core.rays.uniform_rays``) and the primary rays of a pinhole
camera looking at the monkey (``core.rays.camera_rays``).

Tracers, all measured in the same run on the same triangles (the evaluated monkey is
copied into a plain triangle mesh object so Blender's peers see exactly these):

- the project's structures: ``grid``, ``bvh``, ``embree`` (Embree through embreex) and
  ``brute`` (all pairs; only on scenes of at most 20k triangles, on a ray subset);
- ``bvhtree``: ``mathutils.bvhtree.BVHTree.FromPolygons`` and a Python loop of
  ``tree.ray_cast`` per ray;
- ``scene_raycast``: ``Scene.ray_cast`` per ray (Blender builds and caches the object's
  BVH on the first call, so its build time is that first call);
- ``gn_raycast``: a Geometry Nodes Raycast node on a cloud of loose vertices (one per
  ray, direction in the point attribute "dir"), hit distance, is-hit and hit corner
  stored as attributes and read back with ``foreach_get``;
- ``trimesh``: ``trimesh.ray.ray_triangle.RayMeshIntersector`` (pure numpy + rtree;
  trimesh's default ``mesh.ray`` would pick Embree when embreex is installed), only on
  scenes of at most 100k triangles, on a ray subset, in calls of 200 rays (its memory
  grows with rays x candidate triangles).

Columns of the speed table (medians of ``--repeats`` runs):
  M          rays traced per run (capped tracers: an evenly strided subset)
  build s    time to build the structure (project kinds: ``accel.build_time``;
             bvhtree: FromPolygons on prepared lists; gn_raycast: the first evaluation
             with one ray once the target is hooked up, i.e. its BVH build plus the
             evaluation overhead; scene_raycast: its first call; trimesh: the Trimesh
             and its rtree)
  Mrays/s    M / trace time, everything the caller pays included (list conversion for
             the per-ray loops, foreach_set + depsgraph evaluation + foreach_get for GN)
  x BVHTree  Mrays/s over the bvhtree loop's in this run; x Embree likewise
  hit %      share of the M rays that hit
  RSS MiB    peak extra resident memory of one build + trace, from a separate untimed
             pass: VmHWM after minus VmRSS before (peak reset through
             /proc/self/clear_refs, freed heap returned by malloc_trim first); sees every
             allocation, Blender's and Embree's included, but may undercount memory the
             allocator reused
  traced MiB peak of tracemalloc over the same pass: numpy arrays and Python objects
             only (numpy reports to tracemalloc), not Blender's or Embree's C++ heaps

Columns of the speed-against-error table, against a float64 Moller-Trumbore reference
(tests/reference.py) on ``--ref-rays`` rays of each batch, evenly strided:
  disagree %   rays where hit/miss differs or another triangle is hit
  flips        rays hit by one and missed by the other
  other tri    rays where both hit but different triangles
  non-grazing  disagreements left after excluding the rays the reference marks ambiguous
               (grazing an edge or vertex, near ties): a watertight kernel may
               legitimately differ there
  max/median rel t err   |t - t_ref| / t_ref over rays both hit, t in units of the
               direction as given (Blender's distances are divided by |d|)

Benchmarks print tables; they never assert times.  Run the full configuration on a
quiet machine: these numbers move with the load.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import gc
import importlib.util
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memory import PeakMemory, trim  # noqa: E402
from _package import ROOT, core_package  # noqa: E402

core_package()
from hybrid_raycast import core  # noqa: E402
from hybrid_raycast.core.rays import camera_rays, uniform_rays  # noqa: E402

PROJECT_KINDS = ("grid", "bvh", "embree", "brute")
PEERS = ("bvhtree", "scene_raycast", "gn_raycast", "trimesh")
#: above these triangle counts a tracer is skipped (with the reason printed)
MAX_TRIANGLES = {"brute": 20_000, "trimesh": 100_000}
SKIP_REASON = {
    "brute": "all pairs: only on scenes of at most 20k triangles",
    "trimesh": "runs out of memory at ~300k triangles (issue 3): only up to 100k",
}
#: Suzanne's triangle count at each Subdivision Surface level (level 0 is the raw monkey)
MONKEY_TRIANGLES = {0: 968, **{lv: 3936 * 4 ** (lv - 1) for lv in range(1, 7)}}


# -- rays ----------------------------------------------------------------------------------
def camera_setup(mesh, m):
    """A pinhole camera in front of the monkey's face (it faces -Y), framing its bounding
    sphere closely so most rays hit; an image of about ``m`` pixels at 4:3."""
    lo, hi = (np.asarray(b, np.float64) for b in mesh.bounds())
    centre = (lo + hi) / 2
    radius = np.linalg.norm(hi - lo) / 2
    fov = 40.0
    view = np.array([0.35, -1.0, 0.3])
    view /= np.linalg.norm(view)
    eye = centre + view * (0.5 * radius / math.tan(math.radians(fov / 2)))  # ~78% of rays hit
    width = max(1, round(math.sqrt(m * 4 / 3)))
    height = max(1, round(m / width))
    return dict(origin=eye, look_at=centre, up=(0.0, 0.0, 1.0), fov_deg=fov, width=width, height=height)


def strided(m, k):
    """At most k indices spread evenly over range(m): for camera rays a sparser image."""
    if k >= m:
        return np.arange(m)
    return np.round(np.linspace(0, m - 1, k)).astype(np.int64)


# -- the float64 reference ----------------------------------------------------------------
def load_reference():
    path = ROOT / "tests" / "reference.py"
    if not path.exists():
        raise SystemExit(f"the float64 reference {path} is missing")
    spec = importlib.util.spec_from_file_location("_bench_reference", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# -- Blender: scenes and peers ------------------------------------------------------------
def monkey_level(size):
    return min(MONKEY_TRIANGLES, key=lambda lv: abs(math.log(MONKEY_TRIANGLES[lv] / size)))


def monkey_triangles(level):
    """(vertices (V,3) float32, triangles (T,3) int32) of Suzanne subdivided ``level`` times,
    evaluated by Blender and triangulated by its loop triangles."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_monkey_add()
    src = bpy.context.object
    if level:
        mod = src.modifiers.new("Subdivision", "SUBSURF")
        mod.levels = level
        mod.render_levels = level
    me = src.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    me.calc_loop_triangles()
    v = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", v)
    t = np.empty(len(me.loop_triangles) * 3, np.int32)
    me.loop_triangles.foreach_get("vertices", t)
    bpy.data.objects.remove(src)
    return v.reshape(-1, 3), t.reshape(-1, 3)


def triangle_object(name, vertices, triangles):
    """A mesh object whose polygons are exactly these triangles, in this order, linked
    into the scene: polygon index == triangle index for Blender's peers."""
    import bpy

    me = bpy.data.meshes.new(name)
    me.vertices.add(len(vertices))
    me.vertices.foreach_set("co", vertices.ravel())
    me.loops.add(triangles.size)
    me.loops.foreach_set("vertex_index", triangles.ravel())
    me.polygons.add(len(triangles))
    me.polygons.foreach_set("loop_start", np.arange(0, triangles.size, 3, dtype=np.int32))
    me.update()
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


# -- tracers: build() -> seconds; trace(o, d) -> (t (M,) float64 in units of d, inf on a miss,
#    triangle (M,) int, -1 on a miss); release() drops the structure
class Unavailable(Exception):
    pass


class ProjectTracer:
    def __init__(self, kind, scene, threads):
        self.name = kind
        self.kind = kind
        self.mesh = scene["mesh"]
        self.config = {} if threads is None else {"threads": threads}
        self.accel = None
        if kind == "embree" and not core.embree_available():
            raise Unavailable("embreex is not installed")

    def build(self):
        self.accel = core.build(self.mesh, self.kind, **self.config)
        return self.accel.build_time

    def trace(self, o, d):
        h = self.accel.trace(o, d)
        return h.t.astype(np.float64), h.triangle

    def stats(self):
        return self.accel.stats()

    def release(self):
        self.accel = None


class BVHTreeLoop:
    """mathutils.bvhtree.BVHTree.FromPolygons and a per-ray Python loop of ray_cast.

    ray_cast normalises the direction and returns the distance in world units, so
    t = distance / |d|.  Its distance argument is left at its default (FLT_MAX)."""

    name = "bvhtree"

    def __init__(self, scene, threads):
        from mathutils.bvhtree import BVHTree

        self.cls = BVHTree
        # the list conversion is the caller's business; not part of the build time
        self.verts = scene["mesh"].vertices.tolist()
        self.tris = scene["mesh"].triangles.tolist()
        self.tree = None

    def build(self):
        t0 = time.perf_counter()
        self.tree = self.cls.FromPolygons(self.verts, self.tris, all_triangles=True)
        return time.perf_counter() - t0

    def trace(self, o, d):
        cast = self.tree.ray_cast
        t = np.full(len(o), np.inf)
        tri = np.full(len(o), -1, np.int64)
        for i, (oi, di) in enumerate(zip(o.tolist(), d.tolist())):
            _, _, index, dist = cast(oi, di)
            if index is not None:
                t[i] = dist
                tri[i] = index
        return t / np.linalg.norm(d.astype(np.float64), axis=1), tri

    def release(self):
        self.tree = None


def drop_cached_bvh(bpy, target, positions):
    """Re-evaluate ``target`` so its evaluated mesh, and the BVH Blender caches on it, is
    new: writing the same positions tags the geometry as changed."""
    me = target.data
    me.vertices.foreach_set("co", positions)
    me.update()
    bpy.context.evaluated_depsgraph_get()


class SceneRayCast:
    """Scene.ray_cast per ray against the triangle object (the only object with faces).

    Blender builds the object's BVH on the first call and caches it with the evaluated
    mesh: build() re-evaluates the mesh (untimed), then times that first call; the
    build time is the first call's.  It returns a hit location (float32), not a
    distance: t = (location - o) . d / |d|^2, so t carries the location's rounding."""

    name = "scene_raycast"

    def __init__(self, scene, threads):
        import bpy

        self.bpy = bpy
        self.target = scene["object"]
        self.scene = bpy.context.scene
        self.positions = scene["mesh"].vertices.ravel()

    def build(self):
        drop_cached_bvh(self.bpy, self.target, self.positions)
        self.depsgraph = self.bpy.context.evaluated_depsgraph_get()
        t0 = time.perf_counter()
        self.scene.ray_cast(self.depsgraph, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
        return time.perf_counter() - t0

    def trace(self, o, d):
        cast = self.scene.ray_cast
        dg = self.depsgraph
        loc = np.full((len(o), 3), np.nan)
        tri = np.full(len(o), -1, np.int64)
        for i, (oi, di) in enumerate(zip(o.tolist(), d.tolist())):
            hit, location, _, index, _, _ = cast(dg, oi, di)
            if hit:
                loc[i] = location
                tri[i] = index
        # it returns the hit location, not a distance: t = (location - o) . d / |d|^2
        d64 = d.astype(np.float64)
        t = ((loc - o) * d64).sum(axis=1) / (d64 * d64).sum(axis=1)
        return np.where(tri >= 0, t, np.inf), tri

    def release(self):
        self.depsgraph = None
        drop_cached_bvh(self.bpy, self.target, self.positions)  # frees the BVH


class GNRaycast:
    """The Geometry Nodes Raycast node over a cloud of loose vertices, one per ray.

    Object Info (Original space; every transform is the identity) feeds Target
    Geometry; Source Position = position, Ray Direction = the point attribute "dir",
    Ray Length = 1e30; Hit Distance, Is Hit and the hit corner (the Index field with
    Interpolation 'Nearest' samples the target's face corners) are stored as point
    attributes.  bpy 5.0 cannot resize a PointCloud from Python, hence a mesh of loose
    vertices (the node treats both as points).  Hit Distance is in world units along
    the normalised direction: t = distance / |d|; triangle = corner // 3 because the
    target's polygon i owns corners 3i..3i+2."""

    name = "gn_raycast"

    def __init__(self, scene, threads):
        import bpy

        self.bpy = bpy
        self.target = scene["object"]
        self.positions = scene["mesh"].vertices.ravel()
        rays_mesh = bpy.data.meshes.new("bench_rays")
        self.obj = bpy.data.objects.new("bench_rays", rays_mesh)
        bpy.context.scene.collection.objects.link(self.obj)
        mod = self.obj.modifiers.new("Raycast", "NODES")
        mod.node_group = self._node_group()
        self.count = -1
        self.release()

    def _node_group(self):
        bpy = self.bpy
        ng = bpy.data.node_groups.new("bench_raycast", "GeometryNodeTree")
        ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        nodes, link = ng.nodes, ng.links.new
        group_in = nodes.new("NodeGroupInput")
        group_out = nodes.new("NodeGroupOutput")
        info = nodes.new("GeometryNodeObjectInfo")
        info.transform_space = "ORIGINAL"
        self.info = info
        direction = nodes.new("GeometryNodeInputNamedAttribute")
        direction.data_type = "FLOAT_VECTOR"
        direction.inputs["Name"].default_value = "dir"
        ray = nodes.new("GeometryNodeRaycast")
        ray.data_type = "INT"
        ray.inputs["Interpolation"].default_value = "Nearest"
        ray.inputs["Ray Length"].default_value = 1e30
        link(info.outputs["Geometry"], ray.inputs["Target Geometry"])
        link(nodes.new("GeometryNodeInputPosition").outputs[0], ray.inputs["Source Position"])
        link(direction.outputs["Attribute"], ray.inputs["Ray Direction"])
        link(nodes.new("GeometryNodeInputIndex").outputs[0], ray.inputs["Attribute"])
        geometry = group_in.outputs[0]
        for name, output, data_type in (
            ("hit_dist", "Hit Distance", "FLOAT"),
            ("is_hit", "Is Hit", "BOOLEAN"),
            ("hit_corner", "Attribute", "INT"),
        ):
            store = nodes.new("GeometryNodeStoreNamedAttribute")
            store.data_type = data_type
            store.domain = "POINT"
            store.inputs["Name"].default_value = name
            link(geometry, store.inputs["Geometry"])
            link(ray.outputs[output], store.inputs["Value"])
            geometry = store.outputs[0]
        link(geometry, group_out.inputs[0])
        return ng

    def _set_rays(self, o, d):
        me = self.obj.data
        if len(o) != self.count:
            me.clear_geometry()
            me.vertices.add(len(o))
            if "dir" not in me.attributes:
                me.attributes.new("dir", "FLOAT_VECTOR", "POINT")
            self.count = len(o)
        me.vertices.foreach_set("co", np.ascontiguousarray(o, np.float32).ravel())
        me.attributes["dir"].data.foreach_set("vector", np.ascontiguousarray(d, np.float32).ravel())
        me.update()

    def _evaluate(self):
        depsgraph = self.bpy.context.evaluated_depsgraph_get()
        ev = self.obj.evaluated_get(depsgraph).data
        n = len(ev.vertices)
        dist = np.empty(n, np.float32)
        ev.attributes["hit_dist"].data.foreach_get("value", dist)
        hit = np.empty(n, bool)
        ev.attributes["is_hit"].data.foreach_get("value", hit)
        corner = np.empty(n, np.int32)
        ev.attributes["hit_corner"].data.foreach_get("value", corner)
        return dist, hit, corner

    def build(self):
        """The first evaluation with the target (one ray): it builds the target's BVH.
        ``release`` left the target freshly evaluated without a BVH and the Object Info
        node empty."""
        self._set_rays(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32))
        self.bpy.context.evaluated_depsgraph_get()
        t0 = time.perf_counter()
        self.info.inputs["Object"].default_value = self.target
        self._evaluate()
        return time.perf_counter() - t0

    def trace(self, o, d):
        self._set_rays(o, d)
        dist, hit, corner = self._evaluate()
        t = np.where(hit, dist.astype(np.float64) / np.linalg.norm(d.astype(np.float64), axis=1), np.inf)
        return t, np.where(hit, corner // 3, -1)

    def release(self):
        """Drop the rays, unhook the target and re-evaluate it: its cached BVH is freed."""
        self._set_rays(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32))
        self.info.inputs["Object"].default_value = None
        drop_cached_bvh(self.bpy, self.target, self.positions)

    def close(self):
        """Remove the ray object and its node group, so later peers' evaluations skip them."""
        bpy = self.bpy
        ng = self.obj.modifiers["Raycast"].node_group
        me = self.obj.data
        bpy.data.objects.remove(self.obj)
        bpy.data.meshes.remove(me)
        bpy.data.node_groups.remove(ng)


class TrimeshRays:
    """trimesh.ray.ray_triangle.RayMeshIntersector (numpy, candidates from an rtree).

    build() constructs the Trimesh (process=False) and its rtree of triangle bounds;
    intersects_id(multiple_hits=False, return_locations=True) gives hit locations for
    the rays that hit: t = (location - o) . d / |d|^2.  It finds candidates with one
    rtree query per ray and tests all of them at once, so memory grows with rays x
    candidates: the rays go in chunks of ``chunk``."""

    name = "trimesh"

    def __init__(self, scene, threads):
        try:
            import trimesh
            from trimesh.ray.ray_triangle import RayMeshIntersector

            import rtree  # noqa: F401  (trimesh's ray module needs it)
        except ImportError as e:
            raise Unavailable(f"{e}") from None
        self.trimesh = trimesh
        self.cls = RayMeshIntersector
        self.mesh = scene["mesh"]

    def build(self):
        t0 = time.perf_counter()
        tm = self.trimesh.Trimesh(self.mesh.vertices, self.mesh.triangles, process=False)
        self.ray = self.cls(tm)
        tm.triangles_tree  # noqa: B018  (built lazily: force it here)
        return time.perf_counter() - t0

    #: rays per intersects_id call: its memory grows with rays x candidate triangles
    chunk = 200

    def trace(self, o, d):
        o64 = o.astype(np.float64)
        d64 = d.astype(np.float64)
        t = np.full(len(o), np.inf)
        idx = np.full(len(o), -1, np.int64)
        for s in range(0, len(o), self.chunk):
            oc, dc = o64[s : s + self.chunk], d64[s : s + self.chunk]
            tri, ray, loc = self.ray.intersects_id(oc, dc, multiple_hits=False, return_locations=True)
            t[s + ray] = ((loc - oc[ray]) * dc[ray]).sum(axis=1) / (dc[ray] ** 2).sum(axis=1)
            idx[s + ray] = tri
        return t, idx

    def release(self):
        self.ray = None


PEER_CLASSES = {"bvhtree": BVHTreeLoop, "scene_raycast": SceneRayCast, "gn_raycast": GNRaycast, "trimesh": TrimeshRays}


# -- running ------------------------------------------------------------------------------
def parse_size(text):
    text = text.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(text[-1:], 1)
    return int(float(text[:-1] if mult > 1 else text) * mult)


def make_scene(size, args):
    level = monkey_level(size)
    v, t = monkey_triangles(level)
    mesh = core.TriangleMesh(v, t)
    obj = triangle_object("bench_target", mesh.vertices, mesh.triangles)
    cam = camera_setup(mesh, args.rays)
    rays = {"random": uniform_rays(mesh, args.rays, args.seed), "camera": camera_rays(**cam)}
    name = f"monkey-L{level}"
    return dict(name=name, level=level, mesh=mesh, object=obj, rays=rays, camera=cam)


def reference_hits(scene, args, ref):
    out = {}
    for kind, (o, d) in scene["rays"].items():
        idx = strided(len(o), args.ref_rays)
        t0 = time.perf_counter()
        hits = ref.reference_trace(scene["mesh"].tri_vertices, o[idx], d[idx])
        out[kind] = dict(idx=idx, hits=hits, seconds=time.perf_counter() - t0)
    return out


def errors(t, tri, ref):
    """Disagreement and relative t error of (t, tri) against RefHits ``ref``."""
    hit = np.isfinite(t) & (tri >= 0)
    flips = hit != ref.hit
    both = hit & ref.hit
    other = both & (tri != ref.triangle)
    bad = flips | other
    rel = np.abs(t[both] - ref.t[both]) / ref.t[both]
    return dict(
        checked=int(len(t)),
        disagree=int(bad.sum()),
        flips=int(flips.sum()),
        other_triangle=int(other.sum()),
        non_grazing=int((bad & ~ref.ambiguous).sum()),
        max_rel_t_err=float(rel.max()) if rel.size else None,
        median_rel_t_err=float(np.median(rel)) if rel.size else None,
    )


def capped(m, cap, ref_idx):
    """The rays a tracer with at most ``cap`` rays traces: all, or an evenly strided
    subset, taken from the reference rays when they are enough (so all are checked)."""
    if not cap or cap >= m:
        return np.arange(m)
    if cap <= len(ref_idx):
        return ref_idx[strided(len(ref_idx), cap)]
    return strided(m, cap)


def ref_subset(ref, pos):
    return type(ref)(*(getattr(ref, f)[pos] for f in ("t", "triangle", "u", "v", "ambiguous")))


def tracer_cap(name, args):
    return {"brute": args.brute_rays, "trimesh": args.trimesh_rays}.get(name)


def run_tracer(tracer, scene, refs, args):
    """Timed builds and traces (medians), errors, then an untimed memory pass per batch."""
    cap = tracer_cap(tracer.name, args)
    builds = []
    for _ in range(args.repeats):
        tracer.release()
        gc.collect()
        builds.append(tracer.build())
    stats = tracer.stats() if hasattr(tracer, "stats") else None
    results = {}
    for kind, (o, d) in scene["rays"].items():
        ref = refs[kind]
        sel = capped(len(o), cap, ref["idx"])
        os_, ds = o[sel], d[sel]
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            t, tri = tracer.trace(os_, ds)
            times.append(time.perf_counter() - t0)
        _, in_sel, in_ref = np.intersect1d(sel, ref["idx"], return_indices=True)
        if in_sel.size == min(len(sel), len(ref["idx"])):  # check the rays both have
            check = errors(t[in_sel], tri[in_sel], ref_subset(ref["hits"], in_ref))
        else:  # a cap above --ref-rays: trace the reference rays once more, untimed
            check = errors(*tracer.trace(o[ref["idx"]], d[ref["idx"]]), ref["hits"])
        med = statistics.median(times)
        results[kind] = dict(
            rays=int(len(sel)),
            trace_s=med,
            trace_runs_s=times,
            rays_per_s=len(sel) / med if med > 0 else float("inf"),
            hit_fraction=float(np.mean(np.isfinite(t) & (tri >= 0))),
            **check,
        )
    tracer.release()
    for kind, (o, d) in scene["rays"].items():
        sel = capped(len(o), cap, refs[kind]["idx"])
        os_, ds = o[sel], d[sel]
        with PeakMemory() as pm:
            tracer.build()
            tracer.trace(os_, ds)
            tracer.release()
        results[kind].update(peak_rss_bytes=pm.rss, peak_traced_bytes=pm.traced)
    return dict(build_s=statistics.median(builds), build_runs_s=builds, stats=stats, by_rays=results)


def make_tracer(name, scene, args):
    n = scene["mesh"].triangle_count
    if n > MAX_TRIANGLES.get(name, n):
        raise Unavailable(SKIP_REASON[name])
    if name in PROJECT_KINDS:
        return ProjectTracer(name, scene, args.threads)
    try:
        return PEER_CLASSES[name](scene, args.threads)
    except ImportError as e:
        raise Unavailable(str(e)) from None


# -- printing -----------------------------------------------------------------------------
def _f(x, spec):
    return "n/a" if x is None else format(x, spec)


def _mib(b):
    return "n/a" if b is None else f"{b / 2**20:.1f}"


def _ratio(a, b):
    return "n/a" if not a or not b else f"{a / b:#.3g}x"


def print_tables(scene, rows, refs):
    for kind in scene["rays"]:
        o = scene["rays"][kind][0]
        desc = (
            "random: origins uniform in the box padded by 1%, directions uniform on the sphere"
            if kind == "random"
            else "camera: pinhole {width}x{height}, fov {fov_deg:g} deg, looking at the monkey".format(**scene["camera"])
        )
        by = {name: r["by_rays"][kind] for name, r in rows.items() if isinstance(r, dict)}
        base = by.get("bvhtree", {}).get("rays_per_s")
        emb = by.get("embree", {}).get("rays_per_s")
        print(f"\n### {scene['name']}, {desc}; M = {len(o):,}\n")
        print("| tracer | M | build s | Mrays/s | x BVHTree | x Embree | hit % | RSS MiB | traced MiB |")
        print("|---|--:|--:|--:|--:|--:|--:|--:|--:|")
        for name, r in rows.items():
            if not isinstance(r, dict):
                print(f"| {name} | n/a: {r} | | | | | | | |")
                continue
            k = r["by_rays"][kind]
            rps = k["rays_per_s"]
            print(
                f"| {name} | {k['rays']:,} | {r['build_s']:#.3g} | {rps / 1e6:#.3g} | {_ratio(rps, base)} | {_ratio(rps, emb)}"
                f" | {100 * k['hit_fraction']:.1f} | {_mib(k['peak_rss_bytes'])} | {_mib(k['peak_traced_bytes'])} |"
            )
        ref = refs[kind]
        print(
            f"\nSpeed against error, {kind} rays: float64 Moller-Trumbore reference (tests/reference.py) on "
            f"{len(ref['idx']):,} of the {len(o):,} rays (evenly strided), computed in {ref['seconds']:.1f} s; "
            f"{int(ref['hits'].ambiguous.sum())} of them graze an edge/vertex or tie (ambiguous).\n"
        )
        print("| tracer | Mrays/s | checked | disagree % | flips | other tri | non-grazing | max rel t err | median rel t err |")
        print("|---|--:|--:|--:|--:|--:|--:|--:|--:|")
        for name, r in rows.items():
            if not isinstance(r, dict):
                continue
            k = r["by_rays"][kind]
            print(
                f"| {name} | {k['rays_per_s'] / 1e6:#.3g} | {k['checked']:,} | {100 * k['disagree'] / max(1, k['checked']):.2f}"
                f" | {k['flips']} | {k['other_triangle']} | {k['non_grazing']} | {_f(k['max_rel_t_err'], '.2e')}"
                f" | {_f(k['median_rel_t_err'], '.2e')} |"
            )


def print_goals(scene, rows):
    r = {name: v for name, v in rows.items() if isinstance(v, dict)}

    def rps(name):
        return r[name]["by_rays"]["random"]["rays_per_s"] if name in r else None

    def build(name):
        return r[name]["build_s"] if name in r else None

    n = scene["mesh"].triangle_count
    m = len(scene["rays"]["random"][0])
    where = "" if n > 500_000 and m >= 100_000 else " (NOT the goal configuration of 1M triangles, 100k rays)"
    print(f"\n### Goals, {scene['name']}, {m:,} random rays{where}\n")
    print("| ratio | measured | goal |")
    print("|---|--:|---|")
    print(f"| BVH rays/s / BVHTree loop rays/s | {_ratio(rps('bvh'), rps('bvhtree'))} | >= 1.0x (stretch 2x) |")
    print(f"| BVH rays/s / Embree rays/s | {_ratio(rps('bvh'), rps('embree'))} | reported |")
    print(f"| grid rays/s / BVH rays/s | {_ratio(rps('grid'), rps('bvh'))} | reported |")
    print(f"| grid build / BVH build | {_ratio(build('grid'), build('bvh'))} | <= 0.5x |")


def memory_check(scene, args):
    """Trace ``--memory-rays`` random rays with grid and BVH; peak memory over the mesh's own."""
    mesh = scene["mesh"]
    m = args.memory_rays
    o = np.empty((m, 3), np.float32)
    d = np.empty((m, 3), np.float32)
    rng = np.random.default_rng(args.seed + 1)
    step = 1 << 20
    for s in range(0, m, step):  # in chunks: the generator's float64 temporaries stay small
        o[s : s + step], d[s : s + step] = uniform_rays(mesh, min(step, m - s), rng)
    mesh_bytes = mesh.vertices.nbytes + mesh.triangles.nbytes + mesh.tri_vertices.nbytes + mesh.valid.nbytes
    rays_bytes = o.nbytes + d.nbytes
    print(f"\n### Memory check, {scene['name']}, {m:,} random rays\n")
    print(
        f"Baseline: the mesh ({_mib(mesh_bytes)} MiB: vertices, triangles, corners, validity) and the rays "
        f"({_mib(rays_bytes)} MiB) already resident.  Extra = structure + tracing + the Hits output "
        f"({_mib(16 * m)} MiB).  Goal: extra RSS <= 1024 MiB.  One run each, timed with tracemalloc on.\n"
    )
    print("| structure | build s | trace s | Mrays/s | extra RSS MiB | extra traced MiB | goal |")
    print("|---|--:|--:|--:|--:|--:|---|")
    out = []
    for kind in ("grid", "bvh"):
        try:
            tracer = ProjectTracer(kind, scene, args.threads)
        except Unavailable as e:
            print(f"| {kind} | n/a: {e} | | | | | |")
            continue
        with PeakMemory() as pm:
            b = tracer.build()
            t0 = time.perf_counter()
            tracer.trace(o, d)
            ts = time.perf_counter() - t0
            tracer.release()
        ok = pm.rss is not None and pm.rss <= 2**30
        print(f"| {kind} | {b:.3f} | {ts:.2f} | {m / ts / 1e6:.3f} | {_mib(pm.rss)} | {_mib(pm.traced)} | {'met' if ok else 'NOT met'} |")
        out.append(dict(kind=kind, rays=m, build_s=b, trace_s=ts, peak_rss_bytes=pm.rss, peak_traced_bytes=pm.traced))
    return out


def _json_value(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return str(x)


def versions():
    out = {"python": platform.python_version(), "numpy": np.__version__}
    for mod in ("bpy", "embreex", "trimesh", "rtree"):
        try:
            m = __import__(mod)
            out[mod] = getattr(m.app, "version_string", None) if mod == "bpy" else getattr(m, "__version__", "?")
        except ImportError:
            out[mod] = None
    return out


# -- the engine table (--engines) ---------------------------------------------------------
#: the scenes of the engine table: name -> what it is
ENGINE_SCENES = {
    "icospheres": "3 geodesic spheres (frequency 128, 327,680 triangles each), radius 1, centres 2.5 apart on x",
    "suzanne": "Suzanne, Subdivision Surface level 5, evaluated by Blender",
    "suzanne10m": "Suzanne at level 5 instanced 10x, rows of 5, 3 units apart (the --scale 10m scene)",
}
OPEN3D_PYTHON = ROOT / ".venv-open3d" / "bin" / "python"
#: the rows of the engine table (keys for --tracers)
ENGINE_TRACERS = ("raw", "raw1", "embree", "embree1", "embree_fast", "bvh", "bvh1", "grid", "grid1", "bvhtree", "open3d")


def icospheres_mesh():
    from hybrid_raycast.core.scenes import geodesic_sphere_arrays

    v, t = geodesic_sphere_arrays(128)
    vertices = np.concatenate([v + (x, 0.0, 0.0) for x in (-2.5, 0.0, 2.5)])
    triangles = np.concatenate([t + i * len(v) for i in range(3)])
    return core.TriangleMesh(vertices, triangles)


def engine_scene(name, args):
    if name == "icospheres":
        mesh = icospheres_mesh()
    elif name == "suzanne10m":
        mesh = instanced_monkey(10)
    else:
        mesh = core.TriangleMesh(*monkey_triangles(5))
    cam = camera_setup(mesh, args.rays)
    rays = {"random": uniform_rays(mesh, args.rays, args.seed), "camera": camera_rays(**cam)}
    return dict(name=name, what=ENGINE_SCENES[name], mesh=mesh, rays=rays, camera=cam)


class RawEmbreex:
    """embreex as a user would call it: EmbreeScene(robust=True), the indexed
    TriangleMesh(scene, vertices, triangles), a one-ray run to commit; trace =
    ``scene.run(o, d, output=1)`` over 65,536-ray chunks on a thread pool (embreex's ray
    loop releases the GIL).  Build is split into geometry (embreex copying the arrays
    into Embree's buffers) and commit (Embree's BVH build)."""

    chunk = 1 << 16

    def __init__(self, mesh, threads):
        from embreex import mesh_construction, rtcore_scene

        self.rtcore_scene, self.mesh_construction = rtcore_scene, mesh_construction
        self.name = f"raw embreex, {threads}-thread pool over 64k-ray chunks"
        self.mesh, self.threads, self.scene = mesh, threads, None

    def build(self):
        self.scene = None
        gc.collect()
        t0 = time.perf_counter()
        scene = self.rtcore_scene.EmbreeScene(robust=True)
        self._geometry = self.mesh_construction.TriangleMesh(scene, self.mesh.vertices, self.mesh.triangles)
        t1 = time.perf_counter()
        one = np.zeros((1, 3), np.float32)
        scene.run(one, one + np.float32(1), dists=np.zeros(1, np.float32))
        t2 = time.perf_counter()
        self.scene, self.split = scene, (t1 - t0, t2 - t1)
        return t2 - t0

    def _run(self, a):
        o, d = self._rays
        r = self.scene.run(o[a : a + self.chunk], d[a : a + self.chunk], output=1)
        return r["primID"]

    def trace(self, o, d):
        from concurrent.futures import ThreadPoolExecutor

        self._rays = (o, d)
        starts = range(0, len(o), self.chunk)
        if self.threads <= 1:
            return np.concatenate([self._run(a) for a in starts]).astype(np.int64)
        with ThreadPoolExecutor(self.threads) as pool:
            return np.concatenate(list(pool.map(self._run, starts))).astype(np.int64)


class EngineProject:
    """``core.build(mesh, kind, **config)``; trace returns the triangle index per ray."""

    def __init__(self, mesh, kind, label, **config):
        if kind == "embree" and not core.embree_available():
            raise Unavailable("embreex is not installed")
        self.name, self.mesh, self.kind, self.config, self.accel = label, mesh, kind, config, None

    def build(self):
        self.accel = None
        gc.collect()
        self.accel = core.build(self.mesh, self.kind, **self.config)
        return self.accel.build_time

    def trace(self, o, d):
        return self.accel.trace(o, d).triangle.astype(np.int64)


class EngineBVHTree(BVHTreeLoop):
    """Blender's BVHTree, a Python loop of ray_cast per ray, on an evenly strided subset."""

    def __init__(self, mesh, cap):
        super().__init__({"mesh": mesh}, None)
        self.cap = cap
        self.name = f"mathutils BVHTree, per-ray loop ({cap:,} rays)"

    def trace(self, o, d):
        return super().trace(o, d)[1]


class Open3DServer:
    """Open3D's RaycastingScene in .venv-open3d (scripts/bench_open3d.py), driven one
    command at a time so its runs interleave with the others'; times are measured inside
    that process (no pipe overhead)."""

    def __init__(self, scene, tmp):
        import subprocess

        if not OPEN3D_PYTHON.exists():
            raise Unavailable("no .venv-open3d (make open3d-venv)")
        mesh = scene["mesh"]
        np.savez(tmp / "mesh.npz", vertices=mesh.vertices, triangles=mesh.triangles.astype(np.uint32))
        paths = []
        for kind, (o, d) in scene["rays"].items():
            paths.append(tmp / f"{kind}.npy")
            np.save(paths[-1], np.concatenate([o, d], axis=1).astype(np.float32))
        self.tmp, self.kinds = tmp, list(scene["rays"])
        self.proc = subprocess.Popen(
            [str(OPEN3D_PYTHON), str(ROOT / "scripts" / "bench_open3d.py"), str(tmp / "mesh.npz"), *map(str, paths),
             "--out", str(tmp)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        hello = self._read()
        if "error" in hello:
            self.close()
            raise Unavailable(hello["error"])
        self.name = f"Open3D {hello['open3d']} RaycastingScene.cast_rays (own venv, numpy {hello['numpy']})"
        self.rss0, self.peak = hello.get("rss_bytes"), None

    def _read(self):
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read()[-300:]
            raise Unavailable(f"bench_open3d.py stopped: {err.strip()}")
        return json.loads(line)

    def _ask(self, cmd):
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        out = self._read()
        if "error" in out:
            raise RuntimeError(out["error"])
        return out

    def build(self):
        return self._ask("build")["s"]

    def trace_named(self, kind):
        return self._ask(f"trace {kind}")["s"]

    def primitives(self):
        self.peak = self._ask("quit").get("peak_rss_bytes")
        self.proc.wait(timeout=60)
        return {k: np.load(self.tmp / f"{k}.prim.npy") for k in self.kinds}

    def close(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def engine_rows(scene, args, tmp):
    """Build every tracer ``--repeats`` times and time its traces ``--repeats`` times,
    round-robin (one run of each tracer per round), so a change in the machine's load
    hits every tracer alike."""
    mesh = scene["mesh"]
    threads = core.accel.default_threads() if args.threads is None else args.threads
    has_embree = core.embree_available()
    makers = [
        ("raw", lambda: RawEmbreex(mesh, threads)),
        ("raw1", lambda: RawEmbreex(mesh, 1)),
        ("embree", lambda: EngineProject(mesh, "embree", f"core.build(mesh, 'embree'), defaults ({core.accel.default_threads()} threads)")),
        ("embree1", lambda: EngineProject(mesh, "embree", "core.build(mesh, 'embree', threads=1)", threads=1)),
        # Open3D's scene has no flags (RaycastingScene.cpp: rtcNewScene, no rtcSetSceneFlags);
        # embreex's and ours are RTC_SCENE_FLAG_ROBUST: this row shows what that costs
        ("embree_fast", lambda: EngineProject(mesh, "embree", "core.build(mesh, 'embree', robust=False)", robust=False)),
        ("bvh", lambda: EngineProject(mesh, "bvh", f"numpy BVH ({threads} threads)", threads=threads)),
        ("bvh1", lambda: EngineProject(mesh, "bvh", "numpy BVH (1 thread)", threads=1)),
        ("grid", lambda: EngineProject(mesh, "grid", f"numpy grid ({threads} threads)", threads=threads)),
        ("grid1", lambda: EngineProject(mesh, "grid", "numpy grid (1 thread)", threads=1)),
        ("bvhtree", lambda: EngineBVHTree(mesh, args.loop_rays)),
        ("open3d", lambda: Open3DServer(scene, tmp)),
    ]
    if args.tracers:
        makers = [(key, make) for key, make in makers if key in args.tracers]
    caps = {"bvh": args.numpy_rays, "bvh1": args.numpy_rays, "grid": args.numpy_rays, "grid1": args.numpy_rays,
            "bvhtree": args.loop_rays}
    tracers, rows = {}, {}
    for key, make in makers:
        if key in ("raw", "raw1", "embree", "embree1", "embree_fast") and not has_embree:
            rows[key] = dict(name=key, error="embreex is not installed")
            continue
        try:
            tracers[key] = make()
        except (Unavailable, ImportError) as e:
            rows[key] = dict(name=key, error=str(e))
    try:
        for key, tr in tracers.items():
            rows[key] = dict(name=tr.name, builds=[], traces={k: [] for k in scene["rays"]}, prim={}, rays={})
        for r in range(args.build_repeats or args.repeats):
            for key, tr in tracers.items():
                # the first round also gives the peak memory
                with PeakMemory(traced=False) if r == 0 and key != "open3d" else contextlib.nullcontext() as pm:
                    rows[key]["builds"].append(tr.build())
                if pm is not None:
                    rows[key]["rss"] = pm.rss
                if key == "raw":
                    rows[key].setdefault("splits", []).append(tr.split)
        for kind, (o, d) in scene["rays"].items():
            for r in range(args.repeats):
                for key, tr in tracers.items():
                    sub = strided(len(o), caps[key]) if key in caps else slice(None)
                    oo, dd = o[sub], d[sub]
                    rows[key]["rays"][kind] = len(oo)
                    if key == "open3d":
                        rows[key]["traces"][kind].append(tr.trace_named(kind))
                        continue
                    with PeakMemory(traced=False) if r == 0 else contextlib.nullcontext() as pm:
                        t0 = time.perf_counter()
                        rows[key]["prim"][kind] = tr.trace(oo, dd)
                        rows[key]["traces"][kind].append(time.perf_counter() - t0)
                    if pm is not None and pm.rss is not None and rows[key].get("rss") is not None:
                        rows[key]["rss"] = max(rows[key]["rss"], pm.rss)
        if "open3d" in tracers:
            o3 = tracers["open3d"]
            rows["open3d"]["prim"] = o3.primitives()
            if o3.peak is not None and o3.rss0 is not None:
                rows["open3d"]["rss"] = max(0, o3.peak - o3.rss0)
    finally:
        if "open3d" in tracers:
            tracers["open3d"].close()
        tracers.clear()
        gc.collect()
    return rows


def print_engine_tables(scene, rows):
    mesh = scene["mesh"]
    med = statistics.median

    def rate(key, kind):
        r = rows.get(key, {})
        return r["rays"][kind] / med(r["traces"][kind]) if "traces" in r else None

    for kind, (o, d) in scene["rays"].items():
        m = len(o)
        desc = ("origins uniform in the box padded by 1%, directions uniform on the sphere" if kind == "random" else
                "pinhole camera {width}x{height}, fov {fov_deg:g} deg, looking at the scene's centre".format(**scene["camera"]))
        print(f"\n### {scene['name']} ({scene['what']}): N = {mesh.triangle_count:,} triangles; {kind} rays, "
              f"M = {m:,} ({desc})\n")
        print("| tracer | rays traced | build s | Mrays/s | x raw embreex | x Open3D | hit % | same triangle as raw embreex % "
              "| extra RSS MiB |")
        print("|---|--:|--:|--:|--:|--:|--:|--:|--:|")
        ref = rows.get("raw", {}).get("prim", {}).get(kind)
        for key, r in rows.items():
            if "error" in r:
                print(f"| {r['name']} | n/a: {r['error']} | | | | | | | |")
                continue
            prim = r["prim"][kind]
            same = "n/a"
            if ref is not None:
                same = f"{100 * np.mean(prim == (ref if len(prim) == m else ref[strided(m, len(prim))])):.3f}"
            rps = rate(key, kind)
            print(f"| {r['name']} | {r['rays'][kind]:,} | {med(r['builds']):#.3g} | {rps / 1e6:#.3g} | {_ratio(rps, rate('raw', kind))}"
                  f" | {_ratio(rps, rate('open3d', kind))} | {100 * np.mean(prim >= 0):.1f} | {same}"
                  f" | {_mib(r['rss']) if r.get('rss') is not None else 'n/a'} |")
    raw, o3d = rows.get("raw", {}), rows.get("open3d", {})
    if "splits" in raw:
        g = med(s[0] for s in raw["splits"])
        c = med(s[1] for s in raw["splits"])
        print(f"\nraw embreex build = geometry {g:.3f} s (embreex's mesh_construction.TriangleMesh copying the arrays) "
              f"+ commit {c:.3f} s (Embree's BVH build)" + (f"; Open3D's whole build {med(o3d['builds']):.3f} s." if "builds" in o3d else "."))


def engine_goals(scene, rows):
    med = statistics.median

    def rate(key, kind):
        r = rows.get(key, {})
        return r["rays"][kind] / med(r["traces"][kind]) if "traces" in r else None

    def build(key):
        r = rows.get(key, {})
        return med(r["builds"]) if "builds" in r else None

    print(f"\n### Goals, {scene['name']}\n")
    print("| ratio | random rays | camera rays | goal |")
    print("|---|--:|--:|---|")
    kinds = list(scene["rays"])
    lines = [
        ("project Embree (defaults) / raw threaded embreex, trace", ("embree", "raw"), ">= 0.85x"),
        ("project Embree (defaults) / Open3D, trace", ("embree", "open3d"), ">= 0.8x"),
        ("project Embree, 2 threads / 1 thread", ("embree", "embree1"), "reported (>= 1.7x)"),
        ("raw embreex, pool / 1 thread", ("raw", "raw1"), "reported"),
        ("project Embree robust=False (Open3D's scene flags) / Open3D, trace", ("embree_fast", "open3d"), "reported"),
        ("project Embree robust=False / robust (default), trace", ("embree_fast", "embree"), "reported"),
        ("numpy BVH / BVHTree loop", ("bvh", "bvhtree"), ">= 2x random, >= 1x camera"),
        ("numpy BVH, 2 threads / 1 thread", ("bvh", "bvh1"), ">= 1.7x (goal on 1M rays; here --numpy-rays)"),
        ("numpy grid, 2 threads / 1 thread", ("grid", "grid1"), ">= 1.7x (goal on 1M rays; here --numpy-rays)"),
        ("numpy grid / BVHTree loop", ("grid", "bvhtree"), ">= 1x random"),
    ]
    for label, (a, b), goal in lines:
        print(f"| {label} | {' | '.join(_ratio(rate(a, k), rate(b, k)) for k in kinds)} | {goal} |")
    print(f"| project Embree build / raw embreex build | {_ratio(build('embree'), build('raw'))} | | <= 1.3x |")
    print(f"| project Embree build / Open3D build | {_ratio(build('embree'), build('open3d'))} | | reported |")


def engines_main(args):
    import tempfile

    names = [s for s in args.scenes.split(",") if s]
    for s in names:
        if s not in ENGINE_SCENES:
            raise SystemExit(f"unknown scene {s!r}; expected some of {', '.join(ENGINE_SCENES)}")
    print("# Engine table (scripts/bench_trace.py --engines)\n")
    print(f"- date {datetime.datetime.now().isoformat(timespec='seconds')}; {os.cpu_count()} cores; load average at start "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("- " + "; ".join(f"{k} {v}" for k, v in versions().items()))
    print(f"- medians of {args.build_repeats or args.repeats} builds and {args.repeats} traces per tracer, run round-robin (one of each "
          f"tracer per round); M = {args.rays:,} rays per batch (seed {args.seed}); the numpy BVH and grid trace an "
          f"evenly strided subset of {args.numpy_rays:,}, the BVHTree loop one of {args.loop_rays:,}; Open3D runs "
          f"in .venv-open3d (scripts/bench_open3d.py) on the same triangles and rays, driven round by round")
    print("- extra RSS: the larger of the first build's and the first traces' peak resident memory over the RSS just "
          "before each (VmHWM after a reset; a trace's figure comes on top of its resident structure); Open3D: its "
          "process's VmHWM over its RSS with the mesh and rays loaded, so its builds and traces together")
    report = []
    for name in names:
        scene = engine_scene(name, args)
        with tempfile.TemporaryDirectory(prefix="hrc-open3d-") as tmp:
            rows = engine_rows(scene, args, Path(tmp))
        print_engine_tables(scene, rows)
        engine_goals(scene, rows)
        print(f"\nload average at the end of {name}: {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
        sys.stdout.flush()
        report.append(dict(scene=name, triangles=scene["mesh"].triangle_count, load_average_end=os.getloadavg(),
                           rows={k: {f: v for f, v in r.items() if f != "prim"} for k, r in rows.items()}))
    return report


# -- the scale check (--scale) ------------------------------------------------------------
def instanced_monkey(copies):
    """Suzanne at Subdivision Surface level 5 (1,007,616 triangles), ``copies`` times side
    by side in rows of 5, 3 units apart (the monkey is about 2.7 wide): a plain triangle
    soup of copies x 1,007,616 triangles, as instancing extracts it."""
    v, t = monkey_triangles(5)
    vertices = np.empty((copies * len(v), 3), np.float32)
    triangles = np.empty((copies * len(t), 3), np.int32)
    for i in range(copies):
        vertices[i * len(v) : (i + 1) * len(v)] = v + np.array([3.0 * (i % 5), 3.0 * (i // 5), 0.0], np.float32)
        triangles[i * len(t) : (i + 1) * len(t)] = t + i * len(v)
    return core.TriangleMesh(vertices, triangles)


def scale_check(args):
    """Build and trace each structure once on the instanced scene, with its peak memory."""
    copies = max(1, round(parse_size(args.scale) / MONKEY_TRIANGLES[5]))
    t0 = time.perf_counter()
    mesh = instanced_monkey(copies)
    made = time.perf_counter() - t0
    o, d = uniform_rays(mesh, args.rays, args.seed)
    mesh_bytes = mesh.vertices.nbytes + mesh.triangles.nbytes + mesh.tri_vertices.nbytes + mesh.valid.nbytes
    print(f"# Scale check (scripts/bench_trace.py --scale {args.scale})\n")
    print(f"- date {datetime.datetime.now().isoformat(timespec='seconds')}; {os.cpu_count()} cores; load average at start "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}; physical memory "
          f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.1f} GiB")
    print(f"- scene: Suzanne at level 5 instanced {copies}x (rows of 5, 3 units apart): N = {mesh.triangle_count:,} "
          f"triangles, {len(mesh.vertices):,} vertices, made in {made:.1f} s; the TriangleMesh holds {_mib(mesh_bytes)} MiB")
    print(f"- {args.rays:,} random rays (origins uniform in the box padded by 1%, directions uniform), "
          f"{_mib(o.nbytes + d.nbytes)} MiB; one build and one trace per structure, default threads")
    print("- extra RSS: the structure's build + trace peak over the resident mesh and rays (VmHWM after a reset; "
          "tracemalloc stays off, it slows embreex's geometry copy tenfold), the Hits output included\n")
    print("| structure | build s | trace s | Mrays/s | hit % | extra RSS MiB | process peak RSS MiB |")
    print("|---|--:|--:|--:|--:|--:|--:|")
    out = []
    kinds = [k for k in args.kinds.split(",") if k in ("embree", "bvh", "grid")]
    for kind in kinds:
        if kind == "embree" and not core.embree_available():
            print("| embree | n/a: embreex is not installed | | | | | |")
            continue
        with PeakMemory(traced=False) as pm:
            acc = core.build(mesh, kind)
            t0 = time.perf_counter()
            hits = acc.trace(o, d)
            ts = time.perf_counter() - t0
            b = acc.build_time
            del acc
        hit = float(np.mean(hits.hit))
        print(f"| {kind} | {b:.2f} | {ts:.2f} | {len(o) / ts / 1e6:.3f} | {100 * hit:.1f} | {_mib(pm.rss)} | {_mib(pm.hwm)} |")
        sys.stdout.flush()
        out.append(dict(kind=kind, build_s=b, trace_s=ts, hit_fraction=hit, peak_rss_bytes=pm.rss, process_peak_rss_bytes=pm.hwm))
        del hits
        trim()
    print(f"\nprocess peak RSS: VmHWM, reset before each structure (so getrusage's ru_maxrss, which the reset also "
          f"clears, would only see the last one); load average at the end {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return dict(triangles=mesh.triangle_count, copies=copies, rays=len(o), structures=out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10k,100k,1m", help="scene sizes in triangles (nearest subdivision level)")
    ap.add_argument("--rays", type=int, default=None,
                    help="rays per batch, the camera image about this many pixels (default 100,000; --engines: 1,000,000)")
    ap.add_argument("--repeats", type=int, default=5, help="runs per measurement; medians are reported")
    ap.add_argument("--kinds", default=",".join(PROJECT_KINDS), help="project structures to measure")
    ap.add_argument("--peers", default=",".join(PEERS), help="peers to measure ('none' for none)")
    ap.add_argument("--threads", type=int, default=None, help="threads per structure (default: the library's)")
    ap.add_argument("--ref-rays", type=int, default=2000, help="rays checked against the float64 reference")
    ap.add_argument("--brute-rays", type=int, default=2000, help="rays traced by brute force")
    ap.add_argument("--trimesh-rays", type=int, default=1000, help="rays traced by trimesh")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--memory-check", action="store_true", help="also trace --memory-rays random rays with grid and BVH on the largest scene")
    ap.add_argument("--memory-rays", type=int, default=10_000_000)
    ap.add_argument("--json", type=Path, help="write every measurement here")
    ap.add_argument("--engines", action="store_true",
                    help="the engine table instead: raw embreex, the project's Embree, numpy BVH and grid, the BVHTree "
                         "loop and Open3D on --scenes with --rays (default 1M) random and camera rays")
    ap.add_argument("--scenes", default="icospheres,suzanne",
                    help=f"scenes of the engine table, some of {','.join(ENGINE_SCENES)} (suzanne10m: 10M triangles, "
                         f"about 10 minutes with --build-repeats 1 --repeats 3)")
    ap.add_argument("--build-repeats", type=int, default=None, help="builds per tracer in the engine table (default: --repeats)")
    ap.add_argument("--tracers", default=None,
                    help="only these rows of the engine table, e.g. raw,raw1,embree,embree1,open3d (default: all of "
                         + ",".join(ENGINE_TRACERS) + ")")
    ap.add_argument("--loop-rays", type=int, default=200_000, help="rays the BVHTree loop traces in the engine table")
    ap.add_argument("--numpy-rays", type=int, default=262_144, help="rays the numpy BVH and grid trace in the engine table")
    ap.add_argument("--scale", help="instead: build and trace embree, bvh and grid once on Suzanne (level 5) instanced "
                                    "to about this many triangles (e.g. 10m), with peak memory; --rays (default 1M)")
    args = ap.parse_args(argv)
    if args.scale:
        args.rays = args.rays or 1_000_000
        if args.kinds == ",".join(PROJECT_KINDS):
            args.kinds = "embree,bvh,grid"
        report = scale_check(args)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(report, indent=1, default=_json_value))
        return 0
    if args.tracers is not None:
        args.tracers = [t for t in args.tracers.split(",") if t]
        bad = [t for t in args.tracers if t not in ENGINE_TRACERS]
        if bad or not args.engines:
            ap.error(f"--tracers goes with --engines and takes some of {','.join(ENGINE_TRACERS)}; got {bad or args.tracers}")
    if args.engines:
        args.rays = args.rays or 1_000_000
        report = engines_main(args)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(report, indent=1, default=_json_value))
        return 0
    args.rays = args.rays or 100_000
    kinds = [k for k in args.kinds.split(",") if k]
    peers = [p for p in args.peers.split(",") if p and p != "none"]
    for name in kinds + peers:
        if name not in PROJECT_KINDS + PEERS:
            ap.error(f"unknown tracer {name!r}; kinds: {', '.join(PROJECT_KINDS)}; peers: {', '.join(PEERS)}")
    sizes = sorted(parse_size(s) for s in args.sizes.split(",") if s)

    ref = load_reference()
    header = dict(
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        cores=os.cpu_count(),
        load_average=os.getloadavg(),
        machine=platform.machine(),
        versions=versions(),
        repeats=args.repeats,
        rays=args.rays,
        seed=args.seed,
        threads=args.threads,
    )
    print("# Tracing benchmark (scripts/bench_trace.py)\n")
    print(f"- date {header['date']}; {header['cores']} cores ({header['machine']}); load average at start "
          f"{', '.join(f'{x:.2f}' for x in header['load_average'])}")
    print("- " + "; ".join(f"{k} {v}" for k, v in header["versions"].items()))
    print(f"- medians of {args.repeats} runs; rays per batch M = {args.rays:,} (seed {args.seed}); "
          f"threads per structure: {args.threads or 'library default'}")
    print("- ray batches: random (the paper's: origins uniform in the scene box padded by 1%, directions uniform "
          "on the sphere) and camera (pinhole primary rays, row-major from the top row)")
    print(f"- caps: brute force on {args.brute_rays:,} rays and only up to 20k triangles; trimesh on "
          f"{args.trimesh_rays:,} rays and only up to 100k triangles (evenly strided subsets, taken from the "
          f"--ref-rays rays checked against the reference when they are enough)")

    report = dict(header=header, scenes=[])
    scene = rows = None
    for size in sizes:
        scene = make_scene(size, args)
        mesh = scene["mesh"]
        print(f"\n## {scene['name']}: N = {mesh.triangle_count:,} triangles, {len(mesh.vertices):,} vertices "
              f"(Suzanne, Subdivision Surface level {scene['level']}, asked for ~{size:,})")
        refs = reference_hits(scene, args, ref)
        rows = {}
        for name in kinds + peers:
            try:
                tracer = make_tracer(name, scene, args)
            except Unavailable as e:
                rows[name] = str(e)
                continue
            try:
                rows[name] = run_tracer(tracer, scene, refs, args)
            except Exception as e:  # one failing tracer must not lose a long run
                rows[name] = f"failed: {type(e).__name__}: {e}"
            finally:
                if hasattr(tracer, "close"):
                    tracer.close()
            gc.collect()
        print_tables(scene, rows, refs)
        report["scenes"].append(dict(
            name=scene["name"], triangles=mesh.triangle_count, vertices=len(mesh.vertices), level=scene["level"],
            camera={k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in scene["camera"].items()},
            reference={k: dict(rays=len(v["idx"]), ambiguous=int(v["hits"].ambiguous.sum()), seconds=v["seconds"]) for k, v in refs.items()},
            tracers={k: v for k, v in rows.items()},
        ))
    if scene is not None:
        print_goals(scene, rows)
        if args.memory_check:
            report["memory_check"] = memory_check(scene, args)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1, default=_json_value))
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
