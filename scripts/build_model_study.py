"""Build-model candidates and the constants' repeatability, offline (issue 14): no timing.

Refits saved calibrations with each candidate build model and judges it by leave-one-out over
the calibration scenes and on a report's held-out truths (each structure's build and time per
ray, and the grid's work counts from the plan's sample), with the calibration's count models
for the times per ray.  With two calibration files it also prints how far apart each fitted
constant is (``cost.fit_constants``, ``CountFit.constants``), as ``report.py`` does.  The
log-quadratic build (ln T_B = a + b u + c u^2, u = ln(N / N_REF)) also prints its three
constants centred at N_REF (the build there, its exponent b, the curvature c) and its builds at
``LOG_QUADRATIC_SIZES``, and with two files how far apart each of them is.

    .venv/bin/python scripts/build_model_study.py --report docs/report/report.json cal1.json cal2.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import core_package  # noqa: E402

core_package()

from hybrid_raycast.core.decide import calfile, cost  # noqa: E402
from hybrid_raycast.core.decide.evaluate import constants_apart, relative_difference as rel  # noqa: E402

#: (label, model, build terms of the 'sum' form, or the form 'log-quadratic', or None):
#: the candidates of BENCHMARKS.md (issue 14); n = N / N_REF, l = log2 N, u = ln(N / N_REF)
CANDIDATES = [
    ("power c (N l)^p", "power", None),
    ("affine a + c N l", "affine", None),
    ("a + b n", "terms", ("1", "n")),
    ("a + d (l-10) + b n", "terms", ("1", "log2n-10", "n")),
    ("a + d (l-10) + c n (l-16)", "terms", ("1", "log2n-10", "n(log2n-16)")),
    ("b n + c n (l-16)", "terms", ("n", "n(log2n-16)")),
    ("a + d (l-10) + b n + c n (l-16)", "terms", ("1", "log2n-10", "n", "n(log2n-16)")),
    ("ln T = a + b u + c u^2", "terms", "log-quadratic"),
]


@contextmanager
def build_terms(kind: str, names):
    """``cost.BUILD_TERMS[kind] = names`` in the 'sum' form, or ``cost.BUILD_FORMS[kind] =
    names`` for a form's name, for the duration (None: leave both alone)."""
    old_terms, old_forms = dict(cost.BUILD_TERMS), dict(cost.BUILD_FORMS)
    if isinstance(names, str):
        cost.BUILD_FORMS[kind] = names
    elif names is not None:
        cost.BUILD_TERMS[kind] = tuple(names)
        cost.BUILD_FORMS[kind] = "sum"
    try:
        yield
    finally:
        cost.BUILD_TERMS.clear()
        cost.BUILD_TERMS.update(old_terms)
        cost.BUILD_FORMS.clear()
        cost.BUILD_FORMS.update(old_forms)


#: three sizes the log-quadratic build is also stated at (three times are its three
#: constants): the small, middle and large end of the calibration scenes
LOG_QUADRATIC_SIZES = (1_024, 32_768, 1_048_576)


def med_abs(v) -> float:
    v = [x for x in v if math.isfinite(x)]
    return 100.0 * float(np.median(np.abs(v))) if v else math.nan


def judge(cal, truths, kind: str, model: str, names) -> dict:
    """Median |error| of the build and of the break-even, leave-one-out over the calibration
    scenes (count models refitted without the scene) and on the held-out truths."""
    est = cost.MODELS[model][1]
    scenes = [r for r in cal.scenes if kind in r.kinds and "grid" in r.kinds]
    with build_terms(kind, names):
        loo_b, loo_be = [], []
        for i, r in enumerate(scenes):
            rest = scenes[:i] + scenes[i + 1:]
            b = est(cost.fit(rest, (kind,), model=model)[kind], kind, r.triangles).build
            loo_b.append(b / r.kinds[kind].build_time - 1)
            counts = cost.fit_counts(rest, ("grid", kind), cal.spread)
            if r.work and {"grid", kind} <= set(counts):
                rc = cost.break_even(r.kinds[kind].build_time, r.kinds["grid"].per_ray, r.kinds[kind].per_ray)
                re = cost.break_even(b, counts["grid"].predict(r.triangles, r.work), counts[kind].predict(r.triangles, r.work))
                if math.isfinite(rc) and math.isfinite(re) and rc > 0:
                    loo_be.append(re / rc - 1)
        f = cost.fit(scenes, (kind,), model=model)[kind]
    counts = cost.fit_counts(cal.scenes, ("grid", kind), cal.spread)
    held_b, held_be = [], []
    for s in truths:
        n, m = s["triangles"], s["measured"][kind]
        b = est(f, kind, n).build
        held_b.append(b / m["build"] - 1)
        w = s["extra"]["work"]
        rc = cost.break_even(m["build"], s["grid"]["per_ray"], m["per_ray"])
        re = cost.break_even(b, counts["grid"].predict(n, w), counts[kind].predict(n, w))
        if math.isfinite(rc) and math.isfinite(re):
            held_be.append(re / rc - 1)
    return {"loo_build": med_abs(loo_b), "loo_be": med_abs(loo_be), "held_build": med_abs(held_b),
            "held_build_signed": 100.0 * float(np.median(held_b)), "held_be": med_abs(held_be), "fit": f}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibrations", nargs="+", help="calibration JSON files (records are refitted)")
    ap.add_argument("--report", default="docs/report/report.json", help="report.json with the held-out truths")
    ap.add_argument("--kinds", nargs="+", default=["bvh", "embree"])
    args = ap.parse_args(argv)
    try:
        truths = json.loads(Path(args.report).read_text(encoding="utf-8"))["scenes"]
        cals = [calfile.load(p, check_version=False) for p in args.calibrations]
    except (OSError, KeyError, json.JSONDecodeError, calfile.CalibrationError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    truths = [s for s in truths if (s.get("extra") or {}).get("work")]
    names = " / ".join(Path(p).name for p in args.calibrations)
    print(f"{len(truths)} held-out scenes from {args.report}; median |error| in %, per calibration ({names})")
    for kind in args.kinds:
        print(f"\n{kind} build | LOO build | LOO break-even | held-out build (median signed) | held-out break-even"
              + (" | 2 cal.: build constants max apart" if len(cals) == 2 else ""))
        for label, model, terms in CANDIDATES:
            rows = [judge(c, truths, kind, model, terms) for c in cals]
            line = " | ".join(" / ".join(f"{r[key]:.1f}" for r in rows) for key in ("loo_build", "loo_be"))
            line += " | " + " / ".join(f"{r['held_build']:.1f} ({r['held_build_signed']:+.1f})" for r in rows)
            line += " | " + " / ".join(f"{r['held_be']:.1f}" for r in rows)
            if len(rows) == 2:
                ca, cb = (cost.fit_constants(r["fit"], model) for r in rows)
                apart = [rel(v, cb[n]) for n, v in ca.items()
                         if n in cb and (n.startswith("build") or n in ("c_B", "a_B", "p_B"))]
                line += f" | {max(apart):.1f}" if apart else " | -"
            print(f"{label:34s} | {line}")
            if terms == "log-quadratic":
                for r in rows:
                    k = cost.fit_coefficients(r["fit"], model)
                    if "build curvature" in k:
                        print(f"{'':34s}   centred at N_REF = {cost.N_REF:,}: build {k['build at N_REF'] * 1e3:.2f} ms, "
                              f"exponent b {k['build exponent at N_REF']:.4f}, curvature c {k['build curvature']:.5f}; "
                              + ", ".join(f"{n:,}: {cost.MODELS[model][1](r['fit'], kind, n).build * 1e3:.3g} ms"
                                          for n in LOG_QUADRATIC_SIZES))
                if len(rows) == 2 and all("build curvature" in cost.fit_coefficients(r["fit"], model) for r in rows):
                    ka, kb = (cost.fit_coefficients(r["fit"], model) for r in rows)
                    ta, tb = ([cost.MODELS[model][1](r["fit"], kind, n).build for n in LOG_QUADRATIC_SIZES] for r in rows)
                    print(f"{'':34s}   2 cal. apart: " + ", ".join(f"{n} {rel(v, kb[n]):.1f}" for n, v in ka.items())
                          + "; builds at " + ", ".join(f"{n:,} {rel(x, y):.1f}" for n, x, y in zip(LOG_QUADRATIC_SIZES, ta, tb)))
    if len(cals) == 2:
        a, b = (c.refitted() for c in cals)
        apart = constants_apart(a, b)
        print(f"\nconstants of the default model ('{cost.DEFAULT_MODEL}'), |a - b| / mean in %:")
        for n, v in apart.items():
            print(f"  {n:36s} {v:6.1f}")
        print(f"  median {np.median(list(apart.values())):.1f}, max {max(apart.values()):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
