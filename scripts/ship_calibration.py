"""Re-measure the calibration shipped with the package (core/default_calibration.json).

    .venv/bin/python scripts/ship_calibration.py [--model terms|power] [--scale default]
    .venv/bin/python scripts/ship_calibration.py --refit    # no timing: the file's own records
    .venv/bin/python scripts/ship_calibration.py --points   # only the point queries' constants

Run on a quiet machine: the file is what every user without their own calibration gets
(labelled 'shipped defaults').  Prints the constants and the grid's sample ratios.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _package  # noqa: E402

_package.core_package()
from hybrid_raycast.core import decide  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=decide.DEFAULT_MODEL, choices=sorted(decide.MODELS))
    ap.add_argument("--scale", default="default", choices=sorted(decide.RAYS_PER_SCENE))
    ap.add_argument("--output", type=Path, default=decide.DEFAULT_PATH)
    ap.add_argument("--refit", action="store_true",
                    help="fit the shipped file's own records again with the current models and count models "
                         "(Calibration.refitted), measuring nothing: for a change of model, not of machine")
    ap.add_argument("--points", action="store_true",
                    help="measure only the point queries' decision (core.decide.points.calibrate_points) on the "
                         "scale's scenes and put it into the shipped file, keeping the rays' constants")
    args = ap.parse_args(argv)
    if args.points:
        from hybrid_raycast.core import scenes
        from hybrid_raycast.core.decide import points

        cal = decide.load(decide.DEFAULT_PATH, check_version=False)
        model = points.calibrate_points(scenes.calibration_set(args.scale),
                                        progress=lambda f, msg: print(f"[{f * 100:5.1f}%] {msg}", flush=True))
        cal.points = model.to_dict()
        note = "point queries' constants measured separately on the same scenes (scripts/ship_calibration.py --points)"
        cal.notes = [n for n in cal.notes if n != note] + [note]
        cal.save(args.output)
        print(f"wrote {args.output}: {len(model.records)} point cases; grid terms {model.grid_terms}, "
              f"BVH terms {model.bvh_terms}")
        return 0
    if args.refit:
        old = decide.load(decide.DEFAULT_PATH, check_version=False)
        cal = old.refitted(args.model)
        changed = sorted(k for k in set(old.counts) | set(cal.counts)
                         if (old.counts.get(k) and old.counts[k].formula()) != (cal.counts.get(k) and cal.counts[k].formula()))
        cal.notes = list(cal.notes) + [f"refitted without new timing ({', '.join(changed) or 'no'} count model changed)"]
        cal.save(args.output)
        for k in changed:
            print(f"  {k}: {old.counts[k].formula() if k in old.counts else '-'}  ->  "
                  f"{cal.counts[k].formula() if k in cal.counts else '-'}")
        print(cal.describe())
        print(f"wrote {args.output} (refitted, measured {cal.created})")
        return 0

    def progress(f, msg):
        print(f"[{f * 100:5.1f}%] {msg}", flush=True)

    cal = decide.calibrate(scale=args.scale, model=args.model, progress=progress)
    cal.source = "shipped defaults"
    cal.save(args.output)
    print(cal.describe())
    for k in decide.SAMPLE_LADDER:
        med, lo, hi = cal.grid_sample_ratio(k)
        print(f"  grid sample ratio K={k:>6,}: {med:.3f} [{lo:.3f}, {hi:.3f}]")
    print(f"wrote {args.output} in {cal.duration_s:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
