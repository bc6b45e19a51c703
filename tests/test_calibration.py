"""Calibration: the fit is the paper's formula, files round-trip, and bad files never crash.

Also the procedural scenes the calibration runs on (core/scenes.py): deterministic,
the size asked for, closed where they should be.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from hybrid_raycast.core.decide import calfile as CF
from hybrid_raycast.core.decide import evaluate
from hybrid_raycast.core.decide.cost import L_REF, X_REF
from hybrid_raycast.core.decide import measurements as M
from hybrid_raycast.core.decide import settle
from hybrid_raycast.core.decide import truth
from hybrid_raycast.core import scenes as S
from hybrid_raycast.core.rays import uniform_rays
from hybrid_raycast.core.decide import (
    CALIBRATION_FORMAT,
    Calibration,
    CalibrationError,
    KindFit,
    Measurement,
    SceneRecord,
    calibrate,
    fit,
    load,
    load_default,
    load_or_default,
)



def hand_calibration(**kw) -> Calibration:
    fits = {"bvh": KindFit(2e-7, 3e-7, 1e-7, 4e-7, 2e-7, 5e-7, 3)}
    rec = SceneRecord("a", 1000, 100, {"bvh": Measurement(0.01, 0.02, 100, 2), "grid": Measurement(0.005, 0.03, 100, 2)})
    rec.passes = {"bvh": [Measurement(0.01, 0.02, 100, 2, 10, 0.001, 0.019), Measurement(0.012, 0.021, 100, 2)]}
    return Calibration(fits, scenes=[rec], source="hand", created="2026-01-01T00:00:00+00:00", **kw)


# -- the fit -------------------------------------------------------------------------------------

def test_fit_is_the_mean_of_per_scene_ratios_with_an_interval_around_it():
    # c_B(i) = T_B / (N log2 N), c_R(i) = T_R / (M log2 N): paper, section 3
    recs = [
        SceneRecord("s1", 1024, 1000, {"bvh": Measurement(1024 * 10 * 1e-7, 1000 * 10 * 2e-7, 1000)}),
        SceneRecord("s2", 4096, 2000, {"bvh": Measurement(4096 * 12 * 3e-7, 2000 * 12 * 4e-7, 2000)}),
        SceneRecord("s3", 256, 500, {"bvh": Measurement(256 * 8 * 5e-7, 500 * 8 * 9e-7, 500)}),
    ]
    f = evaluate.fit_model(recs, ["bvh"], "paper")["bvh"]  # the paper's model is a compared one
    assert f.c_B == pytest.approx(3e-7, rel=1e-12), f"c_B should be the mean of 1e-7, 3e-7, 5e-7, got {f.c_B}"
    assert f.c_R == pytest.approx(5e-7, rel=1e-12), f"c_R should be the mean of 2e-7, 4e-7, 9e-7, got {f.c_R}"
    assert f.c_B_low == pytest.approx(np.percentile([1e-7, 3e-7, 5e-7], 10))
    assert f.c_R_high == pytest.approx(np.percentile([2e-7, 4e-7, 9e-7], 90))
    assert f.c_B_low <= f.c_B <= f.c_B_high and f.c_R_low <= f.c_R <= f.c_R_high
    assert f.scenes == 3


def test_interval_always_contains_the_mean_even_with_an_outlier():
    recs = [SceneRecord(f"s{i}", 1024, 100, {"bvh": Measurement(1024 * 10 * v, 100 * 10 * v, 100)})
            for i, v in enumerate([1e-7] * 19 + [1e-4])]
    f = evaluate.fit_model(recs, ["bvh"], "paper")["bvh"]
    assert f.c_B_low <= f.c_B <= f.c_B_high, f"mean {f.c_B} outside [{f.c_B_low}, {f.c_B_high}]"


def test_unknown_model_is_refused_by_name():
    with pytest.raises(ValueError, match="unknown calibration model 'cubic'"):
        fit([], ["bvh"], model="cubic")


def test_estimate_is_c_B_N_log2_N_and_c_R_log2_N():
    cal = hand_calibration()
    e = cal.estimate("bvh", 1024)
    assert e.build_time == pytest.approx(2e-7 * 1024 * 10) and e.per_ray == pytest.approx(3e-7 * 10)
    assert (e.build_low, e.build_high) == pytest.approx((1e-7 * 10240, 4e-7 * 10240))
    assert (e.per_ray_low, e.per_ray_high) == pytest.approx((2e-6, 5e-6))
    with pytest.raises(KeyError, match="embree"):
        cal.estimate("embree", 1024)


# -- files ---------------------------------------------------------------------------------------

def test_save_and_load_round_trip_every_field(tmp_path):
    cal = hand_calibration(notes=["a note"], rays_per_scene=100, scale="custom", duration_s=1.5)
    path = cal.save(tmp_path / "sub" / "cal.json")
    back = load(path)
    assert back.to_dict() == cal.to_dict(), "a saved calibration should load back unchanged"
    assert back.estimate("bvh", 5000) == cal.estimate("bvh", 5000)
    assert back.scenes[0].c_B("bvh") == cal.scenes[0].c_B("bvh")


def test_missing_file_is_a_calibration_error_naming_the_path(tmp_path):
    with pytest.raises(CalibrationError, match="no calibration file at .*nothere.json"):
        load(tmp_path / "nothere.json")


@pytest.mark.parametrize("text, reason", [
    ("{not json", "not valid JSON"),
    ("", "not valid JSON"),
    ("[1, 2, 3]", "expected a JSON object"),
    ('{"fits": {}}', "no version information"),
])
def test_corrupt_file_is_a_one_line_calibration_error(tmp_path, text, reason):
    p = tmp_path / "cal.json"
    p.write_text(text)
    with pytest.raises(CalibrationError) as err:
        load(p)
    assert reason in str(err.value), f"expected {reason!r} in {str(err.value)!r}"
    assert "\n" not in str(err.value), "the reason should be one line"


def test_truncated_file_is_refused(tmp_path):
    p = tmp_path / "cal.json"
    p.write_text(hand_calibration().to_json()[:-40])
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load(p)


def _edit(tmp_path, change):
    d = hand_calibration().to_dict()
    change(d)
    p = tmp_path / "cal.json"
    p.write_text(json.dumps(d))
    return p


@pytest.mark.parametrize("field, value, where", [
    ("numpy", "0.0.1", "numpy"),
    ("package", "9.9.9", "package"),
    ("python", "2.7", "python"),
])
def test_foreign_version_is_refused_naming_what_differs(tmp_path, field, value, where):
    p = _edit(tmp_path, lambda d: d["version"].__setitem__(field, value))
    with pytest.raises(CalibrationError, match=f"another setup: {where} '{value}' in the file"):
        load(p)


def test_foreign_machine_is_refused(tmp_path):
    p = _edit(tmp_path, lambda d: d["version"]["machine"].__setitem__("cpus", 999))
    with pytest.raises(CalibrationError, match="machine.cpus 999 in the file"):
        load(p)


def test_other_format_is_refused_even_without_version_checks(tmp_path):
    p = _edit(tmp_path, lambda d: d["version"].__setitem__("format", CALIBRATION_FORMAT + 1))
    with pytest.raises(CalibrationError, match="calibration format"):
        load(p, check_version=False)


@pytest.mark.parametrize("change, reason", [
    (lambda d: d["fits"]["bvh"].__setitem__("c_B", -1.0), "not finite non-negative"),
    (lambda d: d["fits"]["bvh"].__setitem__("c_R", None), "not finite non-negative"),
    (lambda d: d["fits"]["bvh"].__setitem__("c_B_high", 1e-9), "does not contain"),
    (lambda d: d["fits"]["bvh"].pop("c_R"), "malformed"),
    (lambda d: d.__setitem__("fits", {}), "no fitted constants"),
    (lambda d: d.__setitem__("model", "cubic"), "unknown model"),
])
def test_nonsense_constants_are_refused(tmp_path, change, reason):
    with pytest.raises(CalibrationError, match=reason):
        load(_edit(tmp_path, change))


def test_shipped_defaults_load_and_are_labelled():
    assert CF.DEFAULT_PATH.is_file(), f"the shipped defaults are missing: {CF.DEFAULT_PATH}"
    cal = load_default()
    assert cal.source == "shipped defaults", f"shipped defaults came back as {cal.source!r}: {cal.notes}"
    assert "bvh" in cal.fits and len(cal.scenes) >= 8, f"shipped defaults fit {cal.kinds} on {len(cal.scenes)} scenes"


@pytest.mark.parametrize("make, reason", [
    (lambda p: None, "no calibration file"),
    (lambda p: p.write_text("{garbage"), "not valid JSON"),
    (lambda p: p.write_bytes(b"\xff\xfe\x00garbage"), "cal.json"),
    (lambda p: p.write_text(json.dumps({**hand_calibration().to_dict(), "version": {**CF.current_version(), "numpy": "0.1"}})),
     "another setup"),
    (lambda p: p.mkdir(), "cannot read"),
])
def test_load_or_default_falls_back_to_labelled_defaults_with_a_message(tmp_path, make, reason):
    p = tmp_path / "cal.json"
    make(p)
    cal, msg = load_or_default(p)
    assert cal.source == "shipped defaults", f"fallback should be labelled, got {cal.source!r}"
    assert reason in msg and "shipped defaults" in msg, f"message {msg!r} should give the reason ({reason!r}) and the fallback"


def test_load_or_default_loads_a_good_file(tmp_path):
    p = hand_calibration().save(tmp_path / "cal.json")
    cal, msg = load_or_default(p)
    assert cal.source == "hand" and "loaded calibration" in msg


def test_unusable_shipped_defaults_give_a_labelled_builtin_fallback(tmp_path, monkeypatch):
    monkeypatch.setattr(CF, "DEFAULT_PATH", tmp_path / "gone.json")
    cal, msg = load_or_default(None)
    assert cal.source == "built-in fallback" and "bvh" in cal.fits, f"{cal.source}: {msg}"
    assert "no calibration file" in cal.notes[0]


# -- a real (small) calibration run ---------------------------------------------------------------

#: the least a real calibration measures (one pass, two small samples, one build each): these
#: tests check what a calibration records, not its constants
FAST = {"repeats": 1, "sample_ladder": (64, 256), "grid_large_rays": 1024, "small_builds": 1, "work_samples": 256,
        "settle": False, "quiet": None}


def test_calibrate_measures_fits_and_reports_progress_to_one():
    # brute force needs no other module: this checks the mechanics, not the constants
    seen = []
    scenes = [("sphere", S.sphere(80)), ("soup", lambda: S.soup(60, seed=1))]
    cal = calibrate(scenes, kinds=("brute",), rays_per_scene=40, grid=False, model="power",
                    progress=lambda f, m: seen.append((f, m)), **FAST)
    fr = [f for f, _ in seen]
    assert fr == sorted(fr) and fr[0] == 0.0 and fr[-1] == 1.0, f"progress fractions should rise to 1: {fr}"
    assert all(isinstance(m, str) and m for _, m in seen)
    assert [r.name for r in cal.scenes] == ["sphere", "soup"] and cal.scenes[1].triangles == 60
    # two scenes are too few for an exponent or a fixed cost: the power model is the paper's
    # mean ratios, stated at the reference size (N_REF triangles)
    f = cal.fits["brute"]
    assert f.c_B == pytest.approx(np.mean([r.c_B("brute") for r in cal.scenes]) * X_REF)
    assert f.c_R == pytest.approx(np.mean([r.c_R("brute") for r in cal.scenes]) * L_REF)
    assert cal.source == "measured" and cal.rays_per_scene == 40 and cal.version == CF.current_version()
    assert Calibration.from_json(cal.to_json()).to_dict() == cal.to_dict()


def test_calibrate_skips_embree_with_a_note_when_embreex_is_missing(monkeypatch):
    from hybrid_raycast.core import embree

    monkeypatch.setattr(embree, "embree_available", lambda: False)
    cal = calibrate([("s", S.sphere(80))], kinds=("brute", "embree"), rays_per_scene=10, grid=False, **FAST)
    assert "embree" not in cal.fits and any("embreex is not installed" in n for n in cal.notes), cal.notes


def test_calibrate_tiny_set_records_the_grid_but_fits_only_the_candidates():
    cal = calibrate(S.calibration_set("tiny")[:3], kinds=("bvh",), rays_per_scene=200, **FAST)
    assert set(cal.fits) == {"bvh"}, f"fitted {set(cal.fits)}"
    for r in cal.scenes:
        assert set(r.kinds) == {"grid", "bvh"}, f"{r.name} measured {set(r.kinds)}"
        assert all(m.build_time > 0 and m.trace_time > 0 for m in r.kinds.values())


def test_calibrate_keeps_every_passs_measurement_and_its_medians_are_theirs(tmp_path):
    cal = calibrate(S.calibration_set("tiny")[:2], kinds=("bvh",), rays_per_scene=200, **{**FAST, "repeats": 3})
    for r in cal.scenes:
        assert {k: len(v) for k, v in r.passes.items()} == {"grid": 3, "bvh": 3}, f"{r.name}: {r.passes}"
        for k, v in r.passes.items():
            assert r.kinds[k] == M.median_measurement(v)
    back = load(cal.save(tmp_path / "cal.json"))
    assert [r.passes for r in back.scenes] == [r.passes for r in cal.scenes]


def test_a_file_without_passes_loads_with_none(tmp_path):
    d = hand_calibration().to_dict()
    for s in d["scenes"]:
        del s["passes"]
    back = Calibration.from_dict(d)
    assert [r.passes for r in back.scenes] == [{}]
    assert back.scenes[0].kinds == hand_calibration().scenes[0].kinds


def test_measure_break_even_uses_the_estimates_formula_on_measured_times():
    be = truth.measure_break_even(S.torus(2000), 500, kinds=("grid", "bvh"))
    g, b = be.measurements["grid"], be.measurements["bvh"]
    want = b.build_time / (g.per_ray - b.per_ray) if g.per_ray > b.per_ray else math.inf
    assert be.R_C["bvh"] == want and be.rays == 500 and be.triangles == S.torus(2000).triangle_count


# -- the procedural scenes -------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(S.SCENES))
def test_scenes_are_deterministic_and_near_the_size_asked(name):
    for n in (500, 20000):
        a, b = S.make_scene(name, n, seed=3), S.make_scene(name, n, seed=3)
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles), f"{name} not deterministic"
        assert 0.75 * n <= a.triangle_count <= 1.25 * n, f"{name}({n}) has {a.triangle_count} triangles"
        assert a.valid.all(), f"{name}({n}) has {(~a.valid).sum()} degenerate triangles"
    other = S.make_scene(name, 500, seed=4)
    assert not np.array_equal(other.vertices, S.make_scene(name, 500, seed=3).vertices), f"{name}: seeds 3 and 4 give the same mesh"


@pytest.mark.parametrize("make", [lambda: S.sphere(3000), lambda: S.torus(3000), lambda: S.subdivide(S.sphere(200))])
def test_closed_scenes_share_every_edge_with_opposite_winding(make):
    m = make()
    f = m.triangles.astype(np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    fwd = {tuple(x) for x in e}
    assert len(fwd) == len(e), "a directed edge appears twice: inconsistent winding"
    missing = [x for x in fwd if (x[1], x[0]) not in fwd]
    assert not missing, f"{len(missing)} edges have no opposite half-edge (open mesh), e.g. {missing[:3]}"


def test_subdivide_quadruples_and_keeps_the_surface():
    m = S.torus(800)
    s = S.subdivide(m)
    assert s.triangle_count == 4 * m.triangle_count
    assert s.surface_area() == pytest.approx(m.surface_area(), rel=1e-5)


def test_calibration_sets_span_the_sizes_and_have_unique_names():
    for scale in S.SCALES:
        names = [n for n, _ in S.calibration_set(scale)]
        assert len(names) == len(set(names)), f"duplicate names in {scale}: {names}"
    sizes = [f.args[0] for _, f in S.calibration_set("default")]
    assert min(sizes) <= 600 and max(sizes) >= 900_000, f"default set spans {min(sizes)}..{max(sizes)}"
    assert {n.split("-")[0] for n, _ in S.calibration_set("rich")} == set(S.SCENES)
    with pytest.raises(ValueError, match="unknown calibration scale 'huge'"):
        S.calibration_set("huge")
    with pytest.raises(ValueError, match="unknown procedural scene 'cube'"):
        S.make_scene("cube", 10)


# -- the grid's sample ratio ------------------------------------------------------------------------

def _sampled(ratios_by_scene, ladder=(1024, 4096, 16384)) -> Calibration:
    """Scenes whose grid runs 1 us per ray on a large batch and 1/ratio us on a K-ray sample."""
    recs = []
    for i, ratios in enumerate(ratios_by_scene):
        rec = SceneRecord(f"s{i}", 1000, 1000, {"grid": Measurement(0.001, 1000 * 1e-6, 1000)})
        rec.grid_samples = {k: 1e-6 / q for k, q in zip(ladder, ratios)}
        recs.append(rec)
    return Calibration({"bvh": KindFit(1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1)}, scenes=recs, source="hand")


def test_grid_sample_ratio_is_the_median_over_scenes_interpolated_in_log_k():
    cal = _sampled([(0.2, 0.5, 0.8), (0.3, 0.6, 0.9), (0.1, 0.4, 0.7)])
    med, lo, hi = cal.grid_sample_ratio(4096)
    assert med == pytest.approx(0.5) and lo == pytest.approx(np.percentile([0.5, 0.6, 0.4], 10))
    assert hi == pytest.approx(np.percentile([0.5, 0.6, 0.4], 90))
    # halfway between 4096 and 16384 in log2 K (8192) is halfway between 0.5 and 0.8
    assert cal.grid_sample_ratio(8192)[0] == pytest.approx(0.65)
    # clamped at both ends of the ladder
    assert cal.grid_sample_ratio(16)[0] == pytest.approx(0.2) and cal.grid_sample_ratio(1 << 20)[0] == pytest.approx(0.8)


def test_grid_sample_ratio_without_samples_is_one():
    assert hand_calibration().grid_sample_ratio(16384) == (1.0, 1.0, 1.0)


def test_grid_samples_round_trip_with_integer_sample_sizes(tmp_path):
    cal = _sampled([(0.2, 0.5, 0.8)])
    back = load(cal.save(tmp_path / "cal.json"), check_version=False)
    assert back.scenes[0].grid_samples == cal.scenes[0].grid_samples
    assert back.grid_sample_ratio(4096) == cal.grid_sample_ratio(4096)


def test_a_format_1_file_falls_back_to_the_defaults_naming_the_format(tmp_path):
    p = _edit(tmp_path, lambda d: d["version"].__setitem__("format", 1))
    cal, msg = load_or_default(p)
    assert cal.source == "shipped defaults" and "calibration format 1" in msg, msg


def test_calibrate_times_the_grid_on_each_sample_size():
    cal = calibrate(S.calibration_set("tiny")[:2], kinds=("bvh",), rays_per_scene=300, **FAST)
    for r in cal.scenes:
        assert sorted(r.grid_samples) == [64, 256] and all(v > 0 for v in r.grid_samples.values()), r.grid_samples
    med, lo, hi = cal.grid_sample_ratio(128)
    assert 0 < lo <= med <= hi


def test_time_trace_runs_the_batch_as_trace_does_and_leaves_the_chunk_size_alone():
    mesh = S.sphere(200)
    from hybrid_raycast.core.rays import uniform_rays

    o, d = uniform_rays(mesh, 500, seed=3)
    g = M.build(mesh, "grid", threads=2)
    hits, dt = M.time_trace(g, o, d)
    assert dt > 0 and np.array_equal(hits.triangle, g.trace(o, d).triangle)
    assert "chunk_size" not in g.__dict__, "time_trace must not change the structure's chunks"


def test_small_scales_still_time_the_grid_on_a_large_workload_for_the_ratio():
    # 'quick' traces 20,000 rays per scene: as the ratio's reference that is itself a small
    # batch; the grid's reference is at least grid_large_rays (GRID_LARGE_RAYS by default)
    assert M.GRID_LARGE_RAYS >= max(M.SAMPLE_LADDER) and M.GRID_LARGE_RAYS > M.RAYS_PER_SCENE["quick"]
    cal = calibrate(S.calibration_set("tiny")[:2], kinds=("bvh",), rays_per_scene=300,
                    **{**FAST, "grid_large_rays": 4096, "sample_ladder": (256, 1024)})
    for r in cal.scenes:
        assert r.kinds["grid"].rays == 4096 and r.kinds["bvh"].rays == 300
    # the ratio's value is a timing (no bound on it here: a test never fails on a time; a
    # background job starved this one to 1.85): it is defined and ordered
    med, lo, hi = cal.grid_sample_ratio(1024)
    assert 0 < lo <= med <= hi, (med, lo, hi)


def test_a_scale_sets_calibrates_defaults_and_an_argument_wins_over_it(monkeypatch):
    """'tiny' is one pass over its scenes with two sample sizes (``SCALE_SETTINGS``); an
    argument given to calibrate overrides the scale's setting."""
    seen = []

    def fake_measure(mesh, kind, o, d, threads=None, config=None, builds=None, settle=True):
        if mesh.triangle_count in sizes:  # not warm_up's own tiny scene
            seen.append((kind, len(o), builds, settle))
        return Measurement(0.001 * (kind != "grid"), 1e-7 * len(o) * (2 if kind == "grid" else 1), len(o), 1)

    monkeypatch.setattr(M, "measure", fake_measure)
    scenes = [("torus-300", S.torus(300)), ("soup-60", S.soup(60, seed=1))]
    sizes = {m.triangle_count for _, m in scenes}
    monkeypatch.setattr(S, "calibration_set", lambda scale: scenes)
    tiny = M.SCALE_SETTINGS["tiny"]
    cal = calibrate(scale="tiny", kinds=("bvh",), work_samples=64, quiet=None)
    assert cal.scale == "tiny" and all(sorted(r.grid_samples) == list(tiny["sample_ladder"]) for r in cal.scenes)
    assert all(len(v) == tiny["repeats"] for r in cal.scenes for v in r.passes.values())
    assert {n for k, n, _, _ in seen if k == "grid" and n not in tiny["sample_ladder"]} == {tiny["grid_large_rays"]}
    assert {b for k, _, b, _ in seen if k == "bvh"} == {tiny["small_builds"]}
    assert {s for *_, s in seen} == {tiny["settle"]} == {False}
    seen.clear()
    cal = calibrate(scale="tiny", kinds=("bvh",), work_samples=64, quiet=None, repeats=2, sample_ladder=(32,),
                    settle=True)
    assert all(len(v) == 2 for r in cal.scenes for v in r.passes.values()) and {s for *_, s in seen} == {True}
    assert all(sorted(r.grid_samples) == [32] for r in cal.scenes)


def test_a_format_2_file_loads_with_its_constants_meaning_what_they_meant(tmp_path):
    """Format 2 stated the power model's c as the factor of x^p and a count model's constant at
    zero counts; such a file (no x_ref_B / x_ref_R, no refs) still loads here and estimates
    c (N log2 N)^p and a + b log2 N, as it did."""
    from hybrid_raycast.core.decide.cost import CountFit

    def to_format_2(d):
        d["version"]["format"] = 2
        d["model"] = "power"
        d["fits"]["bvh"].update(c_B=2e-8, c_B_low=1e-8, c_B_high=3e-8, extra={"p_B": 1.1, "p_R": 0.8, "a_B": 0.0, "a_R": 0.0})
        d["counts"] = {"bvh": {"terms": ["1", "log2n"], "coef": [2e-7, 1e-7], "low": 0.9, "high": 1.1, "scenes": 5,
                               "form": "linear"}}

    cal = load(_edit(tmp_path, to_format_2))
    assert cal.estimate("bvh", 1 << 16).build_time == pytest.approx(2e-8 * 1048576 ** 1.1, rel=1e-12)
    assert cal.estimate("bvh", 1 << 16).per_ray == pytest.approx(3e-7 * 16 ** 0.8, rel=1e-12)
    assert cal.counts["bvh"] == CountFit(("1", "log2n"), (2e-7, 1e-7), 0.9, 1.1, 5, "linear", ())
    assert cal.count_per_ray("bvh", 1 << 12, {"cells": 1.0})[0] == pytest.approx(2e-7 + 12e-7, rel=1e-12)
    assert "c_B 20.00 ns [10.00, 30.00] x (N log2 N)^1.100" in cal.describe()


def test_a_terms_calibration_round_trips_and_describes_its_constants(tmp_path):
    recs = [SceneRecord(f"s{n}", n, 1000, {"bvh": Measurement(0.04 + 0.12 * n / 65536 * (1 + 0.1 * math.log2(n / 500)),
                                                                1000 * 1e-7 * math.log2(n), 1000)})
            for n in (500, 2000, 8000, 30000, 120000, 500000, 1000000)]
    cal = Calibration(fit(recs, ("bvh",), model="terms"), scenes=recs, model="terms", source="hand")
    back = load(cal.save(tmp_path / "t.json"))
    assert back.to_dict() == cal.to_dict() and back.version["format"] == CALIBRATION_FORMAT == 3
    for n in (100, 700, 65536, 2_000_000):
        assert back.estimate("bvh", n) == cal.estimate("bvh", n)
    text = back.describe()
    assert "terms model" in text and "(n = N / 65,536, N >= 500)" in text and "ms at N = 65,536" in text, text


def test_refitted_fits_the_same_records_again_and_constants_apart_compares_them():
    """``Calibration.refitted`` is ``fit`` of its own records with another model (no new
    timing); two calibrations fitted alike differ by 0 in every constant, and a calibration
    whose builds all took 1.5x as long differs by 100 |1.5 - 1| / 1.25 = 40% in the build at
    the reference size and not at all in the exponents."""
    from hybrid_raycast.core.decide.evaluate import constants_apart, relative_difference

    recs = [SceneRecord(f"s{n}", n, 1000, {"bvh": Measurement(0.04 + 0.12 * n / 65536 * (1 + 0.1 * math.log2(n / 500)),
                                                                1000 * 1e-7 * math.log2(n), 1000)})
            for n in (500, 2000, 8000, 30000, 120000, 500000, 1000000)]
    power = Calibration(fit(recs, ("bvh",), model="power"), scenes=recs, model="power", source="hand")
    terms = power.refitted("terms")
    assert terms.model == "terms" and terms.scenes is power.scenes and terms.counts == {}
    assert terms.fits["bvh"] == fit(recs, ("bvh",), model="terms")["bvh"]
    assert set(constants_apart(power, power.refitted("power")).values()) == {0.0}
    assert constants_apart(power, terms) == {}  # another model's constants are not comparable
    slow = [SceneRecord(r.name, r.triangles, r.rays, {"bvh": Measurement(1.5 * r.kinds["bvh"].build_time,
                                                                         r.kinds["bvh"].trace_time, r.rays)})
            for r in recs]
    apart = constants_apart(power, Calibration(fit(slow, ("bvh",), model="power"), scenes=slow, model="power"))
    assert apart["bvh build at N_REF"] == pytest.approx(relative_difference(1.0, 1.5)) == pytest.approx(40.0)
    assert apart["bvh p_B"] == pytest.approx(0.0, abs=1e-9) and apart["bvh per ray at N_REF"] == pytest.approx(0.0, abs=1e-9)


def test_constants_apart_states_terms_builds_and_count_models_at_their_anchors():
    """With count models the per-ray times are theirs: a structure is compared on its build
    at cost.BUILD_ANCHORS and each count model at its anchor counts, not on the per-ray fit
    no estimate reads.  Builds all 1.5x slower put every anchored build 40% apart and no
    per-ray constant; stated=False compares the coefficients as stored."""
    from hybrid_raycast.core.decide import cost
    from hybrid_raycast.core.decide.evaluate import constants_apart

    def recs(f):
        return [SceneRecord(f"s{n}", n, 1000,
                            {"grid": Measurement(0.01, 1000 * (2e-6 + 5e-8 * c), 1000),
                             "bvh": Measurement(f * (0.015 + 0.004 * (math.log2(n) - 10) + 0.12 * n / 65536),
                                                1000 * (1e-6 + 1e-7 * math.log2(n)), 1000)},
                            work={"cells": c, "refs": None, "hit": h, "length": 0.3, "steps": c / 3 + 2,
                                  "candidates": 2 * c})
                for n, c, h in ((500, 4, 0.6), (2000, 8, 0.1), (8000, 12, 0.5), (30000, 20, 0.3), (120000, 30, 0.8),
                                (500000, 45, 0.4), (1000000, 55, 0.2))]

    a, b = (Calibration(fit(r, ("bvh",)), scenes=r, counts=cost.fit_counts(r, ("grid", "bvh"))) for r in (recs(1), recs(1.5)))
    apart = constants_apart(a, b)
    builds = {f"bvh build at {n:,}" for n in cost.BUILD_ANCHORS}
    rays = {"grid per ray at steps = 5, candidates = 10", "grid per ray at steps = 10, candidates = 13",
            "grid per ray at steps = 10, candidates = 35", "bvh per ray at hit = 0.1, steps = 10",
            "bvh per ray at hit = 0.6, steps = 5", "bvh per ray at hit = 0.6, steps = 10"}
    assert set(apart) == builds | rays
    assert all(apart[k] == pytest.approx(40.0) for k in builds)
    assert all(apart[k] == pytest.approx(0.0, abs=1e-9) for k in rays)
    raw = constants_apart(a, b, stated=False)
    assert {"bvh build 1", "bvh build n", "grid per ray at ref", "grid per ray x steps", "bvh per ray x hit"} <= set(raw)


def test_calibration_repeats_are_passes_over_all_scenes_and_records_keep_each_scenes_medians(monkeypatch):
    """Every scene is measured once per pass (pass-major: all scenes, then all again), each with
    its own mesh and rays (no late binding to the last scene's), the structures' order rotating
    from pass to pass, and each record keeps the medians of its own passes."""
    calls = []

    def fake_measure(mesh, kind, origins, directions, *, threads=None, config=None, builds=None, settle=True):
        if len(origins) != 40:  # warm_up's untimed 64 rays
            return M.Measurement(1.0, 1.0, len(origins), 1)
        calls.append((mesh.triangle_count, kind, len(origins)))
        t = float(len(calls))  # every run a different time: the median is the middle pass's
        return M.Measurement(t, 2 * t, len(origins), 1)

    monkeypatch.setattr(M, "measure", fake_measure)
    scenes = [("a", S.sphere(80)), ("b", lambda: S.soup(60, seed=1)), ("c", S.soup(30, seed=2))]
    cal = calibrate(scenes, kinds=("brute", "bvh"), rays_per_scene=40, grid=False, model="power", repeats=3, quiet=None)
    sizes = [r.triangles for r in cal.scenes]
    assert [(n, k) for n, k, _ in calls] == [
        (sizes[0], "brute"), (sizes[0], "bvh"), (sizes[1], "brute"), (sizes[1], "bvh"), (sizes[2], "brute"), (sizes[2], "bvh"),
        (sizes[0], "bvh"), (sizes[0], "brute"), (sizes[1], "bvh"), (sizes[1], "brute"), (sizes[2], "bvh"), (sizes[2], "brute"),
        (sizes[0], "brute"), (sizes[0], "bvh"), (sizes[1], "brute"), (sizes[1], "bvh"), (sizes[2], "brute"), (sizes[2], "bvh"),
    ]
    assert len(set(sizes)) == 3
    # scene a's brute runs were calls 1, 8 and 13: median 8; its bvh runs 2, 7, 14: median 7
    assert (cal.scenes[0].kinds["brute"].build_time, cal.scenes[0].kinds["brute"].trace_time) == (8.0, 16.0)
    assert cal.scenes[0].kinds["bvh"].build_time == 7.0
    assert cal.scenes[2].kinds["brute"].build_time == 12.0  # calls 5, 12, 17


def test_calibrate_runs_the_jobs_beside_it_in_its_own_passes_and_hands_back_their_results(monkeypatch):
    """``beside``: an evaluation's jobs run in each pass after the calibration's scenes (so
    constants and truths come from the same minutes), made again every pass; ``done`` gets
    each beside scene's results per pass and its own shares, and the calibration's records
    keep only their own measurements."""
    log = []

    def fake_measure(mesh, kind, origins, directions, *, threads=None, config=None, builds=None, settle=True):
        if len(origins) != 40:  # warm_up's untimed rays
            return M.Measurement(1.0, 1.0, len(origins), 1)
        log.append(("cal", mesh.triangle_count, kind))
        return M.Measurement(float(len(log)), 1.0, len(origins), 1)

    monkeypatch.setattr(M, "measure", fake_measure)

    def other(name):
        def make(r):
            return {"x": lambda: log.append((name, r)) or len(log)}
        return make

    got = {}
    scenes = [("a", S.sphere(80)), ("b", S.soup(60, seed=1))]
    cal = calibrate(scenes, kinds=("bvh",), rays_per_scene=40, grid=False, model="power", repeats=2, quiet=None,
                    beside=([other("p"), other("q")], lambda runs, shares: got.update(runs=runs, shares=shares)))
    sizes = [r.triangles for r in cal.scenes]
    assert log == [("cal", sizes[0], "bvh"), ("cal", sizes[1], "bvh"), ("p", 0), ("q", 0),
                   ("cal", sizes[0], "bvh"), ("cal", sizes[1], "bvh"), ("p", 1), ("q", 1)]
    assert got["runs"] == [{"x": [3, 7]}, {"x": [4, 8]}]
    assert [len(s) for s in got["shares"]] == [2, 2]
    assert [r.kinds["bvh"].build_time for r in cal.scenes] == [3.0, 4.0]  # medians of (1, 5) and (2, 6)


# -- the kernel's part of a build -----------------------------------------------------------------

def test_a_measured_build_records_its_page_faults_system_time_and_cpu_time(tmp_path):
    resource = pytest.importorskip("resource", reason="getrusage is POSIX only; elsewhere the fields stay None")
    mesh = S.terrain(20000)
    o, d = uniform_rays(mesh, 1000, seed=0)
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    m = M.measure(mesh, "bvh", o, d, threads=1)
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    assert isinstance(m.build_faults, int) and 0 <= m.build_faults <= r1.ru_minflt - r0.ru_minflt
    assert isinstance(m.build_system, float) and 0.0 <= m.build_system <= m.build_time + 0.05
    # the build's CPU time: at least its system part, at most what the whole measure() took
    spent = (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)
    assert isinstance(m.build_cpu, float) and m.build_system <= m.build_cpu <= spent
    # the numpy BVH builds on one thread: never much more CPU time than wall time (less when
    # another process takes the CPU mid-build, so no lower bound but zero)
    assert 0.0 < m.build_parallelism < 1.5
    # the calibration file keeps them; a file without them (older) loads as None
    rec = SceneRecord("t", mesh.triangle_count, 1000, {"bvh": m, "grid": Measurement(0.005, 0.03, 1000)})
    cal = Calibration({"bvh": KindFit(2e-7, 3e-7, 1e-7, 4e-7, 2e-7, 5e-7, 3)}, scenes=[rec], source="hand",
                      created="2026-01-01T00:00:00+00:00")
    back = load(cal.save(tmp_path / "cal.json")).scenes[0].kinds
    assert (back["bvh"].build_faults, back["bvh"].build_system, back["bvh"].build_cpu) == (
        m.build_faults, m.build_system, m.build_cpu)
    assert back["grid"].build_faults is None and back["grid"].build_system is None and back["grid"].build_cpu is None
    assert back["grid"].build_parallelism is None


def test_median_measurement_takes_the_kernel_figures_only_when_every_run_has_them():
    runs = [Measurement(0.3, 1.0, 10, 2, 100, 0.01, 0.5), Measurement(0.1, 3.0, 10, 2, 301, 0.03, 0.1),
            Measurement(0.2, 2.0, 10, 2, 200, 0.02, 0.38)]
    m = M.median_measurement(runs)
    assert (m.build_time, m.trace_time, m.build_faults, m.build_system, m.build_cpu) == (0.2, 2.0, 200, 0.02, 0.38)
    assert m.build_parallelism == pytest.approx(1.9, rel=1e-12)
    m = M.median_measurement(runs + [Measurement(0.25, 2.5, 10, 2)])
    assert (m.build_time, m.trace_time) == pytest.approx((0.225, 2.25), rel=1e-12)
    assert (m.build_faults, m.build_system, m.build_cpu, m.build_parallelism) == (None, None, None, None)


def test_build_parallelism_is_cpu_seconds_per_second_of_build_and_none_without_either():
    assert Measurement(0.02, 1.0, 10, 2, build_cpu=0.038).build_parallelism == pytest.approx(1.9, rel=1e-12)
    assert Measurement(0.02, 1.0, 10, 2, build_cpu=0.02).build_parallelism == pytest.approx(1.0, rel=1e-12)
    assert Measurement(0.0, 1.0, 10, 2, build_cpu=0.0).build_parallelism is None
    assert Measurement(0.02, 1.0, 10, 2).build_parallelism is None


def test_each_measured_build_comes_right_after_its_scenes_memory_is_written_and_a_rest(monkeypatch):
    """The page warming runs before every timed build, sized from that scene, then the
    process rests IDLE_BEFORE_BUILD and spins BUSY_BEFORE_BUILD, and nothing else comes
    between them and the build (on a VM whose host takes idle memory back, a build after a
    long idle gap waited for the host; Embree's small builds ran on one thread or two
    depending on the work before the rest)."""
    log = []
    monkeypatch.setattr(settle, "warm_pages", lambda n: log.append(("warm", n)))
    monkeypatch.setattr(settle.time, "sleep", lambda s: log.append(("rest", s)))
    monkeypatch.setattr(settle, "spin", lambda s: log.append(("busy", s)))
    real_build = M.build
    monkeypatch.setattr(M, "build", lambda mesh, kind, **cfg: log.append(("build", kind)) or real_build(mesh, kind, **cfg))
    small, large = S.sphere(80), S.soup(3000, seed=1)
    monkeypatch.setattr(M, "SMALL_SCENE", small.triangle_count)  # small: several builds; large: one
    monkeypatch.setattr(M, "SMALL_BUILDS", 3)
    o, d = uniform_rays(small, 50, seed=0)
    M.measure(small, "bvh", o, d, threads=1)
    M.measure(small, "grid", o, d, threads=1)
    M.measure(large, "bvh", o, d, threads=1)
    rest, busy = ("rest", settle.IDLE_BEFORE_BUILD), ("busy", settle.BUSY_BEFORE_BUILD)
    settled = lambda mesh, kind: [("warm", settle.warm_bytes(mesh.triangle_count)), rest, busy, ("build", kind)]  # noqa: E731
    assert log == settled(small, "bvh") * 3 + settled(small, "grid") + settled(large, "bvh")
    assert 0.02 <= settle.IDLE_BEFORE_BUILD <= 0.5  # past the fast state (< 20 ms), short of the host's handback
    assert 0.05 <= settle.BUSY_BEFORE_BUILD <= 0.5  # 20 ms left the state of the work before; 100 ms did not


def test_a_small_scenes_measurement_keeps_its_median_build_with_that_builds_own_kernel_figures(monkeypatch):
    """A fitted structure on a scene of at most SMALL_SCENE triangles is built SMALL_BUILDS
    times, each settled, and the measurement keeps the median build's time, faults, system
    and CPU seconds; the rays are traced through the last structure built.  A larger scene,
    the grid (no constant is fitted to its build) and ``builds=1`` build once."""
    times = iter([0.004, 0.001, 0.003, 0.002, 0.009])
    usage = iter([(0, 0.0, 0.0), (10, 0.001, 0.006),      # 0.004 s
                  (10, 0.001, 0.006), (11, 0.001, 0.007),  # 0.001 s
                  (11, 0.001, 0.007), (41, 0.004, 0.013),  # 0.003 s: the median
                  (41, 0.004, 0.013), (43, 0.004, 0.016),  # 0.002 s
                  (43, 0.004, 0.016), (99, 0.010, 0.034)])  # 0.009 s
    built, traced = [], []

    class Fake:
        threads = 2

        def __init__(self):
            self.build_time = next(times)
            built.append(self)

    monkeypatch.setattr(M, "settle_before_build", lambda n: None)
    monkeypatch.setattr(M, "_kernel_usage", lambda: next(usage))
    monkeypatch.setattr(M, "build", lambda mesh, kind, **cfg: Fake())
    monkeypatch.setattr(M, "time_trace", lambda accel, o, d: traced.append(accel) or (None, 0.5))
    mesh = S.sphere(80)
    assert mesh.triangle_count <= M.SMALL_SCENE and M.SMALL_BUILDS == 5
    o, d = uniform_rays(mesh, 10, seed=0)
    m = M.measure(mesh, "embree", o, d)
    assert len(built) == 5 and traced == [built[-1]]
    assert (m.build_time, m.build_faults, m.build_system, m.build_cpu, m.trace_time, m.rays, m.threads) == (
        0.003, 30, pytest.approx(0.003), pytest.approx(0.006), 0.5, 10, 2)
    assert [M.builds_per_measurement(n, "bvh") for n in (1, M.SMALL_SCENE, M.SMALL_SCENE + 1, 10 ** 6)] == [5, 5, 1, 1]
    assert M.builds_per_measurement(1, "embree") == 5 and M.builds_per_measurement(1, "grid") == 1
    built.clear()
    times = iter([0.007])
    usage = iter([(0, 0.0, 0.0), (3, 0.001, 0.01)])
    assert M.measure(mesh, "bvh", o, d, builds=1).build_time == 0.007 and len(built) == 1


def test_spin_keeps_the_thread_busy_for_the_time_asked_without_sleeping(monkeypatch):
    def no_sleep(s):
        raise AssertionError("spin slept")

    monkeypatch.setattr(settle.time, "sleep", no_sleep)
    t0 = time.perf_counter()
    settle.spin(0.03)
    assert time.perf_counter() - t0 >= 0.03


def test_warm_bytes_is_512_a_triangle_between_16_mib_and_1_gib_and_an_eighth_of_free_memory(monkeypatch):
    page = 4096
    free = {"pages": 1 << 30}  # 4 TiB free: no cap from it
    monkeypatch.setattr(settle.os, "sysconf", lambda name: {"SC_AVPHYS_PAGES": free["pages"], "SC_PAGE_SIZE": page}[name])
    assert settle.warm_bytes(0) == settle.warm_bytes(1000) == 16 << 20
    assert settle.warm_bytes(1_000_000) == 512_000_000
    assert settle.warm_bytes(3_000_000) == 1 << 30
    free["pages"] = (800 << 20) // page  # 800 MiB free: at most 100 MiB
    assert settle.warm_bytes(1_000_000) == 100 << 20
    assert settle.warm_bytes(10) == 16 << 20


def test_warm_pages_writes_the_memory_it_is_asked_for_and_keeps_none_of_it():
    import tracemalloc

    tracemalloc.start()
    try:
        settle.warm_pages(8 << 20)
        current, peak = tracemalloc.get_traced_memory()
        settle.warm_pages(0)
        settle.warm_pages(-5)
    finally:
        tracemalloc.stop()
    assert peak >= 8 << 20 and current < 1 << 20


@pytest.mark.slow
def test_a_quick_calibration_measures_everything_and_a_plan_decides_with_it(tmp_path):
    """A real calibration ('quick': minutes): every pass, every sample size, the grid's
    large-workload reference, the count models; saved, loaded and used by a plan."""
    from hybrid_raycast.core import embree_available
    from hybrid_raycast.core.plan import plan

    kinds = ("bvh", "embree") if embree_available() else ("bvh",)
    cal = calibrate(scale="quick", kinds=kinds)
    assert cal.scale == "quick" and len(cal.scenes) == len(S.calibration_set("quick")) and set(cal.fits) == set(kinds)
    for r in cal.scenes:
        assert sorted(r.grid_samples) == list(M.SAMPLE_LADDER), r.name
        assert r.kinds["grid"].rays >= M.GRID_LARGE_RAYS and r.kinds["bvh"].rays == M.RAYS_PER_SCENE["quick"]
        assert all(len(v) == M.CALIBRATION_REPEATS for v in r.passes.values()), r.name
    assert {"grid", "bvh"} <= set(cal.counts), "a fresh calibration holds the count models"
    back = load(cal.save(tmp_path / "cal.json"))
    mesh = S.make_scene("torus", 20000, seed=3)
    p = plan(mesh, 1e6, back, kinds=("grid",) + kinds)
    assert p.decision in {"GRID", "BVH", "EMBREE"} and set(p.candidates) == {"grid", *kinds}
    if p.grid_built:
        assert 0 < p.break_even_low <= p.break_even <= p.break_even_high or p.break_even == math.inf
    else:  # settled by the calibration alone (Embree): its break-even interval is the floor and the ceiling
        assert p.decision == "EMBREE" and p.samples == 0 and p.grid is None
        assert 0 <= p.break_even_low <= p.break_even <= p.break_even_high == p.break_even_ceiling <= 1e6
    m = plan(mesh, 1e6, back, kinds=("grid", "bvh"), prior=False)  # the measured path, whatever the prior says
    assert m.grid_built and m.samples > 0
    assert 0 < m.break_even_low <= m.break_even <= m.break_even_high or m.break_even == math.inf
