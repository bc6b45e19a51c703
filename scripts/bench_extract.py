"""Benchmark: Blender scene -> TriangleMesh extraction (operators/extract.py).

    cd /work/main && .venv/bin/python scripts/bench_extract.py [--runs 5] [--level 4]
    .venv/bin/python scripts/bench_extract.py --scale 10m     # ~10M triangles: time, rate and peak memory

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

``--scale 10m``: the same two scenes with Suzanne at level 5 (1,007,616 triangles) and as
many copies as make about that many triangles (10 for 10m; rows of 5, 3 units apart): for
each, the depsgraph evaluation, the cold and one warm extraction, their rates, and peak
memory (the RSS high-water mark over the extraction, above what was resident before it,
and the process's high-water mark; Linux only).

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

sys.path.insert(0, str(ROOT / "scripts"))
from _memory import PeakMemory, trim  # noqa: E402
from _timing import median_time  # noqa: E402
from bench_trace import parse_size  # noqa: E402
from hybrid_raycast.operators import extract  # noqa: E402


#: Suzanne's triangle count at Subdivision Surface level 5
LEVEL5_TRIANGLES = 1_007_616


def place(i):
    """Where copy i stands: rows of 5, 3 units apart (Suzanne is about 2.7 wide)."""
    return (3.0 * (i % 5), 3.0 * (i // 5), 0.0)


def build(kind: str, level: int, copies: int = 4):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_monkey_add()
    monkey = bpy.context.object
    mod = monkey.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = level
    if kind == "linked":
        for i in range(1, copies):
            dup = monkey.copy()  # linked duplicate: shares the mesh, copies the modifier
            dup.location = place(i)
            scene.collection.objects.link(dup)
    else:
        coll = bpy.data.collections.new("Monkey")
        scene.collection.children.link(coll)
        scene.collection.objects.unlink(monkey)
        coll.objects.link(monkey)
        bpy.context.view_layer.layer_collection.children["Monkey"].exclude = True
        for i in range(copies):
            e = bpy.data.objects.new(f"Inst{i}", None)
            e.instance_type = "COLLECTION"
            e.instance_collection = coll
            e.location = place(i)
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
    return median_time(f, runs, clock=time.process_time)


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


def _mib(b):
    return "n/a" if b is None else f"{b / 2**20:,.0f}"


def scale_check(size: int, runs: int):
    """Both scenes at level 5 with enough copies for ``size`` triangles: evaluation, cold and
    ``runs`` warm extractions (median), rates and peak memory."""
    copies = max(1, round(size / LEVEL5_TRIANGLES))
    print(f"extraction at scale: bpy {bpy.app.version_string}, numpy {np.__version__}, {os.cpu_count()} cores, "
          f"load average {', '.join(f'{x:.2f}' for x in os.getloadavg())} at start, physical memory "
          f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.1f} GiB")
    print(f"Suzanne at Subdivision Surface level 5 ({LEVEL5_TRIANGLES:,} triangles), {copies} copies in rows of 5\n")
    print(f"| scene | meshes read | triangles | evaluate s | cold extract s | warm extract s (median of {runs}) | warm Mtri/s "
          "| mesh MiB | extract peak extra RSS MiB | process peak RSS MiB |")
    print("|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|")
    out = []
    for kind in ("instanced", "linked"):
        t0 = time.perf_counter()
        dg = build(kind, 5, copies)
        # the trailing Subdivision Surface is evaluated lazily, on first access to the mesh
        for inst in dg.object_instances:
            if inst.object.type == "MESH":
                len(inst.object.data.loop_triangles)
        evaluate = time.perf_counter() - t0
        with PeakMemory(traced=False) as cold_mem:
            cold, mesh = timed(lambda: extract.scene_mesh(dg))
        # what the extraction returns (the corner array and validity are made later, by a build)
        mesh_bytes = sum(a.nbytes for a in (mesh.vertices, mesh.triangles, mesh.object_index, mesh.polygon_index)
                         if a is not None)
        n, read = mesh.triangle_count, mesh.source_info.meshes_read
        del mesh
        trim()
        warms = []
        with PeakMemory(traced=False) as warm_mem:
            for _ in range(runs):
                mesh = None
                t, mesh = timed(lambda: extract.scene_mesh(dg))
                warms.append(t)
        warm = statistics.median(warms)
        peak = max(m.rss for m in (cold_mem, warm_mem)) if cold_mem.rss is not None else None
        print(f"| {kind} | {read} | {n:,} | {evaluate:.2f} | {cold:.2f} | {warm:.2f} | {n / warm / 1e6:.1f} "
              f"| {_mib(mesh_bytes)} | {_mib(peak)} | {_mib(warm_mem.hwm)} |")
        sys.stdout.flush()
        out.append(dict(kind=kind, triangles=n, meshes_read=read, evaluate_s=evaluate, cold_s=cold, warm_s=warm,
                        mesh_bytes=mesh_bytes, peak_extra_rss=peak, process_peak_rss=warm_mem.hwm))
        del mesh
        trim()
    print("\nevaluate = building the scene and Blender's evaluation of every Subdivision Surface (linked: one per "
          "copy; instanced: one); cold = the first scene_mesh after it, warm = the later ones; peak extra RSS = "
          "the larger of the cold and the warm extractions' RSS high-water marks above the RSS before them (VmHWM "
          "after a reset), the TriangleMesh included (mesh MiB: its vertices, triangles, object and polygon "
          "indices); process peak = VmHWM at the end of the warm runs (Blender's evaluated meshes included).  "
          f"Load average at the end {', '.join(f'{x:.2f}' for x in os.getloadavg())}.")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--level", type=int, default=4, help="Subdivision Surface level (4: ~1M triangles)")
    ap.add_argument("--scale", help="instead: level 5 copies for about this many triangles (e.g. 10m), with peak memory")
    args = ap.parse_args(argv)
    if args.scale:
        try:
            size = parse_size(args.scale)
        except ValueError:
            ap.error(f"--scale takes a triangle count such as 10m or 2500k, got {args.scale!r}")
        scale_check(size, args.runs)
        return
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
