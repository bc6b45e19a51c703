"""The evaluation report: the paper's tables on synthetic timings (exact errors, speedups,
the >10% rule, the oracle, the online switch), the model candidates on synthetic
calibration data, and a quick end-to-end run of scripts/report.py on tiny procedural
scenes (no ../shared needed)."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hybrid_raycast.core import report as rep
from hybrid_raycast.core.calibration import Calibration, KindFit, Measurement, SceneRecord, log2n, nlog2n
from hybrid_raycast.core.plan import plan_from_timings

ROOT = Path(__file__).resolve().parents[1]


def scene(grid=(1.0, 1e-6), bvh=(2.0, 0.5e-6), est=None, sample=None, overhead=0.1, name="s"):
    """Grid build 1 s, 1 us/ray; BVH build 2 s, 0.5 us/ray: R_C = 2 / 0.5e-6 = 4e6 exactly."""
    est = est or bvh
    return rep.SceneResult(name, 1024, 2_000_000, rep.Cost(*grid), {"bvh": rep.Cost(*bvh)}, {"bvh": rep.Cost(*est)},
                           grid[1] if sample is None else sample, overhead)


# -- break-even errors ---------------------------------------------------------------------------

def test_relative_error_is_the_papers_percentage_and_infinities_are_handled():
    assert rep.relative_error(150.0, 100.0) == 50.0
    assert rep.relative_error(50.0, 100.0) == -50.0
    for est, true in ((math.inf, math.inf), (1e5, math.inf), (math.inf, 1e5)):
        assert math.isnan(rep.relative_error(est, true)), f"R_est {est}, R_C {true}: the measure is undefined"
    assert rep.never_agreement([(math.inf, math.inf), (1e5, math.inf), (math.inf, 1e5), (1.0, 2.0)]) == {
        "both_never": 1, "only_estimate_never": 1, "only_measured_never": 1}


def test_true_and_estimated_break_even_use_the_sunk_grid_formula():
    s = scene(est=(1.0, 0.5e-6), sample=1.5e-6)
    assert rep.true_break_even(s) == pytest.approx(4e6, rel=1e-12)
    assert rep.estimated_break_even(s) == pytest.approx(1.0 / 1e-6, rel=1e-12)
    assert rep.relative_error(rep.estimated_break_even(s), rep.true_break_even(s)) == pytest.approx(-75.0)
    assert rep.true_break_even(scene(bvh=(2.0, 1e-6))) == math.inf, "equal per-ray times: the BVH never pays"


def test_error_summary_gives_the_papers_sums_and_counts_undefined_apart():
    e = rep.error_summary([10.0, -20.0, 30.0, math.nan])
    assert e["scenes"] == 4 and e["defined"] == 3 and e["undefined"] == 1
    assert e["sum"] == 20.0 and e["sum_abs"] == 60.0
    assert e["median_abs"] == 20.0 and e["median"] == 10.0 and e["max_abs"] == 30.0
    assert e["within_25"] == 2 and e["within_10"] == 1
    assert math.isnan(rep.error_summary([math.nan])["median_abs"])


# -- strategies ---------------------------------------------------------------------------------

def test_strategy_totals_on_known_numbers():
    s = scene()  # estimate exact: R_est = R_C = 4e6
    r = np.array([1e6, 1e7])
    t = rep.strategy_totals(s, r, batch=1)
    np.testing.assert_allclose(t["grid"], [2.0, 11.0])
    np.testing.assert_allclose(t["bvh"], [2.5, 7.0])
    # hybrid: grid build + overhead, then the grid (R <= 4e6) or the BVH
    np.testing.assert_allclose(t["hybrid"], [1.0 + 0.1 + 1.0, 1.0 + 0.1 + 2.0 + 5.0])
    np.testing.assert_allclose(t["oracle"], [2.0, 7.0])
    assert list(t["choice"]) == ["grid", "bvh"]


def test_hybrid_with_samples_from_the_workload_skips_the_estimate_below_k_rays():
    s = scene()
    s.samples = 2_000_000
    t = rep.strategy_totals(s, [1e6, 1e7], batch=1)["hybrid_reuse"]
    # R <= K: the grid alone; R > K: grid build + estimate, then the BVH for the R - K rays left
    np.testing.assert_allclose(t, [2.0, 1.0 + 0.1 + 2.0 + 8e6 * 0.5e-6])


def test_online_switches_on_the_batch_boundary_after_the_estimated_build_time():
    s = scene()
    batch = 1 << 15
    sw = rep.online_switch(s, "bvh", batch)
    assert sw == math.ceil(2.0 / 1e-6 / batch) * batch == 2_031_616
    t = rep.strategy_totals(s, [1e6, 1e7], batch=batch)["online"]
    np.testing.assert_allclose(t, [1.0 + 1.0, 1.0 + sw * 1e-6 + 2.0 + (1e7 - sw) * 0.5e-6])
    # ski rental: never worse than about twice the best fixed choice
    r = np.logspace(3, 9, 61)
    tt = rep.strategy_totals(s, r, batch=batch)
    assert (tt["online"] / tt["oracle"]).max() < 2.0 + 1e-9


def test_online_never_switches_when_the_estimate_is_not_faster_per_ray():
    assert rep.online_switch(scene(est=(2.0, 1e-6))) == math.inf
    t = rep.strategy_totals(scene(est=(2.0, 2e-6)), [1e8])
    assert t["online"][0] == pytest.approx(1.0 + 100.0)


def test_hybrid_choice_matches_plan_from_timings():
    n = 1024  # log2 N = 10, N log2 N = 10240
    cal = Calibration({"bvh": KindFit(1e-5, 5e-8, 1e-5, 1e-5, 5e-8, 5e-8, 1),
                       "embree": KindFit(2e-5, 1e-8, 2e-5, 2e-5, 1e-8, 1e-8, 1)}, source="hand")
    est = {k: rep.Cost(cal.estimate(k, n).build, cal.estimate(k, n).per_ray) for k in ("bvh", "embree")}
    s = rep.SceneResult("s", n, 1, rep.Cost(0.01, 2e-6), dict(est), est, 2e-6, 0.0)
    for r in np.logspace(2, 9, 50):
        want = plan_from_timings(n, r, cal, 0.01, 2e-6, kinds=("grid", "bvh", "embree")).chosen
        assert rep.hybrid_choice(s, [r], ("bvh", "embree"))[0] == want, f"R = {r:.3g}"


def test_pick_accuracy_counts_only_cases_that_differ_by_more_than_ten_percent():
    s = scene(est=(1.0, 0.5e-6))  # R_est = 2e6, R_C = 4e6: picks the BVH too early
    r = [1e6, 3e6, 3.9e6, 1e7]
    # R t_G vs 2 + 0.5e-6 R: 1 vs 2.5 (grid, picked grid), 3 vs 3.5 (grid, picked BVH: wrong),
    # 3.9 vs 3.95 (within 10%: not counted), 10 vs 7 (BVH, picked BVH)
    p = rep.pick_accuracy([s], r)
    assert (p["considered"], p["correct"]) == (3, 2) and p["percent"] == pytest.approx(200 / 3)
    assert p["wrong"] == [("s", 3e6)]
    # counting the grid's build: 2 vs 2.5 (grid), 4 vs 3.5, 4.9 vs 3.95, 11 vs 7 (BVH, BVH, BVH): all right
    q = rep.pick_accuracy([s], r, sunk_grid=False)
    assert (q["considered"], q["correct"]) == (4, 4)


def test_speedup_summary_medians_on_known_numbers():
    s = scene()
    r = [1e6, 1e7]
    sp = rep.speedup_summary([s], r, batch=1)
    hybrid = np.array([2.1, 8.1])
    assert sp["speedup_vs_grid"]["median"] == pytest.approx(np.median(np.array([2.0, 11.0]) / hybrid))
    assert sp["speedup_vs_bvh"]["median"] == pytest.approx(np.median(np.array([2.5, 7.0]) / hybrid))
    assert sp["hybrid_over_oracle"]["median"] == pytest.approx(np.median(hybrid / np.array([2.0, 7.0])))
    assert sp["hybrid_over_oracle"]["cases"] == 2


def test_estimate_cost_is_a_percentage_of_the_grid_only_total_at_a_million_rays():
    assert rep.estimate_cost_percent(scene(overhead=0.1)) == pytest.approx(5.0)  # 0.1 / (1 + 1e6 * 1e-6)


def test_median_per_ray_and_error_components():
    a, b = scene(name="a"), scene(grid=(1.0, 3e-6), name="b")
    assert rep.median_per_ray([a, b]) == {"grid": pytest.approx(2e-6), "bvh": pytest.approx(0.5e-6)}
    c = rep.error_components(scene(est=(3.0, 0.25e-6), sample=1.5e-6))
    assert c == {"build": pytest.approx(50.0), "per_ray": pytest.approx(-50.0), "grid_per_ray": pytest.approx(50.0)}


def test_scene_result_round_trips_through_a_dict():
    s = scene()
    assert rep.SceneResult.from_dict(json.loads(json.dumps(s.to_dict()))) == s


# -- the grid from two batches --------------------------------------------------------------------

def test_two_batch_extrapolation_is_exact_on_an_affine_batch_cost():
    s, f = 1e-6, 0.05  # per-ray part and per-batch part
    t = lambda b: b * s + f  # noqa: E731
    got = rep.extrapolated_per_ray(4096, t(4096), 12288, t(12288), chunk=1 << 15, threads=2)
    assert got == pytest.approx(s + f / (2 * (1 << 15)), rel=1e-9)
    # noise that makes the per-batch part negative falls back on the plain mean
    assert rep.extrapolated_per_ray(100, 0.1, 300, 1.0, 10, 1) == pytest.approx(1.1 / 400)
    assert rep.extrapolated_per_ray(100, 1.0, 300, 0.9, 10, 1) == pytest.approx(1.9 / 400), "a slower small batch: s < 0"


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
    for row in rep.loo_break_even_errors(records(), "bvh", "paper"):
        assert abs(row["error"]) < 1e-9 and abs(row["build_error"]) < 1e-9, row


def test_affine_candidate_recovers_a_fixed_cost_exactly():
    recs = records(a_b=0.002, a_r=1e-7)
    f = rep.fit_model(recs, ("bvh",), "affine")["bvh"]
    assert f.extra["a_B"] == pytest.approx(0.002, rel=1e-6) and f.c_B == pytest.approx(2e-7, rel=1e-6)
    assert f.extra["a_R"] == pytest.approx(1e-7, rel=1e-6) and f.c_R == pytest.approx(2e-7, rel=1e-6)
    assert all(abs(r["error"]) < 1e-6 for r in rep.loo_break_even_errors(recs, "bvh", "affine"))
    # the paper's form cannot carry the fixed cost: it errs on the same data
    assert max(abs(r["build_error"]) for r in rep.loo_break_even_errors(recs, "bvh", "paper")) > 10


def test_affine_model_is_a_calibration_model_that_survives_save_and_load(tmp_path):
    from hybrid_raycast.core.calibration import fit, load

    recs = records(a_b=0.002, a_r=1e-7)
    cal = Calibration(fit(recs, ("bvh",), model="affine"), scenes=recs, model="affine")
    back = load(cal.save(tmp_path / "cal.json"))
    assert back.model == "affine"
    e, n = back.estimate("bvh", 100000), 100000
    assert e.build == pytest.approx(0.002 + 2e-7 * nlog2n(n), rel=1e-6)
    assert e.per_ray == pytest.approx(1e-7 + 2e-7 * log2n(n), rel=1e-6)
    assert e.build_low <= e.build <= e.build_high and e.per_ray_low <= e.per_ray <= e.per_ray_high


def test_reestimate_changes_only_the_estimates():
    s = scene()
    s2 = rep.reestimate(s, records(), "paper")
    assert s2.measured == s.measured and s2.grid == s.grid and s2.grid_sample_per_ray == s.grid_sample_per_ray
    assert s2.estimated["bvh"].build == pytest.approx(2e-7 * nlog2n(1024))


# -- the command ----------------------------------------------------------------------------------

def test_quick_report_writes_well_formed_json_markdown_and_plots(tmp_path):
    out = tmp_path / "report"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "report.py"), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"report.py --quick failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    data = json.loads((out / "report.json").read_text())
    assert data["meta"]["quick"] is True and len(data["scenes"]) == 4
    for s in data["scenes"]:
        assert s["measured"]["bvh"]["per_ray"] > 0 and s["grid"]["per_ray"] > 0, s["name"]
    heads = {h["measure"] for h in data["summary"]["headline"]}
    assert any("median absolute break-even error" in h for h in heads) and any("oracle" in h for h in heads)
    assert {"paper", "affine", "median"} <= set(data["models"])
    for name, m in data["models"].items():
        assert set(m["grid"]) == {"single", "two-batch", "ratio"}, f"model {name}: grid estimators {set(m['grid'])}"
    assert data["sweep"]["rows"], "the speed-against-error sweep recorded nothing"
    md = (out / "report.md").read_text()
    for title in ("## Headline", "## Break-even per scene", "## Speed: hybrid", "## Speed against error", "## Refinements"):
        assert title in md, f"report.md lacks the section {title!r}"
    if importlib.util.find_spec("matplotlib") is not None:
        for p in ("errors.png", "totals.png", "speed_vs_error.png"):
            assert (out / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{p} is not a PNG"
            assert f"]({p})" in md, f"report.md does not show {p}"
    else:
        assert "no plots" in md
