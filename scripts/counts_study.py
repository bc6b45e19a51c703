"""Collect, per scene, the grid sample's work counts beside the true costs, for fitting and
judging count-based cost models (issue 14).  Prints one line per scene, writes JSON.

    flock /tmp/hrc-bench.lock .venv/bin/python scripts/counts_study.py --out out/counts.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import ROOT, SHARED_SCENES, core_package  # noqa: E402

core_package()

from hybrid_raycast.core import load_obj, scenes as scene_lib  # noqa: E402
import numpy as np  # noqa: E402

from hybrid_raycast.core.decide import DEFAULT_MODEL, Calibration, Measurement, SceneRecord, fit  # noqa: E402
from hybrid_raycast.core.decide.cost import fit_counts  # noqa: E402
from hybrid_raycast.core.decide import evaluate as rep  # noqa: E402
from hybrid_raycast.core.decide import available_kinds, measure_break_even, time_trace  # noqa: E402
from hybrid_raycast.core.decide.work import grid_work  # noqa: E402
from hybrid_raycast.core.rays import uniform_rays  # noqa: E402


#: calibration scenes left out of every fit (``--drop``): to compare calibration sets
DROP = None


def load_rows(path):
    """The study's rows, less the calibration scenes ``--drop`` leaves out."""
    rows = json.loads(Path(path).read_text())
    return [r for r in rows if not (DROP and r["group"] == "calibration" and re.search(DROP, r["name"]))]


def records(rows, kinds=("grid", "bvh", "embree")):
    """The study's rows as calibration SceneRecords (medians as Measurements)."""
    out = []
    for r in rows:
        n_rays = 1 << 17
        kk = {k: Measurement(m["build"], m["per_ray"] * n_rays, n_rays) for k, m in r["meas"].items() if k in kinds}
        out.append((r["group"], SceneRecord(r["name"], r["N"], n_rays, kk, {16384: float(np.median(r["sample"]))}, r["work"])))
    return out


#: (label, terms, form) of the grid's and the structure's count models the study compares
GRID_MODELS = [("cells", ("1", "cells"), "linear"), ("cells+refs", ("1", "cells", "refs"), "linear"),
               ("log: cells", ("1", "cells"), "log"), ("log: cells+refs", ("1", "cells", "refs"), "log")]
HDS_MODELS = [("log2n", ("1", "log2n"), "linear"), ("log2n+cells+refs", ("1", "log2n", "cells", "refs"), "linear"),
              ("log2n+hit+length", ("1", "log2n", "hit_log2n", "length_log2n"), "linear"),
              ("log: log2n", ("1", "log2n"), "log"), ("log: log2n+cells", ("1", "log2n", "cells"), "log"),
              ("log: log2n+refs", ("1", "log2n", "refs"), "log"), ("log: cells+refs", ("1", "cells", "refs"), "log"),
              ("log: log2n+cells+refs", ("1", "log2n", "cells", "refs"), "log")]


def repeat_records(rows, recs, r):
    """The calibration records with repeat ``r``'s timings alone: one calibration of three in a row."""
    out = []
    for row, (g, rec) in zip(rows, recs):
        if g != "calibration":
            continue
        kk = {k: Measurement(v[r][0], v[r][1] * rec.rays, rec.rays) for k, v in row["runs"].items() if k in rec.kinds}
        out.append(SceneRecord(rec.name, rec.triangles, rec.rays, kk, rec.grid_samples, rec.work))
    return out


def analyse(path, kind="bvh"):
    """Held-out errors of every (build model, grid count model, structure count model), and how
    far apart the per-ray times are that calibrations on each repeat's timings alone predict."""
    rows = load_rows(path)
    recs = records(rows)
    cal = [r for g, r in recs if g == "calibration"]
    ev_ = [r for g, r in recs if g != "calibration"]
    reps = [repeat_records(rows, recs, r) for r in range(min(len(v) for row in rows for v in row["runs"].values()))]
    mabs = lambda xs: float(np.median([abs(x) for x in xs if math.isfinite(x)])) if any(math.isfinite(x) for x in xs) else math.nan  # noqa: E731
    print(f"{kind}: {len(cal)} calibration scenes, {len(ev_)} evaluated, {len(reps)} repeats; median |error| in %: break-even "
          f"(LOO on calibration / evaluated, fitted on all calibration), grid per-ray, {kind} per-ray, {kind} build (evaluated); "
          f"agree: largest per-ray (grid, {kind}) and build difference between calibrations on single repeats, on the evaluated meshes")
    print(f"{'build':7s} {'grid':16s} {kind + ' per ray':22s} {'LOO':>7s} {'eval':>7s} {'t_G':>6s} {'t_H':>6s} {'T_B':>6s} undef "
          f"{'agree t_G':>9s} {'t_H':>6s} {'T_B':>6s}")
    for model in ("affine", "power"):
        for gname, gt, gf in GRID_MODELS:
            for hname, ht, hf in HDS_MODELS:
                kw = dict(kind=kind, grid="counts", hds="counts", model=model,
                          terms_of={"grid": gt, kind: ht}, forms_of={"grid": gf, kind: hf})
                loo = rep.leave_one_out(cal, **kw)
                held = rep.held_out_errors(cal, ev_, **kw)
                fits = [(fit_counts(rr, ("grid", kind), terms_of=kw["terms_of"], forms_of=kw["forms_of"]),
                         fit(rr, (kind,), model=model)[kind]) for rr in reps]
                worst = [0.0, 0.0, 0.0]
                for a in range(len(fits)):
                    for b in range(a + 1, len(fits)):
                        for rec in ev_:
                            for j, k in enumerate(("grid", kind)):
                                pa, pb = fits[a][0][k].predict(rec.triangles, rec.work), fits[b][0][k].predict(rec.triangles, rec.work)
                                worst[j] = max(worst[j], 200 * abs(pa - pb) / (pa + pb))
                            est = rep.model_functions(model)[1]
                            pa, pb = est(fits[a][1], kind, rec.triangles).build, est(fits[b][1], kind, rec.triangles).build
                            worst[2] = max(worst[2], 200 * abs(pa - pb) / (pa + pb))
                print(f"{model:7s} {gname:16s} {hname:22s} {mabs([x['error'] for x in loo]):7.1f} {mabs([x['error'] for x in held]):7.1f} "
                      f"{mabs([x['grid_error'] for x in held]):6.1f} {mabs([x['per_ray_error'] for x in held]):6.1f} "
                      f"{mabs([x['build_error'] for x in held]):6.1f} {sum(not math.isfinite(x['error']) for x in held):5d} "
                      f"{worst[0]:9.1f} {worst[1]:6.1f} {worst[2]:6.1f}", flush=True)


def agree(path, cal_paths, kind="bvh"):
    """Two calibrations in a row (``ship_calibration.py --output``), refitted under each
    (build model, grid count model, structure count model): how far apart the constants and
    the per-ray times, builds and break-evens they predict on the study's evaluated meshes are."""
    from hybrid_raycast.core.decide import load

    ev_ = [r for g, r in records(json.loads(Path(path).read_text())) if g != "calibration"]
    cals = [load(p, check_version=False) for p in cal_paths]
    d = lambda a, b: 200 * abs(a - b) / (a + b) if a + b > 0 else 0.0  # noqa: E731
    print(f"{len(cals)} calibrations ({', '.join(str(p) for p in cal_paths)}); differences in % of the mean, "
          f"median (max) over {len(ev_)} evaluated meshes; break-even max/min median (max)")
    print(f"{'build':7s} {'grid':16s} {kind + ' per ray':22s} {'t_G':>13s} {'t_H':>13s} {'T_B':>13s} {'R*':>13s}  constants")
    for model in ("affine", "power"):
        for gname, gt, gf in GRID_MODELS:
            for hname, ht, hf in HDS_MODELS:
                fits = [(fit_counts(c.scenes, ("grid", kind), terms_of={"grid": gt, kind: ht}, forms_of={"grid": gf, kind: hf}),
                         fit(c.scenes, (kind,), model=model)[kind]) for c in cals]
                est = rep.model_functions(model)[1]
                cols = {"t_G": [], "t_H": [], "T_B": [], "R*": []}
                for rec in ev_:
                    n, w = rec.triangles, rec.work
                    p = [(f[0]["grid"].predict(n, w), f[0][kind].predict(n, w), est(f[1], kind, n).build) for f in fits]
                    cols["t_G"].append(d(p[0][0], p[1][0]))
                    cols["t_H"].append(d(p[0][1], p[1][1]))
                    cols["T_B"].append(d(p[0][2], p[1][2]))
                    r = [rep.break_even(b, g, h) for g, h, b in p]
                    if all(math.isfinite(x) for x in r):
                        cols["R*"].append(max(r) / min(r))
                consts = "; ".join(f"{k} " + "/".join(f"{a:.3g}|{b:.3g}" for a, b in zip(fits[0][0][k].coef, fits[1][0][k].coef))
                                   for k in ("grid", kind))
                b0, b1 = fits[0][1], fits[1][1]
                consts += f"; build c_B {b0.c_B:.3g}|{b1.c_B:.3g} " + " ".join(f"{x} {b0.extra[x]:.3g}|{b1.extra[x]:.3g}" for x in b0.extra)
                cell = lambda v, f="{:5.1f}": (f.format(np.median(v)) + " (" + f.format(max(v)) + ")") if v else "n/a"  # noqa: E731
                print(f"{model:7s} {gname:16s} {hname:22s} {cell(cols['t_G']):>13s} {cell(cols['t_H']):>13s} {cell(cols['T_B']):>13s} "
                      f"{cell(cols['R*'], '{:5.2f}'):>13s}  {consts}", flush=True)


def _calibration(recs, model=DEFAULT_MODEL):
    """A Calibration fitted on ``recs`` as ``calibrate()`` fits it (affine build and per-ray
    constants, the count models of ``cost.COUNT_TERMS``)."""
    kinds = tuple(k for k in ("bvh", "embree") if all(k in r.kinds for r in recs))
    return Calibration(fit(recs, kinds, model=model), scenes=list(recs), model=model,
                       counts=fit_counts(recs, ("grid",) + kinds), source="counts study")


def evaluate(path, k_samples=16384, plans=5):
    """The issue-14 goals from the study's measurements: models fitted on the calibration
    scenes, judged on the evaluated meshes (break-even errors, picks, hybrid / oracle);
    R_C's own spread over its interleaved repeats; constants fitted on each repeat alone
    (three calibrations from independent timings); five plan() runs per evaluated mesh."""
    rows = load_rows(path)
    recs = records(rows)
    cal_recs = [r for g, r in recs if g == "calibration"]
    cal = _calibration(cal_recs)
    print(cal.describe())
    kinds = tuple(cal.fits)
    results = []
    for row, (g, rec) in zip(rows, recs):
        if g == "calibration":
            continue
        n = rec.triangles
        t_g = cal.count_per_ray("grid", n, rec.work)[0]
        est = {k: rep.Cost(cal.estimate(k, n).build, cal.count_per_ray(k, n, rec.work)[0]) for k in kinds}
        meas = {k: rep.Cost(rec.kinds[k].build_time, rec.kinds[k].per_ray) for k in kinds}
        cost_e = float(np.median(row["sample"])) * k_samples + row["work_time"]
        s = rep.SceneResult(rec.name, n, rec.rays, rep.Cost(rec.kinds["grid"].build_time, rec.kinds["grid"].per_ray),
                            meas, est, t_g, cost_e, k_samples, g,
                            reuse_estimate_time=row["work_time"], floor=cal.break_even_floor(n, ("bvh",)))
        s.extra["R_C_repeats"] = row["R_C_repeats"]
        results.append(s)
    mabs = lambda xs: float(np.median([abs(x) for x in xs if math.isfinite(x)]))  # noqa: E731
    for k in kinds:
        errs = [rep.relative_error(rep.estimated_break_even(s, k), rep.true_break_even(s, k)) for s in results]
        spread = []
        for s in results:
            v = [x for x in s.extra["R_C_repeats"].get(k, []) if x is not None and math.isfinite(x)]
            if len(v) >= 2:
                spread.append(100 * (max(v) - min(v)) / float(np.median(v)))
        e = rep.error_summary(errs)
        print(f"vs {k}: median |error| {e['median_abs']:.1f}% over {e['defined']} of {e['scenes']} scenes "
              f"({rep.never_agreement([(rep.estimated_break_even(s, k), rep.true_break_even(s, k)) for s in results])}); "
              f"R_C's own spread over its repeats: median {np.median(spread):.1f}%")
        for s, x in zip(results, errs):
            v = s.extra["R_C_repeats"].get(k, [])
            print(f"   {s.name:20s} R_C {rep.true_break_even(s, k):12,.0f} R_est {rep.estimated_break_even(s, k):12,.0f} "
                  f"error {x:+7.1f}%  R_C repeats {', '.join(f'{y:,.0f}' for y in v)}")
    for k in kinds:
        fl = [(s.name, s.floor, rep.true_break_even(s, k), cal.break_even_floor(s.triangles, (k,))) for s in results]
        bad = [x for x in fl if x[3] > x[2]]
        print(f"floor on R* vs {k} (calibration alone): median floor / R_C {np.median([x[3] / x[2] for x in fl]):.3f}, "
              f"max {max(x[3] / x[2] for x in fl):.3f}; above R_C on {len(bad)} of {len(fl)} scenes"
              + (": " + ", ".join(f"{n} {f:,.0f} > {r:,.0f}" for n, _, r, f in bad) if bad else ""))
    sp0 = rep.speedup_summary([replace(s, floor=0.0) for s in results])
    print(f"hybrid / oracle without the floor, median: (i) {sp0['hybrid_over_oracle']['median']:.3f}, "
          f"(ii) {sp0['hybrid_reuse_over_oracle']['median']:.3f}")
    pk = rep.pick_accuracy(results)
    sp = rep.speedup_summary(results)
    calls = []
    for s in results:
        t = rep.strategy_totals(s, rep.RAY_COUNTS, ("bvh",), "bvh", batch=1000)
        calls += list(t["online"] / t["oracle"])
    print(f"correct picks (grid vs numpy BVH, > 10% apart): {pk['percent']:.1f}% ({pk['correct']}/{pk['considered']})")
    print(f"hybrid / oracle, median (90th pct): (i) separate samples {sp['hybrid_over_oracle']['median']:.3f} "
          f"({sp['hybrid_over_oracle']['p90']:.3f}); (ii) samples from the workload {sp['hybrid_reuse_over_oracle']['median']:.3f} "
          f"({sp['hybrid_reuse_over_oracle']['p90']:.3f}); online batches of 32k {sp['online_over_oracle']['median']:.3f}; "
          f"calls of 1,000 rays with ski rental across calls {np.median(calls):.3f} (max {max(calls):.2f})")
    # constants from each repeat alone: what two calibrations in a row would give
    fits = [_calibration(repeat_records(rows, recs, r)) for r in range(3)]
    print("calibrations fitted on each repeat's timings alone (1 vs 2, 1 vs 3, 2 vs 3): largest difference of the "
          "per-ray times and builds they predict on the evaluated meshes, and of their break-evens")
    for a, b in ((0, 1), (0, 2), (1, 2)):
        ca, cb = fits[a], fits[b]
        worst, bes = {}, []
        for g, rec in recs:
            if g == "calibration":
                continue
            n = rec.triangles
            for k in ("grid",) + kinds:
                pa, pb = ca.count_per_ray(k, n, rec.work)[0], cb.count_per_ray(k, n, rec.work)[0]
                worst[k] = max(worst.get(k, 0.0), 200 * abs(pa - pb) / (pa + pb))
            for k in kinds:
                pa, pb = ca.estimate(k, n).build, cb.estimate(k, n).build
                worst[k + " build"] = max(worst.get(k + " build", 0.0), 200 * abs(pa - pb) / (pa + pb))
            ra = rep.break_even(ca.estimate("bvh", n).build, ca.count_per_ray("grid", n, rec.work)[0],
                                ca.count_per_ray("bvh", n, rec.work)[0])
            rb = rep.break_even(cb.estimate("bvh", n).build, cb.count_per_ray("grid", n, rec.work)[0],
                                cb.count_per_ray("bvh", n, rec.work)[0])
            if math.isfinite(ra) and math.isfinite(rb):
                bes.append(max(ra, rb) / min(ra, rb))
        print(f"   {a + 1} vs {b + 1}: " + ", ".join(f"{k} {v:.1f}%" for k, v in worst.items())
              + f"; break-even max/min median {np.median(bes):.3f} (max {max(bes):.2f})")
    if plans:
        from hybrid_raycast.core import plan as make_plan

        ratios = []
        for name, group, make in scene_list():
            if group == "calibration":
                continue
            mesh = make()
            be = [make_plan(mesh, 1e6, cal, kinds=("grid",) + kinds, seed=s).candidates["bvh"].break_even for s in range(plans)]
            fin = [x for x in be if math.isfinite(x)]
            ratios.append(max(fin) / min(fin) if len(fin) == len(be) else (1.0 if not fin else math.inf))
            print(f"   {name:20s} {plans} plan() runs: break-evens {', '.join(f'{x:,.0f}' for x in be)}", flush=True)
        print(f"{plans} plan() runs per evaluated mesh (one calibration, other sample rays each run): max/min median "
              f"{np.median(ratios):.3f}, max {max(ratios):.3f}, {sum(r <= 1.2 for r in ratios)}/{len(ratios)} within 1.2")


def scene_list(scale="default", subdivide="teapot:2,stanford-bunny:1,beetle-alt:2,fandisk:3"):
    todo = [(n, "calibration", f) for n, f in scene_lib.calibration_set(scale)]
    for p in sorted(SHARED_SCENES.glob("*.obj")):
        todo.append((p.stem, "real", (lambda p=p: load_obj(p))))
    for spec in filter(None, subdivide.split(",")):
        stem, lv = spec.split(":")

        def make(stem=stem, lv=int(lv)):
            m = load_obj(SHARED_SCENES / f"{stem}.obj")
            for _ in range(lv):
                m = scene_lib.subdivide(m)
            return m
        todo.append((f"{stem}-x{4 ** int(lv)}", "subdivided", make))
    return todo


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(ROOT / "out" / "counts.json"))
    ap.add_argument("--rays", type=int, default=1 << 17)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--samples", type=int, default=16384)
    ap.add_argument("--scale", default="default")
    ap.add_argument("--analyse", default="", help="print the held-out errors of the count models on a saved JSON")
    ap.add_argument("--kind", default="bvh")
    ap.add_argument("--evaluate", default="", help="print the issue-14 goals from a saved JSON (no timing)")
    ap.add_argument("--plans", type=int, default=5)
    ap.add_argument("--agree", nargs="+", default=[], metavar="CALIBRATION",
                    help="with --analyse's JSON as --out: compare calibration files refitted under each model (no timing)")
    ap.add_argument("--subdivide", default="teapot:2,stanford-bunny:1,beetle-alt:2,fandisk:3")
    ap.add_argument("--only", default="", help="measure only the scenes whose name matches this regular expression")
    ap.add_argument("--append", action="store_true",
                    help="keep the rows already in --out and add (or replace) the measured scenes: a study in short locked runs")
    ap.add_argument("--drop", default="", help="leave the calibration scenes matching this regular expression out of the fits")
    args = ap.parse_args(argv)
    global DROP
    DROP = args.drop or None
    if args.agree:
        return agree(args.out, args.agree, args.kind)
    if args.analyse:
        return analyse(args.analyse, args.kind)
    if args.evaluate:
        return evaluate(args.evaluate, plans=args.plans)
    kinds, _ = available_kinds(("grid", "bvh", "embree"))
    todo = scene_list(args.scale, args.subdivide)
    if args.only:
        todo = [t for t in todo if re.search(args.only, t[0])]
    rows = json.loads(Path(args.out).read_text()) if args.append and Path(args.out).exists() else []
    rows = [r for r in rows if r["name"] not in {t[0] for t in todo}]
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
