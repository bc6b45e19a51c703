"""Benchmark: frames at the speed of the trace (a scene kept across frames) against a ``scene.ray_cast`` loop.

    .venv/bin/python scripts/bench_frames.py [--frames 20] [--loop-frames 2] [--scenario NAME ...]
        [--structure auto] [--small] [--memory]                                  (make bench-frames)

Each scenario starts from an empty file (``read_factory_settings(use_empty=True)``, every
session cleared) and times one call per frame after ``scene.frame_set(f)`` (Blender's own
evaluation, paid by both methods, timed apart): ours is the median over the frames after
the first; the ``scene.ray_cast`` loop (one call per ray in Python, each ray through
mathutils Vectors, as bench_scan.py) casts the same rays on the first ``--loop-frames``
frames, its per-frame median extrapolated to the frame count.  One markdown row per
scenario: triangles, rays per frame, frames, s/frame of ours and of the loop, loop / ours,
and the goal.  After every timed call the session's ``timings`` (a dict of seconds:
'extract', 'bottom_builds', 'top_level', 'trace', ...) is read when the session has one,
and its per-key medians are printed.

Scenarios (``--scenario`` repeatable; default all, gn-instances only with ``--memory``):
- static-sensor: bench_scan's static scene (40 m ground of 8,450 triangles, seven real meshes
  of ../shared/scenes standing still, 166,625 triangles), an Ouster OS1-64 (64 x 2,048 =
  131,072 rays) ``api.scan`` per frame; only the sensor (an Empty) moves.  Also the trace
  alone: ``api.cast`` of the frame's world rays with the structure the scan used, cast twice
  on the scanned frame (nothing changed) and the second timed.  Goal >= 25x, and a frame
  <= 1.3x the trace alone.
- rigid: bench_scan's moving scene (three meshes keyframed in location and rotation), the
  sensor standing still, ``api.scan`` per frame.  Goal >= 15x.
- deforming: a 12 x 12 m grid of 101,250 triangles under a Wave modifier beside a 40 m ground
  of 42,632 triangles and bench_scan's four static meshes (107,859; 251,741 in all), the OS1-64
  standing still, ``api.scan`` per frame.  Goal >= 6x.
- flythrough: bench_scan's static scene, a camera keyframed along a 36 m pass (turning
  slightly), 640 x 360 pinhole primary rays through pixel centres (``core.camera_rays``
  with the camera's angle) per frame, one ``api.cast`` per frame, 64 frames by default.
  Goal >= 20x.
- cast-per-frame: all ten meshes of ../shared/scenes and a second rocker-arm on a ring of
  13 m, on the 8,450-triangle ground (201,893 triangles); 65,536 rays a frame over a
  Fibonacci sphere of directions from a point moving 10 m across the scene, one
  ``api.cast`` per frame.  Two rows: cast-static (only the ray origin moves; goal 20x) and
  cast-rigid (beetle-alt and cow move rigidly, keyframed as in bench_scan; goal 12x).
- repeat-after-frame-set: bench_scan's static scene with nothing animated; per frame a
  1,000-ray ``api.cast`` right after ``scene.frame_set(f)``, then the same cast again on the
  same frame; ratio of the medians (goal <= 1.2x); no loop.
- gn-instances (``--memory``; run first, so the peak RSS before it is this process's
  start-up): a 317 x 317 point grid with a geometry-nodes Instance on Points picking one of
  ten small meshes (a collection excluded from the view layer) per point, 100,489
  instances; the peak RSS growth (``resource.getrusage`` ru_maxrss over the RSS before)
  of the session's extraction and the first 65,536-ray ``api.cast`` (its structures), the
  triangles of the flat soup (``layout.triangle_count``), and the median s per later cast.
``--small``: tiny sizes for a smoke run (fewer rays, smaller grids; the real meshes stay).
Prints the core count and load average before and after; fails on nothing.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
import weakref
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from _package import SHARED_SCENES, load_addon  # noqa: E402

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Vector  # noqa: E402

import bench_scan  # noqa: E402

med = statistics.median
SCENARIOS = ("static-sensor", "rigid", "deforming", "flythrough", "cast-per-frame", "repeat-after-frame-set",
             "gn-instances")
ALIASES = {"cast-static": "cast-per-frame", "cast-rigid": "cast-per-frame"}
#: the meshes of cast-per-frame: every mesh of ../shared/scenes and a second rocker-arm
CAST_MESHES = ("stanford-bunny", "beetle-alt", "rocker-arm", "fandisk", "homer", "teapot", "spot", "cow", "woody",
               "suzanne", "rocker-arm")
CAST_MOVING = {"beetle-alt": ((-15.0, 3.0), (15.0, 3.0)), "cow": ((10.0, -14.0), (-10.0, -2.0))}


# -- helpers ------------------------------------------------------------------------------------

def reset(pkg):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    clear = getattr(pkg.operators.session, "clear", None)
    if clear is not None:
        clear()


def triangles(scene):
    dg = bpy.context.evaluated_depsgraph_get()
    total = 0
    for inst in dg.object_instances:
        ob = inst.object
        if ob.type == "MESH":
            total += len(ob.data.loop_triangles)
    return total


def current_session(pkg):
    """The session the last call used: looked up without a fingerprint when the store is
    reachable (no side effect on the timings), else ``session.get``."""
    ses = pkg.operators.session
    dg = bpy.context.evaluated_depsgraph_get()
    store, key = getattr(ses, "SESSIONS", None), getattr(ses, "session_key", None)
    if store is not None and key is not None:
        s = store.get(key(dg, False))
        if s is not None:
            return s
    return ses.get(dg)


class Recorder:
    """After every timed call: the session's ``timings`` (a copy, or None when it keeps
    none), and whether the session is the one of the previous call (weakly held)."""

    def __init__(self, pkg):
        self.pkg, self.recs, self.new, self._prev = pkg, [], 0, None

    def __call__(self, keep=True):
        s = current_session(self.pkg)
        t = getattr(s, "timings", None)
        rec = {k: float(v) for k, v in t.items() if isinstance(v, (int, float))} if isinstance(t, dict) and t else None
        if keep:
            self.recs.append(rec)
            self.new += self._prev is None or self._prev() is not s
        self._prev = weakref.ref(s)
        return rec

    def sessions_line(self, what="frames after the first"):
        return f"a new session on {self.new} of the {len(self.recs)} {what}"


def breakdown_line(recs, what="per frame, frames after the first"):
    recs = [r for r in recs if r]
    if not recs:
        return "breakdown: not recorded"
    keys = []
    for r in recs:
        keys += [k for k in r if k not in keys]
    parts = [f"{k} {med([r[k] for r in recs if k in r]):.4f}" for k in keys]
    return f"breakdown (median s {what}, {len(recs)} calls): " + ", ".join(parts)


def ray_cast_loop(scene, dg, o, d, distance=None):
    """Seconds of BlAInder's method: one ``scene.ray_cast`` per ray, Vectors made per ray."""
    kw = {} if distance is None or not np.isfinite(distance) else {"distance": float(distance)}
    t0 = time.perf_counter()
    dirs = [Vector(x) for x in d.tolist()]
    if np.ndim(o) == 1:
        ov = Vector(np.asarray(o, np.float64).tolist())
        for v in dirs:
            scene.ray_cast(dg, ov, v, **kw)
    else:
        for ov, v in zip([Vector(x) for x in np.asarray(o).tolist()], dirs):
            scene.ray_cast(dg, ov, v, **kw)
    return time.perf_counter() - t0


def fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1).astype(np.float32)


def fmt_s(x):
    return "n/a" if x is None else f"{x:.4f}"


class Row:
    def __init__(self, name, tris, rays, frames, ours, loop, goal):
        self.name, self.tris, self.rays, self.frames, self.ours, self.loop, self.goal = (
            name, tris, rays, frames, ours, loop, goal)

    def ratio(self):
        return None if self.loop is None or self.ours is None else self.loop / self.ours

    def line(self):
        r = self.ratio()
        return (f"| {self.name} | {self.tris:,} | {self.rays:,} | {self.frames} | {fmt_s(self.ours)} | "
                f"{fmt_s(self.loop)} | {'n/a' if r is None else f'{r:.1f}x'} | {self.goal} |")


def goal_x(row, want):
    r = row.ratio()
    return f">= {want:g}x: {'yes' if r is not None and r >= want else 'no'}"


def loop_summary(name, frames, ours_all, loop_ts, n_loop):
    print(f"  {name}: {frames} frames, ours {sum(ours_all):.2f} s measured (first frame {ours_all[0]:.3f} s, "
          f"min {min(ours_all):.3f}, max {max(ours_all):.3f}); ray_cast loop ~{med(loop_ts) * frames:.1f} s "
          f"extrapolated from {n_loop} frames ({min(loop_ts):.2f}-{max(loop_ts):.2f} s each)")


# -- scans: static-sensor, rigid, deforming ---------------------------------------------------------

def small_sensor(sensor, small):
    sensor.hybrid_raycast_sensor.preset = "OS1_64"
    sensor.hybrid_raycast_sensor.noise_sigma = 0.0
    if small:
        sensor.hybrid_raycast_sensor.azimuth_steps = 128  # 64 x 128 = 8,192 rays


def run_scans(pkg, args, name, scene, sensor, frames, want, trace_alone=False):
    api, scan_mod = pkg.api, pkg.operators.scan
    small_sensor(sensor, args.small)
    scene.frame_set(1)
    tris = triangles(scene)
    model, phys = scan_mod.sensor_model(sensor)
    sub, _ = pkg.core.returns.beam_directions(model.pattern().directions, phys.beam_divergence, phys.beam_samples)
    materials = scan_mod.sensor_settings(sensor, scene).materials
    rays = len(sub)
    t_set, t_scan, t_trace, structures = [], [], [], set()
    rec = Recorder(pkg)
    for f in range(1, frames + 1):
        t0 = time.perf_counter()
        scene.frame_set(f)
        t1 = time.perf_counter()
        r = api.scan(sensor, structure=args.structure)
        t2 = time.perf_counter()
        t_set.append(t1 - t0)
        t_scan.append(t2 - t1)
        structures.add(r.structure)
        rec(keep=f > 1)
        if trace_alone and f > 1:
            dg = bpy.context.evaluated_depsgraph_get()
            pose = scan_mod.sensor_pose(sensor.evaluated_get(dg))
            o, d = pose[:3, 3].astype(np.float32), (sub @ pose[:3, :3].T).astype(np.float32)
            kw = dict(tmax=model.range_max, structure=r.structure, materials=materials)
            api.cast(o, d, **kw)  # nothing changed since the scan: the same session and structure
            ta = time.perf_counter()
            api.cast(o, d, **kw)
            t_trace.append(time.perf_counter() - ta)
    loop_ts = []
    n_loop = min(args.loop_frames, frames)
    for f in range(1, n_loop + 1):
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        pose = scan_mod.sensor_pose(sensor.evaluated_get(dg))
        loop_ts.append(ray_cast_loop(scene, dg, pose[:3, 3], sub @ pose[:3, :3].T, model.range_max))
    ours = med(t_scan[1:]) if frames > 1 else t_scan[0]
    row = Row(name, tris, rays, frames, ours, med(loop_ts), "")
    row.goal = goal_x(row, want)
    print(f"{name}: {tris:,} triangles, {rays:,} rays per frame, structures {', '.join(sorted(structures))}; "
          f"frame_set median {med(t_set) * 1e3:.1f} ms (excluded)")
    if trace_alone:
        if t_trace:
            tr = med(t_trace)
            row.goal += f"; frame / trace {ours / tr:.2f} <= 1.3: {'yes' if ours / tr <= 1.3 else 'no'}"
            print(f"  trace alone (api.cast of the scan's world rays, {r.structure}, second of two casts on the "
                  f"scanned frame): median {tr:.4f} s; frame / trace {ours / tr:.2f}")
        else:
            row.goal += "; frame / trace: n/a (one frame)"
    loop_summary(name, frames, t_scan, loop_ts, n_loop)
    print(f"  {breakdown_line(rec.recs)}; {rec.sessions_line()}")
    return [row]


def static_sensor(pkg, args):
    frames = args.frames or 20
    scene, sensor = bench_scan.build_scene(pkg, frames, static=True)
    return run_scans(pkg, args, "static-sensor", scene, sensor, frames, 25, trace_alone=True)


def rigid(pkg, args):
    frames = args.frames or 20
    scene, sensor = bench_scan.build_scene(pkg, frames, static=False)
    return run_scans(pkg, args, "rigid", scene, sensor, frames, 15)


def deforming(pkg, args):
    frames = args.frames or 20
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, frames
    n_ground, n_wave = (9, 21) if args.small else (146, 225)  # n^2 * 2 triangles
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=n_ground, y_subdivisions=n_ground, size=40.0,
                                    location=(0, 0, -1.0))
    for name, (x, y) in bench_scan.STATIC:
        bench_scan.mesh_object(pkg, name).location = (x, y, 0.0)
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=n_wave, y_subdivisions=n_wave, size=12.0, location=(0, 13.0, -0.5))
    wave = bpy.context.object
    wave.name = "Wave"
    w = wave.modifiers.new("Wave", "WAVE")
    w.height, w.width, w.speed, w.narrowness = 0.4, 1.5, 0.25, 1.5
    sensor = bpy.data.objects.new("Lidar", None)
    sensor.location = (0.0, 0.0, 0.8)
    scene.collection.objects.link(sensor)
    return run_scans(pkg, args, "deforming", scene, sensor, frames, 6)


# -- casts: flythrough, cast-per-frame ------------------------------------------------------------

def run_casts(pkg, args, name, scene, frames, rays_of, want, distance=None):
    """``rays_of(f, dg)`` -> (origins, directions) of frame f (after frame_set); one api.cast per frame."""
    api = pkg.api
    scene.frame_set(1)
    tris = triangles(scene)
    t_set, t_cast, structures = [], [], set()
    rec = Recorder(pkg)
    n = 0
    for f in range(1, frames + 1):
        t0 = time.perf_counter()
        scene.frame_set(f)
        t1 = time.perf_counter()
        o, d = rays_of(f, bpy.context.evaluated_depsgraph_get())  # made outside both timings
        n = len(d)
        t2 = time.perf_counter()
        r = api.cast(o, d, structure=args.structure)
        t_cast.append(time.perf_counter() - t2)
        t_set.append(t1 - t0)
        structures.add(r.structure)
        rec(keep=f > 1)
    loop_ts = []
    n_loop = min(args.loop_frames, frames)
    for f in range(1, n_loop + 1):
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        o, d = rays_of(f, dg)
        loop_ts.append(ray_cast_loop(scene, dg, o[0] if np.ndim(o) == 2 and np.all(o == o[0]) else o, d, distance))
    ours = med(t_cast[1:]) if frames > 1 else t_cast[0]
    row = Row(name, tris, n, frames, ours, med(loop_ts), "")
    row.goal = goal_x(row, want)
    print(f"{name}: {tris:,} triangles, {n:,} rays per frame, structures {', '.join(sorted(structures))}; "
          f"frame_set median {med(t_set) * 1e3:.1f} ms (excluded)")
    loop_summary(name, frames, t_cast, loop_ts, n_loop)
    print(f"  {breakdown_line(rec.recs)}; {rec.sessions_line()}")
    return [row]


def flythrough(pkg, args):
    frames = args.frames or 64
    scene, sensor = bench_scan.build_scene(pkg, frames, static=True)
    sensor.animation_data_clear()
    cam_data = bpy.data.cameras.new("Camera")
    cam = bpy.data.objects.new("Camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    w, h = (64, 36) if args.small else (640, 360)
    scene.render.resolution_x, scene.render.resolution_y = w, h
    cam.location, cam.rotation_euler = (-18.0, -16.0, 1.2), (np.radians(85.0), 0.0, -0.35)
    cam.keyframe_insert("location", frame=1)
    cam.keyframe_insert("rotation_euler", frame=1)
    cam.location, cam.rotation_euler = (18.0, -16.0, 1.2), (np.radians(85.0), 0.0, 0.35)
    cam.keyframe_insert("location", frame=frames)
    cam.keyframe_insert("rotation_euler", frame=frames)
    fov = np.degrees(cam_data.angle)  # sensor fit AUTO: spans the larger image side, as camera_rays

    def rays_of(f, dg):
        m = np.array(cam.evaluated_get(dg).matrix_world, np.float64)
        eye = m[:3, 3]
        return pkg.core.camera_rays(eye, eye - m[:3, 2], m[:3, 1], fov, w, h)

    return run_casts(pkg, args, "flythrough", scene, frames, rays_of, 20)


def cast_scene(pkg, frames, moving):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, frames
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=65, y_subdivisions=65, size=40.0, location=(0, 0, -1.0))
    for i, name in enumerate(CAST_MESHES):
        a = 2 * np.pi * i / len(CAST_MESHES)
        ob = bench_scan.mesh_object(pkg, name)
        ob.location = (13.0 * np.cos(a), 13.0 * np.sin(a), 0.0)
        if moving and name in CAST_MOVING:
            (ax, ay), (bx, by) = CAST_MOVING[name]
            ob.location = (ax, ay, 0.0)
            ob.keyframe_insert("location", frame=1)
            ob.location = (bx, by, 0.0)
            ob.keyframe_insert("location", frame=frames)
            ob.rotation_euler.z = 0.0
            ob.keyframe_insert("rotation_euler", frame=1)
            ob.rotation_euler.z = 3.0
            ob.keyframe_insert("rotation_euler", frame=frames)
    scene.frame_set(1)
    return scene


def cast_per_frame(pkg, args, variants=("cast-static", "cast-rigid")):
    frames = args.frames or 20
    d = fibonacci_sphere(4096 if args.small else 65536)
    rows = []
    for name in variants:
        reset(pkg)
        scene = cast_scene(pkg, frames, moving=name == "cast-rigid")

        def rays_of(f, dg):
            s = (f - 1) / max(1, frames - 1)
            return np.array([-5.0 + 10.0 * s, -3.0 + 6.0 * s, 0.8], np.float32), d

        rows += run_casts(pkg, args, name, scene, frames, rays_of, 20 if name == "cast-static" else 12)
    return rows


# -- repeat-after-frame-set ------------------------------------------------------------------

def repeat_after_frame_set(pkg, args):
    frames = args.frames or 20
    api = pkg.api
    scene, sensor = bench_scan.build_scene(pkg, frames + 1, static=True)
    sensor.animation_data_clear()  # nothing in the scene is animated
    tris = triangles(scene)
    o = np.array([0.0, 0.0, 0.8], np.float32)
    d = fibonacci_sphere(1000)
    for _ in range(3):  # the first cast plans, the next settle
        api.cast(o, d, structure=args.structure)
    after, same = [], []
    rec = Recorder(pkg)
    rec(keep=False)
    for f in range(1, frames + 1):
        scene.frame_set(f + 1)  # a new frame every time (the scene was built at frame 1)
        t0 = time.perf_counter()
        api.cast(o, d, structure=args.structure)
        after.append(time.perf_counter() - t0)
        rec(keep=f > 1)  # a dict look-up: no fingerprint, nothing the next cast could reuse
        t0 = time.perf_counter()
        api.cast(o, d, structure=args.structure)
        same.append(time.perf_counter() - t0)
    a, s = (med(after[1:]), med(same[1:])) if frames > 1 else (after[0], same[0])
    ratio = a / s
    print(f"repeat-after-frame-set: {tris:,} triangles, 1,000 rays; api.cast right after frame_set median "
          f"{a * 1e3:.3f} ms, the same cast again on that frame {s * 1e3:.3f} ms: {ratio:.2f}x")
    print(f"  {breakdown_line(rec.recs, 'per cast after frame_set, frames after the first')}; "
          f"{rec.sessions_line('frames after the first (after frame_set)')}")
    return [Row("repeat-after-frame-set", tris, 1000, frames, a, None,
                f"after frame_set / same frame {ratio:.2f} <= 1.2: {'yes' if ratio <= 1.2 else 'no'}")]


# -- gn-instances ------------------------------------------------------------------------------

def current_rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def gn_scene(n_side):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    parts = bpy.data.collections.new("Parts")
    scene.collection.children.link(parts)
    makers = (
        lambda: bpy.ops.mesh.primitive_cube_add(size=0.2),
        lambda: bpy.ops.mesh.primitive_uv_sphere_add(radius=0.1, segments=12, ring_count=6),
        lambda: bpy.ops.mesh.primitive_ico_sphere_add(radius=0.1, subdivisions=1),
        lambda: bpy.ops.mesh.primitive_cone_add(radius1=0.1, depth=0.2, vertices=12),
        lambda: bpy.ops.mesh.primitive_cylinder_add(radius=0.1, depth=0.2, vertices=12),
        lambda: bpy.ops.mesh.primitive_cylinder_add(radius=0.1, depth=0.2, vertices=6),
        lambda: bpy.ops.mesh.primitive_torus_add(major_radius=0.1, minor_radius=0.03, major_segments=12,
                                                 minor_segments=6),
        lambda: bpy.ops.mesh.primitive_plane_add(size=0.2),
        lambda: bpy.ops.mesh.primitive_grid_add(x_subdivisions=4, y_subdivisions=4, size=0.2),
        lambda: bpy.ops.mesh.primitive_circle_add(radius=0.1, vertices=8, fill_type="NGON"),
    )
    for make in makers:
        make()
        ob = bpy.context.object
        scene.collection.objects.unlink(ob)
        parts.objects.link(ob)
    bpy.context.view_layer.layer_collection.children["Parts"].exclude = True  # only their instances show
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=n_side - 1, y_subdivisions=n_side - 1, size=100)
    host = bpy.context.object
    tree = bpy.data.node_groups.new("inst", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gi, go = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
    iop, info = tree.nodes.new("GeometryNodeInstanceOnPoints"), tree.nodes.new("GeometryNodeCollectionInfo")
    rnd = tree.nodes.new("FunctionNodeRandomValue")
    rnd.data_type = "INT"
    by_id = {(k, x.identifier): x for k, xs in (("in", rnd.inputs), ("out", rnd.outputs)) for x in xs}
    by_id["in", "Min_002"].default_value, by_id["in", "Max_002"].default_value = 0, 9  # the INT sockets
    info.inputs["Collection"].default_value = parts
    info.inputs["Separate Children"].default_value = True
    info.inputs["Reset Children"].default_value = True
    iop.inputs["Pick Instance"].default_value = True
    tree.links.new(gi.outputs[0], iop.inputs["Points"])
    tree.links.new(info.outputs[0], iop.inputs["Instance"])
    tree.links.new(by_id["out", "Value_002"], iop.inputs["Instance Index"])
    tree.links.new(iop.outputs[0], go.inputs[0])
    host.modifiers.new("GN", "NODES").node_group = tree
    bpy.context.view_layer.update()
    return scene


def gn_instances(pkg, args):
    api, session = pkg.api, pkg.operators.session
    if args.flat:  # heavy instancing no longer counts: the first call traces the flat soup
        session.INSTANCED_FROM = float("inf")
    m = 4096 if args.small else 65536
    gn_scene(32 if args.small else 317)
    dg = bpy.context.evaluated_depsgraph_get()
    n_inst = sum(1 for i in dg.object_instances if i.is_instance)
    rng = np.random.default_rng(0)
    half = 16.0 if args.small else 50.0
    o = np.stack([rng.uniform(-half, half, m), rng.uniform(-half, half, m), np.full(m, 5.0)], axis=1).astype(np.float32)
    d = np.stack([rng.uniform(-0.3, 0.3, m), rng.uniform(-0.3, 0.3, m), -np.ones(m)], axis=1).astype(np.float32)
    base, peak0 = current_rss(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    t0 = time.perf_counter()
    s = session.get(dg)
    t1 = time.perf_counter()
    r = api.cast(o, d, structure=args.structure)
    t2 = time.perf_counter()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    rec = Recorder(pkg)
    rec0 = rec(keep=False)
    soup = s.layout.triangle_count
    ts = []
    for _ in range(max(3, min(args.frames or 5, 7))):
        ta = time.perf_counter()
        api.cast(o, d, structure=args.structure)
        ts.append(time.perf_counter() - ta)
        rec()
    mib = 1 << 20
    masked = " (the peak before was higher: run --scenario gn-instances alone)" if peak <= peak0 else ""
    print(f"gn-instances{' (flat)' if args.flat else ''}: {n_inst:,} geometry-nodes instances of 10 meshes, {soup:,} triangles in the flat soup; "
          f"extraction {t1 - t0:.3f} s, first cast (plan, structures) {t2 - t1:.3f} s ({r.structure}); "
          f"RSS before {base / mib:.0f} MiB, peak before {peak0 / mib:.0f} MiB, peak after {peak / mib:.0f} MiB, "
          f"growth {(peak - base) / mib:.0f} MiB{masked}; later casts median {med(ts):.4f} s")
    print("  first cast " + breakdown_line([rec0], "first cast"))
    print(f"  {breakdown_line(rec.recs, 'per later cast')}; {rec.sessions_line('later casts')}")
    return [Row("gn-instances", soup, m, len(ts), med(ts), None,
                f"n/a (peak RSS growth {(peak - base) / mib:.0f} MiB{', masked' if masked else ''})")]


RUNNERS = {"static-sensor": static_sensor, "rigid": rigid, "deforming": deforming, "flythrough": flythrough,
           "cast-per-frame": cast_per_frame, "repeat-after-frame-set": repeat_after_frame_set,
           "gn-instances": gn_instances}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=None, help="frames per scenario (default 20; 64 for flythrough)")
    ap.add_argument("--loop-frames", type=int, default=2, help="frames the scene.ray_cast loop is timed on")
    ap.add_argument("--scenario", action="append", choices=SCENARIOS + tuple(ALIASES),
                    help="repeatable; default all (gn-instances only with --memory)")
    ap.add_argument("--structure", default="auto", choices=("auto", "grid", "bvh", "embree"))
    ap.add_argument("--small", action="store_true", help="tiny sizes, for a smoke run")
    ap.add_argument("--memory", action="store_true", help="also gn-instances: peak RSS of a 100k-instance session")
    ap.add_argument("--flat", action="store_true",
                    help="gn-instances as a flat soup (no two levels from the first call), to compare memory and "
                         "speed; run it in its own process")
    args = ap.parse_args(argv)
    if args.frames is not None and args.frames < 1 or args.loop_frames < 1:
        ap.error("--frames and --loop-frames must be at least 1")
    if not SHARED_SCENES.is_dir():
        print(f"needs the meshes in {SHARED_SCENES}", file=sys.stderr)
        return 2
    named = args.scenario or [s for s in SCENARIOS if s != "gn-instances" or args.memory]
    if "gn-instances" in named and not args.memory:
        ap.error("gn-instances needs --memory")
    cast_variants = [s for s in named if s in ALIASES]
    if "cast-per-frame" in named:
        cast_variants = ["cast-static", "cast-rigid"]
    wanted = {ALIASES.get(s, s) for s in named}
    order = [s for s in SCENARIOS if s in wanted]
    if "gn-instances" in order:  # first: the peak RSS before it is the process's start-up
        order.remove("gn-instances")
        order.insert(0, "gn-instances")
    pkg = load_addon()
    pkg.register()
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at start; structure {args.structure!r}; "
          f"ours: median s per frame over the frames after the first (frame_set excluded); the ray_cast loop: "
          f"median of {args.loop_frames} frames{'; --small' if args.small else ''}")
    rows = {}
    for name in order:
        reset(pkg)
        t0 = time.perf_counter()
        if name == "cast-per-frame":
            out = cast_per_frame(pkg, args, tuple(cast_variants))
        else:
            out = RUNNERS[name](pkg, args)
        rows[name] = out
        print(f"  ({name} took {time.perf_counter() - t0:.0f} s; load average {os.getloadavg()[0]:.2f})", flush=True)
    reset(pkg)
    print()
    print("| scenario | triangles | rays per frame | frames | ours s/frame | ray_cast loop s/frame | loop / ours "
          "| goal |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for name in SCENARIOS:
        for row in rows.get(name, ()):
            print(row.line())
    print()
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    pkg.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
