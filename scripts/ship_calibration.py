"""Re-measure the calibration shipped with the package (core/default_calibration.json).

    .venv/bin/python scripts/ship_calibration.py [--model affine|paper] [--scale default]

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
from hybrid_raycast.core import decide as C  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=C.DEFAULT_MODEL, choices=sorted(C.MODELS))
    ap.add_argument("--scale", default="default", choices=sorted(C.RAYS_PER_SCENE))
    ap.add_argument("--output", type=Path, default=C.DEFAULT_PATH)
    args = ap.parse_args(argv)

    def progress(f, msg):
        print(f"[{f * 100:5.1f}%] {msg}", flush=True)

    cal = C.calibrate(scale=args.scale, model=args.model, progress=progress)
    cal.source = "shipped defaults"
    cal.save(args.output)
    print(cal.describe())
    for k in C.SAMPLE_LADDER:
        med, lo, hi = cal.grid_sample_ratio(k)
        print(f"  grid sample ratio K={k:>6,}: {med:.3f} [{lo:.3f}, {hi:.3f}]")
    print(f"wrote {args.output} in {cal.duration_s:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
