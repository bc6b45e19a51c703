"""The plan: break-even arithmetic on known numbers, the decision, the online switch, and a
small end-to-end plan whose trace equals brute force."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybrid_raycast.core import build, scenes
from hybrid_raycast.core.decide import Calibration, KindFit
from hybrid_raycast.core.hits import Hits
from hybrid_raycast.core.mesh import TriangleMesh
from hybrid_raycast.core.plan import plan, plan_from_timings, trace_online
from hybrid_raycast.core.rays import camera_rays, uniform_rays


def cal_of(**fits) -> Calibration:
    """A hand-made calibration: kind=(c_B, c_R) or kind=(c_B, c_R, c_B_low, c_B_high, c_R_low, c_R_high)."""
    out = {}
    for k, v in fits.items():
        b, r = v[0], v[1]
        lo_b, hi_b, lo_r, hi_r = v[2:] if len(v) == 6 else (b, b, r, r)
        out[k] = KindFit(b, r, lo_b, hi_b, lo_r, hi_r, 1)
    return Calibration(out, source="hand")


# N = 1024: log2 N = 10, N log2 N = 10240 (exact in binary)
N = 1024


# -- the arithmetic ---------------------------------------------------------------------------------

def test_break_even_is_build_over_per_ray_gain_exactly():
    cal = cal_of(bvh=(1e-7, 1e-7, 5e-8, 2e-7, 5e-8, 2e-7))
    p = plan_from_timings(N, 1000, cal, grid_build_time=0.01, grid_per_ray=3e-6, kinds=("grid", "bvh"))
    T_B, t_H = 1e-7 * N * 10, 1e-7 * 10
    assert p.candidates["bvh"].build_time == pytest.approx(T_B, rel=1e-15)
    assert p.candidates["bvh"].per_ray == pytest.approx(t_H, rel=1e-15)
    want = T_B / (3e-6 - t_H)
    assert p.break_even == pytest.approx(want, rel=1e-12), f"R* = T_B/(t_G - t_H) = {want}, plan says {p.break_even}"
    assert p.break_even_low == pytest.approx(5e-8 * N * 10 / (3e-6 - 5e-7), rel=1e-12)
    assert p.break_even_high == pytest.approx(2e-7 * N * 10 / (3e-6 - 2e-6), rel=1e-12)
    assert p.break_even_low <= p.break_even <= p.break_even_high
    assert p.break_even_kind == "bvh" and p.grid_build_time == 0.01 and p.grid_per_ray == 3e-6


def test_decision_flips_from_grid_to_bvh_exactly_at_the_break_even():
    cal = cal_of(bvh=(2.0 ** -20, 2.0 ** -22))  # T_B = 2**-20 * 10240, t_H = 10 * 2**-22
    t_g = 2.0 ** -16
    r_star = plan_from_timings(N, 1, cal, 0.0, t_g, kinds=("grid", "bvh")).break_even
    for r, want in ((r_star / 2, "GRID"), (math.floor(r_star), "GRID"), (r_star, "GRID"),
                    (math.floor(r_star) + 1, "BVH"), (10 * r_star, "BVH")):
        got = plan_from_timings(N, r, cal, 0.0, t_g, kinds=("grid", "bvh")).decision
        assert got == want, f"at R = {r} (R* = {r_star}) the plan chose {got}, expected {want}"


def test_a_grid_at_least_as_fast_per_ray_always_wins():
    cal = cal_of(bvh=(1e-7, 2.0 ** -20, 1e-7, 1e-7, 2.0 ** -22, 2.0 ** -18))
    t_g = 10 * 2.0 ** -20  # exactly the estimated t_H = c_R log2 N
    p = plan_from_timings(N, 1e12, cal, 0.5, t_g, kinds=("grid", "bvh"))
    assert math.isinf(p.break_even) and p.decision == "GRID", f"R* = {p.break_even}, chose {p.decision}"
    assert p.break_even_low == pytest.approx(1e-7 * N * 10 / (t_g - 10 * 2.0 ** -22))  # the fast end still breaks even
    assert math.isinf(p.break_even_high)
    d = p.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["break_even"] is None and d["break_even_high"] is None and d["break_even_low"] > 0


def test_with_two_candidates_the_grid_yields_to_the_first_and_the_cheapest_total_wins():
    # embree: cheaper to build, slower per ray; bvh: dearer to build, faster per ray
    cal = cal_of(bvh=(4e-7, 1e-8), embree=(1e-7, 2e-8))
    t_g = 1e-6
    p = plan_from_timings(N, 1, cal, 0.0, t_g)
    tb = {"bvh": 4e-7 * N * 10, "embree": 1e-7 * N * 10}
    th = {"bvh": 1e-7, "embree": 2e-7}
    rs = {k: tb[k] / (t_g - th[k]) for k in tb}
    assert p.break_even_kind == "embree" and p.break_even == pytest.approx(rs["embree"], rel=1e-12)
    # the totals cross where tb_e + R th_e = tb_b + R th_b
    cross = (tb["bvh"] - tb["embree"]) / (th["embree"] - th["bvh"])
    assert rs["embree"] < cross
    for r in (rs["embree"] * 0.99, rs["embree"] * 1.01, cross * 0.99, cross * 1.01):
        got = plan_from_timings(N, r, cal, 0.0, t_g).decision
        want = "GRID" if r <= rs["embree"] else ("EMBREE" if r < cross else "BVH")
        assert got == want, f"R = {r:.4g}: chose {got}, expected {want} (R*_embree {rs['embree']:.4g}, crossing {cross:.4g})"


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(1, 5_000_000),
    cb=st.tuples(*[st.floats(1e-9, 1e-5)] * 3), cr=st.tuples(*[st.floats(1e-9, 1e-5)] * 3),
    cb2=st.tuples(*[st.floats(1e-9, 1e-5)] * 3), cr2=st.tuples(*[st.floats(1e-9, 1e-5)] * 3),
    t_g=st.floats(1e-8, 1e-3), r=st.floats(1, 1e12),
)
def test_interval_is_ordered_and_the_decision_is_the_cheapest_total(n, cb, cr, cb2, cr2, t_g, r):
    def kf(b, c):
        b, c = sorted(b), sorted(c)
        return (b[1], c[1], b[0], b[2], c[0], c[2])

    cal = cal_of(bvh=kf(cb, cr), embree=kf(cb2, cr2))
    p = plan_from_timings(n, r, cal, 0.1, t_g)
    for c in [p.candidates["bvh"], p.candidates["embree"], p]:
        assert c.break_even_low <= c.break_even <= c.break_even_high, f"{c.break_even_low} <= {c.break_even} <= {c.break_even_high} fails"
    totals = {k: float(p.total_time(k, r)) for k in p.candidates}
    best = min(totals.values())
    assert totals[p.chosen] <= best * (1 + 1e-9), f"chose {p.decision} at {totals[p.chosen]}, cheapest is {min(totals, key=totals.get)} at {best}"


def test_total_time_is_sunk_grid_build_versus_build_plus_rays():
    cal = cal_of(bvh=(1e-7, 1e-7))
    p = plan_from_timings(N, 10, cal, 0.25, 4e-6, kinds=("grid", "bvh"))
    r = np.array([0.0, 1e3, 1e6])
    assert np.allclose(p.total_time("grid", r), 4e-6 * r)
    assert np.allclose(p.total_time("grid", r, include_grid_build=True), 0.25 + 4e-6 * r)
    assert np.allclose(p.total_time("bvh", r), 1e-7 * N * 10 + 1e-6 * r)


@pytest.mark.parametrize("bad", [0, -5, 0.0, float("nan"), float("inf"), "many", None])
def test_expected_rays_must_be_positive_and_finite(bad):
    with pytest.raises(ValueError, match="expected_rays must be a positive finite number|expected_rays must be a number"):
        plan_from_timings(N, bad, cal_of(bvh=(1e-7, 1e-7)), 0.0, 1e-6)


def test_uncalibrated_candidates_are_skipped_with_a_note():
    p = plan_from_timings(N, 1e9, cal_of(bvh=(1e-7, 1e-8)), 0.0, 1e-6, kinds=("grid", "bvh", "embree"))
    assert set(p.candidates) == {"grid", "bvh"} and p.decision == "BVH"
    assert any("embree skipped: no calibration constants" in n for n in p.notes), p.notes


def test_interval_straddling_the_budget_is_flagged_uncertain():
    cal = cal_of(bvh=(1e-7, 1e-7, 5e-8, 2e-7, 5e-8, 2e-7))
    p = plan_from_timings(N, 1, cal, 0.0, 3e-6, kinds=("grid", "bvh"))
    mid = plan_from_timings(N, p.break_even, cal, 0.0, 3e-6, kinds=("grid", "bvh"))
    assert p.certain and not mid.certain and any("uncertain" in n for n in mid.notes)


# -- the online switch (fake clock, fake structures) -------------------------------------------------

class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


class FakeAccel:
    """Costs ``per_ray`` fake seconds a ray; every hit names the structure (triangle = code)."""

    def __init__(self, clock, per_ray, code, build_cost=0.0, kind="fake"):
        self.clock, self.per_ray, self.code, self.kind = clock, per_ray, code, kind
        clock.now += build_cost
        self.build_time = build_cost

    def trace(self, origins, directions, tmin=0.0, tmax=np.inf):
        m = len(origins)
        self.clock.now += self.per_ray * m
        return Hits(np.ones(m, np.float32), np.full(m, self.code, np.int32), np.zeros(m, np.float32), np.zeros(m, np.float32))


TWO = TriangleMesh(np.eye(3), [[0, 1, 2], [2, 1, 0]])  # N = 2: N log2 N = 2, log2 N = 1


def run_online(build_estimate, m=100, batch=8, grid_per_ray=2.0 ** -10, c_R=2.0 ** -12, bvh_build=0.5):
    clock = FakeClock()
    grid = FakeAccel(clock, grid_per_ray, code=0)
    built = []

    def builder(mesh, kind, **cfg):
        built.append(kind)
        return FakeAccel(clock, 2.0 ** -12, code=1, build_cost=bvh_build, kind=kind)

    cal = cal_of(bvh=(build_estimate / 2, c_R))
    o = np.zeros((m, 3), np.float32)
    hits, rec = trace_online(TWO, o, o + 1, cal, grid=grid, batch=batch, clock=clock, builder=builder)
    return hits, rec, built, clock


def test_online_switches_exactly_when_grid_time_reaches_the_estimated_build():
    batch_cost = 8 * 2.0 ** -10
    hits, rec, built, clock = run_online(build_estimate=3 * batch_cost)
    assert rec.estimated_build_time == 3 * batch_cost
    assert rec.switched and rec.switch_ray == 24, f"accumulated grid time reaches 3 batches after 24 rays; switched at {rec.switch_ray}"
    assert built == ["bvh"], f"built {built}"
    assert (hits.triangle[:24] == 0).all() and (hits.triangle[24:] == 1).all(), "rays before the switch go to the grid, after it to the BVH"
    assert rec.grid_trace_time == 3 * batch_cost and rec.hds_build_time == 0.5
    assert rec.hds_trace_time == 76 * 2.0 ** -12 and rec.total_time == clock.now


def test_online_does_not_switch_a_batch_early():
    batch_cost = 8 * 2.0 ** -10
    _, rec, _, _ = run_online(build_estimate=3 * batch_cost + 2.0 ** -30)
    assert rec.switch_ray == 32, f"3 batches fall short of the estimate by a hair; expected the switch after 4 (32 rays), got {rec.switch_ray}"


def test_online_never_switches_when_the_rays_run_out_first():
    hits, rec, built, _ = run_online(build_estimate=1.0)
    assert not rec.switched and rec.switch_ray is None and built == [] and (hits.triangle == 0).all()


def test_online_does_not_buy_a_structure_that_is_not_faster_per_ray():
    _, rec, built, _ = run_online(build_estimate=8 * 2.0 ** -10, c_R=2.0 ** -9)
    assert not rec.switched and built == [] and "not be faster" in rec.note, rec


# -- end to end on a procedural scene ----------------------------------------------------------------

def _reference(mesh, o, d):
    return build(mesh, "brute").trace(o, d)


def _assert_same(h, ref, what):
    bad = np.flatnonzero(h.triangle != ref.triangle)
    assert bad.size == 0, f"{what}: {bad.size} rays differ from brute force, first {bad[:5].tolist()}: {h.triangle[bad[:5]]} vs {ref.triangle[bad[:5]]}"
    assert np.array_equal(h.t, ref.t), f"{what}: hit distances differ from brute force"


def test_small_plan_reuses_its_grid_and_matches_brute_force():
    mesh = scenes.torus(1500)
    o, d = uniform_rays(mesh, 600, seed=7)
    ref = _reference(mesh, o, d)
    p = plan(mesh, 1, cal_of(bvh=(1e-7, 1e-7)), samples=200, kinds=("grid", "bvh"))
    assert p.decision == "GRID" and p.samples == 200 and p.grid_per_ray > 0 and p.grid_build_time > 0
    assert p.accel() is p.grid, "the grid that won must be reused, not rebuilt"
    _assert_same(p.trace(o, d), ref, "planned grid")
    assert p.structure is None and [e["kind"] for e in p.executed] == ["grid"], p.executed
    json.dumps(p.to_dict(), allow_nan=False)


def test_small_plan_builds_the_bvh_once_when_it_wins_and_matches_brute_force():
    mesh = scenes.sphere(2000)
    o, d = uniform_rays(mesh, 600, seed=8)
    ref = _reference(mesh, o, d)
    p = plan(mesh, 1e15, cal_of(bvh=(1e-12, 1e-12)), rays=(o, d), samples=300, kinds=("grid", "bvh"))
    assert p.decision == "BVH" and p.samples == 300, p.summary()
    _assert_same(p.trace(o[:300], d[:300]), ref.__class__(*(a[:300] for a in (ref.t, ref.triangle, ref.u, ref.v))), "planned bvh, first half")
    first = p.structure
    _assert_same(p.trace(o, d), ref, "planned bvh, all rays")
    assert p.structure is first and [e["build_time"] > 0 for e in p.executed] == [True, False, False], p.executed


def test_plan_reuses_a_grid_passed_in_and_refuses_one_over_another_mesh():
    mesh = scenes.city(800)
    g = build(mesh, "grid")
    p = plan(mesh, 10, cal_of(bvh=(1e-7, 1e-7)), grid=g, samples=100, kinds=("grid", "bvh"))
    assert p.grid is g and p.grid_reused and p.grid_build_time == g.build_time
    with pytest.raises(ValueError, match="another mesh"):
        plan(scenes.city(900), 10, cal_of(bvh=(1e-7, 1e-7)), grid=g)


def test_plan_notes_embree_skipped_when_embreex_is_missing(monkeypatch):
    from hybrid_raycast.core import embree

    monkeypatch.setattr(embree, "embree_available", lambda: False)
    p = plan(scenes.soup(300), 1e9, cal_of(bvh=(1e-9, 1e-9), embree=(1e-12, 1e-12)), samples=50)
    assert "embree" not in p.candidates and any("embreex is not installed" in n for n in p.notes), p.notes
    assert p.decision in ("GRID", "BVH")


def test_online_end_to_end_switches_and_matches_brute_force():
    mesh = scenes.scatter(1600)
    o, d = uniform_rays(mesh, 900, seed=9)
    hits, rec = trace_online(mesh, o, d, cal_of(bvh=(1e-12, 1e-12)), batch=100)
    assert rec.switched and rec.switch_ray == 100, f"a near-free BVH should be bought after the first batch: {rec}"
    _assert_same(hits, _reference(mesh, o, d), "online")


def test_plan_refuses_bad_budgets_and_kinds_before_building_anything():
    with pytest.raises(ValueError, match="positive finite"):
        plan(scenes.sphere(100), 0, cal_of(bvh=(1e-7, 1e-7)))
    with pytest.raises(ValueError, match="must include 'grid'"):
        plan(scenes.sphere(100), 10, cal_of(bvh=(1e-7, 1e-7)), kinds=("bvh",))


def test_online_without_constants_for_the_kind_keeps_the_grid_and_says_so():
    clock = FakeClock()
    grid = FakeAccel(clock, 2.0 ** -10, code=0)
    o = np.zeros((20, 3), np.float32)
    hits, rec = trace_online(TWO, o, o + 1, cal_of(bvh=(1e-9, 1e-9)), grid=grid, kind="embree", batch=4, clock=clock)
    assert not rec.switched and (hits.triangle == 0).all() and "no calibration constants" in rec.note, rec
    d = rec.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["estimated_build_time"] is None


# -- the grid sample's correction and the reuse of workload samples ------------------------------------

def _with_ratio(cal: Calibration, ratio: float, spread=(0.5, 2.0)) -> Calibration:
    """Give a hand-made calibration three scenes whose grid ratio at every K is ratio*spread."""
    from hybrid_raycast.core.decide import Measurement, SceneRecord

    for i, q in enumerate((ratio * spread[0], ratio, ratio * spread[1])):
        rec = SceneRecord(f"r{i}", 100, 100, {"grid": Measurement(0.0, 1e-4, 100)})
        rec.grid_samples = {k: 1e-6 / q for k in (16, 1 << 20)}
        cal.scenes.append(rec)
    cal.spread = (0.0, 100.0)
    return cal


def test_plan_scales_the_sample_time_by_the_calibrated_ratio():
    cal = _with_ratio(cal_of(bvh=(1e-9, 1e-9)), 0.5)
    p = plan(scenes.torus(1500), 1e6, cal, samples=256, kinds=("grid", "bvh"), prior=False)
    assert p.grid_sample_ratio == pytest.approx(0.5)
    assert p.grid_per_ray == pytest.approx(0.5 * p.grid_sample_per_ray, rel=1e-12)
    g = p.candidates["grid"]
    assert (g.per_ray_low, g.per_ray_high) == pytest.approx((0.25 * p.grid_sample_per_ray, 1.0 * p.grid_sample_per_ray))
    assert json.loads(json.dumps(p.to_dict()))["grid_sample_ratio"] == pytest.approx(0.5)


def test_grid_interval_widens_the_break_even_interval_exactly():
    # t_G in [2e-6, 8e-6] around 4e-6; BVH build 0.01 s, 1e-6 s per ray (no spread of its own)
    cal = cal_of(bvh=(0.01 / 10240, 1e-7))
    p = plan_from_timings(N, 1e3, cal, 0.0, 4e-6, grid_per_ray_low=2e-6, grid_per_ray_high=8e-6, kinds=("grid", "bvh"))
    c = p.candidates["bvh"]
    assert c.break_even == pytest.approx(0.01 / 3e-6) and c.break_even_low == pytest.approx(0.01 / 7e-6)
    assert c.break_even_high == pytest.approx(0.01 / 1e-6)


def test_break_even_kind_is_none_when_no_candidate_ever_pays():
    p = plan_from_timings(N, 1e9, cal_of(bvh=(1e-7, 1e-6)), 0.0, 1e-6, kinds=("grid", "bvh"))
    assert math.isinf(p.break_even) and p.break_even_kind is None and p.decision == "GRID"


def test_trace_reuses_the_samples_drawn_from_the_workload():
    mesh = scenes.torus(1500)
    o, d = uniform_rays(mesh, 900, seed=9)
    ref = _reference(mesh, o, d)
    p = plan(mesh, 10, cal_of(bvh=(1e-7, 1e-7)), rays=(o, d), samples=300, kinds=("grid", "bvh"))
    assert p.decision == "GRID" and p.workload_samples == 300
    _assert_same(p.trace(o, d), ref, "grid with reused samples")
    assert p.executed[-1]["rays"] == 600 and p.executed[-1]["reused"] == 300, p.executed
    # copies are other arrays: everything is traced again
    _assert_same(p.trace(o.copy(), d.copy()), ref, "grid on copies")
    assert p.executed[-1]["rays"] == 900 and p.executed[-1]["reused"] == 0, p.executed


def test_a_workloads_sample_takes_one_ray_from_each_of_k_equal_blocks():
    """An ordered workload (here a camera's rows) is covered evenly: the sample holds one
    ray of every block of M / K, a different one for another seed."""
    mesh = scenes.sphere(2000)
    o, d = camera_rays((0, -4, 0.5), (0, 0, 0), (0, 0, 1), 60.0, 64, 48)  # row-major
    m, k = len(o), 300
    picks = []
    for seed in (0, 1):
        p = plan(mesh, 1e6, cal_of(bvh=(1e-7, 1e-7)), rays=(o, d), samples=k, kinds=("grid", "bvh"), seed=seed)
        idx = p.sample[2]
        edges = (np.arange(k + 1) * m) // k
        assert len(idx) == k and (idx >= edges[:-1]).all() and (idx < edges[1:]).all(), idx
        assert any("one from each of K blocks" in n for n in p.notes)
        picks.append(idx)
    assert (picks[0] != picks[1]).any()


def test_a_workload_of_at_most_k_rays_is_answered_while_planning_and_keeps_the_grid():
    mesh = scenes.sphere(2000)
    o, d = uniform_rays(mesh, 250, seed=10)
    tmax = np.full(250, 0.5, np.float32)
    ref = build(mesh, "brute").trace(o, d, 0.0, tmax)
    # a nearly free BVH would win for 250 fresh rays, but none is left to trace
    p = plan(mesh, 250, cal_of(bvh=(1e-12, 1e-12)), rays=(o, d, 0.0, tmax), samples=1000, kinds=("grid", "bvh"))
    assert p.break_even < 250 and p.decision == "GRID", p.summary()
    assert p.samples == 250 and p.workload_samples == 250 and any("answered by the grid" in n for n in p.notes)
    _assert_same(p.trace(o, d, 0.0, tmax), ref, "whole workload from the plan's samples")
    assert p.executed[-1]["rays"] == 0 and p.executed[-1]["reused"] == 250 and p.structure is None, p.executed
    # occlusion answers merge from the same samples
    rest, rays = p.split(o, d, 0.0, tmax)
    assert len(rest) == 0
    occ = p.merge(250, rest, np.zeros(0, bool))
    assert np.array_equal(occ, ref.hit)


def test_partial_occlusion_merge_matches_a_full_occlusion_query():
    mesh = scenes.city(800)
    o, d = uniform_rays(mesh, 700, seed=11)
    p = plan(mesh, 10, cal_of(bvh=(1e-7, 1e-7)), rays=(o, d), samples=200, kinds=("grid", "bvh"))
    rest, (ro, rd, rt0, rt1) = p.split(o, d)
    assert len(rest) == 500 and np.array_equal(ro, o[rest])
    occ = p.merge(700, rest, p.grid.occluded(ro, rd, rt0, rt1))
    assert np.array_equal(occ, build(mesh, "brute").occluded(o, d))


def test_embree_decisions_do_not_mix_in_the_grids_answers():
    pytest.importorskip("embreex")
    mesh = scenes.sphere(2000)
    o, d = uniform_rays(mesh, 600, seed=12)
    p = plan(mesh, 1e15, cal_of(bvh=(1e-6, 1e-6), embree=(1e-12, 1e-12)), rays=(o, d), samples=200)
    assert p.decision == "EMBREE"
    assert p.reusable_samples(o, d) is None
    p.trace(o, d)
    assert p.executed[-1]["rays"] == 600 and p.executed[-1]["reused"] == 0


def test_the_decision_weighs_the_rays_left_after_the_answered_samples():
    # t_G 4e-6, BVH 0.01 s + 1e-6 per ray: R* = 0.01 / 3e-6 = 3,333.3 rays from zero
    cal = cal_of(bvh=(0.01 / 10240, 1e-7))
    fresh = plan_from_timings(N, 4000, cal, 0.0, 4e-6, kinds=("grid", "bvh"))
    assert fresh.decision == "BVH" and fresh.break_even == pytest.approx(0.01 / 3e-6)
    # 1,000 of the 4,000 rays already answered: 3,000 left < R*, the grid finishes them
    left = plan_from_timings(N, 4000, cal, 0.0, 4e-6, kinds=("grid", "bvh"), answered=1000)
    assert left.decision == "GRID" and left.break_even == fresh.break_even
    assert plan_from_timings(N, 4400, cal, 0.0, 4e-6, kinds=("grid", "bvh"), answered=1000).decision == "BVH"
    # a structure that retraces everything (Embree) is charged for all R rays
    cal2 = cal_of(bvh=(1.0, 1e-7), embree=(0.01 / 10240, 1e-7))
    assert plan_from_timings(N, 4000, cal2, 0.0, 4e-6, answered=1000).decision == "GRID"
    assert plan_from_timings(N, 4000, cal2, 0.0, 4e-6, answered=0).decision == "EMBREE"


def test_an_ill_conditioned_break_even_is_said_in_words():
    """t_G / t_H below 1.5: a 10% error in a time per ray moves R* = T_B / (t_G - t_H) by
    t_G / (t_G - t_H) times 10%; the plan says so in its field, its notes and its JSON."""
    cal = cal_of(bvh=(1e-7, 1e-7))  # t_H = 1e-6 at N = 1024
    close = plan_from_timings(N, 1e6, cal, grid_build_time=0.01, grid_per_ray=1.25e-6, kinds=("grid", "bvh"))
    assert "1.25x" in close.ill_conditioned and "about 50%" in close.ill_conditioned
    assert close.ill_conditioned in close.notes and close.to_dict()["ill_conditioned"] == close.ill_conditioned
    # the stated move is the break-even's own sensitivity
    moved = plan_from_timings(N, 1e6, cal, grid_build_time=0.01, grid_per_ray=1.25e-6 * 1.001, kinds=("grid", "bvh"))
    sens = (1 - moved.break_even / close.break_even) / 0.001
    assert sens == pytest.approx(5.0, rel=0.01)
    far = plan_from_timings(N, 1e6, cal, grid_build_time=0.01, grid_per_ray=3e-6, kinds=("grid", "bvh"))
    assert far.ill_conditioned == "" and not any("ill-conditioned" in n for n in far.notes)
    never = plan_from_timings(N, 1e6, cal, grid_build_time=0.01, grid_per_ray=0.9e-6, kinds=("grid", "bvh"))
    assert never.ill_conditioned == ""  # the BVH never beats the grid: no break-even to be ill-conditioned
