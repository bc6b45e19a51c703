"""The point queries' decision (closest point: grid or BVH) against measured truths on held-out meshes.

    flock /tmp/hrc-bench.lock .venv/bin/python scripts/point_decision.py --scenes ../shared/eval/tuning
        [--scale default | --model FILE | --model-from-calibration [FILE]] [--save-model FILE] [--save-records FILE]
    make bench-point-decision    # the shipped constants on both halves

Fits the point decision's constants on the calibration scenes of ``--scale`` (synthetic,
``core.decide.points.calibrate_points``), or reads them from ``--model``, then measures each
held-out mesh (.obj files in ``--scenes``) with its three kinds of points (uniform in the box
grown by a fifth, near the surface, on it) and prints, per case, the measured and the
estimated break-even (points from which the BVH, built with its point index, beats the grid)
and the picks at 100 to 1M points; then the median error and the share of correct picks
where the measured totals differ by more than 10%.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

from hybrid_raycast.core import scenes as S  # noqa: E402
from hybrid_raycast.core.decide import points as P  # noqa: E402
from hybrid_raycast.core.objio import load_obj  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=Path, action="append", default=[])
    ap.add_argument("--scale", default="default")
    ap.add_argument("--model", type=Path, help="read the constants from this file instead of calibrating")
    ap.add_argument("--model-from-calibration", nargs="?", const="shipped", metavar="FILE",
                    help="take the constants of a calibration file (default: the shipped one) instead of calibrating")
    ap.add_argument("--save-model", type=Path)
    ap.add_argument("--save-records", type=Path, help="write the held-out meshes' measured records (JSON) here")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.model_from_calibration:
        from hybrid_raycast.core import decide

        path = decide.DEFAULT_PATH if args.model_from_calibration == "shipped" else Path(args.model_from_calibration)
        model = decide.load(path, check_version=False).point_model()
        if model is None:
            raise SystemExit(f"{path} holds no point-query constants")
        print(f"constants from {path}")
    elif args.model:
        model = P.PointModel.from_dict(json.loads(args.model.read_text()))
        print(f"constants from {args.model}")
    else:
        model = P.calibrate_points(S.calibration_set(args.scale),
                                   progress=lambda f, m: print(f"[{f * 100:5.1f}%] {m}", flush=True))
        print(f"calibrated on {len(model.records)} cases in {time.perf_counter() - t0:.0f} s")
    if args.save_model:
        args.save_model.parent.mkdir(parents=True, exist_ok=True)
        args.save_model.write_text(json.dumps(model.to_dict()))
    print(f"builds {model.builds}\ngrid terms (s per ring, cell, triangle) {model.grid_terms}\n"
          f"bvh terms {model.bvh_terms}\nspread {model.spread}")
    records, halves = [], []
    for d in args.scenes:
        mine = [r for f in sorted(d.glob("*.obj")) for r in P.measure_points(f.stem, load_obj(f))]
        records += mine
        halves.append((d, mine))
    if args.save_records:
        args.save_records.parent.mkdir(parents=True, exist_ok=True)
        args.save_records.write_text(json.dumps([r.__dict__ for r in records]))
    if not records:
        return 0
    ev = P.evaluate(model, records)
    print("")
    print("\n".join(P.table(ev)[:-1]))
    for d, mine in halves if len(halves) > 1 else ():
        print(f"{d}: {P.summary_line(P.evaluate(model, mine))}")
    print(f"all: {P.summary_line(ev)}; {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
