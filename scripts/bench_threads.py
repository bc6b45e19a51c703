"""How each structure's trace scales from 1 to 2 threads, in adjacent pairs (issue 10).

    .venv/bin/python scripts/bench_threads.py                         # both engine scenes, 1M rays, 5 pairs
    .venv/bin/python scripts/bench_threads.py --scenes suzanne --kinds grid --pairs 9
    .venv/bin/python scripts/bench_threads.py --hardware --scenes ""          # the machine's own scaling only

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

By default (``--no-ceiling`` for pairs only) each repeat is a triple: beside the 1-thread and the
2-thread trace, two separate processes (spawned, nothing shared, so no GIL between them)
each trace half of the same rays (every other ray) on one thread at the same moment.  The
1-thread time over that pair's time is what the machine's two cores give this structure's
work with no Python in the way, measured in the same minute as the threads: the hardware's
ceiling for the 2-thread ratio.  '2T / ceiling' is the share of it the threads reach.

``--hardware`` first prints the machine's own 1 -> 2 process scaling on work with no
structure in it: a pure-Python loop (no memory traffic) and a streaming numpy kernel
(sqrt, multiply, add) over arrays of growing size, so a ceiling below 2 can be told apart
from Python: on this VM (2 MiB L2 per core, 32 MiB shared L3) the loop scales about 2x and
the kernel falls from about 2x at 1-4 MiB to 1.3-1.6x at 16 MiB, the size of a grid pool's state.
"""

from __future__ import annotations

import argparse
import gc
import multiprocessing
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

import bench_trace  # noqa: E402
from hybrid_raycast import core  # noqa: E402
from hybrid_raycast.core.factory import unavailable_reason  # noqa: E402

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


def _half_tracer(conn, mesh, kind, o, d):
    """A ceiling process: build ``kind`` on one thread, then trace its rays at each 'go'."""
    acc = core.build(mesh, kind, threads=1)
    timed(acc, o[:65536], d[:65536])  # first-call costs
    conn.send("ready")
    while conn.recv() == "go":
        conn.send(timed(acc, o, d)[0])
    conn.close()


class ProcessPair:
    """Two spawned processes, each with its own structure and half the rays (every other
    ray, so each half is the same mix), tracing at the same moment when ``run`` is called."""

    def __init__(self, mesh, kind, o, d):
        ctx = multiprocessing.get_context("spawn")  # not fork: the parent's threads (Embree's among them) stay behind
        self.conns, self.procs = [], []
        for h in (0, 1):
            mine, theirs = ctx.Pipe()
            p = ctx.Process(target=_half_tracer, daemon=True,
                            args=(theirs, mesh, kind, np.ascontiguousarray(o[h::2]), np.ascontiguousarray(d[h::2])))
            p.start()
            self.conns.append(mine)
            self.procs.append(p)
        for c in self.conns:
            if c.recv() != "ready":
                raise RuntimeError("a ceiling process did not start")

    def run(self) -> tuple[float, float]:
        """(wall s until both halves are traced, the faster half's s)."""
        t0 = time.perf_counter()
        for c in self.conns:
            c.send("go")
        each = [c.recv() for c in self.conns]
        return time.perf_counter() - t0, min(each)

    def close(self):
        for c in self.conns:
            c.send("stop")
        for p in self.procs:
            p.join(timeout=30)


def _spin(kind: str, size: int, go, out):
    """A hardware process: after ``go``, run ``kind`` work ('python', or a numpy kernel over
    arrays of ``size`` float32) for a fixed amount of it and put its own seconds on ``out``."""
    if kind == "python":
        go.wait()
        t0 = time.perf_counter()
        s = 0
        for i in range(4_000_000):
            s += i * i
    else:
        a = np.random.default_rng(0).random(size, dtype=np.float32)
        b = np.empty_like(a)
        go.wait()
        t0 = time.perf_counter()
        for _ in range(max(1, int(4e8) // size)):
            np.sqrt(a, out=b)
            b *= a
            b += 1.0
    out.put(time.perf_counter() - t0)


def hardware_rows(reps: int) -> list[tuple[str, float, float, float]]:
    """(work, median, min, max) of 1-process time / 2-process time over ``reps`` adjacent
    pairs, each process doing the same work (so 2.0 is perfect scaling)."""
    ctx = multiprocessing.get_context("spawn")

    def once(kind, size, k):
        go, out = ctx.Event(), ctx.Queue()
        procs = [ctx.Process(target=_spin, args=(kind, size, go, out), daemon=True) for _ in range(k)]
        for p in procs:
            p.start()
        time.sleep(0.5 + 0.5 * k)  # let them import numpy and fill their arrays before 'go'
        go.set()
        took = max(out.get() for _ in procs)
        for p in procs:
            p.join()
        return took

    rows = []
    for kind, size, label in (("python", 0, "pure-Python loop"),
                              *(("numpy", n, f"numpy sqrt*a+1 over {n * 4 / 2**20:.1f} MiB")
                                for n in (1 << 18, 1 << 20, 1 << 22))):
        r = sorted(once(kind, size, 1) / once(kind, size, 2) * 2 for _ in range(reps))
        rows.append((label, statistics.median(r), r[0], r[-1]))
    return rows


def pairs(mesh, kind, o, d, n, ceiling=True) -> dict:
    """``n`` adjacent (1-thread, 2-thread) traces of the same rays, order alternating; with
    ``ceiling`` each is a triple with the two processes' trace (``ProcessPair``), order rotating."""
    acc = {t: core.build(mesh, kind, threads=t) for t in (1, 2)}
    timed(acc[1], o[:65536], d[:65536])  # first-call costs (Embree starts its threads)
    timed(acc[2], o[:65536], d[:65536])
    procs = ProcessPair(mesh, kind, o, d) if ceiling else None
    one, two, cpu, duo, fast = [], [], [], [], []
    try:
        for i in range(n):
            order = ((1, 2, "P"), (2, "P", 1), ("P", 1, 2))[i % 3] if ceiling else ((1, 2) if i % 2 == 0 else (2, 1))
            for t in order:
                if t == "P":
                    wall, quick = procs.run()
                    duo.append(wall)
                    fast.append(quick)
                    continue
                wall, c = timed(acc[t], o, d)
                (one if t == 1 else two).append(wall)
                if t == 2:
                    cpu.append(c / wall)
    finally:
        if procs is not None:
            procs.close()
    ratios = [a / b for a, b in zip(one, two)]
    out = {"one": statistics.median(one), "two": statistics.median(two), "cpu": statistics.median(cpu),
           "of_medians": statistics.median(one) / statistics.median(two), "median": statistics.median(ratios),
           "lo": min(ratios), "hi": max(ratios)}
    if ceiling:
        ceil = [a / b for a, b in zip(one, duo)]
        out.update({"procs": statistics.median(duo), "ceiling": statistics.median(ceil),
                    "ceil_lo": min(ceil), "ceil_hi": max(ceil),
                    "share": statistics.median([a / b for a, b in zip(ratios, ceil)]),
                    "skew": statistics.median([a / b for a, b in zip(duo, fast)])})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="icospheres,suzanne", help="engine scenes (bench_trace.ENGINE_SCENES)")
    ap.add_argument("--kinds", default="bvh,grid", help="structures, some of grid,bvh,embree")
    ap.add_argument("--rays", type=int, default=1_000_000, help="rays per trace (the issue's 1M)")
    ap.add_argument("--pairs", type=int, default=5, help="adjacent pairs (triples with the ceiling) per row")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-ceiling", dest="ceiling", action="store_false",
                    help="pairs only, without the two processes' trace (the hardware's ceiling)")
    ap.add_argument("--hardware", action="store_true",
                    help="first the machine's own 1 -> 2 process scaling on a Python loop and a numpy kernel")
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
    print(f"# 1 -> 2 threads, {args.rays:,} rays a trace, {args.pairs} adjacent "
          f"{'triples (1 thread, 2 threads, 2 processes)' if args.ceiling else 'pairs'} a row; "
          f"load average {os.getloadavg()[0]:.2f} at the start\n")
    if args.hardware:
        print("| work, same in each process | 2 x 1 process s / 2 processes s, median [min, max] |\n|---|--:|")
        for label, med, lo, hi in hardware_rows(args.pairs):
            print(f"| {label} | {med:.2f} [{lo:.2f}, {hi:.2f}] |", flush=True)
        print()
    if not (scenes and kinds):
        return 0
    ceil_hdr = (" 2 processes s | ceiling: 1T / 2 processes [min, max] | 2T / ceiling | slower / faster process |"
                if args.ceiling else "")
    print("| scene | rays | structure | 1 thread s | 2 threads s | CPU / wall (2T) | ratio of medians "
          f"| median of pair ratios [min, max] | goal >= 1.7 |{ceil_hdr}")
    print("|---|---|---|--:|--:|--:|--:|--:|:-:|" + ("--:|--:|--:|--:|" if args.ceiling else ""))
    t_start = time.perf_counter()
    for name in scenes:
        scene = bench_trace.engine_scene(name, argparse.Namespace(rays=args.rays, seed=args.seed))
        for ray_kind, (o, d) in scene["rays"].items():
            o, d = o[: args.rays], d[: args.rays]
            for kind in kinds:
                r = pairs(scene["mesh"], kind, o, d, args.pairs, ceiling=args.ceiling)
                ok = "yes" if r["median"] >= GOAL else "**no**"
                ceil = (f" {r['procs']:.3f} | {r['ceiling']:.2f} [{r['ceil_lo']:.2f}, {r['ceil_hi']:.2f}] | "
                        f"{r['share']:.2f} | {r['skew']:.2f} |" if args.ceiling else "")
                print(f"| {name} | {ray_kind} | {kind} | {r['one']:.3f} | {r['two']:.3f} | {r['cpu']:.2f} | "
                      f"{r['of_medians']:.2f} | {r['median']:.2f} [{r['lo']:.2f}, {r['hi']:.2f}] | {ok} |{ceil}",
                      flush=True)
    print(f"\n{time.perf_counter() - t_start:.0f} s; load average {os.getloadavg()[0]:.2f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
