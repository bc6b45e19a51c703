"""Time Open3D's RaycastingScene on given triangles and rays (run by bench_trace.py).

    .venv-open3d/bin/python scripts/bench_open3d.py MESH.npz RAYS.npy [RAYS.npy ...] --repeats 3 --out DIR

Runs in its own virtual environment (``make open3d-venv``: open3d-cpu 0.20 needs
numpy 2, which bpy 5.0.1's numpy pin excludes), so it imports nothing from the project.
MESH.npz holds ``vertices`` (V, 3) float32 and ``triangles`` (T, 3) uint32; each
RAYS.npy is (M, 6) float32 [ox, oy, oz, dx, dy, dz], the format ``cast_rays`` takes.
Build = ``RaycastingScene()`` + ``add_triangles`` + a one-ray ``cast_rays`` (the scene
commits, i.e. Embree builds its BVH, on the first cast).  Prints one JSON line with the
times; writes each batch's primitive ids (int64, -1 on a miss) to DIR/<stem>.prim.npy.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("rays", type=Path, nargs="+")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    try:
        import open3d as o3d
    except Exception as e:  # ImportError, or a missing system library such as libusb-1.0
        print(json.dumps({"error": f"open3d cannot be imported: {type(e).__name__}: {e}"}))
        return 0
    with np.load(args.mesh) as z:
        vertices = o3d.core.Tensor(np.ascontiguousarray(z["vertices"], np.float32))
        triangles = o3d.core.Tensor(np.ascontiguousarray(z["triangles"], np.uint32))
    one = o3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], np.float32))
    builds = []
    scene = None
    for _ in range(args.repeats):
        scene = None
        t0 = time.perf_counter()
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(vertices, triangles)
        scene.cast_rays(one)
        builds.append(time.perf_counter() - t0)
    out = {"open3d": o3d.__version__, "numpy": np.__version__, "cores": os.cpu_count(), "build_s": builds, "trace_s": {}}
    invalid = o3d.t.geometry.RaycastingScene.INVALID_ID
    for path in args.rays:
        rays = o3d.core.Tensor(np.load(path))
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            ans = scene.cast_rays(rays)
            times.append(time.perf_counter() - t0)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        prim[prim == invalid] = -1
        np.save(args.out / f"{path.stem}.prim.npy", prim)
        out["trace_s"][path.stem] = times
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
