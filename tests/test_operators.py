"""The operators in background mode: results, every failure, the stale flag, cancelling."""

import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, add_plane, addon, fresh, make_nan, props, simple_scene, unweld  # noqa: E402,F401

pytestmark = pytest.mark.blender

NEVER = 3.4028234663852886e38


def analyze():
    return bpy.ops.hybrid_raycast.analyze()


def test_analyze_fills_every_result_and_agrees_with_its_own_json(fresh, addon):
    simple_scene()
    # a soup and a candidate the calibration cannot settle alone: the grid is measured
    unweld(bpy.data.objects["Cube"])
    props().candidates = {"BVH"}
    assert analyze() == {"FINISHED"}
    p = props()
    assert p.has_results and p.decision in {"GRID", "BVH", "EMBREE"}
    assert p.triangle_count == 14, f"cube + quad ground should give 14 triangles, got {p.triangle_count}"
    assert p.object_count == 2
    assert p.grid_build_time > 0 and p.grid_per_ray > 0 and p.samples_traced == 2048
    assert p.analyzed_rays == pytest.approx(1e6)
    assert p.analyzed_at and p.analysis_duration > 0
    assert not p.stale, p.stale_reason
    rec = json.loads(p.last_analysis_json)
    be = rec["break_even"]
    assert rec["decision"] == p.decision
    if be["rays"] is None:
        assert p.break_even_infinite and p.break_even_rays == pytest.approx(NEVER, rel=1e-6)
    else:
        assert not p.break_even_infinite and p.break_even_rays == pytest.approx(be["rays"], rel=1e-6)
    # the decision follows the break-even rule: the grid up to R*, else the cheapest candidate
    if p.decision == "GRID":
        assert p.analyzed_rays <= p.break_even_rays * (1 + 1e-6), (p.analyzed_rays, p.break_even_rays)
    else:
        assert p.analyzed_rays > p.break_even_rays * (1 - 1e-6), (p.analyzed_rays, p.break_even_rays)
    assert rec["structures"]["grid"]["per_ray"] == pytest.approx(p.grid_per_ray, rel=1e-6)
    # the large-workload estimate is the sample's time times the calibrated batch ratio
    assert 0 < p.grid_sample_ratio == pytest.approx(rec["plan"]["grid_sample_ratio"], rel=1e-6)
    assert p.grid_per_ray == pytest.approx(rec["plan"]["grid_sample_per_ray"] * rec["plan"]["grid_sample_ratio"], rel=1e-5)
    # the sidebar says which estimate it shows: the sample's work counts (shipped calibration) or its time
    work = rec["plan"].get("work")
    assert work is not None, "the shipped calibration holds count models, so the plan estimates from counts"
    assert p.grid_cells_per_ray == pytest.approx(work["cells"], rel=1e-6) and p.grid_cells_per_ray > 0
    # the counts the shipped grid model weighs: the traversal's steps and candidate triangles
    assert p.grid_steps_per_ray == pytest.approx(work["steps"], rel=1e-6) and p.grid_steps_per_ray > 0
    assert p.grid_candidates_per_ray == pytest.approx(work["candidates"], rel=1e-6) and p.grid_candidates_per_ray > 0
    # refs are counted only when a count model weighs them; otherwise the panel hides them
    assert p.grid_refs_per_ray == (0.0 if work["refs"] is None else pytest.approx(work["refs"], rel=1e-6))
    assert rec["summary"]["triangles"] == p.triangle_count
    assert p.break_even_warning == rec["plan"]["ill_conditioned"]
    rec["plan"]["ill_conditioned"] = "ill-conditioned: the grid is only 1.20x slower per ray than bvh, so a 10% error"
    addon.operators.analyze.store_results(p, rec)
    assert p.break_even_warning.startswith("ill-conditioned: the grid is only 1.20x")


def test_sidebar_quotes_only_the_counts_the_grid_model_weighed(fresh, addon):
    """A calibration made before the grid counted its traversal weighs cells: the sample
    still counts steps and candidates, but the sidebar must not quote counts the estimate
    did not use (it falls back to the cells line)."""
    simple_scene()
    unweld(bpy.data.objects["Cube"])  # a soup: the grid is measured
    props().candidates = {"BVH"}
    assert analyze() == {"FINISHED"}
    p = props()
    rec = json.loads(p.last_analysis_json)
    assert rec["plan"]["grid_terms"] and "cells" not in rec["plan"]["grid_terms"], rec["plan"]["grid_terms"]
    work = rec["plan"]["work"]
    assert work["steps"] > 0 and work["candidates"] > 0
    rec["plan"]["grid_terms"] = ["cells"]
    addon.operators.analyze.store_results(p, rec)
    assert p.grid_steps_per_ray == 0.0 and p.grid_candidates_per_ray == 0.0
    assert p.grid_cells_per_ray == pytest.approx(work["cells"], rel=1e-6) and p.grid_cells_per_ray > 0


def test_analyze_settles_for_embree_without_a_grid_above_the_calibrations_ceiling(fresh, addon):
    """Embree beats the grid per ray on every calibration scene: for rays above the
    calibration's ceiling on the break-even, the analysis builds no grid and traces no sample,
    and says so; below the ceiling it measures the grid."""
    from hybrid_raycast.core.plan import NO_SAMPLE_DEAR, NO_SAMPLE_FLOOR

    if not addon.core.embree_available():
        pytest.skip("embreex is not importable here")
    simple_scene()
    p = props()
    p.candidates = {"BVH", "EMBREE"}
    assert analyze() == {"FINISHED"}
    rec = json.loads(p.last_analysis_json)
    ceiling = rec["plan"]["break_even_ceiling"]
    assert not p.grid_built and rec["plan"]["grid_built"] is False and p.decision == "EMBREE"
    assert p.samples_traced == 0 and ceiling is not None and p.analyzed_rays >= ceiling
    assert p.break_even_ceiling == pytest.approx(ceiling, rel=1e-6)
    assert p.break_even_low <= p.break_even_rays <= p.break_even_high == pytest.approx(ceiling, rel=1e-6, abs=1e-9)
    assert any("without a grid or a sample" in n for n in rec["plan"]["notes"])
    if ceiling > 0:  # below the bound the grid is built (0: Embree builds faster on the estimates for N)
        p.expected_rays = ceiling / 4
        assert analyze() == {"FINISHED"}
        assert p.grid_built and p.grid_build_time > 0
        # then a sample decides, or the panel says why none was traced (below the calibration's floor, or
        # where it would cost more than its share of so few rays' trace)
        assert p.samples_traced > 0 or p.no_sample_reason in (NO_SAMPLE_FLOOR, NO_SAMPLE_DEAR)


def test_invoke_in_background_runs_synchronously(fresh):
    simple_scene()
    assert bpy.ops.hybrid_raycast.analyze("INVOKE_DEFAULT") == {"FINISHED"}
    assert props().has_results


def test_render_budget_multiplies_every_factor_and_typing_a_number_switches_to_custom(fresh):
    simple_scene(resolution=(200, 100))
    p = props()
    scene = bpy.context.scene
    scene.render.resolution_percentage = 50
    p.ray_budget = "RENDER"
    p.path_length = 4.0
    samples = p.render_samples
    assert samples >= 1
    assert p.expected_rays == pytest.approx(100 * 50 * samples * 4.0, rel=1e-6)
    p.expected_rays = 12345.0
    assert p.ray_budget == "CUSTOM" and p.custom_rays == pytest.approx(12345.0)


def test_infinite_break_even_is_a_flag_and_null_in_json(fresh, addon, tmp_path):
    core = addon.core
    cal = core.Calibration(fits={"bvh": core.decide.KindFit(1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1)}, source="measured")
    cal.save(addon.operators.calibrate.calibration_path())
    simple_scene()
    props().candidates = {"BVH"}
    assert analyze() == {"FINISHED"}
    p = props()
    assert p.calibration_source == "measured"
    assert p.break_even_infinite and p.break_even_low_infinite and p.break_even_high_infinite
    assert p.break_even_rays == pytest.approx(NEVER, rel=1e-6)
    assert p.decision == "GRID"
    rec = json.loads(p.last_analysis_json)
    assert rec["break_even"] == {"rays": None, "low": None, "high": None, "infinite": True, "against": None}


@pytest.mark.parametrize("setup, message", [
    ("empty", "no geometry"),
    ("non_geometry", "no geometry"),
    ("nan", "NaN or infinite vertex coordinates in 'Broken'"),
    ("zero_rays", "expected rays is 0"),
])
def test_analyze_failures_say_why_and_leave_no_results(fresh, setup, message):
    if setup == "non_geometry":
        cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
        empty = bpy.data.objects.new("Empty", None)
        light = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "SUN"))
        for ob in (cam, empty, light):
            bpy.context.scene.collection.objects.link(ob)
    elif setup == "nan":
        add_cube("Fine")
        make_nan(add_cube("Broken", location=(3, 0, 0)))
    elif setup == "zero_rays":
        add_cube("Cube")
        props().custom_rays = 0.0
    with pytest.raises(RuntimeError) as err:
        analyze()
    assert message in str(err.value), f"expected {message!r} in the report, got {err.value}"
    assert "Traceback" not in str(err.value)
    assert len(str(err.value).strip().splitlines()) == 1, f"not one line: {err.value!r}"
    p = props()
    assert not p.has_results and p.decision == "NONE" and not p.last_analysis_json


def test_missing_and_corrupt_calibration_warn_and_fall_back(fresh, addon, capfd):
    simple_scene()
    assert analyze() == {"FINISHED"}
    p = props()
    assert p.calibration_source == "shipped defaults"
    assert "no calibration file" in p.calibration_message
    assert "no calibration file" in capfd.readouterr().out, "the fallback should be reported as a warning"
    path = addon.operators.calibrate.calibration_path()
    path.write_text("{ not json")
    assert analyze() == {"FINISHED"}
    assert "not valid JSON" in p.calibration_message and p.calibration_source == "shipped defaults"
    assert "not valid JSON" in capfd.readouterr().out


def test_without_embreex_the_decision_is_between_grid_and_bvh(fresh, addon, monkeypatch):
    monkeypatch.setattr(addon.core.embree, "embree_available", lambda: False)
    simple_scene()
    props().custom_rays = 1e12
    assert analyze() == {"FINISHED"}
    p = props()
    assert not p.embree_available and not p.embree_considered
    assert p.decision in {"GRID", "BVH"}
    reason = addon.core.embree.embree_unavailable_reason()
    assert reason and p.embree_unavailable == reason, (p.embree_unavailable, reason)
    assert f"Embree unavailable: {reason}; deciding between the grid and the BVH" in p.notes, p.notes
    record = json.loads(p.last_analysis_json)
    assert "embree" not in record["structures"] and record["embree_unavailable"] == reason
    bpy.context.view_layer.objects.active = bpy.data.objects["Cube"]
    assert bpy.ops.hybrid_raycast.trace(workload="CAMERA") == {"FINISHED"}
    assert p.trace_structure in {"GRID", "BVH"}


def test_stale_flag_follows_geometry_visibility_and_settings_but_not_cameras(fresh):
    simple_scene()
    p = props()
    assert not p.stale, "no results: nothing is stale"
    analyze()
    assert not p.stale, p.stale_reason

    def evaluate():
        bpy.context.evaluated_depsgraph_get()

    bpy.data.objects["Camera"].location.x += 1.0
    evaluate()
    assert not p.stale, f"moving the camera must not make results stale: {p.stale_reason}"
    bpy.data.objects["Cube"].location.x += 1.0
    evaluate()
    assert p.stale and "scene changed" in p.stale_reason
    analyze()
    assert not p.stale
    bpy.data.objects["Cube"].hide_set(True)
    evaluate()
    assert p.stale, "hiding an object changes what is extracted"
    bpy.data.objects["Cube"].hide_set(False)
    analyze()
    add_cube("Another", location=(5, 5, 5))
    evaluate()
    assert p.stale, "adding an object changes the scene"
    analyze()
    p.custom_rays = 5e6
    assert p.stale and "expected rays" in p.stale_reason
    p.custom_rays = 1e6
    assert not p.stale
    p.grid_density = 3.0
    assert p.stale and "grid density" in p.stale_reason


def test_the_ao_bake_does_not_make_results_stale(fresh):
    simple_scene()
    analyze()
    bpy.context.view_layer.objects.active = bpy.data.objects["Cube"]
    assert bpy.ops.hybrid_raycast.trace(workload="AO") == {"FINISHED"}
    bpy.context.evaluated_depsgraph_get()
    assert not props().stale, props().stale_reason
    bpy.data.objects["Cube"].data.vertices[0].co.z += 0.5
    bpy.data.objects["Cube"].data.update()
    bpy.context.evaluated_depsgraph_get()
    assert props().stale, "a real edit after the bake must still count"


def test_calibrate_writes_the_injected_file_and_analyze_uses_it(fresh, addon):
    path = addon.operators.calibrate.calibration_path()
    assert not path.exists()
    assert bpy.ops.hybrid_raycast.calibrate(scale="tiny") == {"FINISHED"}
    assert path.is_file()
    simple_scene()
    analyze()
    assert props().calibration_source == "measured"
    assert str(path) in props().calibration_message


def test_a_calibration_that_stayed_disturbed_is_reported_as_a_warning(addon):
    """The busy-machine note of a calibration (other programs took the CPU through every
    retake) reaches the user as a WARNING; its other notes do not."""
    mod = addon.operators.calibrate
    m = addon.core.decide.load_watch
    busy = m.quiet_notes([(0.4, 1 + m.QUIET_RETRIES), (0.01, 1)], m.QUIET_SHARE)
    cal = addon.core.decide.Calibration({}, notes=["embree skipped: not here"] + busy)
    msgs = mod.apply_calibration(None, {"calibration": cal, "path": "/tmp/x.json", "kinds": ("bvh", "embree")})
    warnings = [text for level, text in msgs if level == "WARNING"]
    assert warnings == [busy[-1]] and "40%" in busy[-1] and busy[-1].endswith(m.BUSY_ADVICE)


def test_calibrate_to_an_unwritable_place_fails_cleanly(fresh, addon, tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    monkeypatch.setattr(addon.operators.calibrate, "CALIBRATION_PATH", str(blocker / "sub" / "calibration.json"))
    with pytest.raises(RuntimeError, match="unwritable path"):
        bpy.ops.hybrid_raycast.calibrate(scale="tiny")


def test_calibration_path_is_the_extension_user_folder_when_installed(addon, monkeypatch):
    mod = addon.operators.calibrate
    monkeypatch.setattr(mod, "CALIBRATION_PATH", None)
    monkeypatch.delenv(mod.ENV, raising=False)
    monkeypatch.setattr(mod, "PACKAGE", "bl_ext.user_default.hybrid_raycast")
    seen = {}

    def fake(package, path="", create=False):
        seen["args"] = (package, path, create)
        return "/somewhere/extensions/.user/user_default/hybrid_raycast"

    monkeypatch.setattr(bpy.utils, "extension_path_user", fake)
    assert str(mod.calibration_path()) == "/somewhere/extensions/.user/user_default/hybrid_raycast/calibration.json"
    assert seen["args"] == ("bl_ext.user_default.hybrid_raycast", "", True)
    monkeypatch.setenv(mod.ENV, "/elsewhere/cal.json")
    assert str(mod.calibration_path()) == "/elsewhere/cal.json"


def test_a_cancelled_analysis_leaves_the_scene_unchanged(fresh, addon):
    simple_scene()
    from hybrid_raycast.operators.analyze import analysis_job
    from hybrid_raycast.operators.jobs import Job

    before = {k: getattr(props(), k) for k in ("has_results", "decision", "triangle_count", "last_analysis_json")}
    job = Job(threaded=True)
    gen = analysis_job(bpy.context.scene, job)
    next(gen)  # extraction is next
    next(gen)  # extraction done; the grid is being built in a worker thread
    job.cancel_event.set()
    gen.close()
    after = {k: getattr(props(), k) for k in before}
    assert after == before, f"a cancelled analysis changed the scene: {before} -> {after}"


def test_a_cancelled_trace_writes_no_images(fresh, addon):
    simple_scene()
    from hybrid_raycast.operators.jobs import Cancelled, Job, run_sync
    from hybrid_raycast.operators.trace import trace_job

    job = Job(threaded=False)
    gen = trace_job(bpy.context.scene, job, workload="CAMERA")
    next(gen)
    job.cancel_event.set()
    with pytest.raises(Cancelled):
        run_sync(gen)
    assert not [i.name for i in bpy.data.images if i.name.startswith("HRC ")]
    assert props().trace_structure == "NONE"


def test_operators_that_change_data_are_undoable(addon):
    ops = addon.operators
    assert "UNDO" in ops.HYBRID_RAYCAST_OT_analyze.bl_options
    assert "UNDO" in ops.HYBRID_RAYCAST_OT_trace.bl_options
    assert "UNDO" not in ops.HYBRID_RAYCAST_OT_calibrate.bl_options  # writes a file, not the scene


def test_every_property_has_a_name_description_and_sane_bounds(addon):
    props_cls = addon.settings.HybridRaycastSettings
    problems = []
    for name, p in props_cls.__annotations__.items():
        kw = p.keywords
        if not kw.get("name") or not kw.get("description"):
            problems.append(f"{name}: no name/description")
        if p.function.__name__ in ("FloatProperty", "IntProperty") and "get" not in kw and "min" not in kw:
            problems.append(f"{name}: no lower bound")
    assert not problems, problems


def test_the_panel_draw_code_runs(fresh, addon):
    """Panels cannot draw without a window; call draw() with a recording layout instead."""
    simple_scene()
    analyze()

    class Rec:
        def __init__(self):
            self.calls = []

        def __getattr__(self, name):
            def f(*a, **k):
                self.calls.append((name, a, k))
                return self
            return f

        def __setattr__(self, k, v):
            if k == "calls":
                object.__setattr__(self, k, v)

    def draw():
        texts, icons = [], []
        for cls in addon.ui.classes:
            layout = Rec()
            panel = type("P", (), {"layout": layout})()
            cls.draw(panel, bpy.context)
            texts += [k.get("text", "") for n, a, k in layout.calls if n == "label"]
            icons += [k.get("icon_value") for n, a, k in layout.calls if n == "template_icon"]
        return texts, icons

    texts, icons = draw()
    p = props()
    assert any(t == p.decision for t in texts), f"the decision is not drawn: {texts}"
    assert any(t.startswith("Break-even:") for t in texts), texts
    if not p.grid_built:  # Embree settled by the calibration alone: said so, no grid figures
        assert "Grid: not built" in texts and any("no grid built" in t for t in texts), texts
    p.candidates = {"BVH"}
    analyze()  # a surface at a million rays: the BVH within the slack of the grid, no grid built
    near, _ = draw()
    assert not p.grid_built and p.settled_slack > 0 and p.decision == "BVH", (p.grid_built, p.settled_slack)
    assert "Grid: not built" in near and any("costs at most 5% more than the grid" in t for t in near), near
    assert any(t.startswith("Interval: [") and "inf]" in t for t in near), near
    unweld(bpy.data.objects["Cube"])  # the same triangles as a soup: measured
    analyze()
    measured, _ = draw()
    assert any(t.startswith("Grid: build") for t in measured), measured
    # without a GPU (background) previews get no icon id; the pixels are still drawn
    pv = addon.ui.plot._previews.get(f"plot {bpy.context.scene.name}")
    assert pv is not None and tuple(pv.image_size) == (256, 256), "the plot preview was not drawn"
    assert all(icons), f"template_icon with icon 0: {icons}"


def test_unregister_removes_the_handlers_and_register_restores_them(addon):
    def ours():
        return [h for name in ("depsgraph_update_post", "frame_change_post", "load_post")
                for h in getattr(bpy.app.handlers, name) if getattr(h, "__module__", "").startswith("hybrid_raycast")]

    assert len(ours()) == 3
    addon.unregister()
    try:
        assert ours() == [], f"handlers left behind: {ours()}"
    finally:
        addon.register()
    assert len(ours()) == 3


def test_the_calibration_scales_have_one_description_in_the_operator_the_settings_and_the_cli(fresh, addon):
    """The Calibrate operator's scales, the scene setting's and the CLI's --scale help all read
    core's SCALE_NOTES, whose full-set text names its minutes and repeats."""
    notes = addon.core.decide.measurements.SCALE_NOTES
    op = bpy.ops.hybrid_raycast.calibrate.get_rna_type().properties["scale"].enum_items
    setting = props().bl_rna.properties["calibration_scale"].enum_items
    for k in ("tiny", "quick", "default"):
        assert op[k].description == setting[k].description == notes[k]
    full = notes["default"]
    assert f"{addon.core.decide.measurements.FULL_CALIBRATION_MINUTES} minutes" in full
    assert f"{addon.core.decide.measurements.CALIBRATION_REPEATS} passes" in full
    assert full in " ".join(addon.operators.cli.parser().format_help().split())


def test_bake_proximity_writes_each_vertexs_distance_to_the_other_geometry(fresh):
    from blender_scenes import add_mesh

    add_cube("Cube", 2.0, (0.0, 0.0, 3.0))  # its bottom face at z = 2
    plane = add_mesh("Probe", [(0, 0, 0), (0.5, 0, 0), (0, 0.5, 0), (0.0, 0.0, 2.5)], [(0, 1, 2)])
    bpy.context.view_layer.objects.active = plane
    bpy.context.view_layer.update()
    assert bpy.ops.hybrid_raycast.bake_proximity() == {"FINISHED"}
    values = np.empty(4, np.float32)
    plane.data.attributes["HRC Proximity"].data.foreach_get("value", values)
    assert values == pytest.approx([2.0, 2.0, 2.0, 0.5], abs=1e-6)
    # signed, to the cube: the fourth vertex is inside it
    assert bpy.ops.hybrid_raycast.bake_proximity(to_object="Cube", attribute="to cube") == {"FINISHED"}
    plane.data.attributes["to cube"].data.foreach_get("value", values)
    assert values == pytest.approx([2.0, 2.0, 2.0, -0.5], abs=1e-6)
    assert not props().stale, "a float attribute changes no triangle"
    # beyond Max Distance: the max distance itself
    assert bpy.ops.hybrid_raycast.bake_proximity(attribute="near", max_distance=1.0) == {"FINISHED"}
    plane.data.attributes["near"].data.foreach_get("value", values)
    assert values == pytest.approx([1.0, 1.0, 1.0, 0.5], abs=1e-6)
    assert "UNDO" in bpy.types.HYBRID_RAYCAST_OT_bake_proximity.bl_options


def test_bake_proximity_refuses_what_it_cannot_measure(fresh):
    from blender_scenes import add_mesh

    plane = add_mesh("Alone", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
    bpy.context.view_layer.objects.active = plane
    with pytest.raises(RuntimeError, match="no triangles to measure against"):
        bpy.ops.hybrid_raycast.bake_proximity()
    with pytest.raises(RuntimeError, match="no object named 'Nope'"):
        bpy.ops.hybrid_raycast.bake_proximity(to_object="Nope")
    with pytest.raises(RuntimeError, match="cannot be measured against itself"):
        bpy.ops.hybrid_raycast.bake_proximity(to_object="Alone")
