"""Embree's build after a rest: how a small build's time depends on what the machine did just
before it (issue 14, sixteenth session).  A timing benchmark: run it alone.

For each mesh and each gap, builds Embree ``--builds`` times, each after the gap spent either
asleep ('rest', the machine idle, as before a user's Analyze click) or spinning on one thread
('busy'), and also right after ``settle_before_build`` (the page warming, ``IDLE_BEFORE_BUILD``
asleep, ``BUSY_BEFORE_BUILD`` spinning) as the calibration and the report's truths measure it
('measured').  Prints the median build and the spread
(max / min - 1) of each row, and how many threads the builds kept busy: the median of each
build's process CPU seconds over its wall seconds, and the share of builds below
``measurements.ONE_THREAD`` (Embree builds on every hardware thread; on a VM that has parked
its idle vCPU the second thread can land on the first's vCPU, and the build runs on about one).

``--before``: instead, each build after the work named (a trace of --rays rays on two threads
through the numpy BVH, the grid or Embree; making 1M uniform rays on one thread; nothing), then
``settle_before_build``, the rows interleaved: what runs before the rest decided the state
until ``settle_before_build`` ended with ``BUSY_BEFORE_BUILD`` of one thread busy
(``--busy-ms`` tries another length; 0 shows the state without it).

``--plan``: each build as a plan makes it, after a pause: the grid built, 8,192 uniform rays
traced through it, then Embree built at once (no settling).

Meshes: the real ones of --scenes that exist (homer, rocker-arm, stanford-bunny), else
procedural ones of the same sizes.

    .venv/bin/python scripts/build_rest_study.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import SHARED_SCENES, core_package  # noqa: E402

core_package()

from hybrid_raycast.core import scenes as scene_lib  # noqa: E402
from hybrid_raycast.core.decide import measurements as M  # noqa: E402
from hybrid_raycast.core.factory import build  # noqa: E402
from hybrid_raycast.core.objio import load_obj  # noqa: E402
from hybrid_raycast.core.rays import uniform_rays  # noqa: E402

REAL = ("homer", "rocker-arm", "stanford-bunny")
GAPS_MS = (0.0, 1.0, 5.0, 20.0, 100.0, 500.0)


def meshes(folder: Path):
    out = [(n, load_obj(folder / f"{n}.obj")) for n in REAL if (folder / f"{n}.obj").exists()]
    return out or [("sphere-12k", scene_lib.sphere(12000)), ("torus-20k", scene_lib.torus(20000)),
                   ("soup-70k", scene_lib.soup(70000))]


def timed_build(mesh) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) of one Embree build (CPU NaN where the OS does not
    say)."""
    c, t = M._kernel_usage(), time.perf_counter()
    build(mesh, "embree", threads=2)
    w, c1 = time.perf_counter() - t, M._kernel_usage()
    return w, (c1[2] - c[2]) if c is not None else float("nan")


def measured_build(mesh) -> tuple[float, float]:
    """After what ``measurements._measure`` does before a build (``settle_before_build``)."""
    M.settle_before_build(mesh.triangle_count)
    return timed_build(mesh)


def settled_ms() -> str:
    """The gap column of a build after ``settle_before_build``: its rest + its busy spin, ms."""
    return f"{M.IDLE_BEFORE_BUILD * 1e3:g} + {M.BUSY_BEFORE_BUILD * 1e3:g} busy"


def header(before: str) -> str:
    """The table's head; ``before`` names the column of what preceded the builds."""
    return (f"| mesh | N | {before} | gap ms | build ms, median | spread | threads busy, median | "
            f"builds on about one (< {M.ONE_THREAD:g}) |\n|---|---:|---|---:|---:|---:|---:|---:|")


def row(name, mesh, how, gap, got) -> str:
    wall = np.array([w for w, _ in got])
    busy = np.array([c / w for w, c in got])
    return (f"| {name} | {mesh.triangle_count:,} | {how} | {gap} | {np.median(wall) * 1e3:.2f} | "
            f"{100 * (wall.max() / wall.min() - 1):.0f}% | {np.median(busy):.2f} | {int((busy < M.ONE_THREAD).sum())}/{len(busy)} |")


def before_study(folder: Path, builds: int, rays: int) -> None:
    """Each build after other work, then ``settle_before_build`` (``--before``)."""
    print(header("before the rest"))
    for name, mesh in meshes(folder):
        mesh.valid  # noqa: B018
        o, d = uniform_rays(mesh, rays, seed=0)
        made = {k: build(mesh, k, threads=2) for k in ("bvh", "grid", "embree")}
        work = {f"numpy BVH trace, {rays:,} rays, 2 threads": lambda: made["bvh"].trace(o, d),
                f"grid trace, {rays:,} rays, 2 threads": lambda: made["grid"].trace(o, d),
                f"Embree trace, {rays:,} rays": lambda: made["embree"].trace(o, d),
                "1M uniform rays made, 1 thread": lambda: uniform_rays(mesh, 1_000_000, seed=1),
                "nothing": lambda: None}
        got = {k: [] for k in work}
        for _ in range(max(1, builds)):
            for k, f in work.items():
                f()
                got[k].append(measured_build(mesh))
        for k, g in got.items():
            print(row(name, mesh, k, settled_ms(), g), flush=True)


def plan_study(folder: Path, builds: int, pause: float = 0.3) -> None:
    """Embree built as ``plan`` builds it, right after the grid's sample (``--plan``)."""
    print(header("before the build"))
    for name, mesh in meshes(folder):
        mesh.valid  # noqa: B018
        o, d = uniform_rays(mesh, 8192, seed=0)
        got = []
        for _ in range(max(1, builds)):
            time.sleep(pause)
            build(mesh, "grid", threads=2).trace(o, d)
            got.append(timed_build(mesh))
        print(row(name, mesh, "grid built, 8,192 rays traced, Embree at once", f"{pause * 1e3:g} before the grid", got),
              flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=str(SHARED_SCENES), help="folder of real .obj meshes")
    ap.add_argument("--builds", type=int, default=11, help="builds per row (default 11)")
    ap.add_argument("--before", action="store_true", help="builds after other work instead of after a gap")
    ap.add_argument("--rays", type=int, default=200_000, help="rays of each trace before a build (--before)")
    ap.add_argument("--plan", action="store_true", help="builds as a plan makes them, right after the grid's sample")
    ap.add_argument("--busy-ms", type=float, default=None,
                    help=f"spin this long before each measured build instead of measurements.BUSY_BEFORE_BUILD "
                         f"({M.BUSY_BEFORE_BUILD * 1e3:g} ms)")
    args = ap.parse_args(argv)
    if args.busy_ms is not None:
        M.BUSY_BEFORE_BUILD = args.busy_ms / 1e3
    if M.unavailable_reason("embree"):
        raise SystemExit(f"embree: {M.unavailable_reason('embree')}")
    if args.plan:
        plan_study(Path(args.scenes), args.builds)
        return 0
    if args.before:
        before_study(Path(args.scenes), args.builds, args.rays)
        return 0
    print(header("before the build"))
    for name, mesh in meshes(Path(args.scenes)):
        mesh.valid  # noqa: B018 -- computed once, outside every timed build
        timed_build(mesh)
        rows = [(how, f"{gap:g}", gap / 1e3) for gap in GAPS_MS for how in ("rest", "busy")]
        for how, label, seconds in rows + [("measured", settled_ms(), None)]:
            got = []
            for _ in range(max(1, args.builds)):
                if how == "measured":
                    got.append(measured_build(mesh))
                    continue
                (time.sleep if how == "rest" else M.spin)(seconds)
                got.append(timed_build(mesh))
            print(row(name, mesh, how, label, got))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
