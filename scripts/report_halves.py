"""The decision's goals on the two halves of the evaluation set, side by side.

    .venv/bin/python scripts/report_halves.py                 # measure both halves, then the table
    .venv/bin/python scripts/report_halves.py --tables-only   # the table from the last run's reports

Measures the final half with a calibration made in the same passes as its truths
(``scripts/report.py``, about 14 minutes on 2 cores), then the tuning half with that calibration
reused (about 4 minutes), each into its own folder under --out, and prints one table: every goal
of the decision with its target and the figure of each half.  ../shared/eval/SOURCES.md says how
the halves may be used: the final half judges a model frozen on the tuning half.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _package  # noqa: E402

_package.core_package()
from hybrid_raycast.core.decide import evaluate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EVAL = ROOT.parent / "shared" / "eval"
HALVES = ("tuning", "final")


def _measure(out: Path, eval_dir: Path) -> None:
    """report.py on the final half with a fresh calibration, then on the tuning half with it."""
    cal = out / "calibration.json"
    common = ["--sweep-scenes", "", "--calibrations", "1", "--no-plots", "--no-points"]
    for half, reuse in (("final", []), ("tuning", ["--reuse-calibration"])):
        cmd = [sys.executable, str(ROOT / "scripts" / "report.py"), *reuse, "--calibration", str(cal),
               "--scenes", str(eval_dir / half), "--out", str(out / half), *common]
        print("$", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)


def _hybrid(scenes, kinds) -> tuple[float, float, str, float]:
    """(median, worst, its scene and ray count) of hybrid (i) / oracle over every (scene, R),
    and the share of those cases planned without a grid."""
    ratios, worst, settled = [], (0.0, "", 0.0), []
    for s in scenes:
        t = evaluate.strategy_totals(s, evaluate.RAY_COUNTS, kinds)
        r = t["hybrid"] / t["oracle"]
        ratios += list(r)
        settled += list(t["settled"])
        i = int(np.argmax(r))
        if r[i] > worst[0]:
            worst = (float(r[i]), s.name, float(evaluate.RAY_COUNTS[i]))
    return float(np.median(ratios)), worst, float(np.mean(settled))


def rows(report: dict) -> dict:
    """{goal: figure} of one half's report.json."""
    fields = {f.name for f in dataclasses.fields(evaluate.SceneResult)}
    scenes = [evaluate.SceneResult.from_dict({k: v for k, v in d.items() if k in fields}) for d in report["scenes"]]
    s = report["summary"]
    out = {}
    out["break-even error vs the numpy BVH, median absolute"] = f"{s['errors']['median_abs']:.1f}%"
    out["R_C's own spread between its passes, median (max)"] = (f"{s['rc_repeatability']['median']:.0f}% "
                                                                 f"({s['rc_repeatability']['max']:.0f}%)")
    out["break-even error vs Embree, median absolute"] = f"{s['embree']['errors']['median_abs']:.1f}%"
    p = s["picks"]
    out["correct picks (totals differ > 10%)"] = f"{p['percent']:.1f}% ({p['correct']}/{p['considered']})"
    pr = s["plan_repeatability"]
    out["five plans, max / min: vs BVH; vs Embree"] = "; ".join(
        f"{pr[k]['median']:.3f} (max {pr[k]['max']:.2f})" for k in ("bvh", "embree") if k in pr)
    c = s["interval_coverage"]
    out["break-even interval vs the BVH holds R_C"] = f"{c['held']} / {c['scenes']} (its top 'never' on {c['never_above']})"
    for label, kinds in (("grid vs numpy BVH", ("bvh",)), ("with Embree", ("bvh", "embree"))):
        med, (w, name, r), settled = _hybrid(scenes, kinds)
        out[f"hybrid / oracle, {label}: median; worst"] = f"{med:.3f}; {w:.3f} ({name}, {r:,.0f} rays)"
        out[f"cases planned without a grid, {label}"] = f"{100 * settled:.0f}%"
    return out


TARGETS = {
    "break-even error vs the numpy BVH, median absolute": "<= 25%",
    "R_C's own spread between its passes, median (max)": "shown",
    "break-even error vs Embree, median absolute": "<= 15%",
    "correct picks (totals differ > 10%)": ">= 95%",
    "five plans, max / min: vs BVH; vs Embree": "<= 1.2",
    "break-even interval vs the BVH holds R_C": ">= 90%",
    "hybrid / oracle, grid vs numpy BVH: median; worst": "1.05; 1.25",
    "hybrid / oracle, with Embree: median; worst": "1.05; 1.25",
}


def table(reports: dict) -> str:
    figures = {half: rows(r) for half, r in reports.items()}
    lines = ["| goal | target | " + " | ".join(f"{h} half" for h in figures) + " |",
             "|---|---|" + "--:|" * len(figures)]
    for goal in next(iter(figures.values())):
        lines.append(f"| {goal} | {TARGETS.get(goal, '-')} | " + " | ".join(f[goal] for f in figures.values()) + " |")
    dates = ", ".join(f"{h} {r['meta']['date']}" for h, r in reports.items())
    return "\n".join(lines + ["", f"Reports: {dates}."])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "halves", help="the reports' folder (default out/halves)")
    ap.add_argument("--eval", type=Path, default=EVAL, help="the evaluation set with tuning/ and final/ (default ../shared/eval)")
    ap.add_argument("--tables-only", action="store_true", help="print the table from the reports already in --out")
    args = ap.parse_args(argv)
    if not args.tables_only:
        if not all((args.eval / h).is_dir() for h in HALVES):
            print(f"no evaluation set at {args.eval} (tuning/ and final/): nothing to measure", file=sys.stderr)
            return 2
        _measure(args.out, args.eval)
    paths = {h: args.out / h / "report.json" for h in HALVES}
    missing = [str(p) for p in paths.values() if not p.is_file()]
    if missing:
        print(f"no report at {', '.join(missing)}: run without --tables-only first", file=sys.stderr)
        return 2
    print(table({h: json.loads(p.read_text()) for h, p in paths.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
