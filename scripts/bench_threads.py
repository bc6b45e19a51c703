"""How each structure's trace scales from 1 to 2 threads, in adjacent pairs (issue 10).

    .venv/bin/python scripts/bench_threads.py                         # both engine scenes, 1M rays, 5 pairs
    .venv/bin/python scripts/bench_threads.py --scenes suzanne --kinds grid --pairs 9

On this 2-core VM the speed of the whole machine drifts by 20-30% within minutes, so a
ratio of two medians taken minutes apart (the engine table's '2 threads / 1 thread' rows)
moves by as much as the effect it measures: 1.5x to 1.9x on the same code.  Here each
repeat is a pair, the 1-thread and the 2-thread trace of the same rays one right after the
other (their order alternating between pairs, so a trend favours neither), and the table
gives the median of the pairs' ratios beside the ratio of the medians, with the pairs'
range.  Scenes and rays are the engine table's (``bench_trace.engine_scene``: 3 icospheres
of 983,040 triangles, Suzanne at level 5 of 1,007,616; uniform random and pinhole camera
rays), each structure built once per thread count.  'CPU / wall' is the 2-thread trace's
process CPU time over its wall time (about 1.9 when both threads run the whole time).
Run it alone (the bench lock), as every timing here.
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

import bench_trace  # noqa: E402
from hybrid_raycast import core  # noqa: E402
from hybrid_raycast.core.decide.measurements import unavailable_reason  # noqa: E402

GOAL = 1.7
#: the structures worth a 1M-ray trace (brute force is not)
KINDS = ("grid", "bvh", "embree")


def timed(acc, o, d) -> tuple[float, float]:
    """(wall s, process CPU s) of one trace, after a collection so no earlier garbage is
    collected inside it."""
    gc.collect()
    c0, t0 = time.process_time(), time.perf_counter()
    acc.trace(o, d)
    return time.perf_counter() - t0, time.process_time() - c0


def pairs(mesh, kind, o, d, n) -> dict:
    """``n`` adjacent (1-thread, 2-thread) traces of the same rays, order alternating."""
    acc = {t: core.build(mesh, kind, threads=t) for t in (1, 2)}
    timed(acc[1], o[:65536], d[:65536])  # first-call costs (Embree starts its threads)
    timed(acc[2], o[:65536], d[:65536])
    one, two, cpu = [], [], []
    for i in range(n):
        for t in ((1, 2) if i % 2 == 0 else (2, 1)):
            wall, c = timed(acc[t], o, d)
            (one if t == 1 else two).append(wall)
            if t == 2:
                cpu.append(c / wall)
    ratios = [a / b for a, b in zip(one, two)]
    return {"one": statistics.median(one), "two": statistics.median(two), "cpu": statistics.median(cpu),
            "of_medians": statistics.median(one) / statistics.median(two), "median": statistics.median(ratios),
            "lo": min(ratios), "hi": max(ratios)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="icospheres,suzanne", help="engine scenes (bench_trace.ENGINE_SCENES)")
    ap.add_argument("--kinds", default="bvh,grid", help="structures, some of grid,bvh,embree")
    ap.add_argument("--rays", type=int, default=1_000_000, help="rays per trace (the issue's 1M)")
    ap.add_argument("--pairs", type=int, default=5, help="adjacent 1-thread/2-thread pairs per row")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    scenes = [s for s in args.scenes.split(",") if s]
    kinds = [k for k in args.kinds.split(",") if k]
    bad = [s for s in scenes if s not in bench_trace.ENGINE_SCENES] + [k for k in kinds if k not in KINDS]
    if bad or args.rays < 1 or args.pairs < 1:
        print(f"error: unknown scene or structure {bad}, or --rays/--pairs below 1", file=sys.stderr)
        return 2
    for k in list(kinds):
        why = unavailable_reason(k)
        if why:
            print(f"{k}: skipped ({why})")
            kinds.remove(k)
    print(f"# 1 -> 2 threads, {args.rays:,} rays a trace, {args.pairs} adjacent pairs a row; "
          f"load average {os.getloadavg()[0]:.2f} at the start\n")
    print("| scene | rays | structure | 1 thread s | 2 threads s | CPU / wall (2T) | ratio of medians "
          "| median of pair ratios [min, max] | goal >= 1.7 |")
    print("|---|---|---|--:|--:|--:|--:|--:|:-:|")
    t_start = time.perf_counter()
    for name in scenes:
        scene = bench_trace.engine_scene(name, argparse.Namespace(rays=args.rays, seed=args.seed))
        for ray_kind, (o, d) in scene["rays"].items():
            o, d = o[: args.rays], d[: args.rays]
            for kind in kinds:
                r = pairs(scene["mesh"], kind, o, d, args.pairs)
                ok = "yes" if r["median"] >= GOAL else "**no**"
                print(f"| {name} | {ray_kind} | {kind} | {r['one']:.3f} | {r['two']:.3f} | {r['cpu']:.2f} | "
                      f"{r['of_medians']:.2f} | {r['median']:.2f} [{r['lo']:.2f}, {r['hi']:.2f}] | {ok} |", flush=True)
    print(f"\n{time.perf_counter() - t_start:.0f} s; load average {os.getloadavg()[0]:.2f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
