"""Benchmark: Blender scene -> TriangleMesh extraction (operators/extract.py).

    cd /work/main && .venv/bin/python scripts/bench_extract.py [--runs 5] [--level 4]

Scenes (about 1M triangles each):
  linked     a Suzanne with a Subdivision Surface modifier (level 4: 251,904 triangles)
             and three linked duplicates (Alt+D: same mesh, own modifier), so Blender
             evaluates four meshes and the extractor reads four;
  instanced  the same subdivided Suzanne once, placed four times by collection instances,
             so the extractor reads one mesh and transforms it four times.

What is timed: ``scene_mesh(depsgraph)`` only. The depsgraph is evaluated before timing
(Blender evaluates a trailing Subdivision Surface lazily, on the first access to the mesh,
so a first "cold" extraction is run and reported separately: it includes Blender's
subdivision). Then the median (min, max) of --runs warm runs. A breakdown of a warm run
by phase and two alternative triangle reads (Blender's ``loop_triangles.foreach_get``)
follow, each the median of --runs.
Prints a table; fails on nothing.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if "hybrid_raycast" not in sys.modules:  # the repo root is the package; skip its bpy __init__
    _pkg = types.ModuleType("hybrid_raycast")
    _pkg.__path__ = [str(ROOT)]
    sys.modules["hybrid_raycast"] = _pkg

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from hybrid_raycast.core.mesh import TriangleMesh  # noqa: E402
from hybrid_raycast.operators import extract  # noqa: E402


def build(kind: str, level: int):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_monkey_add()
    monkey = bpy.context.object
    mod = monkey.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = level
    if kind == "linked":
        for i in range(3):
            dup = monkey.copy()  # linked duplicate: shares the mesh, copies the modifier
            dup.location = (3.0 * (i + 1), 0.0, 0.0)
            scene.collection.objects.link(dup)
    else:
        coll = bpy.data.collections.new("Monkey")
        scene.collection.children.link(coll)
        scene.collection.objects.unlink(monkey)
        coll.objects.link(monkey)
        bpy.context.view_layer.layer_collection.children["Monkey"].exclude = True
        for i in range(4):
            e = bpy.data.objects.new(f"Inst{i}", None)
            e.instance_type = "COLLECTION"
            e.instance_collection = coll
            e.location = (3.0 * i, 0.0, 0.0)
            e.rotation_euler = (0.1 * i, 0.2 * i, 0.3 * i)
            e.scale = (1.0, 1.0 + 0.5 * i, -1.0 if i == 3 else 1.0)
            scene.collection.objects.link(e)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    depsgraph.update()
    return depsgraph


def timed(f):
    t = time.perf_counter()
    r = f()
    return time.perf_counter() - t, r


def median_cpu(f, runs):
    """Median process CPU time of f: steadier than wall time when other jobs share the cores."""
    ts = []
    for _ in range(runs):
        c = time.process_time()
        f()
        ts.append(time.process_time() - c)
    return statistics.median(ts)


def breakdown(depsgraph, runs):
    """Where a warm run spends its time (medians), and two slower ways to read triangles."""
    vl = depsgraph.view_layer
    groups, names, _, _ = extract._collect(depsgraph, vl, False, None)
    meshes = {}
    for inst in depsgraph.object_instances:
        if inst.object.type == "MESH":
            meshes.setdefault(inst.object.data.as_pointer(), inst.object.data)
    meshes = list(meshes.values())

    def read_all(read):
        return lambda: [read(me) for me in meshes]

    def blender_vertices(me):
        a = np.empty(len(me.loop_triangles) * 3, np.int32)
        me.loop_triangles.foreach_get("vertices", a)
        return a

    def blender_loops(me):
        a = np.empty(len(me.loop_triangles) * 3, np.int32)
        me.loop_triangles.foreach_get("loops", a)
        return extract._corner_verts(me)[a]

    mesh = extract._assemble(groups, names)
    rows = [
        ("collect: walk object_instances, read meshes, fetch matrices",
         median_cpu(lambda: extract._collect(depsgraph, vl, False, None), runs)),
        (f"  of which reading {len(meshes)} mesh(es) (positions, numpy quad rule, polygons)",
         median_cpu(read_all(extract.mesh_triangles), runs)),
        ("    instead: triangles by loop_triangles.foreach_get('vertices')",
         median_cpu(read_all(blender_vertices), runs)),
        ("    instead: loop_triangles.foreach_get('loops') + .corner_vert",
         median_cpu(read_all(blender_loops), runs)),
        ("assemble: batched matmul per mesh, indices, TriangleMesh",
         median_cpu(lambda: extract._assemble(groups, names), runs)),
        ("  of which TriangleMesh validation",
         median_cpu(lambda: TriangleMesh(mesh.vertices, mesh.triangles, mesh.object_index,
                                          mesh.polygon_index, mesh.object_names), runs)),
        ("whole scene_mesh", median_cpu(lambda: extract.scene_mesh(depsgraph), runs)),
    ]
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--level", type=int, default=4, help="Subdivision Surface level (4: ~1M triangles)")
    args = ap.parse_args(argv)
    cores = os.cpu_count()
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = cores
    print(f"extraction benchmark: bpy {bpy.app.version_string}, numpy {np.__version__}, "
          f"{cores} cores ({usable} usable), load average {os.getloadavg()[0]:.1f} at start, "
          f"goal <= 0.200 s per extraction")
    print()
    head = f"{'scene':10s} {'objects':>7s} {'meshes read':>11s} {'triangles':>10s} {'cold s':>8s} " \
           f"{'median s':>9s} {'min s':>7s} {'max s':>7s} {'cpu s':>7s} {'Mtri/s':>7s} {'goal':>5s}"
    print(head)
    print("-" * len(head))
    breakdowns = {}
    for kind in ("linked", "instanced"):
        dg = build(kind, args.level)
        cold, mesh = timed(lambda: extract.scene_mesh(dg))
        times, cpu = [], []
        for _ in range(args.runs):
            c = time.process_time()
            times.append(timed(lambda: extract.scene_mesh(dg))[0])
            cpu.append(time.process_time() - c)
        med = statistics.median(times)
        info = mesh.source_info
        n_read = info.meshes_read
        print(f"{kind:10s} {len(mesh.object_names):7d} {n_read:11d} {mesh.triangle_count:10,d} {cold:8.3f} "
              f"{med:9.3f} {min(times):7.3f} {max(times):7.3f} {statistics.median(cpu):7.3f} "
              f"{mesh.triangle_count / med / 1e6:7.1f} "
              f"{'met' if med <= 0.2 else 'MISS':>5s}")
        breakdowns[kind] = breakdown(dg, args.runs)
    for kind, rows in breakdowns.items():
        print()
        print(f"breakdown of a warm run, scene '{kind}' (median CPU time of {args.runs}):")
        for label, t in rows:
            print(f"  {label:66s} {t * 1e3:8.1f} ms cpu")
    print()
    print("cold = first extraction after the depsgraph update; it includes Blender's lazy subdivision "
          "of the trailing Subdivision Surface modifier.\nmedian/min/max = wall time over warm runs; "
          "cpu = median process CPU time (all threads), steadier than wall time on a shared machine.")


if __name__ == "__main__":
    main()
