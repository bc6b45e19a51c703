"""The README's picture of a sweep: docs/sweep.png, one frame scanned with FRAME and with SWEEP motion.

    .venv/bin/python scripts/sweep_figure.py [--output docs/sweep.png] [--speed 20] [--distance 10]

Scene: a 40 x 40 m ground plane and a 2 m cube, turned 45 degrees about Z (a corner towards
the sensor), ``--distance`` metres along the sensor's X axis (azimuth 0, where a turn starts
and ends), moving along -Y at ``--speed`` m/s (linear keyframes, 10 frames per second); the
sensor is an Empty 1 m above the ground, a Velodyne VLP-16 preset turning at ``--rate`` Hz.
Frame 1 is scanned through ``api.scan`` twice: with motion FRAME every ray sees the cube
where it is at the frame; with SWEEP each block of firings sees it at its own time, so the
rays fired at the start of the turn (azimuth just above 0) and those fired at its end (just
below 360) see it ``speed / rate`` metres apart: the cube, moving against the turn, shows
twice, as in a real scan. Both are plotted top-down (x, y), coloured by each point's firing
time within the sweep, with the cube's outline at the start (solid) and the end (dashed) of
the sweep. About 2 s on two cores. matplotlib is used here only.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

FPS = 10
#: half the diagonal of the 2 m cube's square footprint
HALF_DIAGONAL = math.sqrt(2.0)


def _fcurves(ob):
    action = ob.animation_data.action
    if hasattr(action, "fcurves"):  # before Blender 5.0
        return action.fcurves
    from bpy_extras import anim_utils  # layered actions (4.4+; the only kind in 5.0)

    return anim_utils.action_get_channelbag_for_slot(action, ob.animation_data.action_slot).fcurves


def _outline(cx, cy):
    h = HALF_DIAGONAL
    return [(cx - h, cy), (cx, cy - h), (cx + h, cy), (cx, cy + h)]


def build_scene(speed: float, distance: float, rate: float, max_skew: float):
    """(scene, sensor, cube) in a new empty file; at frame 1 the cube's lowest corner is on
    the X axis (it spans azimuths 0 to about 16 degrees at the start of the turn)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = FPS, 1.0
    scene.frame_start, scene.frame_end = 1, 5
    bpy.ops.mesh.primitive_plane_add(size=40.0, location=(0.0, 0.0, 0.0))
    bpy.context.active_object.name = "Ground"
    bpy.ops.mesh.primitive_cube_add(size=2.0, location=(distance, HALF_DIAGONAL, 1.0), rotation=(0.0, 0.0, math.pi / 4))
    cube = bpy.context.active_object
    cube.name = "Cube"
    cube.keyframe_insert("location", frame=1)
    cube.location.y -= speed * 4 / FPS
    cube.keyframe_insert("location", frame=5)
    for fc in _fcurves(cube):  # uniform motion: no ease in or out
        for k in fc.keyframe_points:
            k.interpolation = "LINEAR"
    sensor = bpy.data.objects.new("Lidar", None)
    sensor.location = (0.0, 0.0, 1.0)
    scene.collection.objects.link(sensor)
    s = sensor.hybrid_raycast_sensor
    s.preset = "VLP16"
    s.rotation_rate = rate
    s.sweep_tolerance = max_skew
    scene.frame_set(1)
    return scene, sensor, cube


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output", default=str(ROOT / "docs" / "sweep.png"))
    ap.add_argument("--speed", type=float, default=20.0, help="the cube's speed along -Y, m/s (default 20)")
    ap.add_argument("--distance", type=float, default=10.0, help="the cube's centre along X, m (default 10)")
    ap.add_argument("--rate", type=float, default=10.0, help="the sensor's rotation rate, Hz (default 10)")
    ap.add_argument("--max-skew", type=float, default=0.02, help="SWEEP's Max Skew, m (default 0.02)")
    ap.add_argument("--dpi", type=int, default=100)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    from _bpy_exit import exit_past_bpy
    from _package import load_addon

    pkg = load_addon()
    pkg.register()
    scene, sensor, cube = build_scene(args.speed, args.distance, args.rate, args.max_skew)
    results = {}
    for motion in ("FRAME", "SWEEP"):
        sensor.hybrid_raycast_sensor.motion = motion
        results[motion] = pkg.api.scan(sensor, frame=1)
    sweep = 1.0 / args.rate
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5), dpi=args.dpi, sharey=True, layout="constrained")
    for ax, (motion, r) in zip(axes, results.items()):
        ms = (r.time - r.time.min()) * 1e3  # frame 1 is the first: its scene time is 0
        a = ax.scatter(r.points[:, 0], r.points[:, 1], c=ms, s=1.5, cmap="viridis", vmin=0, vmax=sweep * 1e3,
                       linewidths=0, rasterized=True)
        on_cube = r.point_object_names == "Cube"
        ax.scatter(r.points[on_cube, 0], r.points[on_cube, 1], c=ms[on_cube], s=8, cmap="viridis", vmin=0,
                   vmax=sweep * 1e3, linewidths=0)
        for dy, ls in ((0.0, "-"), (-args.speed * sweep, "--")):
            ax.add_patch(Polygon(_outline(args.distance, HALF_DIAGONAL + dy), fill=False, ec="k", lw=0.7, ls=ls))
        ax.plot(0.0, 0.0, "r+", ms=10)
        ax.set_aspect("equal")
        ax.set_xlim(-1.0, args.distance + 3.0)
        ax.set_ylim(-3.0 - args.speed * sweep, 5.0)
        ax.set_xlabel("x (m)")
        ax.set_title(f"motion {motion}: {int(on_cube.sum())} points on the cube"
                     + (f", {r.blocks} blocks" if motion == "SWEEP" else ""), fontsize=10)
    axes[0].set_ylabel("y (m)")
    fig.colorbar(a, ax=axes, label="firing time in the sweep (ms)", shrink=0.9)
    fig.suptitle(f"A 2 m cube crossing azimuth 0 at {args.speed:g} m/s, seen by a {args.rate:g} Hz VLP-16 at the "
                 f"red cross; outlines: the cube at the start and the end of the sweep", fontsize=10)
    fig.savefig(args.output, dpi=args.dpi)
    print(f"wrote {args.output}: FRAME {len(results['FRAME']):,} points, SWEEP {len(results['SWEEP']):,} points "
          f"in {results['SWEEP'].blocks} blocks")
    pkg.unregister()
    exit_past_bpy(0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
