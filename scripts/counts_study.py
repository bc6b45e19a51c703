"""Collect, per scene, the grid sample's work counts beside the true costs, for fitting and
judging count-based cost models (issue 14).  Prints one line per scene, writes JSON.

    flock /tmp/hrc-bench.lock .venv/bin/python scripts/counts_study.py --out out/counts.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

from hybrid_raycast.core import load_obj, scenes as scene_lib  # noqa: E402
from hybrid_raycast.core.decide import available_kinds, measure_break_even, time_trace  # noqa: E402
from hybrid_raycast.core.decide.work import grid_work  # noqa: E402
from hybrid_raycast.core.rays import uniform_rays  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(ROOT / "out" / "counts.json"))
    ap.add_argument("--rays", type=int, default=1 << 17)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--samples", type=int, default=16384)
    ap.add_argument("--scale", default="default")
    ap.add_argument("--subdivide", default="teapot:2,stanford-bunny:1,beetle-alt:2,fandisk:3")
    args = ap.parse_args(argv)
    kinds, _ = available_kinds(("grid", "bvh", "embree"))
    todo = [(n, "calibration", f) for n, f in scene_lib.calibration_set(args.scale)]
    folder = ROOT.parent / "shared" / "scenes"
    for p in sorted(folder.glob("*.obj")):
        todo.append((p.stem, "real", (lambda p=p: load_obj(p))))
    for spec in filter(None, args.subdivide.split(",")):
        stem, lv = spec.split(":")

        def make(stem=stem, lv=int(lv)):
            m = load_obj(folder / f"{stem}.obj")
            for _ in range(lv):
                m = scene_lib.subdivide(m)
            return m
        todo.append((f"{stem}-x{4 ** int(lv)}", "subdivided", make))
    rows = []
    print(f"load {os.getloadavg()}", flush=True)
    for name, group, make in todo:
        mesh = make()
        be = measure_break_even(mesh, args.rays, kinds, repeats=args.repeats, seed=1)
        g = be.structures["grid"]
        sample = []
        for r in range(3):  # the sample's time, three fresh samples (its noise, for comparison)
            o, d = uniform_rays(mesh, args.samples, seed=100 + r)
            h, dt = time_trace(g, o, d)
            sample.append(dt / len(o))
        t0 = time.perf_counter()
        w = grid_work(g, o, d, h.t)
        wt = time.perf_counter() - t0
        row = {"name": name, "group": group, "N": mesh.triangle_count, "work": w.to_dict(), "work_time": wt,
               "sample": sample, "R_C": be.R_C, "R_C_repeats": be.R_C_repeats,
               "meas": {k: {"build": m.build_time, "per_ray": m.per_ray} for k, m in be.measurements.items()},
               "runs": {k: [[m.build_time, m.per_ray] for m in v] for k, v in be.runs.items()}}
        rows.append(row)
        print(f"{name:22s} N {mesh.triangle_count:8d} cells {w.cells:6.1f} refs {w.refs:7.1f} hit {w.hit:.2f} len {w.length:.2f}"
              f"  t_G {row['meas']['grid']['per_ray'] * 1e6:5.2f} sample {sample[0] * 1e6:5.2f} t_H {row['meas']['bvh']['per_ray'] * 1e6:5.2f}"
              f"  B_H {row['meas']['bvh']['build'] * 1e3:7.1f} ms  work {wt * 1e3:.0f} ms", flush=True)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(rows, default=float))
    print(f"load {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
