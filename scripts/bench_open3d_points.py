"""Open3D's point queries on given triangles and points, for bench_proximity.py (its peer).

    .venv-open3d/bin/python scripts/bench_open3d_points.py MESH.npz POINTS.npy --out RESULT.npz [--repeats 3]

Runs in its own virtual environment (``make open3d-venv``), so it imports nothing from the
project.  MESH.npz holds ``vertices`` (V, 3) float32 and ``triangles`` (T, 3) uint32.  Times
``RaycastingScene.compute_closest_points`` on the points (after a one-point query, so the
scene's BVH is built beforehand; medians of ``--repeats``) and prints one JSON line
{"open3d": version, "build_s", "closest_s", "points"}; writes the distances of the last run
and ``compute_occupancy`` (ray parity) per point to RESULT.npz.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("points")
    ap.add_argument("--out", required=True)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    import open3d as o3d

    z = np.load(args.mesh)
    pts = np.ascontiguousarray(np.load(args.points), np.float32)
    t0 = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(z["vertices"], np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(z["triangles"], np.uint32)))
    scene.compute_closest_points(o3d.core.Tensor(pts[:1]))
    build = time.perf_counter() - t0
    q = o3d.core.Tensor(pts)
    times, out = [], None
    for _ in range(max(1, args.repeats)):
        t0 = time.perf_counter()
        out = scene.compute_closest_points(q)
        times.append(time.perf_counter() - t0)
    near = out["points"].numpy().astype(np.float64)
    dist = np.linalg.norm(near - pts.astype(np.float64), axis=1)
    occupancy = scene.compute_occupancy(q).numpy()
    np.savez(args.out, distance=dist, occupancy=occupancy)
    print(json.dumps({"open3d": o3d.__version__, "build_s": build, "closest_s": statistics.median(times),
                      "points": int(len(pts))}), flush=True)


if __name__ == "__main__":
    main()
