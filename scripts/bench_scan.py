"""Benchmark: sensor scans of an animated scene, against a per-ray ``scene.ray_cast`` loop.

    .venv/bin/python scripts/bench_scan.py [--frames 100] [--loop-frames 3]     (make bench-scan)

Scene: a 40 x 40 m ground (8,192 triangles), four static real meshes from ../shared/scenes
(bunny, homer, teapot, rocker-arm) and three moving ones (beetle-alt, cow, spot) keyframed
across the frame range, each scaled to about 3 m; the sensor is an Empty 1.8 m above the
ground at the centre.  Sensor: 64 channels over +-16.6 deg x 2,048 azimuth steps = 131,072
rays per frame (the Ouster OS1-64 preset, no noise).

Timed per frame, after ``scene.frame_set(f)`` (Blender's own evaluation, paid by both and
timed separately):
- ``api.scan``: extraction and the structure's build (the moving meshes change every
  frame, so the session extracts and builds again each frame; the first frame plans, later
  frames keep its choice, as the Scan operator does), 131,072 rays, the physics, the arrays;
- the same plus writing the frame's binary PLY (what the Scan operator does);
- BlAInder's method: the same 131,072 directions through ``scene.ray_cast`` one call per
  ray in a Python loop.  The loop is timed on ``--loop-frames`` frames only (it takes
  seconds per frame) and its per-frame median is extrapolated to the frame count.
``--static``: the meshes stand still and only the sensor (an Empty) moves, as when a
vehicle drives through a static scene.
``--returns DUAL --beam-samples 4 --beam-divergence 3``: every beam a cone of sub-rays and
up to two returns; the ``scene.ray_cast`` loop then casts the same sub-rays.
``--motion SWEEP``: each block of firings against the scene at its own time; with
``--compare-frame`` the same frames are also scanned with FRAME motion in the same run, in a
pass of their own after the first, and the table gains the SWEEP / FRAME ratio; ``--passes K``
repeats both passes K times in turn and takes the ratio's median over every pair.
Prints a table (medians over frames; frames per second = 1 / median); fails on nothing.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from _package import SHARED_SCENES, load_addon  # noqa: E402

import bpy  # noqa: E402
import numpy as np  # noqa: E402

STATIC = (("stanford-bunny", (8.0, 4.0)), ("homer", (-9.0, 6.0)), ("teapot", (5.0, -9.0)), ("rocker-arm", (-7.0, -7.0)))
MOVING = (("beetle-alt", (-15.0, 3.0), (15.0, 3.0)), ("cow", (10.0, -14.0), (-10.0, -2.0)), ("spot", (-3.0, 14.0), (9.0, -12.0)))


def mesh_object(pkg, name, size=3.0):
    m = pkg.core.load_obj(SHARED_SCENES / f"{name}.obj")
    v = m.vertices.astype(np.float64)
    lo, hi = v.min(0), v.max(0)
    v = (v - (lo + hi) / 2) * (size / (hi - lo).max())
    v[:, 2] -= v[:, 2].min() + 1.0  # stand on the ground at z = -1
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(v))
    me.vertices.foreach_set("co", v.astype(np.float32).ravel())
    tris = m.triangles.astype(np.int32)
    me.loops.add(tris.size)
    me.loops.foreach_set("vertex_index", tris.ravel())
    me.polygons.add(len(tris))
    me.polygons.foreach_set("loop_start", np.arange(0, tris.size, 3, dtype=np.int32))
    me.polygons.foreach_set("loop_total", np.full(len(tris), 3, np.int32))
    me.update()
    me.validate()
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def build_scene(pkg, frames, static=False):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, frames
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=65, y_subdivisions=65, size=40.0, location=(0, 0, -1.0))
    for name, (x, y) in STATIC:
        mesh_object(pkg, name).location = (x, y, 0.0)
    for name, a, b in MOVING:
        ob = mesh_object(pkg, name)
        ob.location = (*a, 0.0)
        if static:
            continue
        ob.keyframe_insert("location", frame=1)
        ob.location = (*b, 0.0)
        ob.keyframe_insert("location", frame=frames)
        ob.rotation_euler.z = 0.0
        ob.keyframe_insert("rotation_euler", frame=1)
        ob.rotation_euler.z = 3.0
        ob.keyframe_insert("rotation_euler", frame=frames)
    sensor = bpy.data.objects.new("Lidar", None)
    sensor.location = (0.0, 0.0, 0.8)
    scene.collection.objects.link(sensor)
    if static:  # only the sensor moves
        sensor.keyframe_insert("location", frame=1)
        sensor.location = (6.0, 3.0, 0.8)
        sensor.keyframe_insert("location", frame=frames)
    sensor.hybrid_raycast_sensor.preset = "OS1_64"
    sensor.hybrid_raycast_sensor.noise_sigma = 0.0
    scene.frame_set(1)
    return scene, sensor


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--loop-frames", type=int, default=3)
    ap.add_argument("--static", action="store_true", help="the meshes stand still; only the sensor (an Empty) moves")
    ap.add_argument("--returns", default="STRONGEST", choices=("STRONGEST", "FIRST", "LAST", "DUAL"))
    ap.add_argument("--beam-samples", type=int, default=1)
    ap.add_argument("--beam-divergence", type=float, default=0.0, help="milliradians")
    ap.add_argument("--motion", default="FRAME", choices=("FRAME", "SWEEP"))
    ap.add_argument("--compare-frame", action="store_true", help="also scan every frame with FRAME motion")
    ap.add_argument("--passes", type=int, default=1,
                    help="with --compare-frame: rounds of a pass of each motion (the ratio's median is over all)")
    ap.add_argument("--scan-frames", type=int, default=None,
                    help="scan only the first N frames of the animation (default: every frame)")
    args = ap.parse_args(argv)
    if not SHARED_SCENES.is_dir():
        print(f"needs the meshes in {SHARED_SCENES}", file=sys.stderr)
        return 2
    pkg = load_addon()
    pkg.register()
    scan_mod = pkg.operators.scan
    scene, sensor = build_scene(pkg, args.frames, static=args.static)
    dg = bpy.context.evaluated_depsgraph_get()
    tris = sum(len(o.evaluated_get(dg).data.loop_triangles) for o in scene.objects if o.type == "MESH")
    s = sensor.hybrid_raycast_sensor
    s.returns, s.beam_samples, s.beam_divergence, s.motion = (args.returns, args.beam_samples, args.beam_divergence,
                                                              args.motion)
    model, phys = scan_mod.sensor_model(sensor)
    sub, _ = pkg.core.returns.beam_directions(model.pattern().directions, phys.beam_divergence, phys.beam_samples)
    rays = len(sub)
    moving = "only the sensor moves" if args.static else f"{len(MOVING)} moving meshes"
    print(f"sensor: returns {args.returns}, {args.beam_samples} sample(s) per beam over {args.beam_divergence:g} mrad, "
          f"motion {args.motion}")
    print(f"scene: {tris:,} triangles ({moving}), {rays:,} rays per frame, "
          f"{args.frames} frames, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")

    t_set, t_scan, t_write, points, structures, t_frame, blocks = [], [], [], [], set(), [], []
    out = Path(tempfile.mkdtemp(prefix="hrc-bench-scan-"))
    structure = frame_structure = "auto"
    scanned = min(args.frames, args.scan_frames or args.frames)
    for f in range(1, scanned + 1):
        t0 = time.perf_counter()
        scene.frame_set(f)
        t1 = time.perf_counter()
        r = pkg.api.scan(sensor, structure=structure)
        structure = r.structure  # as the Scan operator does: plan on the first frame, then keep its choice
        t2 = time.perf_counter()
        t_scan.append(t2 - t1)
        t_set.append(t1 - t0)
        blocks.append(r.blocks)
        ta = time.perf_counter()
        scan_mod.write_scan(r, out / f"frame_{f:04d}.ply", "ply")
        t_write.append(time.perf_counter() - ta)
        points.append(len(r))
        structures.add(r.structure)
    ratios, round_medians = [], []
    for k in range(args.passes if args.compare_frame else 0):
        # the same frames with FRAME motion, in a pass of their own (interleaved, one scan would
        # find the other's extraction of the same instant); further rounds repeat both passes,
        # so a drift of the machine's speed shows as the spread between rounds
        t_sweep = t_scan if k == 0 else []
        for f in range(1, scanned + 1) if k else ():
            scene.frame_set(f)
            ta = time.perf_counter()
            structure = pkg.api.scan(sensor, structure=structure).structure
            t_sweep.append(time.perf_counter() - ta)
        s.motion = "FRAME"
        t_round = []
        for f in range(1, scanned + 1):
            scene.frame_set(f)
            ta = time.perf_counter()
            frame_structure = pkg.api.scan(sensor, structure=frame_structure).structure  # its own plan, then kept
            t_round.append(time.perf_counter() - ta)
        s.motion = args.motion
        t_frame += t_round
        pairs = [a / b for a, b in zip(t_sweep, t_round)]
        ratios += pairs
        round_medians.append(statistics.median(pairs))
    size = sum(p.stat().st_size for p in out.iterdir())
    for p in out.iterdir():
        p.unlink()
    out.rmdir()

    from mathutils import Vector

    t_loop = []
    for f in range(1, args.loop_frames + 1):
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        pose = scan_mod.sensor_pose(sensor.evaluated_get(dg))
        d = sub @ pose[:3, :3].T
        o = Vector(pose[:3, 3].tolist())
        t0 = time.perf_counter()
        dirs = [Vector(x) for x in d.tolist()]
        hits = 0
        for v in dirs:
            if scene.ray_cast(dg, o, v, distance=model.range_max)[0]:
                hits += 1
        t_loop.append(time.perf_counter() - t0)
    med = statistics.median
    scan_s, write_s, set_s, loop_s = med(t_scan), med(t_write), med(t_set), med(t_loop)
    print(f"structures used: {', '.join(sorted(structures))}; points per frame median {med(points):,.0f}; "
          f"PLY {size / scanned / 2**20:.1f} MiB per frame; {scanned} frames scanned")
    print()
    print("| method | s per frame (median) | frames/s | x faster than the ray_cast loop |")
    print("|---|---:|---:|---:|")
    print(f"| api.scan (arrays) | {scan_s:.3f} | {1 / scan_s:.2f} | {loop_s / scan_s:.1f} |")
    print(f"| api.scan + binary PLY | {scan_s + write_s:.3f} | {1 / (scan_s + write_s):.2f} | "
          f"{loop_s / (scan_s + write_s):.1f} |")
    print(f"| scene.ray_cast loop ({args.loop_frames} frames timed) | {loop_s:.3f} | {1 / loop_s:.3f} | 1.0 |")
    if t_frame:
        fr = med(t_frame)
        print(f"| api.scan, FRAME motion (same frames) | {fr:.3f} | {1 / fr:.2f} | {loop_s / fr:.1f} |")
        print()
        print(f"{args.motion} / FRAME: median of per-frame ratios {med(ratios):.2f} over {len(ratios)} pairs "
              f"(min {min(ratios):.2f}, max {max(ratios):.2f}; each round's median "
              f"{', '.join(f'{x:.2f}' for x in round_medians)}); sweep blocks per frame median {med(blocks):.0f}")
    print()
    print(f"scene.frame_set (Blender's evaluation, excluded above): median {set_s * 1e3:.1f} ms per frame")
    print(f"api.scan first frame {t_scan[0]:.3f} s, min {min(t_scan):.3f} s, max {max(t_scan):.3f} s")
    print(f"{scanned} frames: api.scan {sum(t_scan):.1f} s measured; ray_cast loop ~{loop_s * scanned:.0f} s "
          f"extrapolated from {args.loop_frames} frames ({min(t_loop):.2f}-{max(t_loop):.2f} s each)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    pkg.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
