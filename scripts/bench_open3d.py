"""Time Open3D's RaycastingScene on given triangles and rays, on request (run by bench_trace.py).

    .venv-open3d/bin/python scripts/bench_open3d.py MESH.npz RAYS.npy [RAYS.npy ...] --out DIR

Runs in its own virtual environment (``make open3d-venv``: open3d-cpu 0.20 needs
numpy 2, which bpy 5.0.1's numpy pin excludes), so it imports nothing from the project.
MESH.npz holds ``vertices`` (V, 3) float32 and ``triangles`` (T, 3) uint32; each
RAYS.npy is (M, 6) float32 [ox, oy, oz, dx, dy, dz], the format ``cast_rays`` takes.

It answers one command per line on stdin with one JSON line on stdout, so the caller
can interleave Open3D's runs with its own tracers' (the machine's load moves):
``build`` (``RaycastingScene()`` + ``add_triangles`` + a one-ray ``cast_rays``: the scene
commits, i.e. Embree builds its BVH, on the first cast) -> {"s": seconds};
``trace STEM`` (``cast_rays`` on RAYS STEM.npy, default threads) -> {"s": seconds};
``quit`` writes each batch's last primitive ids (int64, -1 on a miss) to
DIR/<stem>.prim.npy, answers {"done": true, "peak_rss_bytes": VmHWM} and exits.  The first
line says {"open3d": version, ..., "rss_bytes": VmRSS with the mesh and rays loaded} or
{"error": ...}, so the caller gets Open3D's extra peak memory (build + traces) as the difference.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def vm(field):
    """A /proc/self/status memory field in bytes (None off Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def say(obj):
    print(json.dumps(obj), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("rays", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    try:
        import open3d as o3d
    except Exception as e:  # ImportError, or a missing system library such as libusb-1.0
        say({"error": f"open3d cannot be imported: {type(e).__name__}: {e}"})
        return 0
    with np.load(args.mesh) as z:
        vertices = o3d.core.Tensor(np.ascontiguousarray(z["vertices"], np.float32))
        triangles = o3d.core.Tensor(np.ascontiguousarray(z["triangles"], np.uint32))
    rays = {p.stem: o3d.core.Tensor(np.load(p)) for p in args.rays}
    one = o3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], np.float32))
    invalid = o3d.t.geometry.RaycastingScene.INVALID_ID
    say({"open3d": o3d.__version__, "numpy": np.__version__, "cores": os.cpu_count(), "rss_bytes": vm("VmRSS")})
    scene, prim = None, {}
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "build":
            scene = None
            t0 = time.perf_counter()
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(vertices, triangles)
            scene.cast_rays(one)
            say({"s": time.perf_counter() - t0})
        elif cmd[0] == "trace" and scene is not None and cmd[1:] and cmd[1] in rays:
            t0 = time.perf_counter()
            ans = scene.cast_rays(rays[cmd[1]])
            say({"s": time.perf_counter() - t0})
            prim[cmd[1]] = ans["primitive_ids"].numpy()
        elif cmd[0] == "quit":
            for stem, p in prim.items():
                p = p.astype(np.int64)
                p[p == invalid] = -1
                np.save(args.out / f"{stem}.prim.npy", p)
            say({"done": True, "peak_rss_bytes": vm("VmHWM")})
            return 0
        else:
            say({"error": f"bad command {line.strip()!r} (build first; trace one of {sorted(rays)})"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
