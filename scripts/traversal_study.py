"""Grid and structure per-ray count models on the grid traversal's own counts (issue 14).

Counts, on K = 8,192 uniform sample rays, what the grid's traversal really does
(``UniformGrid.traversal_work``: steps, candidate pairs, kernel tests) on every calibration
scene (seeded as ``calibrate``'s work sample) and every evaluated mesh of a report, then
fits count models on a calibration file's per-ray times and judges them: leave-one-out on
the calibration scenes, and on the report's held-out truths (per-ray error, and break-even
error with the report's own build estimates).  No timing: run it beside anything.

    .venv/bin/python scripts/traversal_study.py --calibration core/default_calibration.json \
        --report docs/report/report.json --scale grid=0.963 bvh=0.976 embree=0.925

--scale multiplies a kind's calibration per-ray times (to put a shipped file on the level of
the report's joint calibration: the ratio of their 'at ref' constants).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

import numpy as np  # noqa: E402

from hybrid_raycast.core import scenes as scene_lib  # noqa: E402
from hybrid_raycast.core.decide import calfile  # noqa: E402
from hybrid_raycast.core.decide.cost import CountFit, break_even  # noqa: E402
from hybrid_raycast.core.decide.measurements import WORK_SAMPLES, sample_work  # noqa: E402
import report as report_script  # noqa: E402

GRID = [("cells",), ("cells", "refs"), ("steps",), ("steps", "candidates"), ("steps", "candidates", "tests"),
        ("steps", "refs")]
HDS = [("log2n",), ("log2n", "steps"), ("log2n", "candidates"), ("log2n", "tests")]


def counts(cal, shared: Path, names, k: int) -> dict:
    """name: the Work dict (with traversal counts) of every calibration scene and evaluated mesh."""
    out = {}
    for i, (name, make) in enumerate(scene_lib.calibration_set("default")):
        out[name] = sample_work(make(), WORK_SAMPLES, seed=7919 * (i + 1) + 1).to_dict()
    for name, _, make in report_script.real_scenes(shared, 1 << 22):
        if name in names:
            out[name] = sample_work(make(), k, seed=0).to_dict()
    return out


def med(v) -> float:
    return float(np.median(v)) if len(v) else math.nan


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--calibration", default="core/default_calibration.json")
    ap.add_argument("--report", default="docs/report/report.json")
    ap.add_argument("--shared", default="../shared/scenes")
    ap.add_argument("--samples", type=int, default=8192)
    ap.add_argument("--scale", nargs="*", default=[], help="kind=factor on the calibration's per-ray times")
    a = ap.parse_args(argv)
    cal = calfile.load(a.calibration, check_version=False)
    rep = json.loads(Path(a.report).read_text())
    scale = {k: float(v) for k, v in (s.split("=") for s in a.scale)}
    W = counts(cal, Path(a.shared), {s["name"] for s in rep["scenes"]}, a.samples)
    held = [s for s in rep["scenes"] if s["name"] in W]

    def rows(kind):
        return [(r.triangles, W[r.name], scale.get(kind, 1.0) * r.kinds[kind].per_ray) for r in cal.scenes if r.name in W]

    def judge(kind, names, truth):
        rr = rows(kind)
        f = CountFit.fit(rr, ("1",) + names)
        loo = [100 * (CountFit.fit(rr[:i] + rr[i + 1:], ("1",) + names).predict(n, w) / t - 1) for i, (n, w, t) in enumerate(rr)]
        per = [100 * (f.predict(s["triangles"], W[s["name"]]) / truth(s) - 1) for s in held]
        return f, med(np.abs(loo)), med(np.abs(per)), med(per)

    print(f"{len(cal.scenes)} calibration scenes ({a.calibration}), {len(held)} held-out meshes ({a.report}); "
          "median |error| % (median signed)\n")
    print("| grid per ray from | LOO | held-out per ray |\n|---|--:|--:|")
    grids = {}
    for g in GRID:
        f, loo, per, sig = judge("grid", g, lambda s: s["grid"]["per_ray"])
        grids[g] = f
        print(f"| {' + '.join(g)} | {loo:.1f} | {per:.1f} ({sig:+.1f}) |")
    for kind in ("bvh", "embree"):
        if not all(kind in r.kinds for r in cal.scenes):
            continue
        print(f"\n| {kind} per ray from | LOO | held-out per ray | " + " | ".join(f"break-even, grid on {' + '.join(g)}" for g in GRID)
              + " |\n|---|--:|--:|" + "--:|" * len(GRID))
        for h in HDS:
            fh, loo, per, sig = judge(kind, h, lambda s: s["measured"][kind]["per_ray"])
            cells = []
            for g in GRID:
                be = []
                for s in held:
                    m, e, w = s["measured"][kind], s["estimated"][kind], W[s["name"]]
                    rc = break_even(m["build"], s["grid"]["per_ray"], m["per_ray"])
                    re_ = break_even(e["build"], grids[g].predict(s["triangles"], w), fh.predict(s["triangles"], w))
                    if math.isfinite(rc) and math.isfinite(re_):
                        be.append(100 * (re_ / rc - 1))
                cells.append(f"{med(np.abs(be)):.1f} ({med(be):+.1f})")
            print(f"| {' + '.join(h)} | {loo:.1f} | {per:.1f} ({sig:+.1f}) | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
