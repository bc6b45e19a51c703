"""The evaluation report: ``core.decide.evaluate``'s tables on synthetic timings (exact
errors, speedups, the >10% rule, the oracle, the online switch), the model candidates on
synthetic calibration data, a measured scene on a hand-made calibration; scripts/report.py's
own helpers (its Markdown, its calibration files); and end-to-end runs of scripts/report.py on
tiny procedural scenes (no ../shared needed): one on a hand-made calibration file, fast, and
``--quick``, which calibrates (slow)."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hybrid_raycast.core.decide import evaluate
from hybrid_raycast.core.decide import Calibration, Cost, KindFit, Measurement, SceneRecord, log2n, nlog2n

ROOT = Path(__file__).resolve().parents[1]


def scene(grid=(1.0, 1e-6), bvh=(2.0, 0.5e-6), est=None, sample=None, overhead=0.1, name="s", raw=None):
    """Grid build 1 s, 1 us/ray; BVH build 2 s, 0.5 us/ray: R_C = 2 / 0.5e-6 = 4e6 exactly.

    sample: the grid's estimated time per ray (default exact); raw: the uncorrected K-sample time."""
    est = est or bvh
    return evaluate.SceneResult(name, 1024, 2_000_000, Cost.point("grid", *grid), {"bvh": Cost.point("bvh", *bvh)},
                                {"bvh": Cost.point("bvh", *est)},
                           grid[1] if sample is None else sample, overhead, grid_sample_per_ray=raw)


def report_script():
    """scripts/report.py as a module (its own helpers: the Markdown, the calibration files),
    without running it."""
    spec = importlib.util.spec_from_file_location("report_script", ROOT / "scripts" / "report.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# -- break-even errors ---------------------------------------------------------------------------

def test_relative_error_is_the_papers_percentage_and_infinities_are_handled():
    assert evaluate.relative_error(150.0, 100.0) == 50.0
    assert evaluate.relative_error(50.0, 100.0) == -50.0
    for est, true in ((math.inf, math.inf), (1e5, math.inf), (math.inf, 1e5)):
        assert math.isnan(evaluate.relative_error(est, true)), f"R_est {est}, R_C {true}: the measure is undefined"
    assert evaluate.never_agreement([(math.inf, math.inf), (1e5, math.inf), (math.inf, 1e5), (1.0, 2.0)]) == {
        "both_never": 1, "only_estimate_never": 1, "only_measured_never": 1}


def test_true_and_estimated_break_even_use_the_sunk_grid_formula():
    s = scene(est=(1.0, 0.5e-6), sample=1.5e-6)
    assert evaluate.true_break_even(s) == pytest.approx(4e6, rel=1e-12)
    assert evaluate.estimated_break_even(s) == pytest.approx(1.0 / 1e-6, rel=1e-12)
    assert evaluate.relative_error(evaluate.estimated_break_even(s), evaluate.true_break_even(s)) == pytest.approx(-75.0)
    assert evaluate.true_break_even(scene(bvh=(2.0, 1e-6))) == math.inf, "equal per-ray times: the BVH never pays"


def test_error_summary_gives_the_papers_sums_and_counts_undefined_apart():
    e = evaluate.error_summary([10.0, -20.0, 30.0, math.nan])
    assert e["scenes"] == 4 and e["defined"] == 3 and e["undefined"] == 1
    assert e["sum"] == 20.0 and e["sum_abs"] == 60.0
    assert e["median_abs"] == 20.0 and e["median"] == 10.0 and e["max_abs"] == 30.0
    assert e["within_25"] == 2 and e["within_10"] == 1
    assert math.isnan(evaluate.error_summary([math.nan])["median_abs"])


# -- strategies ---------------------------------------------------------------------------------

def test_strategy_totals_on_known_numbers():
    s = scene()  # estimate exact: R_est = R_C = 4e6
    r = np.array([1e6, 1e7])
    t = evaluate.strategy_totals(s, r, batch=1)
    np.testing.assert_allclose(t["grid"], [2.0, 11.0])
    np.testing.assert_allclose(t["bvh"], [2.5, 7.0])
    # hybrid: grid build + overhead, then the grid (R <= 4e6) or the BVH
    np.testing.assert_allclose(t["hybrid"], [1.0 + 0.1 + 1.0, 1.0 + 0.1 + 2.0 + 5.0])
    np.testing.assert_allclose(t["oracle"], [2.0, 7.0])
    assert list(t["choice"]) == ["grid", "bvh"]


def test_hybrid_with_samples_from_the_workload_skips_the_estimate_below_k_rays(monkeypatch):
    monkeypatch.setattr(evaluate, "sample_count", lambda k, r: k)  # K fixed: the arithmetic (the cut by R apart)
    s = scene()
    s.samples = 2_000_000
    t = evaluate.strategy_totals(s, [1e6, 1e7], batch=1)["hybrid_reuse"]
    # R <= K: the grid alone; R > K: grid build + estimate, then the BVH for the R - K rays left
    np.testing.assert_allclose(t, [2.0, 1.0 + 0.1 + 2.0 + 8e6 * 0.5e-6])


def test_reuse_totals_are_the_arithmetic_of_the_kept_samples(monkeypatch):
    monkeypatch.setattr(evaluate, "sample_count", lambda k, r: k)  # K fixed: the arithmetic (the cut by R apart)
    s = scene(overhead=0.1)  # R_est = R_C = 4e6
    s.samples, s.reuse_estimate_time = 100_000, 0.15
    t = evaluate.strategy_totals(s, [5e4, 1e6, 1e7], batch=1)
    # (i) separate samples: grid build + e + the choice on all R rays
    np.testing.assert_allclose(t["hybrid"], [1.0 + 0.1 + 0.05, 1.0 + 0.1 + 1.0, 1.0 + 0.1 + 2.0 + 5.0])
    # (ii) R <= K: the grid answered everything while planning; else grid build + e' + the choice on R - K
    np.testing.assert_allclose(t["hybrid_reuse"], [1.0 + 0.05, 1.0 + 0.15 + 0.9e6 * 1e-6,
                                                   1.0 + 0.15 + 2.0 + (1e7 - 1e5) * 0.5e-6])
    # net cost of (ii) at 1e6 rays: e' less what the grid would have spent on the K rays, over T_B^G + R t_G
    assert evaluate.estimate_cost_percent(s, 1e6, reuse=True) == pytest.approx(100 * (0.15 - 1e5 * 1e-6) / 2.0)
    assert evaluate.estimate_cost_percent(s, 1e6) == pytest.approx(100 * 0.1 / 2.0)


def test_reuse_keeps_the_grid_when_it_answered_everything_while_planning(monkeypatch):
    monkeypatch.setattr(evaluate, "sample_count", lambda k, r: k)  # K fixed: the arithmetic (the cut by R apart)
    s = scene(est=(0.01, 0.5e-6))  # R_est = 0.01 / 0.5e-6 = 2e4
    s.samples = 100_000
    t = evaluate.strategy_totals(s, [1e4, 5e4], batch=1)
    # with separate samples the plan picks the BVH past R_est; with workload samples every
    # ray up to K was answered while planning, so nothing is built
    assert list(t["choice"]) == ["grid", "bvh"] and list(t["choice_reuse"]) == ["grid", "grid"]
    np.testing.assert_allclose(t["hybrid_reuse"], [1.0 + 0.01, 1.0 + 0.05])


def test_the_hybrid_prices_the_fewer_samples_a_plan_takes_for_fewer_rays():
    """For R below K / SAMPLE_SHARE the plan samples SAMPLE_SHARE R rays: the evaluation takes
    that plan's estimate cost and estimates (``at_samples``), not the full sample's."""
    from hybrid_raycast.core.decide.work import SAMPLE_SHARE, sample_count

    s = scene(overhead=0.1)
    s.samples, s.reuse_estimate_time = 16384, 0.12
    k = sample_count(16384, 1e5)
    assert k == int(SAMPLE_SHARE * 1e5) < 16384
    s.at_samples = {k: {"grid_per_ray": s.grid_estimate_per_ray, "estimated": dict(s.estimated),
                        "estimate_time": 0.01, "reuse_estimate_time": 0.02}}
    t = evaluate.strategy_totals(s, [1e5, 1e7], batch=1)
    assert t["hybrid"][0] == pytest.approx(1.0 + 0.01 + 1e5 * 1e-6)  # the grid kept, the small sample's cost
    assert t["hybrid_reuse"][0] == pytest.approx(1.0 + 0.02 + (1e5 - k) * 1e-6)
    assert t["hybrid"][1] == pytest.approx(1.0 + 0.1 + 2.0 + 5.0)  # the full sample for 1e7 rays
    # the small sample's own estimates decide for its rays
    s.at_samples[k]["estimated"] = {"bvh": Cost.point("bvh", 1e-3, 0.5e-6), **{kk: c for kk, c in s.estimated.items()
                                                                              if kk != "bvh"}}
    assert evaluate.hybrid_choice(s, [1e5, 1e7]).tolist() == ["bvh", "bvh"]
    assert evaluate.hybrid_choice(s, [1e5])[0] == "bvh" != evaluate.hybrid_choice(scene(overhead=0.1), [1e5])[0]


def test_the_hybrid_decides_without_a_sample_where_one_would_cost_too_much():
    """Above the floor and up to ``unsampled_below`` the plan takes no sample: the hybrid pays
    the grid and its choice, made by ``rule.unsampled`` on the estimates for N (the grid at its
    low end, the BVH at its high end), and no estimate."""
    s = scene(overhead=0.1)
    s.samples, s.unsampled_below, s.floor = 16384, 5e5, 1e3
    s.prior_estimated = {"grid": Cost("grid", 1.0, 0.9, 1.1, 1e-6, 0.9e-6, 1.1e-6),
                         "bvh": Cost("bvh", 0.2, 0.2, 0.2, 0.5e-6, 0.4e-6, 0.6e-6)}
    # unsampled: BVH if 0.2 + R 0.6e-6 < R 0.9e-6, i.e. from R = 0.2 / 0.3e-6 = 666,667: the grid up to 5e5
    t = evaluate.strategy_totals(s, [5e2, 2e5, 1e6], batch=1)
    assert list(t["choice"][:2]) == ["grid", "grid"] and list(t["choice_reuse"][:2]) == ["grid", "grid"]
    assert t["hybrid"][1] == pytest.approx(1.0 + 2e5 * 1e-6) == t["hybrid_reuse"][1]  # no estimate paid
    assert evaluate.unsampled_rays(s, [5e2, 2e5, 1e6]).tolist() == [False, True, False]
    s.prior_estimated["bvh"] = Cost("bvh", 0.01, 0.01, 0.01, 0.5e-6, 0.4e-6, 0.6e-6)  # now 0.01 / 0.3e-6 = 33,333
    t = evaluate.strategy_totals(s, [2e5], batch=1)
    assert t["choice"][0] == "bvh" and t["hybrid"][0] == pytest.approx(1.0 + 2.0 + 2e5 * 0.5e-6)


def test_embree_retraces_the_sample_rays():
    s = scene()
    s.measured["embree"] = s.estimated["embree"] = Cost.point("embree", 0.5, 0.1e-6)
    s.samples, s.reuse_estimate_time = 100_000, 0.15
    t = evaluate.strategy_totals(s, [1e7], kinds=("bvh", "embree"), batch=1)
    assert t["choice"][0] == "embree"
    assert t["hybrid_reuse"][0] == pytest.approx(1.0 + 0.15 + 0.5 + 1e7 * 0.1e-6), "all R rays, not R - K"


def test_online_switches_on_the_batch_boundary_after_the_estimated_build_time():
    s = scene()
    batch = 1 << 15
    sw = evaluate.online_switch(s, "bvh", batch)
    assert sw == math.ceil(2.0 / 1e-6 / batch) * batch == 2_031_616
    t = evaluate.strategy_totals(s, [1e6, 1e7], batch=batch)["online"]
    np.testing.assert_allclose(t, [1.0 + 1.0, 1.0 + sw * 1e-6 + 2.0 + (1e7 - sw) * 0.5e-6])
    # ski rental: never worse than about twice the best fixed choice
    r = np.logspace(3, 9, 61)
    tt = evaluate.strategy_totals(s, r, batch=batch)
    assert (tt["online"] / tt["oracle"]).max() < 2.0 + 1e-9


def test_online_never_switches_when_the_estimate_is_not_faster_per_ray():
    assert evaluate.online_switch(scene(est=(2.0, 1e-6))) == math.inf
    t = evaluate.strategy_totals(scene(est=(2.0, 2e-6)), [1e8])
    assert t["online"][0] == pytest.approx(1.0 + 100.0)


def test_pick_accuracy_counts_only_cases_that_differ_by_more_than_ten_percent():
    s = scene(est=(1.0, 0.5e-6))  # R_est = 2e6, R_C = 4e6: picks the BVH too early
    r = [1e6, 3e6, 3.9e6, 1e7]
    # R t_G vs 2 + 0.5e-6 R: 1 vs 2.5 (grid, picked grid), 3 vs 3.5 (grid, picked BVH: wrong),
    # 3.9 vs 3.95 (within 10%: not counted), 10 vs 7 (BVH, picked BVH)
    p = evaluate.pick_accuracy([s], r)
    assert (p["considered"], p["correct"]) == (3, 2) and p["percent"] == pytest.approx(200 / 3)
    assert p["wrong"] == [("s", 3e6)]
    # counting the grid's build: 2 vs 2.5 (grid), 4 vs 3.5, 4.9 vs 3.95, 11 vs 7 (BVH, BVH, BVH): all right
    q = evaluate.pick_accuracy([s], r, sunk_grid=False)
    assert (q["considered"], q["correct"]) == (4, 4)


def test_speedup_summary_medians_on_known_numbers():
    s = scene()
    r = [1e6, 1e7]
    sp = evaluate.speedup_summary([s], r, batch=1)
    hybrid = np.array([2.1, 8.1])
    assert sp["speedup_vs_grid"]["median"] == pytest.approx(np.median(np.array([2.0, 11.0]) / hybrid))
    assert sp["speedup_vs_bvh"]["median"] == pytest.approx(np.median(np.array([2.5, 7.0]) / hybrid))
    assert sp["hybrid_over_oracle"]["median"] == pytest.approx(np.median(hybrid / np.array([2.0, 7.0])))
    assert sp["hybrid_over_oracle"]["cases"] == 2


def test_estimate_cost_is_a_percentage_of_the_grid_only_total_at_a_million_rays():
    assert evaluate.estimate_cost_percent(scene(overhead=0.1)) == pytest.approx(5.0)  # 0.1 / (1 + 1e6 * 1e-6)


def test_median_per_ray_and_error_components():
    a, b = scene(name="a"), scene(grid=(1.0, 3e-6), name="b")
    assert evaluate.median_per_ray([a, b]) == {"grid": pytest.approx(2e-6), "bvh": pytest.approx(0.5e-6)}
    c = evaluate.error_components(scene(est=(3.0, 0.25e-6), sample=1.5e-6, raw=3e-6))
    assert c == {"build": pytest.approx(50.0), "per_ray": pytest.approx(-50.0), "grid_per_ray": pytest.approx(50.0),
                 "grid_sample": pytest.approx(200.0)}
    assert math.isnan(evaluate.error_components(scene())["grid_sample"]), "no raw sample recorded"


def test_scene_result_round_trips_through_a_dict():
    s = scene(raw=2e-6)
    s.reuse_estimate_time = 0.05
    assert evaluate.SceneResult.from_dict(json.loads(json.dumps(s.to_dict()))) == s


# -- the grid's estimate --------------------------------------------------------------------------

def test_the_uncorrected_estimate_is_the_raw_sample_used_as_it_is():
    s = scene(est=(1.0, 0.5e-6), sample=1.5e-6, raw=3e-6)  # the plan corrected 3 us by a ratio of 0.5
    assert s.grid_sample_ratio == pytest.approx(0.5) and scene().grid_sample_ratio is None
    assert evaluate.estimated_break_even(s) == pytest.approx(1.0 / 1e-6)
    u = evaluate.with_grid_estimate(s, s.grid_sample_per_ray)
    assert u.grid_estimate_per_ray == 3e-6 and evaluate.estimated_break_even(u) == pytest.approx(1.0 / 2.5e-6)
    assert s.grid_estimate_per_ray == 1.5e-6 and s.estimated == u.estimated, "the original is left alone"
    assert evaluate.sample_ratio([1e-6, 2e-6, None], [2e-6, 2e-6, 1e-6])["median"] == pytest.approx(0.75)


def hand_calibration(ratio=0.5):
    """BVH constants that make it far faster per ray than the grid; grid samples whose
    large-workload / sample ratio is ``ratio`` at every K."""
    recs = []
    for i, n in enumerate((500, 2000, 8000)):
        rec = SceneRecord(f"c{i}", n, 1000, {"grid": Measurement(0.001, 1e-3, 1000)})
        rec.grid_samples = {k: 1e-6 / ratio for k in (256, 1024, 4096)}
        recs.append(rec)
    return Calibration({"bvh": KindFit(1e-7, 1e-9, 1e-7, 1e-7, 1e-9, 1e-9, 3)}, scenes=recs, model="power", source="hand")


def test_a_measured_scene_takes_the_plans_corrected_grid_estimate_once():
    from hybrid_raycast.core import scenes as S

    s, rays, _, _ = evaluate.measure_scene("t", "procedural", S.make_scene("sphere", 2000, seed=5), hand_calibration(0.5),
                                           ("bvh",), rays=4000, seed=0, samples=512, repeats=2, plan_repeats=2)
    assert s.samples == 512 and s.grid_sample_ratio == pytest.approx(0.5)
    assert s.grid_estimate_per_ray == pytest.approx(0.5 * s.grid_sample_per_ray, rel=1e-12)
    # the headline's R_est is the plan's own break-even, with the corrected grid time
    assert evaluate.estimated_break_even(s) == pytest.approx(s.extra["plan_break_even"]["bvh"], rel=1e-12)
    e = s.estimated["bvh"]
    assert evaluate.estimated_break_even(s) == pytest.approx(evaluate.break_even(e.build_time, 0.5 * s.grid_sample_per_ray, e.per_ray))
    # the comparison is the raw sample, not corrected twice nor left corrected
    u = evaluate.grid_estimators(s)["uncorrected"]
    assert u.grid_estimate_per_ray == s.grid_sample_per_ray
    assert set(evaluate.grid_estimators(s)) == set(evaluate.GRID_ESTIMATES)
    # the reuse plan drew its K samples from the workload
    assert s.extra["reuse_plan"]["workload_samples"] == 512 and s.reuse_estimate_time > 0 and len(rays[0]) == 4000


def test_decide_model_compares_models_under_the_plans_estimate():
    def entry(plan, uncorrected, loo):
        held = lambda x: {"held_out": {"median_abs": x}}  # noqa: E731
        return {"loo": {"median_abs": loo}, "grid": {"plan": held(plan), "uncorrected": held(uncorrected)}}

    # affine is worse than paper uncorrected but better under the plan's estimate, and better leave-one-out
    models = {"paper": entry(30.0, 20.0, 400.0), "affine": entry(15.0, 70.0, 25.0), "median": entry(40.0, 20.0, 500.0)}
    best, text = evaluate.decide_model(models, "affine", "affine")
    assert best == "affine" and "agrees with the default" in text
    models["affine"] = entry(35.0, 10.0, 25.0)  # no longer beats paper where it counts
    assert evaluate.decide_model(models, "affine", "affine")[0] == "paper"
    models["affine"] = entry(math.nan, 10.0, 25.0)
    assert evaluate.decide_model(models, "affine", "affine")[0] == "paper"


def test_markdown_tolerates_undefined_errors_and_summaries(tmp_path):
    R = report_script()
    never = [scene(bvh=(2.0, 2e-6), raw=2e-6, name=f"n{i}") for i in range(2)]  # the BVH never pays: errors undefined
    for s in never:
        s.samples = 1024
    summ = evaluate.summarise(never, ("bvh",))
    assert summ["errors"]["defined"] == 0 and math.isnan(summ["errors"]["sum"])
    summ["headline"] = R.headline(summ, 1024)
    cal = {"scenes": 3, "rays_per_scene": 1000, "ladder": [1024], "how": "hand", "model": "affine",
           "default_model": "affine", "ratio_at_samples": None}
    meta = {"command": "test", "date": "today", "duration_s": 1.0, "cpus": 2, "processor": "cpu", "load_before": None,
            "load_after": None, "python": "3", "numpy": "1", "quick": True, "calibration": cal, "rays": 1000,
            "samples": 1024, "threads": {}, "sweep_rays": 0, "sweep_repeats": 0}
    data = R.jsonable({"meta": meta, "summary": summ, "scenes": evaluate.scene_rows(never), "plots": [], "notes": []})
    R.write_markdown(tmp_path / "r.md", data)
    md = (tmp_path / "r.md").read_text()
    assert "sum of errors n/a" in md and "| never (never, never) |" not in md and "never [" in md
    assert evaluate.fnum(None, 1, None) == "n/a" and evaluate.fnum(math.inf) == "never" and R.fbe(None) == "never"


# -- model candidates -----------------------------------------------------------------------------

def records(a_b=0.0, a_r=0.0, c_b=2e-7, c_r=2e-7, sizes=(500, 5000, 50000, 500000), t_grid=5e-6):
    out = []
    for n in sizes:
        rec = SceneRecord(f"s{n}", n, 1000)
        rec.kinds["bvh"] = Measurement(a_b + c_b * nlog2n(n), (a_r + c_r * log2n(n)) * 1000, 1000)
        rec.kinds["grid"] = Measurement(0.001, t_grid * 1000, 1000)
        out.append(rec)
    return out


def test_leave_one_out_is_exact_when_the_papers_model_holds():
    for row in evaluate.loo_break_even_errors(records(), "bvh", "paper"):
        assert abs(row["error"]) < 1e-9 and abs(row["build_error"]) < 1e-9, row


def test_affine_candidate_recovers_a_fixed_cost_exactly():
    recs = records(a_b=0.002, a_r=1e-7)
    f = evaluate.fit_model(recs, ("bvh",), "affine")["bvh"]
    assert f.extra["a_B"] == pytest.approx(0.002, rel=1e-6) and f.c_B == pytest.approx(2e-7, rel=1e-6)
    assert f.extra["a_R"] == pytest.approx(1e-7, rel=1e-6) and f.c_R == pytest.approx(2e-7, rel=1e-6)
    assert all(abs(r["error"]) < 1e-6 for r in evaluate.loo_break_even_errors(recs, "bvh", "affine"))
    # the paper's form cannot carry the fixed cost: it errs on the same data
    assert max(abs(r["build_error"]) for r in evaluate.loo_break_even_errors(recs, "bvh", "paper")) > 10


def test_a_compared_model_is_never_a_calibration_model(tmp_path):
    """'affine', 'paper' and 'median' are the evaluation's (``evaluate.COMPARED_MODELS``): a
    calibration file naming one is refused by name, so a plan never estimates with one."""
    from hybrid_raycast.core.decide import CalibrationError, MODELS, load

    assert not set(evaluate.COMPARED_MODELS) & set(MODELS)
    recs = records(a_b=0.002, a_r=1e-7)
    cal = Calibration(evaluate.fit_model(recs, ("bvh",), "affine"), scenes=recs, model="affine")
    with pytest.raises(CalibrationError, match="unknown model 'affine'"):
        load(cal.save(tmp_path / "cal.json"))
    e, n = evaluate.COMPARED_MODELS["affine"][1](cal.fits["bvh"], "bvh", 100000), 100000
    assert e.build_time == pytest.approx(0.002 + 2e-7 * nlog2n(n), rel=1e-6)
    assert e.per_ray == pytest.approx(1e-7 + 2e-7 * log2n(n), rel=1e-6)
    assert e.build_low <= e.build_time <= e.build_high and e.per_ray_low <= e.per_ray <= e.per_ray_high


def test_reestimate_changes_only_the_estimates():
    s = scene()
    s2 = evaluate.reestimate(s, records(), "paper")
    assert s2.measured == s.measured and s2.grid == s.grid and s2.grid_estimate_per_ray == s.grid_estimate_per_ray
    assert s2.estimated["bvh"].build_time == pytest.approx(2e-7 * nlog2n(1024))


# -- the command ----------------------------------------------------------------------------------

def calibration_file(path) -> Path:
    """A hand-made calibration file of the package's default model, as ``--reuse-calibration``
    loads it: five scenes, the grid 5 us per ray on the workload and 10 us on K = 256 sample
    rays (a ratio of 0.5), no count models."""
    from hybrid_raycast.core.decide import DEFAULT_MODEL, fit

    recs = []
    for n in (500, 2000, 8000, 32000, 128000):
        rec = SceneRecord(f"c{n}", n, 1000, {"bvh": Measurement(0.001 + 2e-7 * nlog2n(n), (1e-7 + 2e-7 * log2n(n)) * 1000, 1000),
                                             "grid": Measurement(0.001, 5e-6 * 1000, 1000)})
        rec.grid_samples = {256: 1e-5, 1024: 8e-6}
        recs.append(rec)
    return Calibration(fit(recs, ("bvh",), model=DEFAULT_MODEL), scenes=recs, model=DEFAULT_MODEL, rays_per_scene=1000,
                       scale="hand", source="hand", created="2026-01-01T00:00:00+00:00").save(path)


def test_report_on_a_reused_calibration_writes_every_part(tmp_path):
    """report.py's plumbing in a few seconds: a calibration file reused (none measured, none
    again), one tiny scene measured once on 2,000 rays, a sweep of one (density, K), no plots."""
    out = tmp_path / "report"
    cal = calibration_file(tmp_path / "cal.json")
    args = ["--quick", "--out", str(out), "--calibration", str(cal), "--reuse-calibration", "--calibrations", "1",
            "--no-embree", "--only", "q-sphere-3k", "--rays", "2000", "--repeats", "1", "--plan-repeats", "2",
            "--samples", "256", "--sweep-k", "256", "--sweep-density", "2", "--sweep-rays", "2000", "--no-plots"]
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "report.py"), *args], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, f"report.py failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    assert "calibrating" not in proc.stdout, "the calibration file was not reused"
    data = json.loads((out / "report.json").read_text())
    assert set(data) == {"meta", "summary", "models", "model_decision", "best_model", "grid_sample_ratio", "model_docs",
                         "sweep", "notes", "plots", "scenes", "points"}
    # the decision for point queries on the same scene, with the shipped point constants (the hand-made
    # calibration has none): three kinds of points, each judged
    pts = data["points"]
    assert pts["scenes"] == 1 and [c["points_kind"] for c in pts["cases"]] == ["box", "near", "surface"]
    assert pts["picked"] > 0 and "## Point queries" in (out / "report.md").read_text()
    meta = data["meta"]
    assert meta["calibration"]["how"].startswith("reused from cal.json") and meta["kinds"] == ["bvh"]
    assert meta["calibration"]["ladder"] == [256, 1024] and meta["calibration"]["counts"] == {}
    assert meta["calibration"]["ratio_at_samples"]["median"] == pytest.approx(0.5)
    assert (meta["rays"], meta["samples"], meta["repeats"]) == (2000, 256, 1)
    [s] = data["scenes"]
    assert (s["name"], s["group"], s["rays"], s["samples"]) == ("q-sphere-3k", "procedural", 2000, 256)
    assert s["measured"]["bvh"]["per_ray"] > 0 and s["grid"]["per_ray"] > 0
    # no count models: the plan's grid estimate is the K-sample time x the calibration's ratio
    assert s["grid_estimate_per_ray"] == pytest.approx(0.5 * s["grid_sample_per_ray"], rel=1e-9)
    assert len(s["extra"]["plan_repeats"]["bvh"]) == 2 and s["extra"]["reuse_plan"]["workload_samples"] == 256
    summ = data["summary"]
    heads = [h["measure"] for h in summ["headline"]]
    assert heads[0] == "median absolute break-even error, evaluated meshes"
    assert not any("two calibrations in a row" in h for h in heads) and "calibration_repeatability" not in summ
    assert set(summ["count_models"]) == {"bvh"} and "embree" not in summ
    assert {"paper", "affine", "median"} <= set(data["models"]) and data["best_model"] in data["models"]
    for m in data["models"].values():
        assert set(m["grid"]) == {"plan", "sample x ratio", "uncorrected"}
    assert "**Decision.** " + data["model_decision"] in (out / "report.md").read_text()
    sw = data["sweep"]
    assert sw["scenes"] == ["q-sphere-3k"] and [(r["density"], r["K"]) for r in sw["rows"]] == [(2.0, 256)]
    assert set(sw["tables"]) == {"plan", "sample x ratio", "uncorrected"}
    assert [b["K"] for b in sw["batch"]] == [256, 2000], "the batch sizes at density 2, then the workload"
    assert data["grid_sample_ratio"]["scale"] == "hand" and len(data["grid_sample_ratio"]["scenes"]) == 5
    md = (out / "report.md").read_text()
    for title in ("## Headline", "## Break-even per scene", "## Speed: hybrid", "## Speed against error",
                  "## The grid's small-batch ratio", "## Refinements", "## Figures"):
        assert title in md, f"report.md lacks the section {title!r}"
    assert "| q-sphere-3k | procedural | 2,880 |" in md and data["plots"] == [] and not list(out.glob("*.png"))


@pytest.mark.slow
def test_quick_report_writes_well_formed_json_markdown_and_plots(tmp_path):
    out = tmp_path / "report"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "report.py"), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"report.py --quick failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    data = json.loads((out / "report.json").read_text())
    assert data["meta"]["quick"] is True and len(data["scenes"]) == 4
    for s in data["scenes"]:
        assert s["measured"]["bvh"]["per_ray"] > 0 and s["grid"]["per_ray"] > 0, s["name"]
    heads = [h["measure"] for h in data["summary"]["headline"]]
    assert any("median absolute break-even error" in h for h in heads)
    assert any("(ii)" in h and "oracle" in h for h in heads) and any("(i)" in h and "oracle" in h for h in heads)
    from hybrid_raycast.core.decide import DEFAULT_MODEL

    cal = data["meta"]["calibration"]
    assert cal["model"] == cal["default_model"] == DEFAULT_MODEL, "the headline is the add-on as it stands"
    assert cal["ladder"] == [256, 1024] and cal["ratio_at_samples"]["median"] > 0
    from hybrid_raycast.core.decide.cost import terms

    assert set(cal["counts"]) >= {"grid", "bvh"}, "a fresh calibration holds the count models"
    for s in data["scenes"]:
        # the estimate is the count model on the plan's own work counts (no timing involved)
        t = terms(s["triangles"], s["extra"]["work"])
        g = cal["counts"]["grid"]
        refs = g.get("refs") or [0.0] * len(g["terms"])  # the counts each constant is stated at
        if g.get("form", "linear") == "log":  # a power law: exp(c_1 + sum c_j log((1 + term_j) / (1 + ref_j)))
            want = math.exp(sum(c * (1.0 if k == "1" else math.log1p(t[k]) - math.log1p(r))
                                for k, c, r in zip(g["terms"], g["coef"], refs)))
        else:
            want = sum(c * (t[k] - r) for k, c, r in zip(g["terms"], g["coef"], refs))
        assert s["grid_estimate_per_ray"] == pytest.approx(want, rel=1e-9), s["name"]
        assert len(s["extra"]["plan_repeats"]["bvh"]) == 2
        assert s["R_est"] == (pytest.approx(s["extra"]["plan_break_even"]["bvh"]) if s["R_est"] is not None else None)
        assert s["extra"]["reuse_plan"]["workload_samples"] == s["samples"] == 1024
    assert {"paper", "affine", "median"} <= set(data["models"])
    for name, m in data["models"].items():
        assert set(m["grid"]) == {"plan", "sample x ratio", "uncorrected"}, f"model {name}: grid estimators {set(m['grid'])}"
    # the affine (default) model under the plan's estimate reproduces the headline's error
    assert data["models"][DEFAULT_MODEL]["grid"]["plan"]["held_out"]["median_abs"] == data["summary"]["errors"]["median_abs"]
    assert data["sweep"]["rows"], "the speed-against-error sweep recorded nothing"
    for r in data["sweep"]["rows"]:
        assert r["sample x ratio"]["per_ray"] == pytest.approx(r["uncorrected"]["per_ray"] * r["calibration_ratio"], rel=1e-9)
        assert r["plan"]["per_ray"] == pytest.approx(r["uncorrected"]["per_ray"] * r["ratio"], rel=1e-9)
    assert set(data["sweep"]["tables"]) == {"plan", "sample x ratio", "uncorrected"}
    md = (out / "report.md").read_text()
    for title in ("## Headline", "## Break-even per scene", "## Speed: hybrid", "## Speed against error",
                  "## The grid's small-batch ratio", "## Refinements"):
        assert title in md, f"report.md lacks the section {title!r}"
    assert "not in `core.plan` yet" not in md and "proposed refinement" not in md
    if "embree" in data["meta"]["kinds"]:
        em = data["summary"]["embree"]
        for r, s in zip(em["scenes"], data["scenes"]):
            # one figure per pass, each the build's CPU seconds over its wall seconds
            assert len(r["parallelism"]) == len(s["extra"]["R_C_repeats"]["embree"]), r["name"]
            assert all(0.0 <= x < 2.0 * os.cpu_count() + 1 for x in r["parallelism"]), r["name"]
            assert r["build_error"] == pytest.approx(100 * (r["build_est"] / r["build"] - 1), rel=1e-9)
        assert em["parallelism"]["builds"] == sum(len(r["parallelism"]) for r in em["scenes"])
        assert 0.0 <= em["parallelism"]["one_thread_share"] <= 1.0
        assert em["calibration_parallelism"]["builds"] > 0, "a fresh calibration records its builds' CPU time"
        assert "threads busy per pass" in md and "## With Embree as a third candidate" in md
    if importlib.util.find_spec("matplotlib") is not None:
        for p in ("errors.png", "totals.png", "speed_vs_error.png"):
            assert (out / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{p} is not a PNG"
            assert f"]({p})" in md, f"report.md does not show {p}"
    else:
        assert "no plots" in md


def test_parallelism_summary_counts_the_builds_that_kept_about_one_thread_busy():
    got = evaluate.parallelism_summary([1.0, 1.05, 1.9, 1.29, None, math.nan, 1.8])
    assert got == {"builds": 5, "median": pytest.approx(1.29), "one_thread_share": pytest.approx(3 / 5)}
    empty = evaluate.parallelism_summary([None])
    assert empty["builds"] == 0 and math.isnan(empty["median"]) and math.isnan(empty["one_thread_share"])


def test_the_calibrations_builds_are_each_pass_where_the_file_keeps_them_else_each_scenes_median():
    kept = SceneRecord("a", 1000, 10, {"embree": Measurement(0.01, 1.0, 10, 2, build_cpu=0.019)})
    kept.passes = {"embree": [Measurement(0.01, 1.0, 10, 2, build_cpu=0.019), Measurement(0.02, 1.0, 10, 2, build_cpu=0.02)]}
    old = SceneRecord("b", 1000, 10, {"embree": Measurement(0.01, 1.0, 10, 2, build_cpu=0.015)})
    none = SceneRecord("c", 1000, 10, {"grid": Measurement(0.01, 1.0, 10, 2)})
    cal = SimpleNamespace(scenes=[kept, old, none])
    assert evaluate.calibration_parallelism(cal, "embree") == pytest.approx([1.9, 1.0, 1.5])


def test_the_reports_later_calibrations_are_saved_beside_the_first():
    R = report_script()
    assert R.again_path("out/report_calibration.json", 2) == Path("out/report_calibration_2.json")
    assert R.again_path("/tmp/cal", 3) == Path("/tmp/cal_3.json")


def test_large_builds_list_both_calibrations_builds_with_their_page_faults():
    fits = {"bvh": KindFit(2e-7, 3e-7, 1e-7, 4e-7, 2e-7, 5e-7, 3)}

    def cal(bvh_1m, faults):
        recs = [SceneRecord("small", 1024, 100, {"bvh": Measurement(0.001, 0.01, 100, 2, 10, 0.0)}),
                SceneRecord("big", 1_048_576, 100, {"bvh": Measurement(bvh_1m, 0.5, 100, 2, faults, 0.25),
                                                    "grid": Measurement(0.4, 0.6, 100, 2)}),
                SceneRecord("only here", 300_000, 100, {"bvh": Measurement(0.3, 0.2, 100, 2)})]
        return Calibration(fits, scenes=recs if faults else recs[:2], source="hand", created="2026-01-01T00:00:00+00:00")

    rows = evaluate.large_builds(cal(1.2, 120_000), cal(0.8, None))
    assert [(r["scene"], r["kind"]) for r in rows] == [("big", "bvh"), ("big", "grid")]  # >= 262,144 in both
    assert rows[0] == {"scene": "big", "triangles": 1_048_576, "kind": "bvh", "build": [1.2, 0.8],
                       "faults": [120_000, None], "system": [0.25, 0.25]}
    assert rows[1]["faults"] == [None, None]


def test_report_halves_prints_every_goal_of_both_halves_side_by_side(tmp_path):
    """scripts/report_halves.py --tables-only: one row per goal with each half's figure, the
    hybrid's worst case recomputed from the reports' scenes (here the BVH wins from 4e6 rays
    on, and the sampled hybrid pays its grid build and estimate on top of the oracle)."""
    summary = {"errors": {"median_abs": 12.5}, "rc_repeatability": {"median": 40.0, "max": 90.0},
               "embree": {"errors": {"median_abs": 7.5}},
               "picks": {"percent": 97.5, "correct": 39, "considered": 40},
               "plan_repeatability": {"bvh": {"median": 1.03, "max": 1.05}},
               "interval_coverage": {"held": 1, "scenes": 1, "never_above": 0}}
    for half in ("tuning", "final"):
        (tmp_path / half).mkdir()
        (tmp_path / half / "report.json").write_text(json.dumps(
            {"meta": {"date": f"{half} date"}, "summary": summary, "scenes": [scene(name=half).to_dict()]}))
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_halves.py"), "--tables-only", "--out",
                          str(tmp_path)], capture_output=True, text=True, check=True).stdout
    lines = {ln.split(" | ")[0].lstrip("| "): ln for ln in out.splitlines() if ln.startswith("| ")}
    assert lines["break-even error vs the numpy BVH, median absolute"].endswith("| <= 25% | 12.5% | 12.5% |")
    assert "| 97.5% (39/40) |" in lines["correct picks (totals differ > 10%)"]
    worst = lines["hybrid / oracle, grid vs numpy BVH: median; worst"]
    assert "(tuning, " in worst and "(final, " in worst, worst
    totals = evaluate.strategy_totals(scene(), evaluate.RAY_COUNTS)
    assert f"{np.max(totals['hybrid'] / totals['oracle']):.3f} (" in worst
    assert "tuning date" in out and "final date" in out
    missing = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_halves.py"), "--tables-only", "--out",
                              str(tmp_path / "none")], capture_output=True, text=True)
    assert missing.returncode == 2 and "run without --tables-only first" in missing.stderr
