"""The evaluation report of issue 4: the paper's protocol on real meshes, as JSON, Markdown and PNG.

    .venv/bin/python scripts/report.py                      # full run, writes docs/report/
    .venv/bin/python scripts/report.py --quick --out out/report-quick   # smoke run, ~20 s
    .venv/bin/python scripts/report.py --reuse-calibration --rays 500000

Protocol (Hapala, Karlik, Havran 2011, section 4, with this project's additions):

1. calibrate the cost model on the package's procedural scenes (``core.decide``),
   never on the evaluated meshes; ``--reuse-calibration`` loads ``--calibration`` when it
   holds a valid calibration made here instead of measuring again;
2. on every real mesh of ``--scenes`` (../shared/scenes) and on larger versions made by
   midpoint subdivision (up to ``--max-triangles``): build the grid and each hierarchical
   structure for real (builds: median of up to three), trace ``--rays`` of the paper's
   uniform random rays through each, and take the true break-even R_C; then run
   ``core.plan`` as the add-on does, with the default K sample rays, and take its
   estimate R_est (the grid's K-sample time times the calibration's small-batch ratio,
   ``Plan.grid_per_ray``); once with K uniform samples (the sidebar's Analyze) and once
   with K samples drawn from the workload (``api.cast``, the Trace operator), for the
   estimate's cost in each;
3. speed against error (``--sweep-scenes``): for grid densities and sample counts K, the
   error of the plan's estimate (and of the uncorrected time / K) against its own cost,
   and the per-ray time against batch size;
4. the calibration model's refinements, judged by held-out error: leave-one-out on the
   calibration scenes, and the evaluated meshes, under the plan's grid estimate.

Totals for 1e3..1e8 rays are extrapolated from the measured build and per-ray times
(``T_B + R t``), the paper's method.  ``--quick`` replaces everything by tiny procedural
scenes (other generators' seeds and sizes than the calibration's) and small ray counts: a
check that the pipeline runs, not a measurement.

matplotlib is needed for the plots only (requirements-dev.txt); without it the JSON and
Markdown are still written and the Markdown says the plots are missing.

The measuring and the arithmetic are ``core.decide.evaluate``'s (``measure_truths``,
``measure_scene``, ``sweep_scene``, ``summarise``, ``model_comparison``, ...); this script
holds the command's arguments and calibration files, the headline's rows, the JSON, the
Markdown and the plots.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import ROOT, SHARED_SCENES, core_package  # noqa: E402

core_package()

from hybrid_raycast.core import load_obj, scenes as scene_lib  # noqa: E402
from hybrid_raycast.core.decide import cost, evaluate, points  # noqa: E402
from hybrid_raycast.core.decide import (  # noqa: E402
    CALIBRATION_FORMAT, DEFAULT_PATH, QUIET_SHARE, SAMPLE_LADDER, Calibration, CalibrationError, calibrate, load, warm_up,
)
from hybrid_raycast.core.decide.evaluate import GRID_ESTIMATES, fnum  # noqa: E402
from hybrid_raycast.core.decide.measurements import CALIBRATION_REPEATS, ONE_THREAD  # noqa: E402
from hybrid_raycast.core.factory import available_kinds  # noqa: E402
from hybrid_raycast.core.plan import DEFAULT_SAMPLES  # noqa: E402


#: larger versions of the real meshes: (mesh, subdivision levels); each level is 4x the triangles
SUBDIVIDED = [("teapot", 2), ("beetle-alt", 1), ("stanford-bunny", 1), ("rocker-arm", 2), ("beetle-alt", 2),
              ("homer", 3), ("fandisk", 3), ("stanford-bunny", 2), ("rocker-arm", 3)]
#: the scenes of the speed-against-error sweep (by name, when present)
SWEEP_SCENES = ["cow", "homer", "beetle-alt", "stanford-bunny", "beetle-alt-x16", "stanford-bunny-x16"]
SWEEP_K = [1024, 2048, 4096, 8192, 16384, 32768, 65536]
SWEEP_DENSITY = [0.5, 1.0, 2.0, 4.0, 8.0]
#: the scenes drawn in the time-against-rays figure
TOTALS_PLOT = ["cow", "stanford-bunny", "beetle-alt-x16", "stanford-bunny-x16"]

QUICK = dict(
    rays=20000, cal_scale="tiny", cal_rays=4000, cal_ladder=[256, 1024], sweep_rays=8000, sweep_k=[256, 1024],
    sweep_density=[1.0, 2.0], sweep_repeats=1, samples=1024, repeats=2, plan_repeats=2, cal_repeats=1,
    quiet_share=0.0,  # a smoke run: no retakes on a busy machine
)


def log(msg: str):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


# -- the scenes ------------------------------------------------------------------------------------

def quick_scenes():
    """Tiny procedural stand-ins for the real meshes (not the calibration's sizes or seeds)."""
    spec = [("sphere", 3000), ("torus", 6000), ("city", 2500), ("terrain", 8000)]
    return [(f"q-{g}-{n // 1000}k", "procedural", (lambda g=g, n=n: scene_lib.make_scene(g, n, seed=101))) for g, n in spec]


def real_scenes(folder: Path, max_triangles: int):
    """(name, group, factory) for every .obj in ``folder`` and the subdivided versions."""
    paths = {p.stem: p for p in sorted(folder.glob("*.obj"))}
    out = [(stem, "real", (lambda p=p: load_obj(p))) for stem, p in paths.items()]
    for stem, levels in SUBDIVIDED:
        if stem not in paths:
            continue

        def make(p=paths[stem], levels=levels):
            m = load_obj(p)
            for _ in range(levels):
                m = scene_lib.subdivide(m)
            return m

        out.append((f"{stem}-x{4 ** levels}", "subdivided", make, paths[stem], levels))
    # sizes without building: the first mesh tells its count, subdivision multiplies by 4
    sized = []
    counts = {}
    for entry in out:
        name, group, make = entry[:3]
        if group == "real":
            counts[name] = load_obj(paths[name]).triangle_count
            sized.append((counts[name], name, group, make))
        else:
            n = counts.get(entry[3].stem, 0) * 4 ** entry[4]
            if n <= max_triangles:
                sized.append((n, name, group, make))
    return [(name, group, make) for _, name, group, make in sorted(sized, key=lambda x: (x[0], x[1]))]


# -- writing -----------------------------------------------------------------------------------------

def jsonable(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (np.floating,)):
        return jsonable(float(x))
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


def write_markdown(path: Path, R: dict):
    """report.md from the JSON-able results (infinities and NaN already None: every number
    goes through ``fnum``)."""
    meta, summ = R["meta"], R["summary"]
    L = []
    w = L.append
    cal = meta["calibration"]
    w("# Hybrid decision: evaluation report (issue 4)\n")
    w(f"Generated by `{meta['command']}` on {meta['date']} in {fnum(meta['duration_s'] / 60, 1)} min; "
      f"{meta['cpus']} cores ({meta['processor']}), load average {meta['load_before']} before and "
      f"{meta['load_after']} after (other jobs shared the machine). Python {meta['python']}, numpy {meta['numpy']}.\n")
    if meta["quick"]:
        w("**Quick mode**: tiny procedural scenes and few rays; a smoke run, not a measurement.\n")
    w(f"Protocol (Hapala, Karlik, Havran 2011, section 4): calibration on the package's procedural scenes "
      f"({cal['scenes']} scenes, {fnum(cal['rays_per_scene'])} rays each, the grid also timed on samples of "
      f"{', '.join(fnum(k) for k in cal['ladder'])} rays; {cal['how']}); evaluation on {len(R['scenes'])} scenes never "
      f"used for fitting: real meshes from `../shared/scenes` and larger versions made by midpoint subdivision. "
      f"On each, every structure is really built and traced with **{fnum(meta['rays'])} rays** of the paper's "
      f"distribution in {meta.get('repeats', 1)} passes over all the scenes, medians of the passes (origins uniform in "
      f"the padded scene box, directions uniform on the sphere); R_C = T_B^H / (t_G - t_H) from those "
      f"measurements (the grid's build is sunk, as in the estimate). R_est comes from `core.plan` as the add-on "
      f"runs it: the '{cal['model']}' calibration model, K = {fnum(meta['samples'])} sample rays, the default grid "
      f"density, and the grid's time per ray taken as the K-sample time times the calibration's small-batch ratio "
      f"for K (`Plan.grid_per_ray`). Totals for 1e3..1e8 rays are extrapolated from the measured build and "
      f"per-ray times (T_B + R t), the paper's method. Threads per structure: numpy grid and BVH "
      f"{meta['threads'].get('grid')}, Embree (embreex) {meta['threads'].get('embree', 'not measured')}.\n")
    # -- headline
    ratio = cal.get("ratio_at_samples") or {}
    w("## Headline (grid against the numpy BVH, the paper's setting)\n")
    counts = cal.get("counts") or {}
    if counts:
        how = ("the count models: the grid's time per ray from the work counts of K = "
               f"{fnum(meta['samples'])} sample rays (" + cost.CountFit(**counts["grid"]).formula()
               + "), each structure's from the same counts (`core.decide.cost.COUNT_TERMS`), its build from the "
               f"'{cal['model']}' model")
    else:
        how = (f"the '{cal['model']}' model and the time of K = {fnum(meta['samples'])} sample rays / K times the "
               f"calibration's ratio {fnum(ratio.get('median'), 2)} [{fnum(ratio.get('low'), 2)}, {fnum(ratio.get('high'), 2)}]")
    w(f"As the add-on stands: `core.plan` with {how}. R_C: medians of {meta.get('repeats', 1)} interleaved builds "
      f"and traces of every structure on {fnum(meta['rays'])} uniform rays, in {meta.get('repeats', 1)} passes over all the "
      f"scenes as the calibration measures its own (`core.decide.measure_break_evens`). "
      f"The hybrid's total is given two ways: "
      f"**(i)** K uniform samples apart from the workload, their cost counted (the sidebar's Analyze); "
      f"**(ii)** K samples drawn from the workload and their answers kept (`api.cast`, the Trace operator): the "
      f"estimate then costs its arithmetic plus the gap between the grid's sample time and what those rays cost "
      f"with the chosen structure, and for R <= K the grid answers the whole workload while planning.\n")
    w("| measure | goal | measured | met |\n|---|---|---:|:---:|")
    for row in summ["headline"]:
        w(f"| {row['measure']} | {row['goal']} | {row['value']} | {row['met']} |")
    w("")
    ic = summ.get("interval_coverage")
    if ic and ic["scenes"]:
        w(f"The break-even interval against the numpy BVH (the calibration's spread) holds the measured R_C on "
          f"{ic['held']} of {ic['scenes']} scenes ({fnum(ic['percent'], 0)}%; goal 90%); its upper end is 'never' on "
          f"{ic['never_above']} of them.\n")
    rc = summ.get("rc_repeatability")
    if rc:
        w(f"R_C's own repeatability: the interleaved repeats of each scene's builds and traces give break-evens whose "
          f"spread (max - min) is a median {fnum(rc['median'], 1)}% of R_C (max {fnum(rc['max'], 0)}%, {rc['scenes']} "
          f"scenes): errors below that are noise.\n")
    cm = summ.get("count_models") or {}
    if cm:
        w("## Count models: held-out error of each direction (issue 14)\n")
        w("Leave-one-out over the calibration scenes: each scene in turn is left out, the models are fitted on the "
          "others, and its break-even is estimated from its own records (the grid's work counts on K uniform sample "
          "rays, or its K-sample time x the others' ratio) and compared with its measured one (medians of interleaved "
          "repeats). Median absolute errors in %. 'sample x ratio' + 'affine log2n' is the estimator before issue 14.\n")
        for k, rows in cm.items():
            w(f"Against {k}:\n")
            w("| grid time per ray | structure's time per ray | break-even error | grid per-ray error | "
              "structure per-ray error | undefined |\n|---|---|---:|---:|---:|---:|")
            for r in rows:
                w(f"| {r['grid']} | {r['per_ray']} | {fnum(r['loo'], 1)} | {fnum(r['grid_error'], 1)} | "
                  f"{fnum(r['per_ray_error'], 1)} | {r['undefined']} of {r['scenes']} |")
            w("")
    ests = R.get("models", {}).get(cal["model"], {}).get("grid", {})
    if ests:
        w("On the evaluated meshes (fitted on all calibration scenes), by grid estimator, median absolute break-even "
          "error against the numpy BVH: " + "; ".join(f"{name} {fnum(v['held_out']['median_abs'], 1, None)} "
                                                      f"({fnum(v['picks']['percent'], 1, None)} correct picks)"
                                                      for name, v in ests.items()) + ".\n")
    for crep in (summ.get("calibration_repeatability"), summ.get("calibration_repeatability_first")):
        if not crep:
            continue
        w(f"Two calibrations in a row{' (' + crep['pair'] + ')' if crep.get('pair') else ''}, each constant's "
          "difference |a - b| / mean in %, as the model states it "
          "(each build at 1,024 to 1,048,576 triangles, each time per ray at its model's anchor counts): "
          + ", ".join(f"{k} {fnum(v, 1)}" for k, v in crep["constants"].items())
          + ". The same as the file stores the coefficients (the four build terms trade against each other, "
          "a slope against an intercept): "
          + ", ".join(f"{k} {fnum(v, 1)}" for k, v in crep["coefficients"].items())
          + ". Per-ray times they predict on the evaluated scenes' counts, median (max) difference: "
          + ", ".join(f"{k} {fnum(v['median'], 1)}% ({fnum(v['max'], 1)}%)" for k, v in crep["per_ray"].items()) + ".\n")
        if crep.get("large_builds"):
            w("The builds on the calibration scenes of at least 262,144 triangles, in each calibration (medians of "
              "its passes): time, the process's minor page faults and its system CPU time during the build.\n")
            w("| scene | N | structure | build ms (1st, 2nd) | apart | page faults (1st, 2nd) | system ms (1st, 2nd) |")
            w("|---|---:|---|---:|---:|---:|---:|")

            def pair(v, scale=1.0, digits=0):
                return ", ".join("-" if x is None else f"{x * scale:,.{digits}f}" for x in v)

            for b in crep["large_builds"]:
                w(f"| {b['scene']} | {b['triangles']:,} | {b['kind']} | {pair(b['build'], 1e3)} | "
                  f"{fnum(evaluate.relative_difference(*b['build']), 1)}% | {pair(b['faults'])} | {pair(b['system'], 1e3)} |")
            w("")
    # -- per scene
    w(f"## Break-even per scene ({cal['model']} model, the plan's grid estimate)\n")
    counted = any((s["extra"].get("work") or {}).get("cells") is not None for s in R["scenes"])
    how = ("t_G est: the grid's count model (`core.decide.cost.COUNT_TERMS`) on the sample's work counts per ray "
           "(cells: the 3D-DDA's; steps, candidates: the traversal's own), what the estimate used; ratio: "
           "t_G est / t_G sample" if counted else
           "ratio: the calibration's correction for K; t_G est = sample x ratio, what the estimate used")
    w("Times per ray in µs, builds in ms. t_G sample: the grid's time per ray on the plan's K samples; " + how + ". "
      "Error = 100 (R_est - R_C) / R_C. 'never': the grid is at least as fast per ray, so the BVH never pays. "
      "Components: the estimate's own "
      "error on the BVH build, on the BVH time per ray, on the grid's time per ray as estimated, and (for comparison) "
      "the raw sample's (each 100 (est - true) / true).\n")
    w("| scene | group | N | grid build | t_G | t_G sample | cells | steps, candidates | ratio | t_G est | BVH build | t_H | "
      "R_C (repeats) | R_est [low, high] | error | err build | err t_H | err t_G est | err t_G sample |")
    w("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for s in R["scenes"]:
        m, c, work = s["measured"]["bvh"], s["components"], s["extra"].get("work") or {}
        halves = ", ".join(fbe(x) for x in s["extra"].get("R_C_repeats", {}).get("bvh", []))
        w(f"| {s['name']} | {s['group']} | {fnum(s['triangles'])} | {scaled(s['grid']['build_time'], 1e3, 1)} | "
          f"{scaled(s['grid']['per_ray'], 1e6, 2)} | {scaled(s['grid_sample_per_ray'], 1e6, 2)} | "
          f"{fnum(work.get('cells'), 1)} | {fnum(work.get('steps'), 1)}, {fnum(work.get('candidates'), 1)} | "
          f"{fnum((s['extra'].get('grid_sample_ratio') or [None])[0], 2)} | {scaled(s['grid_estimate_per_ray'], 1e6, 2)} | "
          f"{scaled(m['build_time'], 1e3, 0)} | {scaled(m['per_ray'], 1e6, 2)} | {fbe(s['R_C'])} ({halves}) | "
          f"{fbe(s['R_est'])} [{fbe(s['extra'].get('break_even_low'))}, {fbe(s['extra'].get('break_even_high'))}] | "
          f"{fnum(s['error'], 0, True)} | {fnum(c['build'], 0, True)} | {fnum(c['per_ray'], 0, True)} | "
          f"{fnum(c['grid_per_ray'], 0, True)} | {fnum(c.get('grid_sample'), 0, True)} |")
    es, nv = summ["errors"], summ["never"]
    w(f"\nOver {es['defined']} scenes with both break-evens finite (left out of the sums: {nv['both_never']} where both "
      f"say the BVH never pays, {nv['only_estimate_never']} where only the estimate says so, "
      f"{nv['only_measured_never']} where only the measurement does): **sum of errors {fnum(es['sum'], 0, True)}, sum of "
      f"absolute errors {fnum(es['sum_abs'], 0, None)}**, median error {fnum(es['median'], 1, True)}, median absolute "
      f"error {fnum(es['median_abs'], 1, None)}, mean absolute {fnum(es['mean_abs'], 1, None)}, {es['within_25']} within "
      f"25% and {es['within_10']} within 10%.\n")
    for g, gs in summ.get("errors_by_group", {}).items():
        w(f"- {g}: median absolute error {fnum(gs['median_abs'], 1, None)} over {gs['defined']} scenes "
          f"(sum {fnum(gs['sum'], 0, True)}, sum of absolute values {fnum(gs['sum_abs'], 0, None)})")
    w("")
    er = summ.get("evaluated_ratio")
    if er:
        w(f"Does the calibration's ratio carry over? On the evaluated scenes the grid's true time per ray over its "
          f"raw K-sample time has median {fnum(er['median'], 2)} [{fnum(er['p10'], 2)}, {fnum(er['p90'], 2)}] "
          f"(10th, 90th percentile, {er['scenes']} scenes), against {fnum(ratio.get('median'), 2)} "
          f"[{fnum(ratio.get('low'), 2)}, {fnum(ratio.get('high'), 2)}] from the calibration scenes.\n")
    # -- speed
    w("## Speed: hybrid, online, oracle\n")
    mp = summ["median_per_ray"]
    w("Median time per ray over the scenes: " + ", ".join(f"{k} {scaled(v, 1e6, 2)} µs" for k, v in mp.items()) + ".\n")
    sp = summ["speedups"]
    w(f"Over {sp.get('speedup_vs_grid', {}).get('cases', 0)} (scene, R) cases, R = 1e3..1e8 (21 counts, four a "
      f"decade). (i): K uniform samples apart from the workload; (ii): samples from the workload, reused.\n")
    w("| ratio | median | 90th percentile | min | max |\n|---|---:|---:|---:|---:|")
    for k, lab in (("speedup_vs_grid", "always-grid / hybrid (i)"), ("speedup_vs_bvh", "always-BVH / hybrid (i)"),
                   ("reuse_speedup_vs_grid", "always-grid / hybrid (ii)"),
                   ("reuse_speedup_vs_bvh", "always-BVH / hybrid (ii)"),
                   ("hybrid_over_oracle", "hybrid (i) / oracle"),
                   ("hybrid_reuse_over_oracle", "hybrid (ii) / oracle"),
                   ("online_over_oracle", "online / oracle"),
                   ("online_over_hybrid", "online / hybrid (i)")):
        if k in sp:
            v = sp[k]
            w(f"| {lab} | {fnum(v['median'], 3)} | {fnum(v['p90'], 3)} | {fnum(v['min'], 3)} | {fnum(v['max'], 3)} |")
    pk = summ["picks"]
    w(f"\nCorrect picks: {pk['correct']} of {pk['considered']} cases where the grid's remaining cost R t_G and the "
      f"BVH's T_B^H + R t_H differ by more than 10% (**{fnum(pk['percent'], 1, None)}**); counting the grid's build "
      f"in its cost instead: {fnum(summ['picks_total']['percent'], 1, None)} of {summ['picks_total']['considered']}.\n")
    wb = summ.get("wasted_builds") or {}
    if wb.get("cases"):
        w(f"**Check failed:** in {wb['cases']} (scene, R) cases with R <= K the plan with workload samples chose "
          f"another structure than the grid although the grid had answered every ray while planning.\n")
    w("Median over the scenes per ray count (hybrid's total over each strategy's; oracle = best fixed choice):\n")
    w("| R | always-grid / hybrid (i) | always-BVH / hybrid (i) | hybrid (i) / oracle | hybrid (ii) / oracle | "
      "online / oracle | hybrid picks BVH |")
    w("|---:|---:|---:|---:|---:|---:|---:|")
    for row in summ["by_ray_count"]:
        w(f"| {fnum(row['R'], 0) if row['R'] is None else format(row['R'], '.0e')} | {fnum(row['grid'], 3)} | "
          f"{fnum(row['bvh'], 3)} | {fnum(row['hybrid_oracle'], 3)} | {fnum(row['reuse_oracle'], 3)} | "
          f"{fnum(row['online_oracle'], 3)} | {fnum(scaled_raw(row['bvh_share'], 100), 0, None)} |")
    ecost = summ["estimate_cost"]
    w(f"\nThe estimate's own cost at 1e6 rays, as % of the grid-only total: (i) tracing K uniform sample rays through "
      f"the grid, plus arithmetic: median **{fnum(ecost['median'], 2, None)}**, max {fnum(ecost['max'], 2, None)} "
      f"({ecost['max_scene']}); (ii) with the samples from the workload, net of what the chosen structure would have "
      f"spent on those rays: median **{fnum(ecost['reuse_median'], 2, None)}**, max {fnum(ecost['reuse_max'], 2, None)}.\n")
    if summ.get("embree"):
        em = summ["embree"]
        esp = em["speedups"]
        w("## With Embree as a third candidate (the add-on's default when embreex is installed)\n")
        w(f"Break-even error of the grid against Embree ({cal['model']} model): median absolute "
          f"{fnum(em['errors']['median_abs'], 1, None)} over {em['errors']['defined']} scenes (sum "
          f"{fnum(em['errors']['sum'], 0, True)}, sum of absolute values {fnum(em['errors']['sum_abs'], 0, None)}). "
          f"Hybrid choosing among grid, BVH and Embree: hybrid / oracle median (i) "
          f"{fnum(stat(esp, 'hybrid_over_oracle'), 3)} (90th percentile {fnum(stat(esp, 'hybrid_over_oracle', 'p90'), 3)}, "
          f"worst {fnum(stat(esp, 'hybrid_over_oracle', 'max'), 2)}), "
          f"(ii) {fnum(stat(esp, 'hybrid_reuse_over_oracle'), 3)} (Embree retraces the sample rays); always-Embree / "
          f"hybrid (i) median {fnum(stat(esp, 'speedup_vs_embree'), 3)}.\n")
        par, cpar = em.get("parallelism"), em.get("calibration_parallelism")
        if par and par["builds"]:
            w(f"Embree builds on every hardware thread. Its truths' builds kept a median of {fnum(par['median'], 2)} "
              f"threads busy (CPU seconds per second of build, `Measurement.build_parallelism`), and "
              f"{fnum(100 * par['one_thread_share'], 0)}% of the {par['builds']} builds about one (below {ONE_THREAD:g})"
              + (f"; the calibration's, {fnum(cpar['median'], 2)} and {fnum(100 * cpar['one_thread_share'], 0)}% of "
                 f"{cpar['builds']} builds" if cpar and cpar["builds"] else "")
              + ". A build on one thread takes about 1.5-1.9x as long (BENCHMARKS.md, \"Embree's builds on one "
                "thread or two\").\n")
        w("| scene | N | Embree build ms | estimated | build error | threads busy per pass | t_E µs | R_C(Embree) | "
          "R_est(Embree) | error |\n|---|---:|---:|---:|---:|---|---:|---:|---:|---:|")
        for r in em["scenes"]:
            busy = ", ".join(fnum(x, 1) for x in r.get("parallelism") or []) or "-"
            w(f"| {r['name']} | {fnum(r['triangles'])} | {scaled(r['build'], 1e3, 1)} | "
              f"{scaled(r.get('build_est', math.nan), 1e3, 1)} | {fnum(r.get('build_error', math.nan), 0, True)} | {busy} | "
              f"{scaled(r['per_ray'], 1e6, 3)} | {fbe(r['R_C'])} | {fbe(r['R_est'])} | {fnum(r['error'], 0, True)} |")
        w("")
    # -- sweep
    sw = R.get("sweep")
    if sw and sw["rows"]:
        w("## Speed against error: sample rays K and grid density\n")
        w(f"Sweep scenes: {', '.join(sw['scenes'])}; the grid's true time per ray on {fnum(meta['sweep_rays'])} rays "
          f"at each density; {meta['sweep_repeats']} estimate(s) per (scene, density, K), each a `core.plan` call on "
          f"that density's grid; cost = the estimate's time (K uniform samples, (i)) as % of that density's "
          f"grid-only total at 1e6 rays. 'plan' is the plan's own estimate (the count model on the K sample rays' "
          f"work counts); 'sample x ratio' the same sample's time x the calibration's ratio for K; 'uncorrected' "
          f"its time / K (the paper's method). The truths here are one trace of {fnum(meta['sweep_rays'])} rays "
          f"per density, outside the interleaved passes: a timed estimate follows the machine's state between the "
          f"two, the count model does not. The calibration measures the "
          f"ratio at the default density; 'ratio' is the one the plan applied, 'measured' the true / sample ratio "
          f"the sweep found (median).\n")
        ests = tuple(e for e in GRID_ESTIMATES if e in sw["tables"])
        w("| density | K | ratio: plan / measured | " + " | ".join(
            f"{e}: median abs error (median error) | cost % median / max" for e in ests) + " |")
        w("|---:|---:|---:|" + "---:|---:|" * len(ests))
        idx = {e: {(r["density"], r["K"]): r for r in sw["tables"][e]} for e in ests}
        for r in sw["tables"][ests[0]]:
            key = (r["density"], r["K"])
            cells = []
            for e in ests:
                t = idx[e][key]
                cells.append(f"{fnum(t['median_abs_error'], 1, None)} ({fnum(t['median_error'], 1, True)}) | "
                             f"{fnum(t['median_cost_pct'], 2)} / {fnum(t['max_cost_pct'], 2)}")
            w(f"| {fnum(r['density'], 1)} | {fnum(r['K'])} | {fnum(r.get('ratio'), 2)} / {fnum(r.get('measured_ratio'), 2)} | "
              + " | ".join(cells) + " |")
        w("")
        w("**Defaults.** " + sw["choice"]["text"] + "\n")
        if sw.get("batch"):
            w("Raw time per ray (µs) against batch size at density 2 (the last column is the evaluation's "
              f"{fnum(meta['rays'])}-ray workload): why a small sample overstates the grid's cost per ray, and what the "
              f"ratio corrects.\n")
            ks = sorted({b["K"] for b in sw["batch"]})
            w("| scene | structure | " + " | ".join(fnum(k) for k in ks) + " |")
            w("|---|---|" + "---:|" * len(ks))
            for sc in sw["scenes"]:
                for kind in ("grid", "bvh"):
                    vals = {b["K"]: b[kind] for b in sw["batch"] if b["scene"] == sc}
                    w(f"| {sc} | {kind} | " + " | ".join(scaled(vals[k], 1e6, 2) if k in vals else "" for k in ks) + " |")
            w("")
    # -- the ratio
    gr = R.get("grid_sample_ratio")
    if gr and gr.get("scenes"):
        w("## The grid's small-batch ratio (from the calibration)\n")
        w(f"What `core.plan` multiplies its K-sample time by: on each calibration scene ('{gr['scale']}' set), the "
          f"grid's time per ray on the calibration's {fnum(gr['rays'])} rays over its time per ray on K uniform "
          f"sample rays (`SceneRecord.grid_sample_ratio`); the plan takes the median over the scenes, interpolated in "
          f"log2 K between the measured sizes and clamped at the ends (`Calibration.grid_sample_ratio`), with the "
          f"{fnum(gr['spread'][0], 0)}th / {fnum(gr['spread'][1], 0)}th percentiles as its interval.\n")
        ladder = gr["ladder"]
        w("| scene | N | t_G µs | " + " | ".join(f"K = {fnum(k)}" for k in ladder) + " |")
        w("|---|---:|---:|" + "---:|" * len(ladder))
        for r in gr["scenes"]:
            w(f"| {r['scene']} | {fnum(r['triangles'])} | {scaled(r['true'], 1e6, 2)} | "
              + " | ".join(fnum(r["ratio"].get(str(k)), 2) for k in ladder) + " |")
        w("\nMedian [low, high] at the K used here: " + ", ".join(
            f"K = {fnum(int(k))}: {fnum(v['median'], 2)} [{fnum(v['low'], 2)}, {fnum(v['high'], 2)}]"
            + ("" if v["measured"] else " (interpolated)") for k, v in gr["ratios"].items()) + ".\n")
    # -- models
    mc = R.get("models")
    if mc:
        w("## Refinements of the two-constant model (item 5)\n")
        w("Held-out break-even error of each calibration model: leave-one-out over the calibration scenes (the "
          "grid's time measured on the same rays, so only the model errs) and the evaluated meshes above, with the "
          "plan's grid estimate (so the sample's error is included) and, for comparison, the uncorrected sample. "
          "Models: " + "; ".join(f"**{k}** {v}" for k, v in R["model_docs"].items()) + ".\n")
        w("Medians and sums are over the scenes where both break-evens are finite; 'never' counts the others as "
          "both / only the estimate / only the measurement saying the BVH never pays.\n")
        w("| model | LOO median abs error | LOO sum / sum abs | LOO never | LOO build / per-ray median abs | held-out build / "
          "per-ray median abs | grid estimate | held-out median abs error | held-out sum / sum abs | never | correct picks | "
          "hybrid (i) / oracle | hybrid (ii) / oracle |")
        w("|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|")
        for name, m in mc.items():
            loo = m["loo"]
            for i, (g, v) in enumerate(m["grid"].items()):
                ho = v["held_out"]
                first = i == 0
                lead = (f"| {name} | {fnum(loo['median_abs'], 1, None)} | {fnum(loo['sum'], 0)} / {fnum(loo['sum_abs'], 0)} | "
                        f"{'/'.join(str(x) for x in m['loo_never'].values())} | "
                        f"{fnum(m['loo_build_mabs'], 0, None)} / {fnum(m['loo_per_ray_mabs'], 0, None)} | "
                        f"{fnum(m['held_out_build_mabs'], 0, None)} / {fnum(m['held_out_per_ray_mabs'], 0, None)} |"
                        if first else "| | | | | | |")
                w(f"{lead} {g} | {fnum(ho['median_abs'], 1, None)} | {fnum(ho['sum'], 0)} / {fnum(ho['sum_abs'], 0)} | "
                  f"{'/'.join(str(x) for x in v['never'].values())} | {fnum(v['picks']['percent'], 1, None)} | "
                  f"{fnum(v['hybrid_over_oracle'], 3)} | {fnum(v['hybrid_reuse_over_oracle'], 3)} |")
        w("\n**Decision.** " + R["model_decision"] + "\n")
    if R.get("points"):
        w("## Point queries: grid or BVH for the closest point (issue 42)\n")
        w(f"On the {R['points']['scenes']} scenes of up to {fnum(points.CALIBRATION_MAX_TRIANGLES)} triangles, three "
          f"kinds of points each (`core.decide.points.point_sets`: in the box grown by a fifth, near the surface, on "
          f"it); both structures built and every point answered on each, medians of 3. The measured break-even is "
          f"(B_BVH - B_grid) / (t_grid - t_BVH) per point; the estimate is the decision's from the grid's work on the "
          f"plan's sample and the calibration's point constants. Picks judged at 100 to 1M points.\n")
        for line in R["points"]["table"]:
            w(line)
        w("")
    # -- plots
    w("## Figures\n")
    if R["plots"]:
        for p, cap in R["plots"]:
            w(f"![{cap}]({p})\n\n*{cap}*\n")
    else:
        w(f"(no plots: {R.get('plots_missing', 'matplotlib not installed')})\n")
    if R.get("notes"):
        w("## Notes\n")
        for n in R["notes"]:
            w(f"- {n}")
        w("")
    path.write_text("\n".join(L), encoding="utf-8")


def fbe(x):
    """A break-even for the Markdown: JSON's null (or inf) is 'never', as in ``Plan.to_dict``."""
    return "never" if x is None else fnum(x)


def scaled(x, factor, digits):
    """``x * factor`` formatted by ``fnum`` (None and NaN stay 'n/a')."""
    return fnum(scaled_raw(x, factor), digits)


def scaled_raw(x, factor):
    return None if x is None else x * factor


def stat(summary: dict, key: str, field: str = "median"):
    """A figure of a speedup summary, NaN when the summary lacks it (no scenes)."""
    return summary.get(key, {}).get(field, math.nan)


def plots(out: Path, R: dict, scene_objs, sweep_rows):
    """The three figures; returns [(file name, caption)]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []
    # 1. error per scene
    sc = R["scenes"]
    fig, ax = plt.subplots(figsize=(9, 4))
    names = [s["name"] for s in sc]
    errs = [s["error"] if s["error"] is not None and math.isfinite(s["error"]) else 0.0 for s in sc]
    colors = ["tab:blue" if s["group"] != "subdivided" else "tab:orange" for s in sc]
    ax.bar(range(len(sc)), errs, color=colors)
    for i, s in enumerate(sc):
        # whiskers: the error against each half's R_C (the measurement's own noise)
        r_est = math.inf if s["R_est"] is None else s["R_est"]
        halves = [evaluate.relative_error(r_est, math.inf if h is None else h) for h in s["extra"].get("R_C_repeats", {}).get("bvh", [])]
        halves = [h for h in halves if math.isfinite(h)]
        if len(halves) >= 2:
            ax.plot([i, i], [min(halves), max(halves)], color="k", lw=1)
        if s["error"] is None or not math.isfinite(s["error"]):
            ax.text(i, 0, "n/a", ha="center", va="bottom", fontsize=7)
        elif s["R_C"] in (None, math.inf) and s["R_est"] in (None, math.inf):
            ax.text(i, 0, "both\nnever", ha="center", va="bottom", fontsize=6)
    ax.axhspan(-25, 25, color="tab:green", alpha=0.08, label="goal ±25%")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(range(len(sc)), [f"{n}\n{s['triangles'] / 1e3:.0f}k" for n, s in zip(names, sc)], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("break-even error, %")
    ax.set_title(f"Break-even error, {R['meta']['calibration']['model']} model (blue: real, orange: subdivided; "
                 "whiskers: against each half's R_C)", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "errors.png", dpi=110)
    plt.close(fig)
    made.append(("errors.png", "Break-even error per scene, 100 (R_est - R_C) / R_C"))
    # 2. totals against ray count
    want = [s for s in scene_objs if s.name in TOTALS_PLOT] or scene_objs[: min(4, len(scene_objs))]
    fig, axes = plt.subplots(1, len(want), figsize=(4 * len(want), 3.8), squeeze=False)
    r = np.logspace(3, 8, 61)
    for ax, s in zip(axes[0], want):
        t = evaluate.strategy_totals(s, r, ("bvh",))
        for k, style in (("grid", "-"), ("bvh", "-"), ("hybrid", "--"), ("hybrid_reuse", "-."), ("online", ":"),
                         ("oracle", "-")):
            if k in t:
                ax.loglog(r, t[k], style, label=k, lw=2.5 if k == "oracle" else 1.5, alpha=0.35 if k == "oracle" else 1.0)
        rc, re_ = evaluate.true_break_even(s), evaluate.estimated_break_even(s)
        if math.isfinite(rc):
            ax.axvline(rc, color="k", lw=0.6, label="R_C")
        if math.isfinite(re_):
            ax.axvline(re_, color="r", lw=0.6, ls="--", label="R_est")
        ax.set_title(f"{s.name} ({s.triangles:,} tris)", fontsize=9)
        ax.set_xlabel("rays")
        ax.grid(True, which="both", alpha=0.2)
    axes[0][0].set_ylabel("total time, s")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "totals.png", dpi=110)
    plt.close(fig)
    made.append(("totals.png", "Total time against ray count: always-grid, always-BVH, hybrid (i) with separate "
                               "samples and (ii) with samples from the workload, online, oracle"))
    # 3. speed against error
    if sweep_rows and R.get("sweep"):
        tables = R["sweep"]["tables"]
        fig, axes = plt.subplots(1, len(tables), figsize=(4.5 * len(tables), 4), sharey=True, squeeze=False)
        axes = axes[0]
        for ax, (est, table) in zip(axes, tables.items()):
            for dens in sorted({x["density"] for x in table}):
                rows = [x for x in table if x["density"] == dens]
                ax.plot([x["median_cost_pct"] for x in rows], [x["median_abs_error"] for x in rows], "o-", label=f"density {dens:g}")
                for x in rows:
                    ax.annotate(f"{x['K'] / 1024:g}k", (x["median_cost_pct"], x["median_abs_error"]), fontsize=6)
            ax.axhline(25, color="tab:green", lw=0.8, ls="--")
            ax.axvline(5, color="tab:red", lw=0.8, ls="--")
            ax.set_xscale("log")
            ax.set_xlabel("estimate cost, % of grid-only total at 1e6 rays")
            mod = R["meta"]["calibration"]["model"]
            ax.set_title({"plan": f"{mod} model, the plan's estimate", "sample x ratio": "the K-sample time x ratio",
                          "uncorrected": f"{mod} model, uncorrected sample (time / K)"}.get(est, est), fontsize=9)
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.2)
        axes[0].set_ylabel("median |break-even error|, %")
        axes[-1].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "speed_vs_error.png", dpi=110)
        plt.close(fig)
        made.append(("speed_vs_error.png", "The estimate's error against its cost as K (labels, in thousands) and the grid density vary"))
    return made


# -- the headline's rows ---------------------------------------------------------------------------

def repeat_rows(summ: dict) -> list[dict]:
    """Headline rows on Embree's error and the estimate's repeatability (when measured)."""
    rows = []
    em = summ.get("embree")
    if em:
        e = em["errors"]
        rows.append({"measure": "median absolute break-even error against Embree", "goal": "≤ 10%",
                     "value": f"{fnum(e['median_abs'], 1, None)} ({e['defined']} scenes)",
                     "met": "yes" if e["median_abs"] <= 10 else "**no**"})
    for k, r in summ.get("plan_repeatability", {}).items():
        rows.append({"measure": f"{r['runs']} plan() runs per scene, one calibration: max / min of the break-even "
                                f"against {k}, median (max; scenes within 1.2)", "goal": "≤ 1.2",
                     "value": f"{fnum(r['median'], 3)} ({fnum(r['max'], 2)}; {r['within_1_2']}/{r['scenes']})",
                     "met": "yes" if r["max"] <= 1.2 else "**no**"})
    return rows


def calibration_row(c: dict, goal: bool = True) -> dict:
    """The headline row of two calibrations in a row (``c["pair"]`` says which two); with
    goal=False a row beside the goal's, judged against nothing."""
    ratio = c["break_even_ratio"]
    which = f" ({c['pair']})" if c.get("pair") else ""
    return {"measure": f"two calibrations in a row{which}: largest difference of a constant as the model states it "
                       "(median); of a stored coefficient (median); break-evens they give, max / min, median (max)",
            "goal": "≤ 10%" if goal else "-",
            "value": f"{fnum(c['max_constant'], 1, None)} ({fnum(c['median_constant'], 1, None)}); "
                     f"{fnum(c['max_coefficient'], 1, None)} ({fnum(c['median_coefficient'], 1, None)}); "
                     f"{fnum(ratio['median'], 3)} ({fnum(ratio['max'], 2)})",
            "met": ("yes" if c["max_constant"] <= 10 else "**no**") if goal else "-"}


def headline(summ: dict, samples: int) -> list[dict]:
    """The headline rows: measure, goal, value (formatted, tolerant of NaN), met."""
    e, pk, sp, c, rp = summ["errors"], summ["picks"], summ["speedups"], summ["estimate_cost"], summ["errors_repeatable"]

    def met(ok):
        return "yes" if ok else "**no**"

    def ratio(key):
        return f"{fnum(stat(sp, key), 3)} (90th pct {fnum(stat(sp, key, 'p90'), 3)})"

    return [
        {"measure": "median absolute break-even error, evaluated meshes", "goal": "≤ 25% (stretch 10%)",
         "value": f"{fnum(e['median_abs'], 1, None)} ({e['defined']} scenes)", "met": met(e["median_abs"] <= 25)},
        {"measure": "the same on the scenes whose R_C is repeatable (its repeats within 25%)", "goal": "≤ 25%",
         "value": f"{fnum(rp['median_abs'], 1, None)} ({rp['defined']} scenes)", "met": met(rp["median_abs"] <= 25)},
        {"measure": "sum of errors / sum of absolute errors (paper's figures)", "goal": "-",
         "value": f"{fnum(e['sum'], 0, True)} / {fnum(e['sum_abs'], 0, None)}", "met": "-"},
        {"measure": "correct picks where grid and BVH differ by > 10%", "goal": "≥ 95%",
         "value": f"{fnum(pk['percent'], 1, None)} ({pk['correct']}/{pk['considered']})", "met": met(pk["percent"] >= 95)},
        {"measure": f"hybrid total / oracle total, median over (scene, R): **(ii)** K = {samples:,} samples from the "
                    f"workload, reused (`api.cast`, Trace operator)", "goal": "≤ 1.05",
         "value": ratio("hybrid_reuse_over_oracle"), "met": met(stat(sp, "hybrid_reuse_over_oracle") <= 1.05)},
        {"measure": "hybrid total / oracle total, median: **(i)** K uniform samples apart from the workload, their cost "
                    "counted (the sidebar's Analyze)",
         "goal": "≤ 1.05", "value": ratio("hybrid_over_oracle"), "met": met(stat(sp, "hybrid_over_oracle") <= 1.05)},
        {"measure": "estimate cost at 1e6 rays, % of grid-only total, median / max: (i) separate samples; (ii) net, "
                    "samples from the workload", "goal": "< 5%",
         "value": f"(i) {fnum(c['median'], 2, None)} / {fnum(c['max'], 2, None)}; (ii) {fnum(c['reuse_median'], 2, None)} / "
                  f"{fnum(c['reuse_max'], 2, None)}", "met": f"(i) {met(c['median'] < 5)}, (ii) {met(c['reuse_median'] < 5)}"},
        {"measure": "median speedup of the hybrid over always-grid / always-BVH: (ii); (i)", "goal": "-",
         "value": f"{fnum(stat(sp, 'reuse_speedup_vs_grid'), 2)}x / {fnum(stat(sp, 'reuse_speedup_vs_bvh'), 2)}x; "
                  f"{fnum(stat(sp, 'speedup_vs_grid'), 2)}x / {fnum(stat(sp, 'speedup_vs_bvh'), 2)}x", "met": "-"},
        *repeat_rows(summ),
        {"measure": "online (ski rental) total / oracle, median (max)", "goal": "≤ ~2 by construction",
         "value": f"{fnum(stat(sp, 'online_over_oracle'), 3)} ({fnum(stat(sp, 'online_over_oracle', 'max'), 2)})", "met": "-"},
        {"measure": "calls of 1,000 rays: ski rental across calls / oracle, median (max); a plan per call (grid each "
                    "time) / oracle, median (max)", "goal": "-",
         "value": f"{fnum(summ['calls_1000']['online_over_oracle']['median'], 3)} "
                  f"({fnum(summ['calls_1000']['online_over_oracle']['max'], 2)}); "
                  f"{fnum(summ['calls_1000']['per_call_over_oracle']['median'], 3)} "
                  f"({fnum(summ['calls_1000']['per_call_over_oracle']['max'], 2)})", "met": "-"},
    ]


# -- the run -----------------------------------------------------------------------------------------

def point_evaluation(cal, scene_list, meshes) -> dict | None:
    """The decision for point queries on the scenes of up to ``points.CALIBRATION_MAX_TRIANGLES``
    (``points.measure_points``, ``points.evaluate``) with the calibration's constants, and its
    markdown table; None when the calibration has none."""
    model = cal.point_model()
    if model is None:
        log("point queries: the calibration holds no constants for them; left out")
        return None
    records = []
    for (name, _, _), mesh in zip(scene_list, meshes):
        if 0 < mesh.triangle_count <= points.CALIBRATION_MAX_TRIANGLES:
            log(f"  point queries: {name}")
            records += points.measure_points(name, mesh)
    if not records:
        return None
    result = points.evaluate(model, records)
    log(f"point queries: {points.summary_line(result)}")
    return dict(result, table=points.table(result), scenes=len(records) // 3)


def get_calibration(args, beside=None):
    """The calibration the report evaluates, fitted with the package's default model (read
    at run time: the add-on as it stands); a reused file fitted otherwise is refitted.
    beside: when it measures one, a function giving ``calibrate``'s ``beside`` (the truths'
    jobs, measured in the same passes)."""
    path = Path(args.calibration)
    cal, how = None, ""
    if args.reuse_calibration and path.exists():
        try:
            cal = load(path)
            log(f"calibration reused from {path} ({len(cal.scenes)} scenes, {cal.rays_per_scene:,} rays each)")
            how = f"reused from {path.name}, measured {cal.created}"
        except CalibrationError as e:
            log(f"calibration at {path} not usable ({e}); measuring again")
    if cal is None:
        log(f"calibrating ({args.cal_scale} set, {fnum(args.cal_rays) if args.cal_rays else 'default'} rays per scene, "
            f"grid samples {args.cal_ladder})")
        last = [0.0]

        def progress(f, msg):
            if f - last[0] >= 0.1 or f >= 1.0:
                last[0] = f
                log(f"  {f:4.0%} {msg}")

        cal = calibrate(kinds=("bvh", "embree"), scale=args.cal_scale, rays_per_scene=args.cal_rays, progress=progress,
                        model=cost.DEFAULT_MODEL, sample_ladder=tuple(args.cal_ladder),
                        beside=beside() if beside is not None else None, **cal_options(args))
        if path.resolve() == Path(DEFAULT_PATH).resolve():
            # the shipped calibration is re-measured by scripts/ship_calibration.py only: a
            # report that could not reuse it keeps its own in out/
            path = ROOT / "out" / "report_calibration.json"
            path.parent.mkdir(parents=True, exist_ok=True)
        cal.save(path)
        log(f"calibration saved to {path}")
        how = f"measured for this report in {cal.duration_s:.0f} s" + (
            ", in the same passes as the evaluated scenes' truths" if beside is not None else "")
    if cal.model != cost.DEFAULT_MODEL or cal.version.get("format") != CALIBRATION_FORMAT:
        # an older file's constants are stated as it stated them: refit (the records are kept)
        log(f"calibration fitted with '{cal.model}' (format {cal.version.get('format')}): refitting with the default "
            f"model '{cost.DEFAULT_MODEL}'")
        cal = cal.refitted(cost.DEFAULT_MODEL)
        how += f", refitted with '{cal.model}'"
    if not any(r.grid_samples for r in cal.scenes):
        log("warning: the calibration holds no grid samples: the plan's grid estimate is uncorrected (ratio 1)")
    return cal, how


def again_path(first, n: int) -> Path:
    """Where the report saves its calibration number ``n`` (2, 3, ...), beside the first
    (``--calibration``), so each pass of each one can be compared afterwards."""
    first = Path(first)
    return first.with_name(f"{first.stem}_{n}{first.suffix or '.json'}")


def calibrate_again(args, cal: Calibration):
    """Another calibration right after the first (same set and settings); the caller saves it
    (``again_path``)."""
    log(f"calibrating again, for the constants' repeatability ({args.cal_scale} set)")
    return calibrate(kinds=tuple(cal.fits), scale=args.cal_scale, rays_per_scene=args.cal_rays,
                     model=cost.DEFAULT_MODEL, sample_ladder=tuple(args.cal_ladder), **cal_options(args))


def quiet_share(args) -> float | None:
    """The share of the CPU other processes may take before a round is retaken (None: never)."""
    return args.quiet_share if args.quiet_share > 0 else None


def cal_options(args) -> dict:
    return {"quiet": quiet_share(args), **({} if args.cal_repeats is None else {"repeats": args.cal_repeats})}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "docs" / "report"), help="output folder (default docs/report)")
    ap.add_argument("--quick", action="store_true", help="tiny procedural scenes, few rays: a smoke run")
    ap.add_argument("--rays", type=int, default=1_000_000, help="rays per evaluated scene for R_C (default 1M)")
    ap.add_argument("--plan-repeats", type=int, default=5, help="plan() runs per scene for the estimate's repeatability")
    ap.add_argument("--calibrations", type=int, default=3,
                    help="calibrations in a row whose constants are compared: the first is the one used (measured "
                         "with the truths, see --no-joint), the others alone, one after the other; with 3 or more "
                         "the goal's row compares the last two, and the first against the second is shown beside "
                         "it (default 3; 1: none)")
    ap.add_argument("--cal-repeats", type=int, default=None,
                    help="passes of the calibration over its scenes (default: core's, as the add-on calibrates)")
    ap.add_argument("--repeats", type=int, default=5,
                    help="passes over all the scenes, each building and tracing every structure of every scene once "
                         "(interleaved), for R_C from the medians (default 5; with 3 back to back, a scene's t_G - t_H "
                         "moved by 20-40%% between runs)")
    ap.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, help=f"plan's K sample rays (default {DEFAULT_SAMPLES})")
    ap.add_argument("--scenes", default=str(SHARED_SCENES), help="folder of real .obj meshes (default ../shared/scenes)")
    ap.add_argument("--max-triangles", type=int, default=1_500_000, help="largest subdivided scene (default 1.5M)")
    ap.add_argument("--only", default="", help="comma-separated scene names to evaluate (default all)")
    ap.add_argument("--calibration", default=str(ROOT / "out" / "report_calibration.json"), help="calibration file")
    ap.add_argument("--reuse-calibration", action="store_true", help="load --calibration when valid instead of measuring")
    ap.add_argument("--cal-scale", default="default", help="calibration set: tiny, quick or default")
    ap.add_argument("--cal-rays", type=int, default=None,
                    help="rays per calibration scene (default: core.decide's for the scale, as the add-on calibrates)")
    ap.add_argument("--cal-ladder", default=",".join(map(str, SAMPLE_LADDER)),
                    help=f"grid sample sizes K timed by the calibration (default {','.join(map(str, SAMPLE_LADDER))})")
    ap.add_argument("--sweep-scenes", default=",".join(SWEEP_SCENES), help="scenes of the K / density sweep ('' for none)")
    ap.add_argument("--sweep-rays", type=int, default=500_000, help="rays for the grid's true time in the sweep")
    ap.add_argument("--sweep-k", default=",".join(map(str, SWEEP_K)))
    ap.add_argument("--sweep-density", default=",".join(map(str, SWEEP_DENSITY)))
    ap.add_argument("--sweep-repeats", type=int, default=2)
    ap.add_argument("--no-embree", action="store_true", help="leave Embree out even when embreex is installed")
    ap.add_argument("--no-joint", dest="joint", action="store_false",
                    help="a calibration measured by the report runs before the truths, not in the same passes")
    ap.add_argument("--quiet-share", type=float, default=QUIET_SHARE,
                    help=f"take a round of measurements again when other processes took more than this share of the "
                         f"CPU (default {QUIET_SHARE:g}; 0: never; --quick: 0)")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--no-points", dest="points", action="store_false",
                    help="leave out the decision for point queries (closest point: grid or BVH) on the scenes")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    given = {a.split("=")[0] for a in (argv if argv is not None else sys.argv[1:]) if a.startswith("--")}
    if args.quick:
        for k, v in QUICK.items():
            if f"--{k.replace('_', '-')}" not in given:
                setattr(args, k, v)
        if "--calibration" not in given:
            args.calibration = str(Path(args.out) / "calibration-quick.json")
    if isinstance(args.sweep_k, str):
        args.sweep_k = [int(x) for x in args.sweep_k.split(",") if x]
    if isinstance(args.cal_ladder, str):
        args.cal_ladder = [int(x) for x in args.cal_ladder.split(",") if x]
    if isinstance(args.sweep_density, str):
        args.sweep_density = [float(x) for x in args.sweep_density.split(",") if x]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    load_before = loadavg()
    log(f"report: load average {load_before}, {os.cpu_count()} cores, out {out}")

    kinds, notes = available_kinds(("bvh",) if args.no_embree else ("bvh", "embree"))
    if args.quick:
        scene_list = quick_scenes()
        sweep_names = [scene_list[0][0], scene_list[-1][0]] if args.sweep_scenes else []
    else:
        folder = Path(args.scenes)
        if not folder.is_dir():
            raise SystemExit(f"no real meshes at {folder}: pass --scenes DIR, or --quick for procedural stand-ins")
        scene_list = real_scenes(folder, args.max_triangles)
        sweep_names = [x for x in args.sweep_scenes.split(",") if x]
    if args.only:
        keep = set(args.only.split(","))
        scene_list = [x for x in scene_list if x[0] in keep]
    results, sweep_rows, batch_rows = [], [], []
    meshes = []
    for i, (name, group, make) in enumerate(scene_list):
        meshes.append(make())
        log(f"scene {i + 1}/{len(scene_list)}: {name} ({meshes[-1].triangle_count:,} triangles, {group})")
    # a calibration measured here runs the truths in its own passes: the machine's speed
    # drifts by 10-20% over half an hour, and not alike for every structure, so constants
    # and truths measured one after the other differ by that drift as well as by the model
    joint = {}

    def truth_progress(f, msg):
        log(f"  truths: {msg}")

    def beside():
        passes = args.cal_repeats if args.cal_repeats is not None else CALIBRATION_REPEATS
        if passes != args.repeats:
            log(f"the truths take the calibration's passes ({passes}), not --repeats {args.repeats}")
        jobs, finish = evaluate.truth_jobs(meshes, kinds, passes, rays=args.rays, seed=args.seed, progress=truth_progress)
        return jobs, lambda runs, shares: joint.setdefault("truths", finish(runs, shares, quiet_share(args)))

    cal, cal_how = get_calibration(args, beside=beside if args.joint else None)
    warm_up(("grid",) + kinds)
    log(cal.describe())
    ks = sorted(set(args.sweep_k) | {args.samples})
    ratio_info = evaluate.grid_sample_ratios(cal, ks)
    log("  grid sample ratio (large workload / K-sample time per ray) from the calibration: "
        + ", ".join(f"K={k}: {v['median']:.2f} [{v['low']:.2f}, {v['high']:.2f}]" for k, v in ratio_info["ratios"].items()))
    truths = joint.get("truths") or evaluate.measure_truths(meshes, kinds, rays=args.rays, repeats=args.repeats,
                                                            quiet=quiet_share(args), seed=args.seed,
                                                            progress=truth_progress)
    passes = truths[0].repeats if truths else args.repeats
    point_result = point_evaluation(cal, scene_list, meshes) if args.points else None
    for i, (name, group, _) in enumerate(scene_list):
        mesh, be = meshes[i], truths[i]
        meshes[i] = truths[i] = None  # each scene's structures go once it is done
        s, rays, grid, structs = evaluate.measure_scene(name, group, mesh, cal, kinds, be, rays=args.rays,
                                                        samples=args.samples, seed=args.seed,
                                                        plan_repeats=args.plan_repeats)
        notes += [f"{name}: {x}" for x in s.extra["measurement_notes"]]
        rc, re_ = evaluate.true_break_even(s), evaluate.estimated_break_even(s)
        log(f"  grid {s.grid.build_time * 1e3:.1f} ms {s.grid.per_ray * 1e6:.2f} us/ray (estimate {s.grid_estimate_per_ray * 1e6:.2f} "
            f"= sample {s.grid_sample_per_ray * 1e6:.2f} x {fnum(s.grid_sample_ratio, 2)}); "
            f"bvh {s.measured['bvh'].build_time * 1e3:.0f} ms {s.measured['bvh'].per_ray * 1e6:.2f} us/ray; "
            f"R_C {fnum(rc)} R_est {fnum(re_)} ({fnum(evaluate.relative_error(re_, rc), 0, True)})")
        results.append(s)
        if name in sweep_names:
            rows, brows = evaluate.sweep_scene(s, mesh, rays, cal, structs["bvh"], sweep_rays=args.sweep_rays,
                                               densities=args.sweep_density, ks=args.sweep_k,
                                               repeats=args.sweep_repeats, log=log)
            sweep_rows += rows
            batch_rows += brows
        del mesh, rays, grid, structs

    summary = evaluate.summarise(results, kinds)
    summary["headline"] = headline(summary, args.samples)
    if summary.get("embree"):
        summary["embree"]["calibration_parallelism"] = evaluate.parallelism_summary(
            evaluate.calibration_parallelism(cal, "embree"))
    models = evaluate.model_comparison(results, cal)
    summary["count_models"] = {k: evaluate.count_comparison(cal, k, args.samples) for k in kinds}
    if args.calibrations >= 2:
        again = []
        for i in range(args.calibrations - 1):
            again.append(calibrate_again(args, cal))
            notes += [f"calibration {i + 2}: {x}" for x in again[-1].notes]
            saved = again[-1].save(again_path(args.calibration, i + 2))
            log(f"calibration {i + 2} saved to {saved}")
        first = ("measured in the same passes as the truths" if "truths" in joint else
                 "reused from a file" if cal_how.startswith("reused") else "measured alone")
        # the goal's pair first: the last two plain calibrations when there are two
        pairs = ([(again[-2], again[-1], f"calibrations {len(again)} and {len(again) + 1} of the report, "
                                         f"each alone, one right after the other")] if len(again) >= 2 else [])
        pairs.append((cal, again[0], f"the report's own calibration, {first}, and the one after it, alone"))
        for key, (a, b, which), goal in zip(("calibration_repeatability", "calibration_repeatability_first"),
                                            pairs, (True, False)):
            summary[key] = dict(evaluate.calibration_repeatability(a, b, results), pair=which)
            summary["headline"].append(calibration_row(summary[key], goal=goal))
    best_model, decision = evaluate.decide_model(models, cal.model, cost.DEFAULT_MODEL)
    sweep = (evaluate.sweep_summary(sweep_rows, batch_rows, [x.name for x in results], cal.model) if sweep_rows
             else None)
    meta = {
        "command": "python scripts/report.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"), "quick": args.quick, "rays": args.rays,
        "samples": args.samples, "sweep_rays": args.sweep_rays, "repeats": passes, "sweep_repeats": args.sweep_repeats,
        "cpus": os.cpu_count(), "processor": cal.version.get("machine", {}).get("processor", platform.processor()),
        "python": platform.python_version(), "numpy": np.__version__, "load_before": load_before,
        "threads": (results[0].extra["threads"] if results else {}),
        "calibration": {"scenes": len(cal.scenes), "rays_per_scene": cal.rays_per_scene, "how": cal_how,
                        "model": cal.model, "default_model": cost.DEFAULT_MODEL, "ladder": ratio_info["ladder"],
                        "ratio_at_samples": ratio_info["ratios"].get(args.samples),
                        "fits": {k: v.__dict__ for k, v in cal.fits.items()},
                        "counts": {k: dataclasses.asdict(v) for k, v in cal.counts.items()}},
        "kinds": list(kinds), "notes": notes,
    }
    if point_result is not None:
        err, share = 100 * point_result["median_error"], 100 * point_result["picks"] / max(point_result["picked"], 1)
        summary["headline"].append({"measure": "point queries (closest point, grid or BVH): median break-even error; "
                                               "correct picks", "value": f"{fnum(err, 1)}%; {fnum(share, 1)}%",
                                    "goal": "≤ 25%; ≥ 95%", "met": "yes" if err <= 25 and share >= 95 else "**no**"})
    R = {"meta": meta, "summary": summary, "models": models, "model_decision": decision, "best_model": best_model,
         "points": point_result,
         "grid_sample_ratio": ratio_info, "model_docs": {m: evaluate.MODEL_DOCS.get(m, "") for m in models},
         "sweep": sweep, "notes": list(notes), "plots": [],
         "scenes": evaluate.scene_rows(results)}
    if not args.no_plots:
        try:
            R["plots"] = plots(out, R, results, sweep_rows)
        except ImportError as e:
            R["plots_missing"] = f"matplotlib is not installed ({e}); `pip install -r requirements-dev.txt`"
    meta["duration_s"] = time.perf_counter() - t_start
    meta["load_after"] = loadavg()
    (out / "report.json").write_text(json.dumps(jsonable(R), separators=(",", ":")), encoding="utf-8")
    write_markdown(out / "report.md", jsonable(R) | {"meta": jsonable(meta)})
    log(f"wrote {out / 'report.json'}, {out / 'report.md'} and {len(R['plots'])} plots in {meta['duration_s'] / 60:.1f} min")
    for row in summary["headline"]:
        log(f"  {row['measure']}: {row['value']} (goal {row['goal']})")
    return R


if __name__ == "__main__":
    main()
