"""The cost model's arithmetic and the one decision rule (core/decide), on exact numbers.

The break-even formula and the rule are each written once (``cost.break_even``,
``rule.choose``); the plan and the evaluation call them, so these tests check the one
copy against hand-worked figures rather than keeping copies equal.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from hybrid_raycast.core.decide import cost, rule
from hybrid_raycast.core.decide import evaluate as ev
from hybrid_raycast.core.decide.work import SAMPLE_COST_SHARE, SAMPLE_MIN, SAMPLE_SHARE, sample_count
from hybrid_raycast.core.plan import plan_from_timings
from hybrid_raycast.core.decide import Calibration, KindFit, Measurement, SceneRecord


def test_break_even_is_build_over_the_per_ray_gain_and_never_when_the_grid_is_not_slower():
    assert cost.break_even(0.5, 3e-6, 1e-6) == pytest.approx(250_000.0, rel=1e-12)  # 0.5 / 2e-6
    assert math.isinf(cost.break_even(0.5, 1e-6, 1e-6))
    assert math.isinf(cost.break_even(0.5, 1e-6, 2e-6))
    assert cost.break_even(0.0, 2e-6, 1e-6) == 0.0


def costs_of(**figures):
    """{kind: Cost} from kind=(build seconds, seconds per ray)."""
    return {k: cost.Cost.point(k, b, t) for k, (b, t) in figures.items()}


def test_choose_is_the_least_cost_with_the_grid_build_sunk():
    # grid 4 us/ray; bvh: 0.1 s + 1 us/ray (R* = 0.1 / 3e-6 = 33,333); embree: 0.3 s + 0.5 us/ray
    # (R* = 0.3 / 3.5e-6 = 85,714).  bvh vs embree: 0.1 + 1e-6 R = 0.3 + 5e-7 R at R = 400,000.
    cands = costs_of(bvh=(0.1, 1e-6), embree=(0.3, 5e-7))
    got = rule.choose([1_000, 33_333, 33_334, 399_999, 400_001, 1e7], 4e-6, cands)
    assert list(got) == ["grid", "grid", "bvh", "bvh", "embree", "embree"]


def test_choose_breaks_ties_towards_the_grid_then_the_first_name():
    # powers of two, so both totals are exact in binary and tie exactly at R* = 512
    t_g, b, t = 2.0 ** -18, 2.0 ** -10, 2.0 ** -19  # R* = 2^-10 / 2^-19 = 512
    assert rule.choose([512], t_g, costs_of(bvh=(b, t)))[0] == "grid"
    assert rule.choose([513], t_g, costs_of(bvh=(b, t)))[0] == "bvh"
    assert rule.choose([1e6], t_g, costs_of(bvh=(b, t), embree=(b, t)))[0] == "bvh"


def test_choose_with_answered_samples_weighs_the_rays_left_and_embree_retraces_all():
    # 1,000 rays answered: grid costs (R - 1000) t_G, the numpy BVH T_B + (R - 1000) t_H,
    # Embree T_B + R t_E
    cands = costs_of(bvh=(0.02, 1e-6), embree=(0.0, 3.5e-6))
    names, c = rule.costs([5_000], 4e-6, cands, answered=1000)
    assert names == ["grid", "bvh", "embree"]
    assert c[:, 0] == pytest.approx([0.016, 0.024, 0.0175], rel=1e-12)
    assert rule.choose([5_000], 4e-6, cands, answered=1000)[0] == "grid"
    assert rule.choose([5_000], 4e-6, cands, answered=0)[0] == "embree"  # 0.02 > 0.0175
    assert rule.choose([800], 4e-6, costs_of(bvh=(0.0, 1e-6)), answered=1000)[0] == "grid"  # nothing left to trace


def test_over_life_is_the_least_total_with_only_what_is_built_sunk():
    grid, bvh = cost.Cost.point("grid", 0.01, 4e-6), cost.Cost.point("bvh", 0.05, 2e-6)
    ests = {"grid": grid, "bvh": bvh}
    # nothing built: the BVH pays for its extra build (0.04 s) over 0.04 / 2e-6 = 20,000 rays
    kind, totals, be, be_kind = rule.over_life(ests, 19_999)
    assert kind == "grid" and math.isclose(be, 20_000) and be_kind == "bvh"
    assert math.isclose(totals["grid"], 0.01 + 19_999 * 4e-6) and math.isclose(totals["bvh"], 0.05 + 19_999 * 2e-6)
    assert rule.over_life(ests, 20_001)[0] == "bvh"
    assert rule.over_life(ests, 20_000)[0] == "grid"  # a tie keeps the grid
    # the grid built already: the BVH must pay its whole build, 0.05 / 2e-6 = 25,000 rays
    kind, _, be, _ = rule.over_life(ests, 24_000, built={"grid"})
    assert kind == "grid" and math.isclose(be, 25_000)
    assert rule.over_life(ests, 26_000, built={"grid"})[0] == "bvh"
    # the BVH built already: it is cheapest from the first ray, and beats the grid at once
    kind, _, be, _ = rule.over_life(ests, 1, built={"bvh"})
    assert kind == "bvh" and be == 0.0
    # a structure slower per ray never beats the grid; no grid estimate: no break-even
    assert rule.over_life({"grid": grid, "bvh": cost.Cost.point("bvh", 0.0, 5e-6)}, 1e9)[2] == math.inf
    assert rule.over_life({"bvh": bvh}, 10)[2:] == (math.inf, None)


def test_grid_estimate_follows_the_calibration_scenes_power_law():
    recs = [SceneRecord(f"s{n}", n, 1000, {"grid": Measurement(2e-7 * n, 1000 * 1e-9 * n ** 0.1, 1000)})
            for n in (1_000, 10_000, 100_000, 1_000_000)]
    g = cost.grid_estimate(recs, 300_000)
    assert math.isclose(g.build_time, 2e-7 * 300_000, rel_tol=1e-9)
    assert math.isclose(g.per_ray, 1e-9 * 300_000 ** 0.1, rel_tol=1e-9)
    assert g.build_low <= g.build_time <= g.build_high and g.per_ray_low <= g.per_ray <= g.per_ray_high
    assert cost.grid_estimate(recs[:2], 300_000) is None  # fewer than 3 scenes measured the grid


def test_choose_keeps_the_grid_at_or_below_the_floor_whatever_the_costs():
    # bvh is cheaper from 33,334 rays on (R* = 33,333.3); a floor of 50,000 overrides that
    # up to and including 50,000 rays, and changes nothing above it
    cands = costs_of(bvh=(0.1, 1e-6))
    got = rule.choose([1_000, 33_334, 50_000, 50_001], 4e-6, cands, floor=50_000)
    assert list(got) == ["grid", "grid", "grid", "bvh"]
    assert list(rule.choose([33_334, 50_000], 4e-6, cands)) == ["bvh", "bvh"]


def test_plan_and_evaluation_decide_through_the_one_rule():
    """The plan's decision and the evaluation's hybrid are the rule applied to their figures
    (hand numbers: N = 1024, bvh 0.1024 s + 0.5 us/ray, grid 2 us/ray: R* = 68,266.7)."""
    n = 1024
    cal = Calibration({"bvh": KindFit(1e-5, 5e-8, 1e-5, 1e-5, 5e-8, 5e-8, 1)}, source="hand")
    e = cal.estimate("bvh", n)
    assert (e.build_time, e.per_ray) == pytest.approx((0.1024, 5e-7), rel=1e-12)
    s = ev.SceneResult("s", n, 1, cost.Cost.point("grid", 0.01, 2e-6), {"bvh": e}, {"bvh": e}, 2e-6, 0.0, 4096)
    for r, want in ((68_266, "grid"), (68_267, "bvh")):
        assert plan_from_timings(n, r, cal, 0.01, 2e-6, kinds=("grid", "bvh")).chosen == want
        assert ev.hybrid_choice(s, [r])[0] == want
    assert ev.hybrid_reuse_choice(s, [68_267])[0] == "grid"  # 4,096 answered: 64,171 left < R*
    assert ev.hybrid_reuse_choice(s, [68_267 + 4096])[0] == "bvh"


def test_affine_model_estimates_on_exact_numbers():
    f = KindFit(2e-8, 1e-7, 1e-8, 4e-8, 5e-8, 2e-7, 3, extra={"a_B": 1e-3, "a_R": 2e-7})
    e = ev.COMPARED_MODELS["affine"][1](f, "bvh", 1 << 16)  # N log2 N = 65536 * 16 = 1,048,576
    assert (e.build_time, e.build_low, e.build_high) == pytest.approx((1e-3 + 2e-8 * 1048576, 1e-3 + 1e-8 * 1048576,
                                                                  1e-3 + 4e-8 * 1048576), rel=1e-12)
    assert (e.per_ray, e.per_ray_low, e.per_ray_high) == pytest.approx((2e-7 + 1.6e-6, 2e-7 + 8e-7, 2e-7 + 3.2e-6), rel=1e-12)


def test_interleaved_rotates_the_order_each_round_and_keeps_each_jobs_results_in_order():
    from hybrid_raycast.core.decide.load_watch import interleaved

    log = []
    jobs = {k: (lambda k=k: log.append(k) or len(log)) for k in ("a", "b", "c")}
    out = interleaved(jobs, 3)
    assert log == ["a", "b", "c", "b", "c", "a", "c", "a", "b"]
    assert out == {"a": [1, 6, 8], "b": [2, 4, 9], "c": [3, 5, 7]}


def test_in_passes_runs_every_scene_once_a_pass_with_the_order_rotated_by_the_pass():
    """Two scenes, three passes: pass r runs scene 0's jobs, then scene 1's, each rotated by r,
    and each scene's jobs are made again for every pass."""
    from hybrid_raycast.core.decide.load_watch import in_passes

    log, made = [], []

    def scene(name):
        def make(r):
            made.append((name, r))
            return {k: (lambda k=k: log.append(f"{name}{k}") or len(log)) for k in ("a", "b")}
        return make

    shares = [[], []]
    out = in_passes([scene("x"), scene("y")], 3, shares=shares)
    assert log == ["xa", "xb", "ya", "yb", "xb", "xa", "yb", "ya", "xa", "xb", "ya", "yb"]
    assert made == [("x", 0), ("y", 0), ("x", 1), ("y", 1), ("x", 2), ("y", 2)]
    assert out == [{"a": [1, 6, 9], "b": [2, 5, 10]}, {"a": [3, 8, 11], "b": [4, 7, 12]}]
    assert [len(x) for x in shares] == [3, 3]  # one round per scene per pass


def test_measure_break_evens_measures_each_scene_in_passes_with_its_own_medians(monkeypatch):
    """Two scenes in three passes: every pass measures both scenes (scene 0 before scene 1),
    each BreakEven takes the medians of its own scene's passes and keeps the last pass's
    structures only."""
    from hybrid_raycast.core import scenes as S
    from hybrid_raycast.core.decide import truth

    order = []
    real = truth.measure_and_keep

    def spy(mesh, kind, o, d, threads=None, config=None, builds=None):
        order.append((mesh.triangle_count, kind))
        return real(mesh, kind, o, d, threads, config, builds)

    monkeypatch.setattr(truth, "measure_and_keep", spy)
    a, b = S.torus(800), S.sphere(1500)
    got = truth.measure_break_evens([(a, 500), (b, 700)], ("grid", "bvh"), repeats=3)
    na, nb = a.triangle_count, b.triangle_count
    order = [x for x in order if x[0] in (na, nb)]  # not warm_up's tiny scene
    assert [n for n, _ in order] == [na, na, nb, nb] * 3
    assert [k for _, k in order[:4]] == ["grid", "bvh", "grid", "bvh"]
    assert [k for _, k in order[4:6]] == ["bvh", "grid"]
    for be, n, rays in zip(got, (na, nb), (500, 700)):
        assert (be.triangles, be.rays, be.repeats) == (n, rays, 3)
        for k in ("grid", "bvh"):
            assert len(be.runs[k]) == 3
            assert be.measurements[k].build_time == float(np.median([m.build_time for m in be.runs[k]]))
        assert set(be.structures) == {"grid", "bvh"}
        assert all(s.mesh.triangle_count == n for s in be.structures.values())


class _FakeShares:
    """Stands in for OthersShare: each ``with`` block reports the next share of a list."""

    def __init__(self, shares):
        self.shares = list(shares)

    def __call__(self):
        return self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.share = self.shares.pop(0)
        return False


def test_interleaved_takes_a_disturbed_round_again_and_keeps_the_least_disturbed(monkeypatch):
    """A round during which other processes took more than ``quiet`` of the CPU is run again
    (up to ``retries`` times); the quietest take is kept and its share and takes recorded."""
    from hybrid_raycast.core.decide import load_watch as M

    log = []
    jobs = {k: (lambda k=k: log.append(k) or len(log)) for k in ("a", "b")}
    # round 0: 0.3, then 0.02 (kept, 2 takes); round 1: 0.5, 0.2, 0.4 (retries spent: 0.2 kept)
    monkeypatch.setattr(M, "OthersShare", _FakeShares([0.3, 0.02, 0.5, 0.2, 0.4]))
    shares = []
    out = M.interleaved(jobs, 2, quiet=0.1, retries=2, shares=shares)
    assert log == ["a", "b", "a", "b", "b", "a", "b", "a", "b", "a"]
    assert out == {"a": [3, 8], "b": [4, 7]}
    assert shares == [(0.02, 2), (0.2, 3)]
    notes = M.quiet_notes(shares, 0.1)
    assert len(notes) == 2 and "2 of 2 measurement rounds were taken again (3 retakes)" in notes[0]
    assert "1 of 2 rounds stayed busier than that after 2 retakes" in notes[1] and "20%" in notes[1]
    # quiet=None: one take a round, whatever the share; an unreadable share is never retaken
    monkeypatch.setattr(M, "OthersShare", _FakeShares([0.9, None]))
    shares = []
    assert M.interleaved(jobs, 2, shares=shares) == {"a": [11, 14], "b": [12, 13]}
    assert shares == [(0.9, 1), (None, 1)]
    assert M.quiet_notes(shares, None) == []  # nothing was checked: nothing to say
    assert M.quiet_notes([(None, 1)], 0.1)[0].startswith("other processes' share of the CPU could not be read")
    assert M.quiet_notes([(0.01, 1)], 0.1) == []


@pytest.mark.skipif(not Path("/proc/stat").exists(), reason="OthersShare reads Linux's /proc/stat")
def test_others_share_sees_a_process_that_spins_beside_a_sleeping_one():
    """While this process sleeps and a child spins, the child's CPU is other processes'
    share: about one core of the machine's (1 / cores), never more than all of it; a block
    shorter than a few counter ticks has no figure."""
    import os
    import subprocess
    import sys
    import time

    from hybrid_raycast.core.decide.load_watch import OthersShare

    with OthersShare() as short:
        pass
    assert short.share is None
    child = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 3: pass"])
    try:
        time.sleep(0.3)  # the child is running
        with OthersShare() as busy:
            time.sleep(0.6)
    finally:
        child.kill()
        child.wait()
    assert 0.6 / (os.cpu_count() or 1) <= busy.share <= 1.0, busy.share


def test_measure_break_even_takes_medians_of_the_repeats_and_reports_their_spread():
    from hybrid_raycast.core import scenes as S
    from hybrid_raycast.core.decide import measure_break_even

    be = measure_break_even(S.torus(2000), 3000, kinds=("grid", "bvh"), repeats=3)
    for k in ("grid", "bvh"):
        runs = be.runs[k]
        assert len(runs) == 3
        assert be.measurements[k].build_time == float(np.median([m.build_time for m in runs]))
        assert be.measurements[k].trace_time == float(np.median([m.trace_time for m in runs]))
    g, h = be.measurements["grid"], be.measurements["bvh"]
    assert be.R_C["bvh"] == cost.break_even(h.build_time, g.per_ray, h.per_ray)
    reps = [cost.break_even(b.build_time, a.per_ray, b.per_ray) for a, b in zip(be.runs["grid"], be.runs["bvh"])]
    assert be.R_C_repeats["bvh"] == reps
    fin = [x for x in reps if math.isfinite(x)]
    if len(fin) >= 2:
        assert be.repeatability("bvh") == pytest.approx(100 * (max(fin) - min(fin)) / np.median(fin))
    assert set(be.structures) == {"grid", "bvh"}


# -- the count model (issue 14) -------------------------------------------------------------------

def test_grid_work_counts_cells_and_references_on_a_hand_grid():
    """A 4 x 1 x 1 grid of unit cells holding 1, 2, 0, 3 references; rays along +x from
    x = -1.  A miss crosses all four cells (16 points, 4 per cell: mean 1.5 references); a
    hit at x = 1.5 stops in the second cell (11 points in the first, 5 in the second)."""
    from types import SimpleNamespace

    from hybrid_raycast.core.decide.work import grid_work

    g = SimpleNamespace(lo=np.zeros(3), cell_size=np.ones(3), res=np.array([4, 1, 1]),
                        cell_start=np.array([0, 1, 3, 3, 6]))
    o = np.array([[-1.0, 0.5, 0.5], [-1.0, 0.5, 0.5]])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    w = grid_work(g, o[:1], d[:1], np.array([np.inf]))
    assert (w.cells, w.refs, w.hit) == (4.0, 6.0, 0.0)
    assert w.length == pytest.approx(4 / math.sqrt(18), rel=1e-12)
    w = grid_work(g, o[1:], d[1:], np.array([2.5]))
    assert (w.cells, w.refs, w.hit) == (2.0, 2 * 21 / 16, 1.0)
    both = grid_work(g, o, d, np.array([np.inf, 2.5]))
    assert (both.cells, both.refs, both.hit) == (3.0, (6 + 2 * 21 / 16) / 2, 0.5)
    # refs=False skips the reference count and changes nothing else
    lean = grid_work(g, o, d, np.array([np.inf, 2.5]), refs=False)
    assert (lean.cells, lean.refs, lean.hit, lean.length) == (both.cells, None, both.hit, both.length)


def test_a_one_count_model_is_stated_at_its_anchor_counts():
    """A linear model of one count states its time per ray at COUNT_ANCHORS (5 and 40 cells:
    1e-7 + 2e-8 x 5 and 1e-7 + 2e-8 x 40), and keeps its coefficients as stored."""
    rows = [(1 << n, {"cells": c}, 1e-7 + 2e-8 * c) for n, c in ((10, 4), (12, 9), (16, 20), (20, 50))]
    f = cost.CountFit.fit(rows, ("1", "cells"))
    assert cost.COUNT_ANCHORS["cells"] == (5.0, 40.0)
    assert f.constants() == pytest.approx({"at cells = 5": 2e-7, "at cells = 40": 9e-7}, rel=1e-9)
    assert f.coefficients() == pytest.approx({"at ref": 1e-7 + 2e-8 * 15, "x cells": 2e-8}, rel=1e-9)
    for x in (5.0, 40.0):
        assert f.predict(1 << 12, {"cells": x}) == pytest.approx(f.constants()[f"at cells = {x:g}"], rel=1e-12)


def test_the_grid_model_weighs_steps_and_candidates_stated_at_three_points():
    """The grid's count model is a + b steps + c candidates (COUNT_TERMS): fitted exactly on
    data that follow it, stated by its times at the three COUNT_ANCHORS points (each equal to
    the model's prediction there), and its coefficients at the reference (8 steps, 20
    candidates)."""
    assert cost.COUNT_TERMS["grid"] == ("1", "steps", "candidates")
    a, b, c = 3e-7, 4e-8, 1e-8
    rows = [(1 << n, {"cells": 2 * s, "steps": s, "candidates": q}, a + b * s + c * q)
            for n, s, q in ((10, 4, 10), (12, 7, 18), (14, 9, 30), (16, 10, 13), (18, 22, 32), (20, 9, 38))]
    f = cost.fit_counts([SceneRecord(f"s{i}", n, 1000, {"grid": Measurement(0.01, 1000 * t, 1000)}, work=w)
                         for i, (n, w, t) in enumerate(rows)], ("grid",))["grid"]
    assert f.terms == ("1", "steps", "candidates") and f.refs == (0.0, 8.0, 20.0)
    assert f.coefficients() == pytest.approx({"at ref": a + 8 * b + 20 * c, "x steps": b, "x candidates": c}, rel=1e-9)
    assert f.constants() == pytest.approx({"at steps = 5, candidates = 10": a + 5 * b + 10 * c,
                                           "at steps = 10, candidates = 13": a + 10 * b + 13 * c,
                                           "at steps = 10, candidates = 35": a + 10 * b + 35 * c}, rel=1e-9)
    for point, value in zip(cost.COUNT_ANCHORS[("steps", "candidates")], f.constants().values()):
        assert f.predict(1 << 12, dict(zip(("steps", "candidates"), point))) == pytest.approx(value, rel=1e-12)


def test_hit_above_16k_is_the_hit_fraction_times_the_levels_beyond_a_16k_triangle_scene():
    w = {"cells": 10.0, "refs": None, "hit": 0.5, "length": 0.2}
    assert cost.L_CACHED == 14.0
    assert cost.terms(1 << 20, w)["hit_above_16k"] == pytest.approx(0.5 * 6, rel=1e-12)
    assert cost.terms(3 << 14, w)["hit_above_16k"] == pytest.approx(0.5 * math.log2(3), rel=1e-12)
    assert cost.terms(1 << 14, w)["hit_above_16k"] == 0.0 and cost.terms(1000, w)["hit_above_16k"] == 0.0
    assert "hit_above_16k" not in cost.terms(1 << 20, {"cells": 10.0})  # no hit fraction: no term


def test_embrees_count_model_is_exp_of_hit_above_16k_fitted_exactly_and_stated_at_two_points():
    """Embree's time per ray is exp(a + b hit_above_16k) (COUNT_TERMS, COUNT_FORMS): least
    squares on log time recover a and b exactly on data that follow it; the model is stated
    by its times at the COUNT_ANCHORS points, each its prediction there."""
    assert cost.COUNT_TERMS["embree"] == ("1", "hit_above_16k") and cost.COUNT_FORMS["embree"] == "exp"
    a, b = math.log(9e-8), 0.35
    rows = [(n, {"cells": 10.0, "refs": None, "hit": h, "length": 0.1}) for n, h in
            ((500, 0.6), (5000, 0.4), (20000, 0.6), (60000, 0.7), (250000, 0.6), (600000, 0.8), (1_000_000, 0.36))]
    law = lambda n, h: math.exp(a + b * h * max(math.log2(n) - 14.0, 0.0))  # noqa: E731
    recs = [SceneRecord(f"s{i}", n, 1000, {"embree": Measurement(0.001, 1000 * law(n, w["hit"]), 1000)}, work=w)
            for i, (n, w) in enumerate(rows)]
    f = cost.fit_counts(recs, ("embree",))["embree"]
    assert (f.terms, f.form, f.refs) == (("1", "hit_above_16k"), "exp", ())
    assert f.coef == pytest.approx((a, b), rel=1e-9)
    assert (f.low, f.high) == pytest.approx((1.0, 1.0), abs=1e-9)
    assert f.predict(1 << 21, {"hit": 0.5}) == pytest.approx(9e-8 * math.exp(0.35 * 3.5), rel=1e-9)
    assert f.predict(1 << 12, {"hit": 0.9}) == pytest.approx(9e-8, rel=1e-9)  # at most 16k triangles: the constant
    assert f.constants() == pytest.approx({"at hit_above_16k = 0": 9e-8,
                                           "at hit_above_16k = 2.5": 9e-8 * math.exp(0.35 * 2.5)}, rel=1e-9)
    assert f.coefficients() == pytest.approx({"1": 9e-8, "e-folds per hit_above_16k": 0.35}, rel=1e-9)
    assert f.formula() == "90.00 ns x exp(0.350 x hit_above_16k)"
    # stated at a reference count, the constant is the time there and the predictions are the same
    g = cost.CountFit.fit([(n, w, law(n, w["hit"])) for n, w in rows], ("1", "hit_above_16k"), form="exp",
                          reference={"hit_above_16k": 1.0})
    assert g.refs == (0.0, 1.0) and g.coef == pytest.approx((a + b, b), rel=1e-9)
    assert g.formula() == f"{9e-8 * math.exp(0.35) * 1e9:.2f} ns x exp(0.350 x (hit_above_16k - 1))"
    assert g.predict(1 << 21, {"hit": 0.5}) == pytest.approx(f.predict(1 << 21, {"hit": 0.5}), rel=1e-12)
    with pytest.raises(ValueError, match="'exp' count model needs the term '1'"):
        cost.CountFit.fit([(n, w, 1e-7) for n, w in rows], ("hit_above_16k",), form="exp")
    with pytest.raises(ValueError, match="expected 'linear', 'log' or 'exp'"):
        cost.CountFit.fit([(n, w, 1e-7) for n, w in rows], ("1", "hit_above_16k"), form="power")


def test_records_without_traversal_counts_fit_the_grid_on_cells_and_chosen_terms_never_fall_back():
    """Records made before the grid counted its traversal (no steps in their work) give the
    COUNT_FALLBACK model, a + b cells, where the default terms cannot be fitted; terms a
    caller names are fitted or left out, never swapped; with the counts, the default terms."""
    def recs(traversal):
        return [SceneRecord(f"s{n}", n, 1000, {"grid": Measurement(0.01, 1000 * (2e-7 + 3e-8 * c), 1000)},
                            work={"cells": c, "refs": None, "hit": 0.5, "length": 0.2,
                                  **({"steps": c / 2, "candidates": c} if traversal else {})})
                for n, c in ((500, 4), (4000, 9), (30000, 20), (500000, 45))]

    old = cost.fit_counts(recs(False), ("grid",))["grid"]
    assert old.terms == ("1", "cells")
    assert old.constants() == pytest.approx({"at cells = 5": 3.5e-7, "at cells = 40": 1.4e-6}, rel=1e-9)
    assert cost.fit_counts(recs(False), ("grid",), terms_of={"grid": ("1", "steps")}) == {}
    assert cost.fit_counts(recs(True), ("grid",))["grid"].terms == ("1", "steps", "candidates")


def test_count_fit_recovers_exact_coefficients_and_predicts_on_the_terms():
    rows = [(1 << n, {"cells": c, "refs": f, "hit": 0.5, "length": 0.2}, 1e-7 + 2e-8 * c + 5e-9 * f)
            for n, c, f in ((10, 10, 20), (12, 30, 10), (14, 5, 50), (16, 40, 40), (18, 12, 7))]
    f = cost.CountFit.fit(rows, ("1", "cells", "refs"))
    # stated at the reference (15 cells, 0 refs): the '1' constant is the time per ray there
    assert f.refs == (0.0, 15.0, 0.0)
    assert f.coef == pytest.approx((1e-7 + 2e-8 * 15, 2e-8, 5e-9), rel=1e-9)
    assert f.constants() == pytest.approx({"at ref": 4e-7, "x cells": 2e-8, "x refs": 5e-9}, rel=1e-9)
    assert f.coefficients() == f.constants()  # two counts: stated by its coefficients
    assert (f.low, f.high) == pytest.approx((1.0, 1.0), abs=1e-9)
    assert f.predict(1 << 20, {"cells": 100, "refs": 200}) == pytest.approx(1e-7 + 2e-6 + 1e-6, rel=1e-9)
    raw = cost.CountFit.fit(rows, ("1", "cells", "refs"), reference={})  # format 2: stated at zero counts
    assert raw.refs == () and raw.coef == pytest.approx((1e-7, 2e-8, 5e-9), rel=1e-9)
    assert raw.predict(1 << 20, {"cells": 100, "refs": 200}) == pytest.approx(1e-7 + 2e-6 + 1e-6, rel=1e-9)
    t = cost.terms(1 << 10, {"cells": 3, "refs": 4, "hit": 0.25, "length": 0.5})
    assert (t["log2n"], t["hit_log2n"], t["length_log2n"]) == (10.0, 2.5, 5.0)


def test_log_count_fit_recovers_an_exact_power_law_and_predicts_it():
    """form 'log': t = exp(c0) (1 + cells)^c1 (1 + refs)^c2 is fitted exactly on data that
    follow it, and predicts it on counts it never saw."""
    law = lambda c, f: 3e-7 * (1 + c) ** 0.6 * (1 + f) ** 0.25  # noqa: E731
    rows = [(1 << n, {"cells": c, "refs": f, "hit": 0.5, "length": 0.2}, law(c, f))
            for n, c, f in ((10, 10, 20), (12, 30, 10), (14, 5, 50), (16, 40, 40), (18, 12, 7))]
    f = cost.CountFit.fit(rows, ("1", "cells", "refs"), form="log")
    assert f.form == "log"
    # the scale is the time per ray at the reference, 15 cells (1 + cells = 16) and 0 refs
    assert f.coef == pytest.approx((math.log(3e-7 * 16 ** 0.6), 0.6, 0.25), rel=1e-9)
    assert (f.low, f.high) == pytest.approx((1.0, 1.0), abs=1e-9)
    assert f.predict(1 << 20, {"cells": 99, "refs": 15}) == pytest.approx(3e-7 * 100 ** 0.6 * 16 ** 0.25, rel=1e-9)
    assert f.formula() == f"{3e-7 * 16 ** 0.6 * 1e9:.2f} ns x ((1 + cells) / 16)^0.600 x (1 + refs)^0.250"
    raw = cost.CountFit.fit(rows, ("1", "cells", "refs"), form="log", reference={})
    assert raw.coef == pytest.approx((math.log(3e-7), 0.6, 0.25), rel=1e-9)
    assert raw.formula() == "300.00 ns x (1 + cells)^0.600 x (1 + refs)^0.250"
    with pytest.raises(ValueError, match="form"):
        cost.CountFit.fit(rows, ("1", "cells"), form="cubic")
    with pytest.raises(ValueError, match="'1'"):
        cost.CountFit.fit(rows, ("cells",), form="log")


def test_log_count_fit_keeps_every_term_where_the_linear_fit_drops_one():
    """The linear fit's sign constraint drops a term whose slope would be negative (and may keep
    it on the next calibration's timings); the log fit keeps the term set fixed."""
    rows = [(1 << 10, {"cells": c, "refs": 0.0, "hit": 0.0, "length": 0.0}, t)
            for c, t in ((1.0, 3.0), (2.0, 2.0), (3.0, 1.0))]
    lin = cost.CountFit.fit(rows, ("1", "cells"))
    log = cost.CountFit.fit(rows, ("1", "cells"), form="log")
    assert lin.coef[1] == 0.0 and log.coef[1] < 0


def test_power_model_recovers_exact_exponents_and_estimates_on_exact_numbers():
    recs = [SceneRecord(f"s{n}", 1 << n, 1000, {"bvh": Measurement(2e-8 * cost.nlog2n(1 << n) ** 1.1,
                                                                   1000 * 1e-7 * n ** 0.8, 1000)})
            for n in (8, 11, 14, 17, 20)]
    f = cost.fit(recs, ("bvh",), model="power")["bvh"]
    # c_B, c_R: the build and the time per ray of a 65,536-triangle scene (N log2 N = 2^20, log2 N = 16)
    assert (f.c_B, f.extra["p_B"], f.c_R, f.extra["p_R"]) == pytest.approx((2e-8 * 2.0 ** 22, 1.1, 1e-7 * 16 ** 0.8, 0.8), rel=1e-9)
    assert cost.fit_constants(f, "power") == pytest.approx(
        {"build at N_REF": 2e-8 * 2.0 ** 22, "p_B": 1.1, "per ray at N_REF": 1e-7 * 16 ** 0.8, "p_R": 0.8}, rel=1e-9)
    e = cost.MODELS["power"][1](f, "bvh", 1 << 16)  # N log2 N = 1,048,576, log2 N = 16
    assert (e.build_time, e.per_ray) == pytest.approx((2e-8 * 1048576 ** 1.1, 1e-7 * 16 ** 0.8), rel=1e-9)
    assert e.build_low <= e.build_time <= e.build_high


def test_power_model_on_close_sizes_is_the_affine_fit():
    """Sizes within a decade of N log2 N cannot measure an exponent: the power model's build
    is the affine least squares there (exact on affine data), p_B = 1."""
    recs = [SceneRecord(f"s{n}", n, 1000, {"bvh": Measurement(1e-3 + 2e-8 * cost.nlog2n(n), 1000 * 1e-7 * math.log2(n) ** 0.8, 1000)})
            for n in (500, 600, 700, 850, 1000)]
    f = cost.fit(recs, ("bvh",), model="power")["bvh"]
    assert (f.extra["a_B"], f.c_B, f.extra["p_B"]) == pytest.approx((1e-3, 2e-8 * 2.0 ** 20, 1.0), rel=1e-6)
    e = cost.MODELS["power"][1](f, "bvh", 20000)
    assert e.build_time == pytest.approx(1e-3 + 2e-8 * cost.nlog2n(20000), rel=1e-6)


def _lawful_records(ns=(1000, 4000, 16000, 64000, 256000)):
    """Calibration records that follow exact power laws: grid 1e-7 N^0.25 s a ray, the BVH
    gaining half of that, its build 5e-8 (N log2 N)^1.05."""
    return [SceneRecord(f"s{n}", n, 1000, {"grid": Measurement(1e-3, 1000 * 1e-7 * n ** 0.25, 1000),
                                             "bvh": Measurement(5e-8 * cost.nlog2n(n) ** 1.05, 1000 * 0.5e-7 * n ** 0.25, 1000)})
            for n in ns]


def test_prior_floor_is_the_margin_times_lowest_build_over_largest_gain_on_exact_laws():
    n = 30000
    p = cost.prior(_lawful_records(), n, ("bvh",))
    gain = 0.5e-7 * n ** 0.25
    assert p.grid_per_ray == pytest.approx(1e-7 * n ** 0.25, rel=1e-9)
    assert p.per_ray["bvh"] == pytest.approx(p.grid_per_ray - gain, rel=1e-9)
    assert p.floor == pytest.approx(cost.FLOOR_MARGIN * 5e-8 * cost.nlog2n(n) ** 1.05 / gain, rel=1e-9)
    # the floor lies below the true break-even of a scene on the laws, by the margin
    assert p.floor == pytest.approx(cost.FLOOR_MARGIN * cost.break_even(5e-8 * cost.nlog2n(n) ** 1.05, 2 * gain, gain), rel=1e-9)
    assert cost.prior(_lawful_records()[:2], n, ("bvh",)).floor == 0.0  # two scenes bound nothing
    assert cost.prior(_lawful_records(), n, ("bvh", "embree")).floor == 0.0  # embree was not measured


def test_a_plan_below_the_floor_keeps_the_grid_without_a_sample_and_samples_above_it():
    from hybrid_raycast.core import plan, scenes as S
    from hybrid_raycast.core.plan import NO_SAMPLE_DEAR, NO_SAMPLE_FLOOR

    recs = _lawful_records()
    cal = Calibration(cost.fit(recs, ("bvh",), model="power"), scenes=recs, model="power", source="hand")
    mesh = S.torus(3000)
    floor = cal.break_even_floor(mesh.triangle_count, ("bvh",))
    assert floor > 100
    below = plan(mesh, floor * 0.9, cal, kinds=("grid", "bvh"), samples=2000)
    assert (below.samples, below.decision, below.break_even_floor) == (0, "GRID", floor)
    assert below.break_even >= floor / cost.FLOOR_MARGIN * (1 - 1e-9)
    # above the floor, while a sample would cost more than SAMPLE_COST_SHARE of the rays' trace
    # (this calibration times no small batches: a sample's rays cost what the workload's do),
    # the calibration's estimates for N decide
    dear = plan(mesh, floor * 1.1, cal, kinds=("grid", "bvh"), samples=2000)
    assert floor * 1.1 < SAMPLE_MIN / SAMPLE_COST_SHARE and dear.samples == 0 and dear.grid_built
    assert dear.no_sample == NO_SAMPLE_DEAR and below.no_sample == NO_SAMPLE_FLOOR and dear.to_dict()["no_sample"]
    assert "would cost more than 10% of their trace" in " ".join(dear.notes)
    assert dear.grid_per_ray == pytest.approx(cal.grid_estimate(mesh.triangle_count).per_ray_low)
    r = SAMPLE_MIN / SAMPLE_COST_SHARE * 1.01
    above = plan(mesh, r, cal, kinds=("grid", "bvh"), samples=2000, grid=dear.grid)  # a grid built: nothing settles
    assert above.samples == sample_count(2000, r) == SAMPLE_MIN  # the sample is cut to a share of the rays
    assert above.no_sample == ""
    assert plan(mesh, floor * 0.9, cal, kinds=("grid", "bvh"), samples=2000, prior=False).samples == SAMPLE_MIN


def test_a_plans_sample_is_at_most_a_share_of_its_rays_and_never_below_its_least():
    assert sample_count(16384, 1e6) == 16384 and sample_count(16384, 1e8) == 16384
    assert sample_count(16384, 100_000) == int(SAMPLE_SHARE * 100_000) < 16384
    assert sample_count(16384, 3_000) == SAMPLE_MIN == 1024 and sample_count(200, 3_000) == 200


def test_the_evaluated_hybrid_pays_no_estimate_below_the_floor():
    s = ev.SceneResult("x", 1000, 10, cost.Cost.point("grid", 0.01, 1e-6), costs_of(bvh=(0.02, 1e-7)), costs_of(bvh=(0.02, 1e-7)),
                       1e-6, 0.005, 100, floor=500.0)
    t = ev.hybrid_totals(s, [400.0, 600.0])
    assert t["hybrid"].tolist() == pytest.approx([0.01 + 400e-6, 0.01 + 0.005 + 600e-6])
    assert list(t["choice"]) == ["grid", "grid"]


def test_prior_ceiling_bounds_the_rays_from_which_building_the_candidate_beats_building_the_grid():
    """R_0 = (T_B^H - T_B^G) / (t_G - t_H) per scene, over N: the largest, times N and the margin."""
    n = 30000
    recs = _lawful_records()  # the BVH builds dearer than the grid's 1 ms from 4,000 triangles on
    p = cost.prior(recs, n, ("bvh",))
    r0 = [max(5e-8 * cost.nlog2n(m) ** 1.05 - 1e-3, 0.0) / (0.5e-7 * m ** 0.25) / m for m in (1000, 4000, 16000, 64000, 256000)]
    assert p.ceiling["bvh"] == pytest.approx(cost.CEILING_MARGIN * max(r0) * n, rel=1e-9)
    assert p.gain_low["bvh"] == pytest.approx(0.5e-7 * n ** 0.25, rel=1e-9)
    # a scene on the laws pays back the BVH's build over the grid's within the ceiling
    assert cost.break_even(5e-8 * cost.nlog2n(n) ** 1.05 - 1e-3, 2 * p.gain_low["bvh"], p.gain_low["bvh"]) < p.ceiling["bvh"]
    # one scene where the candidate is slower per ray than the grid: no ceiling against it
    slow = recs[:-1] + [SceneRecord("slow", 256000, 1000, {"grid": Measurement(1e-3, 1e-4, 1000),
                                                          "bvh": Measurement(1.0, 2e-4, 1000)})]
    assert "bvh" not in cost.prior(slow, n, ("bvh",)).ceiling
    assert cost.prior(recs[:2], n, ("bvh",)).ceiling == {}  # two scenes bound nothing
    # a candidate that builds faster than the grid on every scene: a ceiling of 0 (any rays)
    fast = [SceneRecord(r.name, r.triangles, 1000, {"grid": Measurement(1.0, r.kinds["grid"].trace_time, 1000),
                                                    "bvh": r.kinds["bvh"]}) for r in recs]
    assert cost.prior(fast, n, ("bvh",)).ceiling["bvh"] == 0.0


def test_a_plan_above_the_ceiling_builds_no_grid_and_takes_the_candidate():
    from hybrid_raycast.core import plan, scenes as S

    recs = _lawful_records()
    cal = Calibration(cost.fit(recs, ("bvh",), model="power"), scenes=recs, model="power", source="hand")
    mesh = _soup_of(S.torus(3000))  # not a surface: only the ceiling settles (see the next test)
    n = mesh.triangle_count
    # the bound: the rays from which building the BVH beats building the grid on the
    # calibration's estimates for N (the grid's at their low end), under the ceiling over its scenes
    ceiling = rule.settle_bound(cal.grid_estimate(n), cal.estimate("bvh", n), cal.prior(n, ("bvh",)).ceiling["bvh"])
    grid = cal.grid_estimate(n)
    assert 0 < ceiling == pytest.approx((cal.estimate("bvh", n).build_time - grid.build_low)
                                        / (grid.per_ray_low - cal.estimate("bvh", n).per_ray))
    assert ceiling < cal.prior(n, ("bvh",)).ceiling["bvh"]
    above = plan(mesh, ceiling * 1.1, cal, kinds=("grid", "bvh"), samples=2000)
    assert (above.grid_built, above.grid, above.samples, above.decision) == (False, None, 0, "BVH")
    assert above.break_even_ceiling == pytest.approx(ceiling) and above.break_even_high == pytest.approx(ceiling)
    assert above.break_even_low <= above.break_even <= above.break_even_high
    d = above.to_dict()
    assert d["grid_built"] is False and d["break_even_ceiling"] == pytest.approx(ceiling)
    assert "no grid built" in above.summary() and "bvh beats building the grid" in above.summary()
    from hybrid_raycast.core.rays import uniform_rays

    hits = above.trace(*uniform_rays(mesh, 500, seed=1)[:2])  # it builds its BVH and traces
    assert above.executed[0]["kind"] == "bvh" and hits.hit.any()
    below = plan(mesh, ceiling * 0.9, cal, kinds=("grid", "bvh"), samples=2000)
    assert below.grid_built and below.grid is not None and below.samples == 0  # too few rays for a sample: the estimates for N decide
    assert plan(mesh, ceiling * 1.1, cal, kinds=("grid", "bvh"), samples=2000, prior=False).grid_built


def _soup_of(mesh):
    """The same triangles with three vertices of their own each: not a surface."""
    from hybrid_raycast.core import TriangleMesh

    return TriangleMesh(mesh.tri_vertices.reshape(-1, 3), np.arange(3 * mesh.triangle_count).reshape(-1, 3))


def test_a_plan_for_a_surface_builds_the_structure_within_the_slack_of_the_grid_without_a_sample():
    """On a surface mesh a plan builds H at once from the rays where, on the calibration's
    estimates for N, building H costs at most SETTLE_SLACK more than building the grid
    (``rule.regret_bound``), below any ceiling; the same triangles as a soup are sampled."""
    from hybrid_raycast.core import plan, scenes as S

    recs = _lawful_records()
    cal = Calibration(cost.fit(recs, ("bvh",), model="power"), scenes=recs, model="power", source="hand")
    mesh = S.torus(3000)
    n = mesh.triangle_count
    grid, bvh = cal.grid_estimate(n), cal.estimate("bvh", n)
    s = 1 + rule.SETTLE_SLACK
    bound = rule.regret_bound(grid, bvh)
    assert bound == pytest.approx((bvh.build_time - s * grid.build_time) / (s * grid.per_ray - bvh.per_ray))
    assert 0 < bound < rule.settle_bound(grid, bvh, cal.prior(n, ("bvh",)).ceiling["bvh"])
    assert rule.settle_bound(grid, bvh, None, surface=True) == pytest.approx(bound)
    assert rule.settle_bound(grid, bvh, None) == math.inf  # no ceiling and no surface: never without a sample
    # above the bound building the BVH costs at most the slack more than building the grid
    for r in (bound, 10 * bound, 1e9):
        assert bvh.build_time + r * bvh.per_ray <= s * (grid.build_time + r * grid.per_ray) * (1 + 1e-12)
    above = plan(mesh, bound * 1.1, cal, kinds=("grid", "bvh"), samples=2000)
    assert (above.grid_built, above.grid, above.samples, above.decision) == (False, None, 0, "BVH")
    assert above.settled_slack == rule.SETTLE_SLACK and above.break_even_ceiling == pytest.approx(bound)
    assert above.break_even_high == math.inf and above.break_even_low <= above.break_even
    assert above.to_dict()["settled_slack"] == rule.SETTLE_SLACK
    assert "at most 5% more than building the grid" in above.summary()
    assert any("a surface mesh" in note for note in above.notes)
    assert plan(mesh, bound * 0.9, cal, kinds=("grid", "bvh"), samples=2000).grid_built
    soup = plan(_soup_of(mesh), bound * 1.1, cal, kinds=("grid", "bvh"), samples=2000)
    assert soup.grid_built and soup.settled_slack == 0.0
    # no faster per ray than (1 + slack) t_G: never within the slack
    assert rule.regret_bound(grid, cost.Cost.point("bvh", bvh.build_time, s * grid.per_ray)) == math.inf


def test_the_evaluated_hybrid_builds_no_grid_above_the_ceiling():
    s = ev.SceneResult("x", 1000, 10, cost.Cost.point("grid", 0.01, 1e-6), costs_of(bvh=(0.02, 1e-7)), costs_of(bvh=(0.02, 1e-7)),
                       1e-6, 0.005, 100, ceiling={"bvh": 1e5}, prior_estimated=costs_of(bvh=(0.03, 2e-7)))
    t = ev.hybrid_totals(s, [5e4, 2e5], kinds=("bvh",))
    assert t["hybrid"].tolist() == pytest.approx([0.01 + 0.005 + 0.02 + 5e4 * 1e-7, 0.02 + 2e5 * 1e-7])
    assert t["settled"].tolist() == [False, True] and list(t["choice"]) == ["bvh", "bvh"]
    again = ev.SceneResult.from_dict(s.to_dict())
    assert again.prior_estimated["bvh"].per_ray == 2e-7 and again.ceiling == {"bvh": 1e5}


def test_nonneg_fit_drops_a_term_that_would_be_negative():
    x = np.array([[1, 1.0], [1, 2.0], [1, 3.0]])
    y = np.array([3.0, 2.0, 1.0])  # falling with x: the slope would be negative
    b = cost.nonneg_relative_lsq(x, y)
    assert b[1] == 0.0 and b[0] > 0


def test_a_plan_with_a_count_model_repeats_exactly_and_uses_the_counts():
    from hybrid_raycast.core import plan, scenes as S

    cal = Calibration({"bvh": KindFit(1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1)}, source="hand",
                      counts={"grid": cost.CountFit(("1", "cells", "refs"), (1e-7, 3e-8, 2e-8), 0.8, 1.25, 5),
                              "bvh": cost.CountFit(("1", "log2n"), (2e-7, 1e-7), 0.9, 1.1, 5)})
    mesh = S.torus(3000)
    plans = [plan(mesh, 1e6, cal, samples=2000, seed=3) for _ in range(5)]
    w = plans[0].work
    g = 1e-7 + 3e-8 * w["cells"] + 2e-8 * w["refs"]
    assert plans[0].grid_per_ray == pytest.approx(g, rel=1e-12)
    assert plans[0].candidates["grid"].per_ray_low == pytest.approx(0.8 * g, rel=1e-12)
    assert plans[0].candidates["bvh"].per_ray == pytest.approx(2e-7 + 1e-7 * math.log2(mesh.triangle_count), rel=1e-12)
    assert len({p.break_even for p in plans}) == 1 and len({p.grid_per_ray for p in plans}) == 1
    assert plans[0].to_dict()["work"] == w
    # the plan names the counts its grid model weighed (the sidebar quotes only those)
    assert plans[0].grid_terms == ("cells", "refs") and plans[0].to_dict()["grid_terms"] == ["cells", "refs"]
    assert "its count model weighs cells, refs" in " ".join(plans[0].notes)
    timed = plan(mesh, 1e6, Calibration(cal.fits, source="hand"), samples=2000, seed=3)
    assert timed.work is None and timed.grid_terms == ()


def test_five_plans_with_fresh_seeds_agree_within_the_goal_on_quasi_random_samples():
    """Issue 14: five plan() runs of one scene give break-evens within max / min 1.2.  With
    the shipped calibration a plan's break-even depends only on its sample's counts, so the
    spread is the sample's.  On this terrain five plans on K = 4,096 independent uniform
    rays spread by 1.34; the default K of quasi-random rays by about 1.08."""
    from hybrid_raycast.core import plan, scenes as S
    from hybrid_raycast.core.decide import load_default
    from hybrid_raycast.core.decide.work import DEFAULT_SAMPLES

    cal, mesh = load_default(), S.make_scene("terrain", 5000, seed=1)
    first = plan(mesh, 1e6, cal, kinds=("grid", "bvh"), seed=0, prior=False)
    assert first.samples == DEFAULT_SAMPLES and any("quasi-random" in n for n in first.notes)
    be = [first.break_even] + [plan(mesh, 1e6, cal, kinds=("grid", "bvh"), grid=first.grid, seed=s).break_even
                               for s in range(1, 5)]
    assert all(math.isfinite(b) for b in be) and len(set(be)) == 5, be
    assert max(be) / min(be) <= 1.2, be


def test_a_plan_counts_references_only_when_a_count_model_weighs_them():
    from hybrid_raycast.core import plan, scenes as S

    mesh = S.torus(3000)
    cells_only = Calibration({"bvh": KindFit(1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1)}, source="hand",
                             counts={"grid": cost.CountFit(("1", "cells"), (1e-7, 3e-8), 0.8, 1.25, 5)})
    p = plan(mesh, 1e6, cells_only, samples=2000, seed=3)
    assert p.work["refs"] is None and p.work["cells"] > 0
    assert p.grid_per_ray == pytest.approx(1e-7 + 3e-8 * p.work["cells"], rel=1e-12)
    # a model that weighs references but is handed counts without them says so by name
    with pytest.raises(ValueError, match="refs"):
        cost.CountFit(("1", "refs"), (1e-7, 3e-8), 0.8, 1.25, 5).predict(3000, p.work)


def test_count_model_survives_save_and_load(tmp_path):
    from hybrid_raycast.core.decide import load

    cal = Calibration({"bvh": KindFit(1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1)}, source="hand",
                      counts={"grid": cost.CountFit(("1", "cells"), (1e-7, 3e-8), 0.8, 1.25, 5),
                              "bvh": cost.CountFit(("1", "log2n"), (-15.0, 0.5), 0.9, 1.1, 5, form="log")})
    back = load(cal.save(tmp_path / "c.json"))
    assert back.counts["bvh"].predict(1 << 12, {}) == pytest.approx(math.exp(-15.0) * 13 ** 0.5, rel=1e-12)
    assert back.counts == cal.counts


def test_a_plan_says_which_candidates_are_missing_and_why(monkeypatch):
    from hybrid_raycast.core import embree, plan, scenes as S

    monkeypatch.setattr(embree, "embree_available", lambda: False)
    cal = Calibration({"embree": KindFit(1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1)}, source="hand")
    p = plan(S.torus(500), 1e6, cal, samples=200)
    assert set(p.candidates) == {"grid"}
    assert set(p.unavailable) == {"bvh", "embree"}
    assert "no calibration constants" in p.unavailable["bvh"] and p.unavailable["embree"]
    assert p.to_dict()["unavailable"] == p.unavailable


def test_the_break_even_and_the_rule_each_have_one_home():
    """One home per concept: the break-even formula is defined only in core/decide/cost.py,
    the decision rule only in core/decide/rule.py, and the old alias modules are gone."""
    import ast
    import importlib.util

    root = Path(cost.__file__).resolve().parents[2]
    homes = {}
    files = sorted(root.glob("*.py")) + [p for d in ("core", "operators", "ui", "scripts") for p in sorted((root / d).rglob("*.py"))]
    for p in files:
        for node in ast.walk(ast.parse(p.read_text(), str(p))):
            if isinstance(node, ast.FunctionDef) and node.name in ("break_even", "choose"):
                homes.setdefault(node.name, []).append(str(p.relative_to(root)))
    assert homes == {"break_even": ["core/decide/cost.py"], "choose": ["core/decide/rule.py"]}, homes
    for alias in ("calibration", "report"):
        assert importlib.util.find_spec(f"{cost.__package__.rsplit('.', 1)[0]}.{alias}") is None, alias


# -- the 'terms' build model and the constants' reference sizes (issue 14) ---------------------

def _terms_law(n):
    """A build that is exactly 15 ms (a 1,024-triangle scene's fixed cost) + 4 ms per doubling
    beyond it + 120 ms per 65,536 triangles + 15 ms per 65,536 triangles and doubling beyond
    65,536: the 'terms' model's form."""
    lg = math.log2(n)
    return 0.015 + 0.004 * (lg - 10) + 0.12 * n / 65536 + 0.015 * n / 65536 * (lg - 16)


def _terms_records(ns=(500, 2000, 8000, 30000, 120000, 500000, 1000000)):
    return [SceneRecord(f"s{n}", n, 1000, {"bvh": Measurement(_terms_law(n), 1000 * 1e-7 * math.log2(n) ** 0.8, 1000)})
            for n in ns]


def test_terms_model_recovers_exact_constants_and_estimates_the_formula():
    """On builds that follow a + d (log2 N - 10) + b N/65,536 + c (N/65,536)(log2 N - 16) exactly,
    the fit returns (a, d, b, c), c_B is the build at 65,536 triangles (a + 6 d + b), and the
    estimate for any N at or above the smallest scene is the formula."""
    f = cost.fit(_terms_records(), ("bvh",), model="terms")["bvh"]
    assert f.extra["terms_B"] == ["1", "log2n-10", "n", "n(log2n-16)"]
    assert f.extra["coef_B"] == pytest.approx([0.015, 0.004, 0.12, 0.015], rel=1e-9)
    assert f.c_B == pytest.approx(0.159, rel=1e-9) and f.extra["n_min"] == 500
    assert (f.c_B_low, f.c_B_high) == pytest.approx((0.159, 0.159), rel=1e-9)  # no scatter: no interval
    est = cost.MODELS["terms"][1]
    for n in (500, 12345, 65536, 3_000_000):
        assert est(f, "bvh", n).build_time == pytest.approx(_terms_law(n), rel=1e-9)
    # 65,536 triangles by hand: log2 N - 10 = 6, N / 65,536 = 1, log2 N - 16 = 0
    assert est(f, "bvh", 65536).build_time == pytest.approx(0.015 + 6 * 0.004 + 0.12, rel=1e-12)
    # per ray: the power model's, stated at log2 N = 16
    assert (f.c_R, f.extra["p_R"]) == pytest.approx((1e-7 * 16 ** 0.8, 0.8), rel=1e-9)
    assert est(f, "bvh", 1 << 12).per_ray == pytest.approx(1e-7 * 12 ** 0.8, rel=1e-9)
    # the constants are the builds at the anchor sizes, by hand: at 1,024 triangles
    # log2 N - 10 = 0, n = 1/64, log2 N - 16 = -6; at 1,048,576 they are 10, 16 and 4
    anchors = {f"build at {n:,}": _terms_law(n) for n in cost.BUILD_ANCHORS}
    assert anchors["build at 1,024"] == pytest.approx(0.015 + 0.12 / 64 - 0.015 * 6 / 64, rel=1e-12)
    assert anchors["build at 1,048,576"] == pytest.approx(0.015 + 0.04 + 0.12 * 16 + 0.015 * 16 * 4, rel=1e-12)
    assert cost.fit_constants(f, "terms") == pytest.approx(
        {**anchors, "per ray at N_REF": 1e-7 * 16 ** 0.8, "p_R": 0.8}, rel=1e-9)
    assert cost.fit_constants(f, "terms", per_ray=False) == pytest.approx(anchors, rel=1e-9)
    # the file's coefficients, for a report that shows how the fit trades them
    assert cost.fit_coefficients(f, "terms") == pytest.approx(
        {"build 1": 0.015, "build log2n-10": 0.004, "build n": 0.12, "build n(log2n-16)": 0.015}, rel=1e-9)


def test_build_anchors_determine_the_terms_model():
    """Four builds at BUILD_ANCHORS are the 'terms' model: its four regressors at the four
    sizes form an invertible matrix, so stating the times there loses nothing."""
    x = np.array([[cost.build_terms(n)[t] for t in cost.BUILD_TERMS["bvh"]] for n in cost.BUILD_ANCHORS])
    assert len(cost.BUILD_ANCHORS) == len(cost.BUILD_TERMS["bvh"])
    assert abs(np.linalg.det(x)) > 1e-6
    coef = np.linalg.solve(x, [_terms_law(n) for n in cost.BUILD_ANCHORS])
    assert coef == pytest.approx([0.015, 0.004, 0.12, 0.015], rel=1e-9)


def test_terms_model_estimates_a_scene_below_the_calibration_as_the_smallest_scene():
    """Below the smallest calibration scene the per-level term is not measured (here it would
    make a 2-triangle build 15 - 4 x 9 = -21 ms): such a scene costs the smallest scene's build."""
    f = cost.fit(_terms_records(), ("bvh",), model="terms")["bvh"]
    assert _terms_law(2) < 0
    assert cost.MODELS["terms"][1](f, "bvh", 2).build_time == pytest.approx(_terms_law(500), rel=1e-9)


def test_terms_model_with_too_few_scenes_or_sizes_is_the_power_model():
    """Four terms need five scenes, and sizes from the fixed-cost regime to the large one (a
    ratio of TERMS_MIN_RATIO = 100): 'quick' (1k-60k) and 'tiny' (500-1k) get the power model."""
    for ns in ((1000, 30000, 1000000), (1000, 2000, 8000, 30000, 60000), (500, 600, 700, 850, 1000)):
        recs = _terms_records(ns)
        assert cost.fit(recs, ("bvh",), model="terms")["bvh"] == cost.fit(recs, ("bvh",), model="power")["bvh"], ns
    assert "coef_B" in cost.fit(_terms_records((500, 2000, 8000, 30000, 50000)), ("bvh",), model="terms")["bvh"].extra


def test_terms_model_spread_brackets_measured_over_fitted():
    """The interval is the 10th/90th percentile of measured / fitted over the scenes, applied to
    every N as a ratio of the build."""
    recs = _terms_records()
    for r, q in zip(recs, (1.3, 0.8, 1.0, 1.0, 1.0, 1.0, 1.0)):
        r.kinds["bvh"].build_time *= q
    f = cost.fit(recs, ("bvh",), model="terms")["bvh"]
    e = cost.MODELS["terms"][1](f, "bvh", 200000)
    assert e.build_low < e.build_time < e.build_high
    assert e.build_low / e.build_time == pytest.approx(f.c_B_low / f.c_B, rel=1e-12)


# -- Embree's build: ln T_B = a + b u + c u^2, u = ln(N / N_REF) -----------------------------

def _logquad_law(n, a=math.log(0.017), b=0.92, c=0.066):
    """A build that is exactly exp(a + b u + c u^2) with u = ln(N / 65,536): 17 ms at 65,536
    triangles, exponent 0.92 there, growing by 2c per e-fold of N (Embree's shape)."""
    u = math.log(n / 65536)
    return math.exp(a + b * u + c * u * u)


def _logquad_records(law=_logquad_law, ns=(500, 2000, 8000, 30000, 120000, 500000, 1000000)):
    return [SceneRecord(f"s{n}", n, 1000, {"embree": Measurement(law(n), 1000 * 1e-8 * math.log2(n) ** 1.5, 1000)})
            for n in ns]


def test_log_quadratic_build_recovers_exact_constants_and_estimates_the_formula():
    """On builds that are exactly exp(a + b u + c u^2), Embree's 'terms' fit (BUILD_FORMS says
    'log-quadratic') returns (a, b, c) centred at N_REF, c_B = exp(a) is the build at 65,536
    triangles, no interval without scatter, and the estimate at any N in the fitted range is the
    formula; the constants are the builds at BUILD_ANCHORS and the coefficients exp(a), b, c."""
    assert cost.BUILD_FORMS["embree"] == "log-quadratic"
    f = cost.fit(_logquad_records(), ("embree",), model="terms")["embree"]
    assert f.extra["form_B"] == "log-quadratic"
    assert f.extra["coef_B"] == pytest.approx([math.log(0.017), 0.92, 0.066], rel=1e-9)
    assert (f.extra["n_min"], f.extra["n_max"]) == (500, 1000000)
    assert (f.c_B, f.c_B_low, f.c_B_high) == pytest.approx((0.017, 0.017, 0.017), rel=1e-9)
    est = cost.MODELS["terms"][1]
    for n in (500, 777, 12345, 65536, 400000, 1000000):
        assert est(f, "embree", n).build_time == pytest.approx(_logquad_law(n), rel=1e-9)
    # 262,144 = 4 x 65,536 by hand: u = ln 4, T = 0.017 x 4^0.92 x exp(0.066 (ln 4)^2)
    assert est(f, "embree", 262144).build_time == pytest.approx(0.017 * 4 ** 0.92 * math.exp(0.066 * math.log(4) ** 2), rel=1e-9)
    # per ray: the power model's, stated at log2 N = 16
    assert (f.c_R, f.extra["p_R"]) == pytest.approx((1e-8 * 16 ** 1.5, 1.5), rel=1e-9)
    # 1,048,576 lies above the largest scene: the slope there carries on (tested below), so the
    # anchors are checked on the estimate, the ones inside the range on the formula too
    anchors = {f"build at {n:,}": est(f, "embree", n).build_time for n in cost.BUILD_ANCHORS}
    assert anchors["build at 16,384"] == pytest.approx(_logquad_law(16384), rel=1e-9)
    assert cost.fit_constants(f, "terms", per_ray=False) == pytest.approx(anchors, rel=1e-12)
    assert cost.fit_coefficients(f, "terms") == pytest.approx(
        {"build at N_REF": 0.017, "build exponent at N_REF": 0.92, "build curvature": 0.066}, rel=1e-9)
    assert "(N / 65,536)^(0.920 + 0.0660 u)" in cost.describe_fit(f, "terms")


def test_log_quadratic_build_is_the_parabola_in_log_space_with_scatter():
    """With scatter the fit is the least-squares parabola through (ln N, ln T_B): numpy.polyfit
    on the uncentred ln N as the independent reference predicts the same builds (centring at
    N_REF changes the constants, never a prediction), its curvature is the same, its other two
    constants are the centred ones moved to N = 1; the interval is the 10th/90th percentile of
    measured / fitted."""
    rng = np.random.default_rng(3)
    recs = _logquad_records()
    q = rng.uniform(0.8, 1.25, len(recs))
    for r, x in zip(recs, q):
        r.kinds["embree"].build_time *= x
    f = cost.fit(recs, ("embree",), model="terms")["embree"]
    ln_n = np.log([r.triangles for r in recs])
    y = np.log([r.kinds["embree"].build_time for r in recs])
    ref = np.polyfit(ln_n, y, 2)
    est = cost.MODELS["terms"][1]
    for n in (500, 7000, 65536, 300000, 1000000):
        assert est(f, "embree", n).build_time == pytest.approx(math.exp(np.polyval(ref, math.log(n))), rel=1e-9)
    a, b, c = f.extra["coef_B"]
    l0 = math.log(65536)
    assert (ref[0], ref[1], ref[2]) == pytest.approx((c, b - 2 * c * l0, a - b * l0 + c * l0 * l0), rel=1e-9)
    ratio = [r.kinds["embree"].build_time / math.exp(np.polyval(ref, v)) for r, v in zip(recs, ln_n)]
    lo, hi = np.percentile(ratio, (10, 90))
    assert f.c_B == pytest.approx(math.exp(a), rel=1e-9)
    assert (f.c_B_low, f.c_B_high) == pytest.approx((f.c_B * min(lo, 1), f.c_B * max(hi, 1)), rel=1e-9)


def test_log_quadratic_build_below_the_smallest_scene_is_the_smallest_scenes():
    f = cost.fit(_logquad_records(), ("embree",), model="terms")["embree"]
    assert cost.MODELS["terms"][1](f, "embree", 3).build_time == pytest.approx(_logquad_law(500), rel=1e-9)


def test_log_quadratic_build_never_falls_with_n_up_to_100m_triangles():
    """A parabola that turns inside the fitted range (c < 0: vertex at u = -b / 2c = ln 8, i.e.
    524,288 triangles) stays at its top beyond it; one whose minimum is inside the range (c > 0,
    vertex at 4,096 triangles) stays at its bottom below it; above the largest scene the build
    goes on with the parabola's slope there (here 0.9 + 2 x 0.03 x ln(1M / 65,536), by hand).
    Every estimate from 1 to 100M triangles is non-decreasing in N."""
    est = cost.MODELS["terms"][1]
    sizes = np.unique(np.geomspace(1, 1e8, 400).astype(np.int64))
    turning = lambda n: _logquad_law(n, b=0.5, c=-0.25 / math.log(8))  # noqa: E731
    rising_late = lambda n: _logquad_law(n, b=0.5, c=0.25 / math.log(16))  # noqa: E731
    for law in (turning, rising_late, _logquad_law):
        f = cost.fit(_logquad_records(law), ("embree",), model="terms")["embree"]
        b = [est(f, "embree", int(n)).build_time for n in sizes]
        assert all(x <= y * (1 + 1e-12) for x, y in zip(b, b[1:])), "the build estimate falls somewhere"
    f = cost.fit(_logquad_records(turning), ("embree",), model="terms")["embree"]
    top = turning(524288)
    assert [est(f, "embree", n).build_time for n in (524288, 1000000, 10 ** 8)] == pytest.approx([top] * 3, rel=1e-9)
    f = cost.fit(_logquad_records(rising_late), ("embree",), model="terms")["embree"]
    assert [est(f, "embree", n).build_time for n in (500, 2000, 4096)] == pytest.approx([rising_late(4096)] * 3, rel=1e-9)
    f = cost.fit(_logquad_records(), ("embree",), model="terms")["embree"]
    u_max = math.log(1000000 / 65536)
    slope = 0.92 + 2 * 0.066 * u_max
    for n in (2_000_000, 10 ** 8):
        want = _logquad_law(1000000) * (n / 1000000) ** slope
        assert est(f, "embree", n).build_time == pytest.approx(want, rel=1e-9)
        assert est(f, "embree", n).build_time < _logquad_law(n)  # the parabola itself would bend up faster


def test_an_unknown_build_form_is_an_error_even_for_a_structure_without_build_terms(monkeypatch):
    """A misspelt BUILD_FORMS entry stops the fit, also for a structure with no BUILD_TERMS
    (Embree), which would otherwise pass silently as the power model; a structure in neither
    table still gets the power model."""
    recs = _logquad_records()
    monkeypatch.setitem(cost.BUILD_FORMS, "embree", "log-quadratc")
    with pytest.raises(ValueError, match="unknown build form 'log-quadratc' for 'embree'"):
        cost.fit(recs, ("embree",), model="terms")
    monkeypatch.delitem(cost.BUILD_FORMS, "embree")
    f = cost.fit(recs, ("embree",), model="terms")["embree"]
    assert "coef_B" not in f.extra and "p_B" in f.extra


def test_log_quadratic_build_survives_save_and_load_and_old_files_estimate_as_before(tmp_path):
    """A calibration file round-trips the log-quadratic build (same estimates after load); a
    'terms' fit written before the form (no form_B: a sum of terms_B) still estimates its sum;
    an unknown form or a short coefficient list is a CalibrationError naming the structure."""
    from hybrid_raycast.core.decide import CalibrationError, load

    recs = _logquad_records()
    cal = Calibration(cost.fit(recs, ("embree",), model="terms"), scenes=recs, source="hand")
    back = load(cal.save(tmp_path / "c.json"))
    assert back.fits == cal.fits
    for n in (100, 5000, 65536, 3_000_000):
        assert back.estimate("embree", n).build_time == pytest.approx(cal.estimate("embree", n).build_time, rel=1e-12)
    assert back.refitted().fits["embree"].extra["coef_B"] == pytest.approx(cal.fits["embree"].extra["coef_B"], rel=1e-12)
    old = cost.KindFit(0.159, 1e-7, 0.159, 0.159, 1e-7, 1e-7, 7,
                       extra={"terms_B": ["1", "log2n-10", "n", "n(log2n-16)"], "coef_B": [0.015, 0.004, 0.12, 0.015],
                              "n_min": 500, "p_R": 1.0, "x_ref_R": 16.0})
    old_back = load(Calibration({"embree": old}, source="hand").save(tmp_path / "old.json"))
    assert old_back.estimate("embree", 65536).build_time == pytest.approx(0.015 + 6 * 0.004 + 0.12, rel=1e-12)
    for extra, what in (({"form_B": "cubic"}, "unknown build form 'cubic' of 'embree'"),
                        ({"coef_B": [1.0, 2.0]}, "three finite coefficients")):
        d = cal.to_dict()
        d["fits"]["embree"]["extra"].update(extra)
        with pytest.raises(CalibrationError, match=re.escape(what)):
            Calibration.from_dict(d)


def test_stating_constants_at_a_reference_changes_no_prediction():
    """Reparametrization: the power model with c at 65,536 triangles predicts what c x^p did
    (a format-2 file, no x_ref), and a count model stated at the reference counts predicts what
    the one stated at zero counts does, on counts neither saw."""
    f = cost.fit(_lawful_records(), ("bvh",), model="power")["bvh"]
    old = KindFit(f.c_B / cost.X_REF ** f.extra["p_B"], f.c_R / cost.L_REF ** f.extra["p_R"], 0, 0, 0, 0, 1,
                  extra={k: f.extra[k] for k in ("p_B", "p_R", "a_B", "a_R")})
    old.c_B_low = old.c_B_high = old.c_B
    old.c_R_low = old.c_R_high = old.c_R
    for n in (700, 30000, 2_000_000):
        a, b = cost.MODELS["power"][1](f, "bvh", n), cost.MODELS["power"][1](old, "bvh", n)
        assert (a.build_time, a.per_ray) == pytest.approx((b.build_time, b.per_ray), rel=1e-12)
    rng = np.random.default_rng(1)
    ns, cells, q = rng.integers(500, 10 ** 6, 12), rng.uniform(3, 60, 12), rng.uniform(0.8, 1.2, 12)
    # laws with noise that no model fits exactly: the grid's in cells, the BVH's in log2 N
    grid = [(int(n), {"cells": float(c)}, float(3e-7 * (1 + c) ** 0.4 * e)) for n, c, e in zip(ns, cells, q)]
    bvh = [(int(n), {"cells": float(c)}, float((5e-7 + 1e-7 * math.log2(n)) * e)) for n, c, e in zip(ns, cells, q)]
    for rows, names, form in ((grid, ("1", "cells"), "log"), (bvh, ("1", "log2n"), "linear")):
        new, raw = cost.CountFit.fit(rows, names, form=form), cost.CountFit.fit(rows, names, form=form, reference={})
        assert new.coef[1] > 0
        assert new.coef != pytest.approx(raw.coef)
        for n, w in ((800, {"cells": 2.0}), (5_000_000, {"cells": 200.0})):
            assert new.predict(n, w) == pytest.approx(raw.predict(n, w), rel=1e-12)
        assert (new.low, new.high) == pytest.approx((raw.low, raw.high), rel=1e-12)


def test_a_plan_and_a_calibration_keep_the_grid_traversal_counts_of_their_sample(tmp_path):
    """The plan's sample and the calibration's work sample carry what the traversal did
    (steps, candidate pairs, kernel tests per ray), equal to the grid's own counts of the
    same rays; a calibration file keeps them, and a count absent from a Work (None) is
    left out of the file's record instead of failing its load."""
    from hybrid_raycast.core import plan, quasi_uniform_rays, scenes as S
    from hybrid_raycast.core.decide import calfile
    from hybrid_raycast.core.decide.measurements import sample_work
    from hybrid_raycast.core.factory import build

    mesh = S.torus(3000)
    cal = Calibration({"bvh": KindFit(1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1)}, source="hand",
                      counts={"grid": cost.CountFit(("1", "cells"), (1e-7, 3e-8), 0.8, 1.25, 5)})
    grid = build(mesh, "grid", threads=1)
    p = plan(mesh, 1e6, cal, samples=2000, seed=3, grid=grid)
    done = grid.traversal_work()
    assert done["rays"] == 2000
    for k in ("steps", "candidates", "tests"):
        assert p.work[k] == pytest.approx(done[k] / 2000, rel=1e-12)
    assert 0 < p.work["tests"] < p.work["candidates"] and p.work["steps"] > 1
    assert any("traversal steps" in n for n in p.notes)
    w = sample_work(mesh, 1500, threads=1, seed=4)
    g2 = build(mesh, "grid", threads=1)
    o, d = quasi_uniform_rays(mesh, 1500, seed=4)  # the rays a plan samples
    g2.trace(o, d)
    assert w.steps == pytest.approx(g2.traversal_work()["steps"] / 1500, rel=1e-12)
    rec = SceneRecord("t", 3000, 1, {"bvh": Measurement(1e-3, 1e-3, 1)}, {}, {**w.to_dict(), "refs": None})
    back = calfile.load(Calibration(cal.fits, scenes=[rec], source="hand", counts=cal.counts).save(tmp_path / "c.json"),
                        check_version=False)
    assert back.scenes[0].work["tests"] == pytest.approx(w.tests) and "refs" not in back.scenes[0].work
    assert cost.terms(3000, back.scenes[0].work)["steps"] == pytest.approx(w.steps)


def test_interval_coverage_counts_the_scenes_whose_interval_holds_r_c_and_the_open_ones():
    def scene(lo, hi):  # R_C = 0.02 / (1e-6 - 1e-7) = 22,222
        return ev.SceneResult("x", 1000, 10, cost.Cost.point("grid", 0.01, 1e-6), costs_of(bvh=(0.02, 1e-7)),
                              costs_of(bvh=(0.02, 1e-7)), 1e-6, 0.005, 100,
                              extra={"break_even_low": lo, "break_even_high": hi})
    got = ev.interval_coverage([scene(10_000, 30_000), scene(10_000, None), scene(30_000, 40_000), scene(1, 2_000)])
    assert got == {"scenes": 4, "held": 2, "percent": 50.0, "never_above": 1}


def test_the_evaluated_hybrid_settles_where_the_plan_does_on_the_estimates_for_n():
    """With the calibration's grid estimate for N, the evaluation builds no grid from the same
    bound as ``plan._settled_without_grid`` (``rule.settle_bound``), below the ceiling."""
    grid_est = cost.Cost("grid", 0.012, 0.01, 0.014, 1.2e-6, 1e-6, 1.4e-6)
    s = ev.SceneResult("x", 1000, 10, cost.Cost.point("grid", 0.01, 1e-6), costs_of(bvh=(0.02, 1e-7)),
                       costs_of(bvh=(0.02, 1e-7)), 1e-6, 0.005, 100, ceiling={"bvh": 1e5},
                       prior_estimated={**costs_of(bvh=(0.03, 2e-7)), "grid": grid_est})
    bound = rule.settle_bound(grid_est, s.prior_estimated["bvh"], 1e5)
    assert bound == pytest.approx((0.03 - 0.01) / (1e-6 - 2e-7)) == pytest.approx(25_000)
    settled, pick = ev.settled_without_grid(s, [24_000, 26_000, 2e5])
    assert settled.tolist() == [False, True, True] and set(pick) == {"bvh"}
    assert rule.settle_bound(None, s.prior_estimated["bvh"], 1e5) == 1e5  # no grid estimate: the ceiling
    # a surface settles from the rays where the BVH comes within the slack of the grid, ceiling or not
    near = rule.regret_bound(grid_est, s.prior_estimated["bvh"])
    assert near == pytest.approx((0.03 - 1.05 * 0.012) / (1.05 * 1.2e-6 - 2e-7)) and near < bound
    flat = ev.SceneResult(**{**s.__dict__, "ceiling": {}, "surface": True})
    settled, _ = ev.settled_without_grid(flat, [near * 0.99, near * 1.01])
    assert settled.tolist() == [False, True]
    assert not ev.settled_without_grid(ev.SceneResult(**{**flat.__dict__, "surface": False}), [1e9])[0].any()


def test_a_surface_reads_the_spread_over_the_calibrations_surfaces(tmp_path):
    """The count models' interval for a surface mesh is the spread over the calibration scenes
    that are surfaces (``scenes.is_surface_scene``): soups, whose trees trace far slower than
    any count predicts, widen the spread over every scene but not that one.  A file without
    it gets it from its own records when loaded; a soup reads the whole spread."""
    from hybrid_raycast.core import scenes as S
    from hybrid_raycast.core.decide import load

    for gen in S.SCENES:
        assert S.is_surface_scene(f"{gen}-600") == S.make_scene(gen, 600).is_surface(), gen
    assert S.is_surface_scene("bunny") is None
    a, b = 3e-7, 4e-8
    names = ["sphere-1k", "torus-2k", "terrain-3k", "city-4k", "soup-1k", "slivers-2k"]
    recs = [SceneRecord(name, 1000 * (i + 1), 1000,
                        {"grid": Measurement(0.01, 1000 * (a + b * s) * (1.0 + 0.02 * i if S.is_surface_scene(name) else 3.0), 1000)},
                        work={"cells": 2.0 * s, "steps": float(s), "candidates": 10.0 + 3 * (i % 3)})
            for i, (name, s) in enumerate(zip(names, (4, 7, 9, 11, 5, 8)))]
    f = cost.fit_counts(recs, ("grid",))["grid"]
    assert f.high > 1.5 and f.surface_high < 1.1 and f.surface_low <= 1.0 <= f.surface_high
    assert f.spread_for(True) == (f.surface_low, f.surface_high) and f.spread_for(False) == (f.low, f.high)
    assert cost.surface_spread(f, recs[4:], "grid") == (None, None)  # fewer than 3 surfaces
    cal = Calibration({}, scenes=recs, counts={"grid": f})
    t, lo, hi = cal.count_per_ray("grid", 4000, recs[0].work, surface=True)
    assert (lo / t, hi / t) == pytest.approx((f.surface_low, f.surface_high))
    assert cal.count_per_ray("grid", 4000, recs[0].work)[2] / t == pytest.approx(f.high)
    assert "surfaces [" in cal.describe()
    # a file keeps the surfaces' spread; one made before it gets it from its own records
    import json

    cal = Calibration({"bvh": KindFit(1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1)}, scenes=recs, counts={"grid": f},
                      source="hand")
    path = cal.save(tmp_path / "c.json")
    assert load(path).counts["grid"] == f
    d = json.loads(path.read_text())
    for key in ("surface_low", "surface_high"):
        d["counts"]["grid"].pop(key)
    path.write_text(json.dumps(d))
    back = load(path).counts["grid"]
    assert (back.surface_low, back.surface_high) == pytest.approx((f.surface_low, f.surface_high), rel=1e-12)
