"""Closest-point queries: this project's tree (numpy alone) against Blender's
``BVHTree.find_nearest`` in a Python loop and Open3D's ``compute_closest_points``, on the same
points, in one run.

    flock /tmp/hrc-bench.lock .venv/bin/python scripts/bench_proximity.py [--repeats 3]

Scenes: flat triangle grids of about 20k and 1M triangles in the unit square (the issue's);
points uniform in the scene's box grown by a fifth.  Ours answers ``--points`` points a run
on the BVH and on the grid (builds timed apart),
the BVHTree loop ``--loop-points`` of them; rates are queries per second, medians of
``--repeats`` runs, ratio = ours / BVHTree's.  Also the winding number's tree against its
exact sum on a closed sphere (max |error|, inside/outside agreement where |w - 0.5| > 0.1).
Open3D runs in its own venv (``make open3d-venv``; ``scripts/bench_open3d_points.py``) on the
same points when .venv-open3d exists: its rate, our rate over it, and on a closed sphere and
the same sphere with a cap cut off the share of points where its ray-parity occupancy
disagrees with the exact winding number (|w - 0.5| > 0.1), beside ours.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

from hybrid_raycast import core  # noqa: E402
from hybrid_raycast.core import scenes as S  # noqa: E402


def flat_grid(n: int) -> core.TriangleMesh:
    k = max(1, int(round((n / 2) ** 0.5)))
    x, y = np.meshgrid(np.linspace(0, 1, k + 1), np.linspace(0, 1, k + 1))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1).astype(np.float32)
    i = np.arange(k * k)
    a = (i // k) * (k + 1) + i % k
    t = np.concatenate([np.stack([a, a + 1, a + k + 2], 1), np.stack([a, a + k + 2, a + k + 1], 1)])
    return core.TriangleMesh(v, t.astype(np.int32))


def points_in(mesh, n, seed):
    lo, hi = (x.astype(float) for x in mesh.bounds())
    pad = 0.2 * np.maximum(hi - lo, 0.2 * (hi - lo).max())
    return np.random.default_rng(seed).uniform(lo - pad, hi + pad, size=(n, 3))


def bvhtree_rate(mesh, pts):
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    tree = BVHTree.FromPolygons(mesh.vertices.tolist(), mesh.triangles.tolist(), all_triangles=True)
    vs = [Vector(p) for p in pts]
    t0 = time.perf_counter()
    for p in vs:
        tree.find_nearest(p)
    return len(pts) / (time.perf_counter() - t0)


O3D_PYTHON = Path(__file__).resolve().parents[1] / ".venv-open3d" / "bin" / "python"


def open3d_points(mesh, pts, repeats):
    """(Open3D's answer as JSON, its distances, its occupancy), or None without its venv."""
    if not O3D_PYTHON.exists():
        return None
    with tempfile.TemporaryDirectory() as d:
        np.savez(f"{d}/mesh.npz", vertices=mesh.vertices, triangles=mesh.triangles.astype(np.uint32))
        np.save(f"{d}/points.npy", pts)
        out = subprocess.run([str(O3D_PYTHON), str(Path(__file__).with_name("bench_open3d_points.py")), f"{d}/mesh.npz",
                              f"{d}/points.npy", "--out", f"{d}/r.npz", "--repeats", str(repeats)],
                             capture_output=True, text=True, check=True)
        z = np.load(f"{d}/r.npz")
        return json.loads(out.stdout.strip().splitlines()[-1]), z["distance"], z["occupancy"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--loop-points", type=int, default=20_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", default="20000,1000000")
    args = ap.parse_args(argv)
    try:
        import bpy  # noqa: F401  (mathutils comes with it)
        have_bpy = True
    except ImportError:
        have_bpy = False
    print(f"closest point: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}, {args.points:,} points (ours), "
          f"{args.loop_points:,} (BVHTree loop), medians of {args.repeats}")
    print("| scene | triangles | BVH build s | ours (BVH) queries/s | ours (grid) /s | BVHTree.find_nearest loop /s | "
          "ratio (BVH) | Open3D compute_closest_points /s | ours / Open3D | max abs(d - Open3D's d) |")
    print("|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|")
    for n in (int(x) for x in args.sizes.split(",")):
        mesh = flat_grid(n)
        builds, ours, loop, grid = [], [], [], []
        for r in range(args.repeats):
            pts = points_in(mesh, args.points, seed=r)
            for kind, rates in (("bvh", ours), ("grid", grid)):
                acc = core.build(mesh, kind)
                t0 = time.perf_counter()
                acc.closest(pts[:1000])  # the point index is made on first use
                if kind == "bvh":
                    builds.append(acc.build_time + time.perf_counter() - t0)
                t0 = time.perf_counter()
                acc.closest(pts)
                rates.append(len(pts) / (time.perf_counter() - t0))
            if have_bpy:
                loop.append(bvhtree_rate(mesh, pts[: args.loop_points]))
        o = statistics.median(ours)
        g = statistics.median(grid)
        b = statistics.median(loop) if loop else float("nan")
        peer = open3d_points(mesh, points_in(mesh, args.points, seed=0), args.repeats)
        if peer is None:
            o3d = "not measured (no .venv-open3d: make open3d-venv) | - | -"
        else:
            info, dist, _ = peer
            rate = info["points"] / info["closest_s"]
            mine = core.build(mesh, "bvh").closest(points_in(mesh, args.points, seed=0)).distance
            o3d = f"{rate:,.0f} | {o / rate:.2f} | {np.abs(mine - dist).max():.1e}"
        print(f"| flat grid | {mesh.triangle_count:,} | {statistics.median(builds):.2f} | {o:,.0f} | {g:,.0f} | "
              f"{b:,.0f} | {o / b:.2f} | {o3d} |")
    mesh = S.sphere(20000)
    pts = points_in(mesh, 4000, seed=9)
    exact = core.build(mesh, "brute").winding_number(pts)
    acc = core.build(mesh, "bvh")
    t0 = time.perf_counter()
    w = acc.winding_number(pts)
    dt = time.perf_counter() - t0
    clear = np.abs(exact - 0.5) > 0.1
    print(f"\nwinding number, sphere {mesh.triangle_count:,} triangles, {len(pts):,} points: tree {len(pts) / dt:,.0f}/s, "
          f"max |w - exact| {np.abs(w - exact).max():.4f}, inside agrees where |w-0.5|>0.1: "
          f"{(acc.inside(pts) == (exact > 0.5))[clear].mean():.1%} of {int(clear.sum()):,}")
    # inside / outside against the exact winding number: ours and Open3D's ray parity
    print("\n| mesh | triangles | points with abs(w - 0.5) > 0.1 | ours wrong | Open3D occupancy wrong |")
    print("|---|--:|--:|--:|--:|")
    holed = core.TriangleMesh(mesh.vertices, mesh.triangles[mesh.tri_vertices.mean(axis=1)[:, 2] < 0.7 * float(
        mesh.bounds()[1][2])])
    for name, m in (("closed sphere", mesh), ("sphere, cap cut off", holed)):
        exact = core.build(m, "brute").winding_number(pts)
        clear = np.abs(exact - 0.5) > 0.1
        ours = core.build(m, "bvh").inside(pts)
        peer = open3d_points(m, pts, 1)
        theirs = ("not measured" if peer is None
                  else f"{((peer[2] > 0.5) != (exact > 0.5))[clear].mean():.1%}")
        print(f"| {name} | {m.triangle_count:,} | {int(clear.sum()):,} | "
              f"{(ours != (exact > 0.5))[clear].mean():.1%} | {theirs} |")


if __name__ == "__main__":
    main()
