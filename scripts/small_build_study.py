"""How much a small scene's recorded build moves, and whether repeated builds are alike (issue 14,
twentieth session).  A timing benchmark: run it alone.

Default: ``--rounds`` settled builds (``measurements.settle_before_build``, then ``build``) of each
small calibration scene (at most ``measurements.SMALL_SCENE`` triangles), the numpy BVH and
Embree, interleaved over scenes and structures.  Prints each row's median and p10-p90, and how far
a median of 5 and a median of ``5 * SMALL_BUILDS`` builds drawn from them moves: the p10-p90 of
that median over 4,000 resamples, as % of the median.  A calibration's record was the median of
5 builds (one a pass) and is now the median of 5 medians of ``SMALL_BUILDS``.

``--order``: after a two-thread trace of 131,072 rays through the numpy BVH on the same scene,
``SMALL_BUILDS`` settled builds in a row, as ``measurements.measure`` now takes them; the median
of each build's position over the rounds.  Equal columns mean the later builds time the state
the first one does.

    .venv/bin/python scripts/small_build_study.py [--rounds 25] [--order] [--kinds bvh,embree]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

from hybrid_raycast.core import scenes as scene_lib  # noqa: E402
from hybrid_raycast.core.decide import available_kinds  # noqa: E402
from hybrid_raycast.core.decide import measurements as M  # noqa: E402
from hybrid_raycast.core.factory import build  # noqa: E402
from hybrid_raycast.core.rays import uniform_rays  # noqa: E402

ORDER_RAYS = 131_072
RESAMPLES = 4000


def small_scenes(limit: int | None):
    """The default calibration set's scenes of at most SMALL_SCENE triangles, made and prepared
    (a scene whose asked size is far above it is not generated: the set reaches 1M triangles)."""
    out = []
    for name, factory in scene_lib.calibration_set("default"):
        if factory.args[0] > 2 * M.SMALL_SCENE:
            continue
        mesh = factory()
        if mesh.triangle_count <= M.SMALL_SCENE:
            M.prepare_mesh(mesh)
            out.append((name, mesh))
    return out[:limit] if limit else out


def settled_build(mesh, kind: str) -> float:
    """Milliseconds of one build after ``settle_before_build``, as a measurement takes it."""
    M.settle_before_build(mesh.triangle_count)
    accel = build(mesh, kind)
    return accel.build_time * 1e3


def spread_of_median(values, n: int, rng) -> float:
    """p10-p90 of the median of n values drawn from ``values``, as % of the median of all."""
    meds = np.median(rng.choice(np.asarray(values), (RESAMPLES, n)), axis=1)
    return float((np.percentile(meds, 90) - np.percentile(meds, 10)) / np.median(values) * 100)


def spread(scenes, kinds, rounds: int) -> None:
    times = {(n, k): [] for n, _ in scenes for k in kinds}
    for _ in range(rounds):
        for n, mesh in scenes:
            for k in kinds:
                times[(n, k)].append(settled_build(mesh, k))
    rng = np.random.default_rng(0)
    many = 5 * M.SMALL_BUILDS
    print(f"{rounds} settled builds a row, interleaved; the spread of a median of 5 and of {many} "
          f"(p10-p90 over {RESAMPLES:,} resamples, % of the median)\n")
    print(f"| scene | kind | median ms | p10-p90 ms | median of 5 | median of {many} |")
    print("|---|---|--:|---|--:|--:|")
    for (n, k), v in times.items():
        print(f"| {n} | {k} | {np.median(v):.3f} | {np.percentile(v, 10):.2f}-{np.percentile(v, 90):.2f} | "
              f"{spread_of_median(v, 5, rng):.1f}% | {spread_of_median(v, many, rng):.1f}% |")


def order(scenes, kinds, rounds: int) -> None:
    times = {(n, k): [[] for _ in range(M.SMALL_BUILDS)] for n, _ in scenes for k in kinds}
    for r in range(rounds):
        for n, mesh in scenes:
            o, d = uniform_rays(mesh, ORDER_RAYS, seed=r)
            for k in kinds:
                bvh = build(mesh, "bvh")
                M.time_trace(bvh, o, d)
                del bvh
                for i in range(M.SMALL_BUILDS):
                    times[(n, k)][i].append(settled_build(mesh, k))
    heads = " | ".join(f"build {i + 1}" for i in range(M.SMALL_BUILDS))
    print(f"after a numpy BVH trace of {ORDER_RAYS:,} rays, {M.SMALL_BUILDS} settled builds in a row; "
          f"median ms of each position over {rounds} rounds\n")
    print(f"| scene | kind | {heads} |")
    print("|---|---|" + "--:|" * M.SMALL_BUILDS)
    for (n, k), cols in times.items():
        print(f"| {n} | {k} | " + " | ".join(f"{np.median(c):.3f}" for c in cols) + " |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=None, help="rounds over the scenes (default 25; 6 with --order)")
    ap.add_argument("--order", action="store_true", help="the builds of one measurement by position, after a trace")
    ap.add_argument("--kinds", default="bvh,embree", help="structures, comma-separated (those not buildable here are left out)")
    ap.add_argument("--scenes", type=int, default=None, help="only the first N small scenes")
    args = ap.parse_args(argv)
    kinds, notes = available_kinds(tuple(k for k in args.kinds.split(",") if k))
    for note in notes:
        print(note)
    if not kinds:
        return 1
    scenes = small_scenes(args.scenes)
    M.warm_up(("bvh",) + tuple(kinds))
    rounds = max(1, args.rounds or (6 if args.order else 25))
    (order if args.order else spread)(scenes, kinds, rounds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
