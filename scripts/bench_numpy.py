"""The numpy grid and BVH against Blender's BVHTree loop, at 1 and 2 threads (issue 10).

    .venv/bin/python scripts/bench_numpy.py                       # both scenes, both ray kinds
    .venv/bin/python scripts/bench_numpy.py --scenes ico --kinds bvh --rays 262144 --repeats 3

Scenes (about 1M triangles each):
  ``monkey``: Suzanne under a Subdivision Surface modifier at level 5 (1,007,616 triangles),
      the scene of ``scripts/bench_trace.py``;
  ``ico``: three icospheres (Blender's ``primitive_ico_sphere_add``, 8 subdivisions,
      327,680 triangles each, 983,040 in all) of radius 1 at x = -2.5, 0, 2.5.
Rays: ``random`` (origins uniform in the padded box, directions uniform on the sphere;
``core.rays.uniform_rays``) and ``camera`` (a pinhole camera framing the scene,
``bench_trace.camera_setup``).  Tracers: ``core.build(mesh, kind, threads=n)`` and the
``BVHTree.ray_cast`` per-ray loop of ``bench_trace``, all in the same run on the same rays.
Prints medians of ``--repeats`` traces (Mrays/s) and ratios to the BVHTree loop.
A benchmark: it prints a table and asserts nothing.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _package import core_package  # noqa: E402
from _timing import median_time  # noqa: E402

core_package()
from hybrid_raycast import core  # noqa: E402
from hybrid_raycast.core.rays import camera_rays, uniform_rays  # noqa: E402

_spec = importlib.util.spec_from_file_location("_bench_trace", HERE / "bench_trace.py")
bench_trace = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_trace)


def icospheres():
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    vs, ts, base = [], [], 0
    for x in (-2.5, 0.0, 2.5):
        bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=8, radius=1.0, location=(x, 0.0, 0.0))
        ob = bpy.context.object
        me = ob.data
        me.calc_loop_triangles()
        v = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", v)
        v = v.reshape(-1, 3) + np.float32([x, 0, 0])  # mesh data is local: apply the location
        t = np.empty(len(me.loop_triangles) * 3, np.int32)
        me.loop_triangles.foreach_get("vertices", t)
        vs.append(v)
        ts.append(t.reshape(-1, 3) + base)
        base += len(v)
        bpy.data.objects.remove(ob)
    return np.concatenate(vs), np.concatenate(ts)


def make_scene(name, m, seed):
    v, t = bench_trace.monkey_triangles(5) if name == "monkey" else icospheres()
    mesh = core.TriangleMesh(v, t)
    cam = bench_trace.camera_setup(mesh, m)
    return mesh, {"random": uniform_rays(mesh, m, seed), "camera": camera_rays(**cam)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="monkey,ico")
    ap.add_argument("--rays", type=int, default=262144)
    ap.add_argument("--raykinds", default="random,camera")
    ap.add_argument("--kinds", default="bvh,grid")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--peer-repeats", type=int, default=1)
    ap.add_argument("--no-peer", action="store_true")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    threads = [int(x) for x in args.threads.split(",")]
    print(f"# {time.strftime('%Y-%m-%d %H:%M:%S')} cores={os.cpu_count()} load={os.getloadavg()[0]:.2f} "
          f"rays={args.rays} repeats={args.repeats}", flush=True)
    print("| scene | rays | tracer | build s | Mrays/s | x BVHTree |")
    print("|---|---|---|--:|--:|--:|", flush=True)
    for sname in args.scenes.split(","):
        mesh, rays = make_scene(sname, args.rays, args.seed)
        label = f"{sname} ({mesh.triangle_count:,})"
        scene = {"mesh": mesh}
        structs = {}
        for kind in args.kinds.split(","):
            a = core.build(mesh, kind, threads=1)
            structs[kind] = a
        peer = None
        if not args.no_peer:
            peer = bench_trace.BVHTreeLoop(scene, 1)
            peer_build = peer.build()
        for rk in args.raykinds.split(","):
            o, d = rays[rk]
            m = len(o)
            base = None
            ref = None
            if peer is not None:
                s = median_time(lambda: peer.trace(o, d), args.peer_repeats)
                base = m / s / 1e6
                print(f"| {label} | {rk} | BVHTree loop | {peer_build:.2f} | {base:.3f} | 1.00x |", flush=True)
            for kind, a in structs.items():
                for n in threads:
                    a.threads = n
                    h = a.trace(o, d)
                    if ref is None:
                        ref = h
                    elif not (np.array_equal(h.triangle, ref.triangle) and np.array_equal(h.t, ref.t)):
                        print(f"!! {kind} threads={n} differs from the first tracer", flush=True)
                    s = median_time(lambda: a.trace(o, d), args.repeats)
                    r = m / s / 1e6
                    ratio = f"{r / base:.2f}x" if base else "-"
                    print(f"| {label} | {rk} | {kind} {n}T | {a.build_time:.2f} | {r:.3f} | {ratio} |", flush=True)
    print(f"# load at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
