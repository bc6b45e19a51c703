"""Collect, per scene, the grid sample's work counts beside the true costs, for fitting and
judging count-based cost models (issue 14).  Prints one line per scene, writes JSON.

    flock /tmp/hrc-bench.lock .venv/bin/python scripts/counts_study.py --out out/counts.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

from hybrid_raycast.core import load_obj, scenes as scene_lib  # noqa: E402
import numpy as np  # noqa: E402

from hybrid_raycast.core.decide import Measurement, SceneRecord  # noqa: E402
from hybrid_raycast.core.decide import evaluate as rep  # noqa: E402
from hybrid_raycast.core.decide import available_kinds, measure_break_even, time_trace  # noqa: E402
from hybrid_raycast.core.decide.work import grid_work  # noqa: E402
from hybrid_raycast.core.rays import uniform_rays  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def records(rows, kinds=("grid", "bvh", "embree")):
    """The study's rows as calibration SceneRecords (medians as Measurements)."""
    out = []
    for r in rows:
        n_rays = 1 << 17
        kk = {k: Measurement(m["build"], m["per_ray"] * n_rays, n_rays) for k, m in r["meas"].items() if k in kinds}
        out.append((r["group"], SceneRecord(r["name"], r["N"], n_rays, kk, {16384: float(np.median(r["sample"]))}, r["work"])))
    return out


GRID_TERMS = {"cells+refs": ("1", "cells", "refs"), "cells": ("1", "cells"), "refs": ("1", "refs")}
HDS_TERMS = {"log2n": ("1", "log2n"), "log2n+hit": ("1", "log2n", "hit_log2n"),
             "log2n+hit+length": ("1", "log2n", "hit_log2n", "length_log2n"),
             "log2n+cells+refs": ("1", "log2n", "cells", "refs"), "cells+refs": ("1", "cells", "refs"),
             "log2n+length": ("1", "log2n", "length_log2n"), "log2n+hit+len+refs": ("1", "log2n", "hit_log2n", "length_log2n", "refs")}


def analyse(path, kind="bvh"):
    recs = records(json.loads(Path(path).read_text()))
    cal = [r for g, r in recs if g == "calibration"]
    ev_ = [r for g, r in recs if g != "calibration"]
    mabs = lambda xs: float(np.median([abs(x) for x in xs if math.isfinite(x)])) if any(math.isfinite(x) for x in xs) else math.nan  # noqa: E731
    print(f"{kind}: {len(cal)} calibration scenes, {len(ev_)} evaluated; median |error| in %: break-even (LOO on calibration / "
          f"evaluated, fitted on all calibration), grid per-ray, {kind} per-ray")
    rows = []
    for gname, gt in [("sample x ratio", None)] + list(GRID_TERMS.items()):
        for hname, ht in [("affine log2n", None)] + list(HDS_TERMS.items()):
            kw = dict(kind=kind, grid="sample" if gt is None else "counts", hds="affine" if ht is None else "counts",
                      terms_of={"grid": gt or ("1", "cells", "refs"), kind: ht or ("1", "log2n")})
            loo = rep.leave_one_out(cal, **kw)
            held = rep.held_out_errors(cal, ev_, **kw)
            rows.append((gname, hname, mabs([x["error"] for x in loo]), mabs([x["error"] for x in held]),
                         mabs([x["grid_error"] for x in held]), mabs([x["per_ray_error"] for x in held]),
                         sum(not math.isfinite(x["error"]) for x in held)))
    print(f"{'grid':16s} {kind + ' per ray':20s} {'LOO':>7s} {'eval':>7s} {'t_G':>6s} {'t_H':>6s} undefined")
    for r in rows:
        print(f"{r[0]:16s} {r[1]:20s} {r[2]:7.1f} {r[3]:7.1f} {r[4]:6.1f} {r[5]:6.1f} {r[6]}")


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(ROOT / "out" / "counts.json"))
    ap.add_argument("--rays", type=int, default=1 << 17)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--samples", type=int, default=16384)
    ap.add_argument("--scale", default="default")
    ap.add_argument("--analyse", default="", help="print the held-out errors of the count models on a saved JSON")
    ap.add_argument("--kind", default="bvh")
    ap.add_argument("--subdivide", default="teapot:2,stanford-bunny:1,beetle-alt:2,fandisk:3")
    args = ap.parse_args(argv)
    if args.analyse:
        return analyse(args.analyse, args.kind)
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
