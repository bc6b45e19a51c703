"""Benchmark: api.cast per call on a cached scene against Blender's scene.ray_cast loop.

    .venv/bin/python scripts/bench_api.py [--runs 7]            # per-call table + fingerprint cost
    .venv/bin/python scripts/bench_api.py --memory 10000000     # peak memory of one big cast (run alone)

Scene (small): a ground plane, a cube, a UV sphere and two collection instances of a cone
(about 1,100 triangles).  Rays: from a ring around the scene toward random points inside
it.  Each size is cast a few times first (the session plans, then settles on a structure
by the online rule), then timed: median of ``--runs`` calls, and the median of ``--runs``
Python loops of ``scene.ray_cast`` over the same rays (each ray through mathutils
Vectors, as a script does).  Fingerprint: ``session.fingerprint`` on a geometry-nodes
instance-on-points scene with about 100,000 instances.  Memory: ``resource.getrusage``
ru_maxrss of this process before and after one cast of N rays (inputs already made).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import load_addon  # noqa: E402
from _timing import median_time  # noqa: E402

import bpy  # noqa: E402
from mathutils import Vector  # noqa: E402

pkg = load_addon()
pkg.register()
api = pkg.api
session = pkg.operators.session


def small_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_plane_add(size=12, location=(0, 0, -1))
    bpy.ops.mesh.primitive_cube_add(size=1.5, location=(1.5, 0, 0))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.8, location=(-1.5, 1.0, 0.3))
    bpy.ops.mesh.primitive_cone_add(radius1=0.5, depth=1.0, location=(0, 0, 0))
    cone = bpy.context.object
    col = bpy.data.collections.new("Cones")
    bpy.context.scene.collection.objects.unlink(cone)
    col.objects.link(cone)
    for i, x in enumerate((-2.5, 2.5)):
        e = bpy.data.objects.new(f"Inst{i}", None)
        e.instance_type, e.instance_collection, e.location = "COLLECTION", col, (x, -2.0, 0.0)
        bpy.context.scene.collection.objects.link(e)
    bpy.context.view_layer.update()


def rays(m, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, m)
    o = np.stack([9 * np.cos(a), 9 * np.sin(a), rng.uniform(-0.5, 2.5, m)], axis=1)
    target = np.stack([rng.uniform(-3, 3, m), rng.uniform(-3, 3, m), rng.uniform(-1.2, 1.2, m)], axis=1)
    return o.astype(np.float32), (target - o).astype(np.float32)


def ray_cast_loop(scene, dg, o, d):
    out = 0
    for i in range(len(o)):
        out += scene.ray_cast(dg, Vector(o[i]), Vector(d[i]))[0]
    return out


def per_call(runs):
    small_scene()
    scene = bpy.context.scene
    tris = session.get(bpy.context.evaluated_depsgraph_get()).mesh.triangle_count
    print(f"api.cast per call on a cached scene ({tris:,} triangles) vs scene.ray_cast loop; "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at start; median of {runs}")
    head = f"{'rays':>8s} {'api.cast ms':>12s} {'ray_cast loop ms':>17s} {'ratio':>7s} {'structure':>10s}"
    print(head)
    print("-" * len(head))
    for m in (1, 100, 1000, 100_000):
        o, d = rays(m, seed=m)
        for _ in range(4):  # plan, then settle (the online rule across calls)
            r = api.cast(o, d)
        n = runs if m < 100_000 else max(3, runs // 2)
        t_api = median_time(lambda: api.cast(o, d), n)
        dg = bpy.context.evaluated_depsgraph_get()
        t_bl = median_time(lambda: ray_cast_loop(scene, dg, o, d), n)
        print(f"{m:8,d} {t_api * 1e3:12.3f} {t_bl * 1e3:17.3f} {t_api / t_bl:7.2f} {r.structure:>10s}")
    o, d = rays(1, seed=1)
    t_fp = median_time(lambda: session.fingerprint(bpy.context.evaluated_depsgraph_get()), 50)
    print(f"\nfingerprint of this scene (incl. evaluated_depsgraph_get): {t_fp * 1e6:.0f} us")


def instances_scene(n_side=317):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=n_side - 1, y_subdivisions=n_side - 1, size=100)
    host = bpy.context.object
    tree = bpy.data.node_groups.new("inst", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gi, go = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
    iop, cube = tree.nodes.new("GeometryNodeInstanceOnPoints"), tree.nodes.new("GeometryNodeMeshCube")
    cube.inputs["Size"].default_value = (0.1, 0.1, 0.1)
    tree.links.new(gi.outputs[0], iop.inputs["Points"])
    tree.links.new(cube.outputs[0], iop.inputs["Instance"])
    tree.links.new(iop.outputs[0], go.inputs[0])
    host.modifiers.new("GN", "NODES").node_group = tree
    bpy.context.view_layer.update()


def fingerprint_cost(runs):
    instances_scene()
    dg = bpy.context.evaluated_depsgraph_get()
    n_inst = len(dg.object_instances)
    t_fp = median_time(lambda: session.fingerprint(dg), max(runs, 20))
    t0 = time.perf_counter()
    s = session.get(dg)
    t_ex = time.perf_counter() - t0
    o, d = rays(1000)
    o[:, 2] += 5.0
    d[:, 2] = -np.abs(d[:, 2]) - 1
    for _ in range(4):
        api.cast(o, d)
    t_cast = median_time(lambda: api.cast(o, d), runs)
    print(f"\n{n_inst:,} geometry-nodes instances ({s.mesh.triangle_count:,} triangles): fingerprint "
          f"{t_fp * 1e3:.3f} ms (median of {max(runs, 20)}), extraction {t_ex:.3f} s, cached 1,000-ray api.cast "
          f"{t_cast * 1e3:.2f} ms ({api.cast(o, d).structure}); load average {os.getloadavg()[0]:.2f}")


def current_rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def memory(m):
    small_scene()
    o = np.empty((m, 3), np.float32)
    d = np.empty((m, 3), np.float32)
    step = 1 << 20
    for a in range(0, m, step):  # made in pieces: no temporary raises the peak above the inputs
        o[a:a + step], d[a:a + step] = rays(min(step, m - a), seed=a)
    api.cast(o[:1000], d[:1000])  # the session exists, planned
    base = max(current_rss(), 0)
    before_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    t0 = time.perf_counter()
    r = api.cast(o, d, progress=lambda done, total: None)
    dt = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    result = sum(getattr(r, k).nbytes for k in ("t", "hit", "points", "normals", "object_index", "instance_index",
                                                 "polygon_index", "triangle", "u", "v"))
    mib = 1 << 20
    print(f"{m:,} rays ({r.structure}) in {dt:.2f} s: result {result / mib:.0f} MiB, RSS before the cast "
          f"{base / mib:.0f} MiB (peak so far {before_peak / mib:.0f} MiB), peak after {peak / mib:.0f} MiB, "
          f"growth {(peak - base) / mib:.0f} MiB "
          f"(bound: result + 512 = {result / mib + 512:.0f} MiB); load average {os.getloadavg()[0]:.2f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--memory", type=int, default=0, help="only: peak memory of one cast of this many rays")
    ap.add_argument("--no-instances", action="store_true", help="skip the 100k-instance fingerprint")
    args = ap.parse_args(argv)
    if args.memory:
        memory(args.memory)
        return
    per_call(args.runs)
    if not args.no_instances:
        fingerprint_cost(args.runs)


if __name__ == "__main__":
    main()
