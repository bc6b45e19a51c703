"""The README's picture of a scan: docs/scan.png, a top-down view of one frame's points.

    .venv/bin/python scripts/scan_picture.py [--frame 50] [--output docs/scan.png]

Scans frame ``--frame`` of the benchmark's animated scene (scripts/bench_scan.py: ground,
four static and three moving real meshes, an Ouster OS1-64 preset with its 1.5 cm range
noise) and plots x, y of every return coloured by range, beside the same points coloured
by the object hit.  matplotlib is used here only (pinned in requirements-dev.txt).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))



def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frame", type=int, default=50)
    ap.add_argument("--output", default=str(ROOT / "docs" / "scan.png"))
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import bench_scan

    pkg = bench_scan.load_addon()
    pkg.register()
    scene, sensor = bench_scan.build_scene(pkg, 100)
    sensor.hybrid_raycast_sensor.preset = "OS1_64"  # with the datasheet's 1.5 cm noise
    r = pkg.api.scan(sensor, frame=args.frame)
    p = r.points
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.4), dpi=110)
    a = axes[0].scatter(p[:, 0], p[:, 1], c=r.range, s=0.15, cmap="viridis", linewidths=0)
    fig.colorbar(a, ax=axes[0], label="range (m)", shrink=0.8)
    names = list(r.object_names)
    idx = r.object_index
    cmap = plt.get_cmap("tab10")
    for i, name in enumerate(names):
        m = idx == i
        if m.any():
            axes[1].scatter(p[m, 0], p[m, 1], s=0.15 if name == "Grid" else 0.6, color=cmap(i % 10), linewidths=0,
                            label=f"{name} ({m.sum():,})")
    axes[1].legend(markerscale=12, fontsize=8, loc="upper right")
    for ax, title in zip(axes, ("coloured by range", "coloured by the object hit")):
        ax.plot(*r.sensor_matrix[:2, 3], "r+", ms=12)
        ax.set_aspect("equal")
        ax.set_xlim(-20, 20)
        ax.set_ylim(-20, 20)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(title)
    fig.suptitle(f"api.scan, Ouster OS1-64 preset (64 x 2,048 rays, 1.5 cm noise), frame {args.frame}: "
                 f"{len(r):,} returns of {r.rays:,} rays, top view")
    fig.tight_layout()
    fig.savefig(args.output)
    print(f"wrote {args.output}: {len(r):,} points")
    pkg.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
