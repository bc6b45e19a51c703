"""The evaluation report of issue 4: the paper's protocol on real meshes, as JSON, Markdown and PNG.

    .venv/bin/python scripts/report.py                      # full run, writes docs/report/
    .venv/bin/python scripts/report.py --quick --out out/report-quick   # smoke run, ~20 s
    .venv/bin/python scripts/report.py --reuse-calibration --rays 500000

Protocol (Hapala, Karlik, Havran 2011, section 4, with this project's additions):

1. calibrate the cost model on the package's procedural scenes (``core.calibration``),
   never on the evaluated meshes; ``--reuse-calibration`` loads ``--calibration`` when it
   holds a valid calibration made here instead of measuring again;
2. on every real mesh of ``--scenes`` (../shared/scenes) and on larger versions made by
   midpoint subdivision (up to ``--max-triangles``): build the grid and each hierarchical
   structure for real (builds: median of up to three), trace ``--rays`` of the paper's
   uniform random rays through each, and take the true break-even R_C; then run
   ``core.plan`` with the default K sample rays and take its estimate R_est;
3. speed against error (``--sweep-scenes``): for grid densities and sample counts K, the
   estimate's error against its own cost; plus the grid's estimate from two sample
   batches (``core.report.extrapolated_per_ray``) and the per-ray time against batch size;
4. the calibration model's refinements, judged by held-out error: leave-one-out on the
   calibration scenes, and the evaluated meshes.

Totals for 1e3..1e8 rays are extrapolated from the measured build and per-ray times
(``T_B + R t``), the paper's method.  ``--quick`` replaces everything by tiny procedural
scenes (other generators' seeds and sizes than the calibration's) and small ray counts: a
check that the pipeline runs, not a measurement.

matplotlib is needed for the plots only (requirements-dev.txt); without it the JSON and
Markdown are still written and the Markdown says the plots are missing.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

from hybrid_raycast.core import build, load_obj, scenes as scene_lib  # noqa: E402
from hybrid_raycast.core import report as rep  # noqa: E402
from hybrid_raycast.core.calibration import (  # noqa: E402
    MODELS, Calibration, CalibrationError, _prepare, available_kinds, calibrate, load, time_trace, warm_up,
)
from hybrid_raycast.core.plan import DEFAULT_SAMPLES, plan  # noqa: E402
from hybrid_raycast.core.rays import uniform_rays  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"

#: larger versions of the real meshes: (mesh, subdivision levels); each level is 4x the triangles
SUBDIVIDED = [("teapot", 2), ("beetle-alt", 1), ("stanford-bunny", 1), ("rocker-arm", 2), ("beetle-alt", 2),
              ("homer", 3), ("fandisk", 3), ("stanford-bunny", 2), ("rocker-arm", 3)]
#: the scenes of the speed-against-error sweep (by name, when present)
SWEEP_SCENES = ["cow", "homer", "beetle-alt", "stanford-bunny", "beetle-alt-x16", "stanford-bunny-x16"]
SWEEP_K = [1024, 2048, 4096, 8192, 16384, 32768, 65536]
SWEEP_DENSITY = [0.5, 1.0, 2.0, 4.0, 8.0]
#: the refinement shown beside the add-on as it stands: (calibration model, grid estimate)
PROPOSAL = ("affine", "ratio")
#: the scenes drawn in the time-against-rays figure
TOTALS_PLOT = ["cow", "stanford-bunny", "beetle-alt-x16", "stanford-bunny-x16"]

QUICK = dict(
    rays=20000, cal_scale="tiny", cal_rays=4000, ratio_rays=8000, sweep_rays=8000, sweep_k=[256, 1024], sweep_density=[1.0, 2.0],
    sweep_repeats=1, samples=1024,
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


# -- measuring -------------------------------------------------------------------------------------

def timed_build(mesh, kind, repeats, **config):
    """Build ``repeats`` times; the last structure and the median build time."""
    times, acc = [], None
    for _ in range(max(1, repeats)):
        acc = None
        acc = build(mesh, kind, **config)
        times.append(acc.build_time)
    return acc, float(statistics.median(times))


def build_repeats(n: int) -> int:
    return 3 if n <= 300_000 else 1


def measure_scene(name, group, mesh, cal, args, kinds):
    """True costs on ``args.rays`` rays, then the plan's estimate: one SceneResult (+ the rays)."""
    _prepare(mesh)
    n = mesh.triangle_count
    o, d = uniform_rays(mesh, args.rays, seed=args.seed)
    half = len(o) // 2

    def halves(acc):
        """Trace the rays as two halves: their sum is the measurement, their difference its repeatability."""
        _, t1 = time_trace(acc, o[:half], d[:half])
        _, t2 = time_trace(acc, o[half:], d[half:])
        return t1 + t2, (t1 / half, t2 / (len(o) - half))

    grid, g_build = timed_build(mesh, "grid", 3)
    g_time, g_halves = halves(grid)
    measured, structs, rc_halves = {}, {}, {}
    for k in kinds:
        acc, b = timed_build(mesh, k, build_repeats(n) if k != "embree" else 3)
        t, h_halves = halves(acc)
        measured[k] = rep.Cost(b, t / len(o))
        structs[k] = acc
        rc_halves[k] = [rep.break_even(b, g, h) for g, h in zip(g_halves, h_halves)]
    p = plan(mesh, rep.COST_AT, cal, samples=args.samples, kinds=("grid",) + tuple(kinds), seed=args.seed + 1)
    est = {k: rep.Cost(c.build_time, c.per_ray) for k, c in p.candidates.items() if k != "grid"}
    # the two-batch grid estimate on the plan's grid: K/4 then 3K/4 new sample rays
    so, sd = uniform_rays(mesh, args.samples, seed=args.seed + 2)
    two = two_batch(p.grid, so, sd)
    s = rep.SceneResult(
        name, n, len(o), rep.Cost(g_build, g_time / len(o)), measured, est, p.grid_per_ray, p.estimate_time,
        p.samples, group,
        extra={"plan_grid_build": p.grid_build_time, "grid_resolution": [int(x) for x in getattr(grid, "res", [])],
               "break_even_low": p.candidates["bvh"].break_even_low, "break_even_high": p.candidates["bvh"].break_even_high,
               "two_batch_per_ray": two["per_ray"], "two_batch_time": two["time"], "R_C_halves": rc_halves,
               "threads": {"grid": grid.threads, **{k: a.threads for k, a in structs.items()}}},
    )
    return s, (o, d), grid, structs


def two_batch(grid, o, d):
    """The grid's time per ray for a large workload from two batches of K/4 and 3K/4 rays."""
    k = len(o)
    b1 = max(1, k // 4)
    _, t1 = time_trace(grid, o[:b1], d[:b1])
    _, t2 = time_trace(grid, o[b1:], d[b1:])
    per = rep.extrapolated_per_ray(b1, t1, k - b1, t2, grid.chunk_size, grid.threads)
    return {"per_ray": per, "time": t1 + t2, "b1": b1, "t1": t1, "b2": k - b1, "t2": t2}


def sweep_scene(s: rep.SceneResult, mesh, rays, cal, args, bvh, ratios):
    """Speed against error on one scene: every (density, K, repeat), both grid estimators."""
    o, d = rays[0][: args.sweep_rays], rays[1][: args.sweep_rays]
    h = s.measured["bvh"]
    rows, batch_rows = [], []
    for density in args.sweep_density:
        grid, g_build = timed_build(mesh, "grid", 3, density=density)
        _, g_time = time_trace(grid, o, d)
        t_g = g_time / len(o)
        r_c = rep.break_even(h.build, t_g, h.per_ray)
        for k in args.sweep_k:
            for r in range(args.sweep_repeats):
                p = plan(mesh, rep.COST_AT, cal, samples=k, grid=grid, kinds=("grid", "bvh"), seed=1000 * r + k)
                e = p.candidates["bvh"]
                so, sd = uniform_rays(mesh, k, seed=2000 * r + k + 7)
                two = two_batch(grid, so, sd)
                r_two = rep.break_even(e.build_time, two["per_ray"], e.per_ray)
                total = g_build + rep.COST_AT * t_g
                rows.append({
                    "scene": s.name, "triangles": s.triangles, "density": density, "K": k, "repeat": r,
                    "grid_build": g_build, "grid_per_ray": t_g, "R_C": r_c,
                    "single": {"per_ray": p.grid_per_ray, "R_est": p.break_even, "error": rep.relative_error(p.break_even, r_c),
                               "cost": p.estimate_time, "cost_pct": 100 * p.estimate_time / total},
                    "two_batch": {"per_ray": two["per_ray"], "R_est": r_two, "error": rep.relative_error(r_two, r_c),
                                  "cost": two["time"], "cost_pct": 100 * two["time"] / total},
                })
                rho = ratios[k]["median"]
                r_ratio = rep.break_even(e.build_time, p.grid_per_ray * rho, e.per_ray)
                rows[-1]["ratio"] = {"per_ray": p.grid_per_ray * rho, "R_est": r_ratio, "error": rep.relative_error(r_ratio, r_c),
                                     "cost": p.estimate_time, "cost_pct": 100 * p.estimate_time / total}
                if density == 2.0 and r == 0:
                    _, tb = time_trace(bvh, so, sd)
                    batch_rows.append({"scene": s.name, "K": k, "grid": p.grid_per_ray, "bvh": tb / k})
        log(f"  sweep {s.name}: density {density:g}, grid {t_g * 1e6:.2f} us/ray, R_C {r_c:,.0f}")
        del grid
    batch_rows.append({"scene": s.name, "K": s.rays, "grid": s.grid.per_ray, "bvh": h.per_ray})
    return rows, batch_rows


def grid_sample_calibration(cal: Calibration, args, ks):
    """The grid's time per ray on K sample rays against a large batch, on the calibration
    scenes (never the evaluated ones): the ratio that corrects a plan's sample."""
    scale = cal.scale if cal.scale in scene_lib.SCALES else "default"
    rows = []
    for i, (name, make) in enumerate(scene_lib.calibration_set(scale)):
        mesh = make()
        _prepare(mesh)
        grid = build(mesh, "grid")
        o, d = uniform_rays(mesh, args.ratio_rays, seed=500 + i)
        _, t = time_trace(grid, o, d)
        row = {"scene": name, "triangles": mesh.triangle_count, "true": t / len(o), "sample": {}}
        for k in ks:
            ts = []
            for r in range(2):
                so, sd = uniform_rays(mesh, k, seed=600 + 10 * i + r)
                _, dt = time_trace(grid, so, sd)
                ts.append(dt / k)
            row["sample"][k] = float(np.median(ts))
        rows.append(row)
        del mesh, grid
    ratios = {k: rep.sample_ratio([r["true"] for r in rows], [r["sample"][k] for r in rows]) for k in ks}
    log("  grid sample ratio (true / sample) on the calibration scenes: "
        + ", ".join(f"K={k}: {v['median']:.2f} [{v['p10']:.2f}, {v['p90']:.2f}]" for k, v in ratios.items()))
    return {"scale": scale, "rays": args.ratio_rays, "ratios": ratios, "scenes": rows}


def grid_estimators(s: rep.SceneResult, ratio: float):
    """The evaluated grid estimators for one scene: name -> SceneResult with that estimate."""
    return {
        "single": s,
        "two-batch": rep.with_grid_estimate(s, s.extra["two_batch_per_ray"], s.extra["two_batch_time"]),
        "ratio": rep.with_grid_estimate(s, s.grid_sample_per_ray * ratio),
    }


# -- calibration model candidates --------------------------------------------------------------------

def model_comparison(scenes, cal: Calibration, ratio: float):
    """Held-out break-even error of each calibration model with each grid estimator."""
    out = {}
    names = list(dict.fromkeys(list(MODELS) + list(rep.CANDIDATE_MODELS)))
    for m in names:
        loo = rep.loo_break_even_errors(cal.scenes, "bvh", m)
        held = [rep.reestimate(s, cal.scenes, m) for s in scenes]
        comps = [rep.error_components(s) for s in held]
        entry = {
            "loo": rep.error_summary([x["error"] for x in loo]), "loo_scenes": loo,
            "loo_never": rep.never_agreement([(x["R_est"], x["R_C"]) for x in loo]),
            "loo_build_mabs": float(np.median([abs(x["build_error"]) for x in loo])),
            "loo_per_ray_mabs": float(np.median([abs(x["per_ray_error"]) for x in loo])),
            "held_out_build_mabs": float(np.median([abs(c["build"]) for c in comps])),
            "held_out_per_ray_mabs": float(np.median([abs(c["per_ray"]) for c in comps])),
            "grid": {},
        }
        for est_name in ("single", "two-batch", "ratio"):
            variant = [grid_estimators(s, ratio)[est_name] for s in held]
            errs = [rep.relative_error(rep.estimated_break_even(s), rep.true_break_even(s)) for s in variant]
            entry["grid"][est_name] = {
                "held_out": rep.error_summary(errs), "errors": {s.name: e for s, e in zip(variant, errs)},
                "never": rep.never_agreement([(rep.estimated_break_even(s), rep.true_break_even(s)) for s in variant]),
                "picks": rep.pick_accuracy(variant), "speedups": rep.speedup_summary(variant),
                "cost_pct": float(np.median([rep.estimate_cost_percent(s) for s in variant])),
                "cost_pct_max": float(np.max([rep.estimate_cost_percent(s) for s in variant])),
            }
        out[m] = entry
    return out


def decide_model(models, current: str) -> tuple[str, str, str]:
    """(model, grid estimator, text): the best combination that cuts both the leave-one-out
    error on the calibration scenes and the error on the evaluated meshes against the paper's
    model with the plan's sample as it is (the paper's method); else the paper's."""
    paper = models["paper"]
    base_loo = paper["loo"]["median_abs"]
    base = paper["grid"]["single"]["held_out"]["median_abs"]
    combos = [(m, g, models[m]["grid"][g]["held_out"]["median_abs"], models[m]["loo"]["median_abs"])
              for m in models for g in models[m]["grid"]]
    ok = [c for c in combos if c[2] < base and c[3] <= base_loo and math.isfinite(c[2])]
    cur = models[current]["grid"]["single"]["held_out"]["median_abs"]
    lines = [f"The paper's model with the plan's grid sample as it is: median absolute error {base:.1f}% on the "
             f"evaluated meshes, {base_loo:.1f}% leave-one-out on the calibration scenes. The calibration's default "
             f"model is '{current}' ({cur:.1f}% on the evaluated meshes with the same sample, "
             f"{models[current]['loo']['median_abs']:.1f}% leave-one-out)."]
    by_model = {m: min(models[m]["grid"][g]["held_out"]["median_abs"] for g in models[m]["grid"]) for m in models}
    lines.append("Best per model over the grid estimates: " + ", ".join(f"{m} {v:.1f}%" for m, v in by_model.items()) + ".")
    if not ok:
        lines.append("No combination cuts both errors against the paper's.")
        return "paper", "single", " ".join(lines)
    m, g, e, loo = min(ok, key=lambda c: c[2])
    lines.append(f"Best combination: the {m} model with the '{g}' grid estimate, {e:.1f}% on the evaluated meshes "
                 f"({loo:.1f}% leave-one-out)" + ("." if g == "single" else
                 "; its grid estimate is not in `core.plan` (a recommendation for the plan, evaluated here)."))
    return m, g, " ".join(lines)


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


def fnum(x, digits=0, pct=False):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if pct is None:  # a bare percentage, no sign
        return f"{x:,.{digits}f}%"
    if isinstance(x, float) and math.isinf(x):
        return "never" if x > 0 else "-inf"
    s = f"{x:+,.{digits}f}" if pct else f"{x:,.{digits}f}"
    return s + ("%" if pct else "")


def sweep_table(rows, estimator, hds=None):
    """Median |error| and median cost per (density, K) over the sweep scenes and repeats.

    hds: {scene: Cost} estimates of the BVH under another calibration model; by default the
    plan's own (the calibration's model)."""
    def error(r):
        e = r[estimator]
        if hds is None:
            return e["error"]
        h = hds[r["scene"]]
        return rep.relative_error(rep.break_even(h.build, e["per_ray"], h.per_ray), r["R_C"])

    cells = {}
    for r in rows:
        cells.setdefault((r["density"], r["K"]), []).append(r)
    out = []
    for (dens, k), rs in sorted(cells.items()):
        errs = [error(r) for r in rs]
        fin = [x for x in errs if x is not None and math.isfinite(x)]
        out.append({"density": dens, "K": k, "median_abs_error": float(np.median(np.abs(fin))) if fin else math.nan,
                    "median_error": float(np.median(fin)) if fin else math.nan, "undefined": len(rs) - len(fin),
                    "median_cost_pct": float(np.median([r[estimator]["cost_pct"] for r in rs])),
                    "max_cost_pct": float(np.max([r[estimator]["cost_pct"] for r in rs])), "cases": len(rs)})
    return out


def choose_defaults(table, goal_cost=5.0, goal_error=25.0):
    """The cheapest (density, K) whose worst-scene cost stays under the goal and whose error is
    within 2 points of the best such; returns (row, reason)."""
    ok = [r for r in table if r["max_cost_pct"] < goal_cost and math.isfinite(r["median_abs_error"])]
    if not ok:
        return None, "no configuration keeps the estimate's cost under the goal on every sweep scene"
    best = min(r["median_abs_error"] for r in ok)
    near = [r for r in ok if r["median_abs_error"] <= best + 2.0]
    pick = min(near, key=lambda r: r["median_cost_pct"])
    return pick, (f"lowest median |error| among configurations whose cost stays under {goal_cost:g}% of the "
                  f"grid-only total at 1e6 rays on every sweep scene is {best:.1f}%; the cheapest within 2 points "
                  f"of it is density {pick['density']:g}, K = {pick['K']:,}")


def write_markdown(path: Path, R: dict):
    meta, summ = R["meta"], R["summary"]
    L = []
    w = L.append
    w("# Hybrid decision: evaluation report (issue 4)\n")
    w(f"Generated by `{meta['command']}` on {meta['date']} in {meta['duration_s'] / 60:.1f} min; "
      f"{meta['cpus']} cores ({meta['processor']}), load average {meta['load_before']} before and "
      f"{meta['load_after']} after (other jobs shared the machine). Python {meta['python']}, numpy {meta['numpy']}.\n")
    if meta["quick"]:
        w("**Quick mode**: tiny procedural scenes and few rays; a smoke run, not a measurement.\n")
    w(f"Protocol (Hapala, Karlik, Havran 2011, section 4): calibration on the package's procedural scenes "
      f"({meta['calibration']['scenes']} scenes, {meta['calibration']['rays_per_scene']:,} rays each, "
      f"{meta['calibration']['how']}); evaluation on {len(R['scenes'])} scenes never used for fitting: "
      f"real meshes from `../shared/scenes` and larger versions made by midpoint subdivision. "
      f"On each, the grid and the BVH are really built (median of three builds below 300k triangles, "
      f"one above) and traced with **{meta['rays']:,} rays** of the paper's distribution (origins uniform in "
      f"the padded scene box, directions uniform on the sphere); R_C = T_B^H / (t_G - t_H) from those "
      f"measurements (the grid's build is sunk, as in the estimate). R_est comes from `core.plan` with "
      f"K = {meta['samples']:,} sample rays and the default grid density. Totals for 1e3..1e8 rays are "
      f"extrapolated from the measured build and per-ray times (T_B + R t), the paper's method. "
      f"Threads per structure: numpy grid and BVH {meta['threads'].get('grid')}, Embree (embreex) 1.\n")
    # -- headline
    h = summ["headline"]
    w("## Headline (grid against the numpy BVH, the paper's setting)\n")
    w(f"As the add-on stands: the calibration's default model ('{meta['calibration']['model']}') and `core.plan`'s grid "
      f"sample (K rays, time / K).\n")
    w("| measure | goal | measured | met |\n|---|---|---:|:---:|")
    for row in h:
        w(f"| {row['measure']} | {row['goal']} | {row['value']} | {row['met']} |")
    w("")
    rc = summ.get("rc_repeatability")
    if rc:
        w(f"R_C's own repeatability: the two halves of each scene's rays give break-evens that differ by a median "
          f"{rc['median']:.1f}% of R_C (max {rc['max']:.0f}%, {rc['scenes']} scenes): errors below that are noise.\n")
    rec = R.get("recommended")
    if rec:
        w(f"With the proposed refinement ({rec['model']} calibration model, '{rec['grid']}' grid estimate: the plan's "
          f"sample time times the small-batch ratio calibrated for its K; see 'Refinements' below), recomputed on the "
          f"same measurements (the ratio correction is not in `core.plan` yet):\n")
        w("| measure | goal | measured | met |\n|---|---|---:|:---:|")
        for row in rec["summary"]["headline"]:
            w(f"| {row['measure']} | {row['goal']} | {row['value']} | {row['met']} |")
        w("")
    # -- per scene
    w(f"## Break-even per scene ({meta['calibration']['model']} model)\n")
    w("Times per ray in µs, builds in ms. Error = 100 (R_est - R_C) / R_C. 'never': the grid is at least as "
      "fast per ray, so the BVH never pays. Components: the estimate's own error on the BVH build, on the "
      "BVH time per ray, and on the grid time per ray from K samples (each 100 (est - true) / true).\n")
    w("| scene | group | N | grid build | t_G | t_G sample | BVH build | t_H | R_C (halves) | R_est [low, high] | error | "
      "err build | err t_H | err t_G |")
    w("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for s in R["scenes"]:
        m, e, c = s["measured"]["bvh"], s["estimated"]["bvh"], s["components"]
        w(f"| {s['name']} | {s['group']} | {s['triangles']:,} | {s['grid']['build'] * 1e3:.1f} | "
          f"{s['grid']['per_ray'] * 1e6:.2f} | {s['grid_sample_per_ray'] * 1e6:.2f} | {m['build'] * 1e3:.0f} | "
          f"{m['per_ray'] * 1e6:.2f} | {fnum(s['R_C'])} ({', '.join(fnum(x) for x in s['extra']['R_C_halves']['bvh'])}) | {fnum(s['R_est'])} [{fnum(s['extra'].get('break_even_low'))}, "
          f"{fnum(s['extra'].get('break_even_high'))}] | {fnum(s['error'], 0, True)} | {fnum(c['build'], 0, True)} | "
          f"{fnum(c['per_ray'], 0, True)} | {fnum(c['grid_per_ray'], 0, True)} |")
    es, nv = summ["errors"], summ["never"]
    w(f"\nOver {es['defined']} scenes with both break-evens finite (left out of the sums: {nv['both_never']} where both "
      f"say the BVH never pays, {nv['only_estimate_never']} where only the estimate says so, "
      f"{nv['only_measured_never']} where only the measurement does): **sum of errors {es['sum']:+,.0f}%, sum of absolute errors {es['sum_abs']:,.0f}%**, "
      f"median error {es['median']:+.1f}%, median absolute error {es['median_abs']:.1f}%, mean absolute "
      f"{es['mean_abs']:.1f}%, {es['within_25']} within 25% and {es['within_10']} within 10%.\n")
    for g, gs in summ.get("errors_by_group", {}).items():
        w(f"- {g}: median absolute error {fnum(gs['median_abs'], 1)}% over {gs['defined']} scenes "
          f"(sum {fnum(gs['sum'], 0)}%, sum of absolute values {fnum(gs['sum_abs'], 0)}%)")
    w("")
    # -- speed
    w("## Speed: hybrid, online, oracle\n")
    mp = summ["median_per_ray"]
    w("Median time per ray over the scenes: " + ", ".join(f"{k} {v * 1e6:.2f} µs" for k, v in mp.items()) + ".\n")
    sp = summ["speedups"]
    w(f"Over {sp['speedup_vs_grid']['cases']} (scene, R) cases, R = 1e3..1e8 (21 counts, four a decade):\n")
    w("| ratio | median | 90th percentile | min | max |\n|---|---:|---:|---:|---:|")
    for k, lab in (("speedup_vs_grid", "always-grid / hybrid"), ("speedup_vs_bvh", "always-BVH / hybrid"),
                   ("hybrid_over_oracle", "hybrid / oracle"),
                   ("hybrid_reuse_over_oracle", "hybrid with samples from the workload / oracle"),
                   ("online_over_oracle", "online / oracle"),
                   ("online_over_hybrid", "online / hybrid")):
        if k in sp:
            v = sp[k]
            w(f"| {lab} | {v['median']:.3f} | {v['p90']:.3f} | {v['min']:.3f} | {v['max']:.3f} |")
    pk = summ["picks"]
    w(f"\nCorrect picks: {pk['correct']} of {pk['considered']} cases where the grid's remaining cost R t_G and the "
      f"BVH's T_B^H + R t_H differ by more than 10% (**{fnum(pk['percent'], 1)}%**); counting the grid's build "
      f"in its cost instead: {fnum(summ['picks_total']['percent'], 1)}% of {summ['picks_total']['considered']}.\n")
    w("Median over the scenes per ray count (hybrid's total over each strategy's; oracle = best fixed choice):\n")
    w("| R | always-grid / hybrid | always-BVH / hybrid | hybrid / oracle | hybrid, samples from the workload / oracle | online / oracle | hybrid picks BVH |")
    w("|---:|---:|---:|---:|---:|---:|---:|")
    for row in summ["by_ray_count"]:
        w(f"| {row['R']:.0e} | {row['grid']:.3f} | {row['bvh']:.3f} | {row['hybrid_oracle']:.3f} | "
          f"{row['reuse_oracle']:.3f} | {row['online_oracle']:.3f} | {row['bvh_share']:.0%} |")
    cost = summ["estimate_cost"]
    w(f"\nThe estimate's own cost (tracing K sample rays through the grid, plus arithmetic) at 1e6 rays: median "
      f"**{cost['median']:.2f}%** of the grid-only total, max {cost['max']:.2f}% ({cost['max_scene']}).\n")
    if summ.get("embree"):
        em = summ["embree"]
        w("## With Embree as a third candidate (the add-on's default when embreex is installed)\n")
        w(f"Break-even error of the grid against Embree ({meta['calibration']['model']} model): median absolute {fnum(em['errors']['median_abs'], 1)}% "
          f"over {em['errors']['defined']} scenes (sum {fnum(em['errors']['sum'], 0)}%, sum of absolute values "
          f"{fnum(em['errors']['sum_abs'], 0)}%). Hybrid choosing among grid, BVH and Embree: hybrid / oracle median "
          f"{em['speedups']['hybrid_over_oracle']['median']:.3f} (90th percentile {em['speedups']['hybrid_over_oracle']['p90']:.3f}); "
          f"always-Embree / hybrid median {em['speedups']['speedup_vs_embree']['median']:.3f}.\n")
        w("| scene | N | Embree build ms | t_E µs | R_C(Embree) | R_est(Embree) | error |\n|---|---:|---:|---:|---:|---:|---:|")
        for r in em["scenes"]:
            w(f"| {r['name']} | {r['triangles']:,} | {r['build'] * 1e3:.1f} | {r['per_ray'] * 1e6:.3f} | {fnum(r['R_C'])} | "
              f"{fnum(r['R_est'])} | {fnum(r['error'], 0, True)} |")
        w("")
    # -- sweep
    sw = R.get("sweep")
    if sw and sw["rows"]:
        w("## Speed against error: sample rays K and grid density\n")
        w(f"Sweep scenes: {', '.join(sw['scenes'])}; the grid's true time per ray on {meta['sweep_rays']:,} rays "
          f"at each density; {meta['sweep_repeats']} estimate(s) per (scene, density, K); cost = the estimate's "
          f"time as % of that density's grid-only total at 1e6 rays. 'single' is `core.plan` as it is (t_G = time "
          f"of the K rays / K); 'two-batch' times K/4 then 3K/4 rays and extrapolates to the workload's chunk "
          f"size (`core.report.extrapolated_per_ray`); ")
        w("'ratio' multiplies the plan's sample time by the median ratio (large-batch time / K-sample time) measured "
          "on the calibration scenes for that K (see below): no extra rays.\n")
        ests = tuple(e for e in ("single", "two_batch", "ratio", "recommended") if e in sw["tables"])
        if "recommended" in sw["tables"]:
            rec_ = R["recommended"]
            w(f"'recommended' is the proposal, the {rec_['model']} model with the '{rec_['grid']}' grid estimate (the other columns use "
              f"the calibration's model, {meta['calibration']['model']}).\n")
        w("| density | K | " + " | ".join(f"{e.replace('_', '-')}: median abs error (median error) | cost % median / max" for e in ests) + " |")
        w("|---:|---:|" + "---:|---:|" * len(ests))
        idx = {e: {(r["density"], r["K"]): r for r in sw["tables"][e]} for e in ests}
        for r in sw["tables"]["single"]:
            key = (r["density"], r["K"])
            cells = []
            for e in ests:
                t = idx[e][key]
                cells.append(f"{fnum(t['median_abs_error'], 1, None)} ({fnum(t['median_error'], 1, True)}) | "
                             f"{t['median_cost_pct']:.2f} / {t['max_cost_pct']:.2f}")
            w(f"| {r['density']:g} | {r['K']:,} | " + " | ".join(cells) + " |")
        w("")
        w("**Defaults.** " + sw["choice"]["text"] + "\n")
        if sw.get("batch"):
            w("Time per ray (µs) against batch size at density 2 (the last column is the evaluation's "
              f"{meta['rays']:,}-ray workload): why a small sample overstates the grid's cost per ray.\n")
            ks = sorted({b["K"] for b in sw["batch"]})
            w("| scene | structure | " + " | ".join(f"{k:,}" for k in ks) + " |")
            w("|---|---|" + "---:|" * len(ks))
            for sc in sw["scenes"]:
                for kind in ("grid", "bvh"):
                    vals = {b["K"]: b[kind] for b in sw["batch"] if b["scene"] == sc}
                    w(f"| {sc} | {kind} | " + " | ".join(f"{vals[k] * 1e6:.2f}" if k in vals else "" for k in ks) + " |")
            w("")
    # -- models
    mc = R.get("models")
    if mc:
        w("## Refinements of the two-constant model (item 5)\n")
        w("Held-out break-even error of each calibration model: leave-one-out over the calibration scenes (the "
          "grid's time measured on the same rays, so only the model errs) and the evaluated meshes above "
          "(the plan's grid sample, so the sample's error is included), each with the three grid estimates. Models: " +
          "; ".join(f"**{k}** {v}" for k, v in R["model_docs"].items()) + ".\n")
        w("Medians and sums are over the scenes where both break-evens are finite; 'never' counts the others as "
          "both / only the estimate / only the measurement saying the BVH never pays.\n")
        w("| model | LOO median abs error | LOO sum / sum abs | LOO never | LOO build / per-ray median abs | held-out build / "
          "per-ray median abs | grid estimate | held-out median abs error | held-out sum / sum abs | never | correct picks | "
          "hybrid / oracle | cost % |")
        w("|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|")
        for name, m in mc.items():
            loo = m["loo"]
            for g, v in m["grid"].items():
                ho = v["held_out"]
                first = g == "single"
                w(f"| {name if first else ''} | {fnum(loo['median_abs'], 1, None) if first else ''} | "
                  f"{(fnum(loo['sum'], 0) + ' / ' + fnum(loo['sum_abs'], 0)) if first else ''} | "
                  f"{'/'.join(str(x) for x in m['loo_never'].values()) if first else ''} | "
                  f"{(fnum(m['loo_build_mabs'], 0) + '% / ' + fnum(m['loo_per_ray_mabs'], 0) + '%') if first else ''} | "
                  f"{(fnum(m['held_out_build_mabs'], 0) + '% / ' + fnum(m['held_out_per_ray_mabs'], 0) + '%') if first else ''} | "
                  f"{g} | {fnum(ho['median_abs'], 1, None)} | {fnum(ho['sum'], 0)} / {fnum(ho['sum_abs'], 0)} | "
                  f"{'/'.join(str(x) for x in v['never'].values())} | "
                  f"{fnum(v['picks']['percent'], 1, None)} | {v['speedups']['hybrid_over_oracle']['median']:.3f} | "
                  f"{v['cost_pct']:.2f} |")
        gr = R.get("grid_sample_ratio")
        if gr:
            w(f"\nGrid sample ratio (large-batch time per ray on {gr['rays']:,} rays / time per ray on K sample rays, "
              f"median of two samples) over the {len(gr['scenes'])} calibration scenes ('{gr['scale']}' set): "
              + ", ".join(f"K = {int(k):,}: {v['median']:.2f} [{v['p10']:.2f}, {v['p90']:.2f}]" for k, v in gr["ratios"].items())
              + " (median [10th, 90th percentile]).")
        w("\n**Decision.** " + R["model_decision"] + "\n")
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
        halves = [rep.relative_error(r_est, math.inf if h is None else h) for h in s["extra"].get("R_C_halves", {}).get("bvh", [])]
        halves = [h for h in halves if math.isfinite(h)]
        if len(halves) == 2:
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
        t = rep.strategy_totals(s, r, ("bvh",))
        for k, style in (("grid", "-"), ("bvh", "-"), ("hybrid", "--"), ("online", ":"), ("oracle", "-")):
            if k in t:
                ax.loglog(r, t[k], style, label=k, lw=2.5 if k == "oracle" else 1.5, alpha=0.35 if k == "oracle" else 1.0)
        rc, re_ = rep.true_break_even(s), rep.estimated_break_even(s)
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
    made.append(("totals.png", "Total time against ray count: always-grid, always-BVH, hybrid, online, oracle"))
    # 3. speed against error
    if sweep_rows and R.get("sweep"):
        tables = R["sweep"]["tables"]
        fig, axes = plt.subplots(1, len(tables), figsize=(4.5 * len(tables), 4), sharey=True)
        for ax, (est, table) in zip(axes, tables.items()):
            for dens in sorted({x["density"] for x in table}):
                rows = [x for x in table if x["density"] == dens]
                ax.plot([x["median_cost_pct"] for x in rows], [x["median_abs_error"] for x in rows], "o-", label=f"density {dens:g}")
                for x in rows:
                    ax.annotate(f"{x['K'] // 1024}k", (x["median_cost_pct"], x["median_abs_error"]), fontsize=6)
            ax.axhline(25, color="tab:green", lw=0.8, ls="--")
            ax.axvline(5, color="tab:red", lw=0.8, ls="--")
            ax.set_xscale("log")
            ax.set_xlabel("estimate cost, % of grid-only total at 1e6 rays")
            rec_ = R.get("recommended") or {}
            mod = R["meta"]["calibration"]["model"]
            ax.set_title({"single": f"{mod} model, one batch (plan as is)", "two_batch": f"{mod} model, two batches",
                          "ratio": f"{mod} model, one batch x calibrated ratio",
                          "recommended": f"{rec_.get('model')} model, {rec_.get('grid')} grid estimate"}[est], fontsize=9)
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.2)
        axes[0].set_ylabel("median |break-even error|, %")
        axes[-1].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "speed_vs_error.png", dpi=110)
        plt.close(fig)
        made.append(("speed_vs_error.png", "The estimate's error against its cost as K (labels, in thousands) and the grid density vary"))
    return made


# -- the run -----------------------------------------------------------------------------------------

def get_calibration(args):
    path = Path(args.calibration)
    if args.reuse_calibration and path.exists():
        try:
            cal = load(path)
            log(f"calibration reused from {path} ({len(cal.scenes)} scenes, {cal.rays_per_scene:,} rays each)")
            return cal, f"reused from {path.name}, measured {cal.created}"
        except CalibrationError as e:
            log(f"calibration at {path} not usable ({e}); measuring again")
    log(f"calibrating ({args.cal_scale} set, {args.cal_rays:,} rays per scene)")
    last = [0.0]

    def progress(f, msg):
        if f - last[0] >= 0.1 or f >= 1.0:
            last[0] = f
            log(f"  {f:4.0%} {msg}")

    cal = calibrate(kinds=("bvh", "embree"), scale=args.cal_scale, rays_per_scene=args.cal_rays, progress=progress)
    cal.save(path)
    return cal, f"measured for this report in {cal.duration_s:.0f} s"


def summarise(scenes, kinds):
    errs = [rep.relative_error(rep.estimated_break_even(s), rep.true_break_even(s)) for s in scenes]
    by_group = {}
    for g in sorted({s.group for s in scenes}):
        by_group[g] = rep.error_summary([e for s, e in zip(scenes, errs) if s.group == g])
    rows = []
    for i, r in enumerate(rep.RAY_COUNTS):
        per = [rep.strategy_totals(s, [r], ("bvh",)) for s in scenes]
        rows.append({"R": float(r),
                     "grid": float(np.median([t["grid"][0] / t["hybrid"][0] for t in per])),
                     "bvh": float(np.median([t["bvh"][0] / t["hybrid"][0] for t in per])),
                     "hybrid_oracle": float(np.median([t["hybrid"][0] / t["oracle"][0] for t in per])),
                     "reuse_oracle": float(np.median([t["hybrid_reuse"][0] / t["oracle"][0] for t in per])),
                     "online_oracle": float(np.median([t["online"][0] / t["oracle"][0] for t in per])),
                     "bvh_share": float(np.mean([t["choice"][0] == "bvh" for t in per]))})
    costs = [rep.estimate_cost_percent(s) for s in scenes]
    imax = int(np.argmax(costs))
    rep_, steady = [], []
    for s, e in zip(scenes, errs):
        a, b = s.extra.get("R_C_halves", {}).get("bvh", (math.nan, math.nan))
        rc = rep.true_break_even(s)
        if all(math.isfinite(x) for x in (a, b, rc)):
            rep_.append(100 * abs(a - b) / rc)
            if rep_[-1] <= 25:
                steady.append(e)
    out = {
        "errors": rep.error_summary(errs), "errors_by_group": by_group,
        "never": rep.never_agreement([(rep.estimated_break_even(s), rep.true_break_even(s)) for s in scenes]),
        "median_per_ray": rep.median_per_ray(scenes, ("grid",) + tuple(kinds)),
        "speedups": rep.speedup_summary(scenes, rep.RAY_COUNTS, ("bvh",)),
        "picks": rep.pick_accuracy(scenes), "picks_total": rep.pick_accuracy(scenes, sunk_grid=False),
        "by_ray_count": rows,
        "rc_repeatability": {"median": float(np.median(rep_)), "max": float(np.max(rep_)), "scenes": len(rep_)} if rep_ else None,
        "errors_repeatable": rep.error_summary(steady),
        "estimate_cost": {"median": float(np.median(costs)), "max": float(costs[imax]), "max_scene": scenes[imax].name,
                          "per_scene": {s.name: c for s, c in zip(scenes, costs)}},
    }
    if "embree" in kinds:
        em = []
        for s in scenes:
            rc = rep.true_break_even(s, "embree")
            re_ = rep.estimated_break_even(s, "embree")
            em.append({"name": s.name, "triangles": s.triangles, "build": s.measured["embree"].build,
                       "per_ray": s.measured["embree"].per_ray, "R_C": rc, "R_est": re_, "error": rep.relative_error(re_, rc)})
        out["embree"] = {"scenes": em, "errors": rep.error_summary([x["error"] for x in em]),
                         "speedups": rep.speedup_summary(scenes, rep.RAY_COUNTS, ("bvh", "embree"))}
    e, pk, sp, c = out["errors"], out["picks"], out["speedups"], out["estimate_cost"]

    def met(ok):
        return "yes" if ok else "**no**"

    out["headline"] = [
        {"measure": "median absolute break-even error, evaluated meshes", "goal": "≤ 25% (stretch 10%)",
         "value": f"{fnum(e['median_abs'], 1, None)} ({e['defined']} scenes)", "met": met(e["median_abs"] <= 25)},
        {"measure": "the same on the scenes whose R_C is repeatable (its two halves within 25%)", "goal": "≤ 25%",
         "value": f"{fnum(out['errors_repeatable']['median_abs'], 1, None)} ({out['errors_repeatable']['defined']} scenes)",
         "met": met(out["errors_repeatable"]["median_abs"] <= 25)},
        {"measure": "sum of errors / sum of absolute errors (paper's figures)", "goal": "-",
         "value": f"{fnum(e['sum'], 0)}% / {fnum(e['sum_abs'], 0)}%", "met": "-"},
        {"measure": "correct picks where grid and BVH differ by > 10%", "goal": "≥ 90%",
         "value": f"{fnum(pk['percent'], 1)}% ({pk['correct']}/{pk['considered']})", "met": met(pk["percent"] >= 90)},
        {"measure": "hybrid total / oracle total, median over (scene, R)", "goal": "≤ 1.10",
         "value": f"{sp['hybrid_over_oracle']['median']:.3f} (90th pct {sp['hybrid_over_oracle']['p90']:.3f})",
         "met": met(sp["hybrid_over_oracle"]["median"] <= 1.10)},
        {"measure": "the same, K sample rays taken from the workload (none when R <= K)", "goal": "≤ 1.10",
         "value": f"{sp['hybrid_reuse_over_oracle']['median']:.3f} (90th pct {sp['hybrid_reuse_over_oracle']['p90']:.3f})",
         "met": met(sp["hybrid_reuse_over_oracle"]["median"] <= 1.10)},
        {"measure": "estimate cost at 1e6 rays, % of grid-only total (median / max)", "goal": "< 5%",
         "value": f"{c['median']:.2f}% / {c['max']:.2f}%", "met": met(c["median"] < 5)},
        {"measure": "median speedup of the hybrid over always-grid / always-BVH", "goal": "-",
         "value": f"{sp['speedup_vs_grid']['median']:.2f}x / {sp['speedup_vs_bvh']['median']:.2f}x", "met": "-"},
        {"measure": "online (ski rental) total / oracle, median (max)", "goal": "≤ ~2 by construction",
         "value": f"{sp['online_over_oracle']['median']:.3f} ({sp['online_over_oracle']['max']:.2f})", "met": "-"},
    ]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "docs" / "report"), help="output folder (default docs/report)")
    ap.add_argument("--quick", action="store_true", help="tiny procedural scenes, few rays: a smoke run")
    ap.add_argument("--rays", type=int, default=2_000_000, help="rays per evaluated scene for R_C (default 2M)")
    ap.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, help=f"plan's K sample rays (default {DEFAULT_SAMPLES})")
    ap.add_argument("--scenes", default=str(SHARED_SCENES), help="folder of real .obj meshes (default ../shared/scenes)")
    ap.add_argument("--max-triangles", type=int, default=1_500_000, help="largest subdivided scene (default 1.5M)")
    ap.add_argument("--only", default="", help="comma-separated scene names to evaluate (default all)")
    ap.add_argument("--calibration", default=str(ROOT / "out" / "report_calibration.json"), help="calibration file")
    ap.add_argument("--reuse-calibration", action="store_true", help="load --calibration when valid instead of measuring")
    ap.add_argument("--cal-scale", default="default", help="calibration set: tiny, quick or default")
    ap.add_argument("--cal-rays", type=int, default=262144, help="rays per calibration scene (default 262144)")
    ap.add_argument("--sweep-scenes", default=",".join(SWEEP_SCENES), help="scenes of the K / density sweep ('' for none)")
    ap.add_argument("--sweep-rays", type=int, default=500_000, help="rays for the grid's true time in the sweep")
    ap.add_argument("--sweep-k", default=",".join(map(str, SWEEP_K)))
    ap.add_argument("--sweep-density", default=",".join(map(str, SWEEP_DENSITY)))
    ap.add_argument("--sweep-repeats", type=int, default=2)
    ap.add_argument("--ratio-rays", type=int, default=262144, help="rays for the grid's large-batch time on the calibration scenes")
    ap.add_argument("--no-embree", action="store_true", help="leave Embree out even when embreex is installed")
    ap.add_argument("--no-plots", action="store_true")
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
    if isinstance(args.sweep_density, str):
        args.sweep_density = [float(x) for x in args.sweep_density.split(",") if x]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    load_before = loadavg()
    log(f"report: load average {load_before}, {os.cpu_count()} cores, out {out}")

    kinds, notes = available_kinds(("bvh",) if args.no_embree else ("bvh", "embree"))
    cal, cal_how = get_calibration(args)
    warm_up(("grid",) + kinds)
    log(cal.describe())
    ks = sorted(set(args.sweep_k) | {args.samples})
    log(f"grid sample ratio on the calibration scenes, K = {ks}")
    ratio_info = grid_sample_calibration(cal, args, ks)

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
    for i, (name, group, make) in enumerate(scene_list):
        mesh = make()
        log(f"scene {i + 1}/{len(scene_list)}: {name} ({mesh.triangle_count:,} triangles, {group})")
        s, rays, grid, structs = measure_scene(name, group, mesh, cal, args, kinds)
        rc, re_ = rep.true_break_even(s), rep.estimated_break_even(s)
        log(f"  grid {s.grid.build * 1e3:.1f} ms {s.grid.per_ray * 1e6:.2f} us/ray (sample {s.grid_sample_per_ray * 1e6:.2f}); "
            f"bvh {s.measured['bvh'].build * 1e3:.0f} ms {s.measured['bvh'].per_ray * 1e6:.2f} us/ray; "
            f"R_C {rc:,.0f} R_est {re_:,.0f} ({fnum(rep.relative_error(re_, rc), 0, True)})")
        results.append(s)
        if name in sweep_names:
            rows, brows = sweep_scene(s, mesh, rays, cal, args, structs["bvh"], ratio_info["ratios"])
            sweep_rows += rows
            batch_rows += brows
        del mesh, rays, grid, structs

    summary = summarise(results, kinds)
    rho = ratio_info["ratios"][args.samples]["median"]
    models = model_comparison(results, cal, rho)
    best_model, best_grid, decision = decide_model(models, cal.model)
    # the proposal shown beside the add-on as it stands: the affine model (its build and
    # per-ray estimates are the accurate ones on held-out scenes) with the grid sample
    # corrected by the calibrated small-batch ratio (no extra rays)
    recommended = None
    prop_model, prop_grid = PROPOSAL
    if prop_model in models and (prop_model, prop_grid) != (cal.model, "single"):
        variant = [grid_estimators(rep.reestimate(s, cal.scenes, prop_model, kinds), rho)[prop_grid] for s in results]
        recommended = {"model": prop_model, "grid": prop_grid, "summary": summarise(variant, kinds)}
        best_model, best_grid = prop_model, prop_grid
    sweep = None
    if sweep_rows:
        tables = {est: sweep_table(sweep_rows, est) for est in ("single", "two_batch", "ratio")}
        picks = {est: choose_defaults(t) for est, t in tables.items()}
        text = " ".join(f"{cal.model} model, grid estimate '{est.replace('_', '-')}': {why}." for est, (_, why) in picks.items())
        if recommended:
            hds = {s.name: rep.reestimate(s, cal.scenes, best_model).estimated["bvh"] for s in results}
            key = best_grid.replace("-", "_")
            tables["recommended"] = sweep_table(sweep_rows, key, hds)
            pick, why = choose_defaults(tables["recommended"])
            picks["recommended"] = (pick, why)
            text += f" The proposed refinement ({best_model} model, '{best_grid}' grid estimate): {why}."
        text += f" The plan's current default is K = {DEFAULT_SAMPLES:,} at density 2."
        sweep = {"scenes": sorted({r["scene"] for r in sweep_rows}, key=lambda n: [x.name for x in results].index(n)),
                 "rows": sweep_rows, "tables": tables, "batch": batch_rows,
                 "choice": {"picks": {est: p for est, (p, _) in picks.items()}, "text": text}}
    meta = {
        "command": "python scripts/report.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"), "quick": args.quick, "rays": args.rays,
        "samples": args.samples, "sweep_rays": args.sweep_rays, "sweep_repeats": args.sweep_repeats,
        "cpus": os.cpu_count(), "processor": cal.version.get("machine", {}).get("processor", platform.processor()),
        "python": platform.python_version(), "numpy": np.__version__, "load_before": load_before,
        "threads": (results[0].extra["threads"] if results else {}),
        "calibration": {"scenes": len(cal.scenes), "rays_per_scene": cal.rays_per_scene, "how": cal_how,
                        "model": cal.model, "fits": {k: v.__dict__ for k, v in cal.fits.items()}},
        "kinds": list(kinds), "notes": notes,
    }
    R = {"meta": meta, "summary": summary, "models": models, "model_decision": decision, "recommended": recommended,
         "grid_sample_ratio": ratio_info, "model_docs": {m: rep.MODEL_DOCS.get(m, "") for m in models},
         "sweep": sweep, "notes": list(notes), "plots": [],
         "scenes": [dict(s.to_dict(), R_C=rep.true_break_even(s), R_est=rep.estimated_break_even(s),
                         error=rep.relative_error(rep.estimated_break_even(s), rep.true_break_even(s)),
                         components=rep.error_components(s)) for s in results]}
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
