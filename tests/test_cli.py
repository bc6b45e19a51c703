"""The -c hybrid_raycast command, called as Blender calls it: handler(argv) -> exit code."""

import io
import json

import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, addon, fresh, make_nan, props, simple_scene  # noqa: E402,F401

pytestmark = pytest.mark.blender


def run(addon, *argv):
    out, err = io.StringIO(), io.StringIO()
    code = addon.operators.cli.main(list(argv), stdout=out, stderr=err)
    return code, out.getvalue(), err.getvalue()


def one_line(err):
    lines = [x for x in err.strip().splitlines() if x]
    assert len(lines) == 1, f"expected one line on stderr, got {lines}"
    return lines[0]


def test_register_adds_the_cli_command_and_unregister_removes_it(addon):
    assert addon._cli_handle is not None
    addon.unregister()
    try:
        assert addon._cli_handle is None
    finally:
        addon.register()
    assert addon._cli_handle is not None


def test_analyze_writes_json_with_every_figure_the_panel_shows(fresh, addon, tmp_path):
    simple_scene()
    code, out, err = run(addon, "analyze", "--rays", "2e6", "--json", str(tmp_path / "a.json"), "--output", str(tmp_path / "o"))
    assert code == 0, err
    doc = json.loads((tmp_path / "a.json").read_text())
    p = props()
    assert doc["decision"] == p.decision and p.decision in {"GRID", "BVH", "EMBREE"}
    assert doc["expected_rays"] == pytest.approx(2e6) and p.ray_budget == "CUSTOM"
    assert doc["summary"]["triangles"] == p.triangle_count == 14
    for key in ("objects", "instances", "bounds", "extraction_seconds"):
        assert key in doc["summary"], key
    for key in ("rays", "low", "high", "infinite", "against"):
        assert key in doc["break_even"], key
    for key in ("width", "height", "samples", "path_length", "source", "rays"):
        assert key in doc["budget"], key
    for kind, c in doc["structures"].items():
        assert c["build_time"] >= 0 and c["per_ray"] > 0, kind
    assert doc["structures"]["grid"]["per_ray"] == pytest.approx(p.grid_per_ray, rel=1e-6)
    for key in ("analyzed_at", "analysis_seconds", "calibration", "certain", "stale", "stale_reason", "settings", "plan"):
        assert key in doc, key
    assert doc["stale"] is False
    assert (tmp_path / "o" / "hybrid_raycast_plot.png").is_file()
    assert f"decision {p.decision}" in out


def test_trace_writes_the_passes_and_the_trace_figures(fresh, addon, tmp_path):
    simple_scene(resolution=(48, 32))
    code, out, err = run(addon, "trace", "--output", str(tmp_path))
    assert code == 0, err
    for stem in ("depth", "normal", "object_id", "plot"):
        assert (tmp_path / f"hybrid_raycast_{stem}.png").is_file(), stem
    doc = json.loads((tmp_path / "hybrid_raycast_trace.json").read_text())
    assert doc["trace"]["rays"] == 48 * 32 and doc["trace"]["workload"] == "CAMERA"
    assert doc["decision"] in {"GRID", "BVH", "EMBREE"}, "trace analyzes first when there is no analysis"
    assert doc["last_trace"]["structure"] == doc["trace"]["structure"].upper()
    # 1,536 rays are fewer than the plan's K samples: planning answered them all, unless
    # Embree was chosen (it never mixes in the grid's answers)
    assert doc["trace"]["rays_traced_after_plan"] == (48 * 32 if doc["trace"]["structure"] == "embree" else 0), doc["trace"]


def test_trace_ao_bakes_the_named_object(fresh, addon):
    simple_scene()
    code, out, err = run(addon, "trace", "--workload", "ao", "--object", "Cube", "--ao-samples", "4")
    assert code == 0, err
    assert "HRC AO" in bpy.data.objects["Cube"].data.color_attributes


def test_report_reuses_a_fresh_analysis_and_reanalyzes_a_stale_one(fresh, addon, tmp_path):
    simple_scene()
    run(addon, "analyze")
    first = props().analyzed_at, props().last_analysis_json
    code, out, err = run(addon, "report", "--json", "-")
    assert code == 0, err
    doc = json.loads(out[out.index("{"):])
    assert props().last_analysis_json == first[1], "report re-analyzed a fresh analysis"
    assert doc["decision"] == props().decision and doc["stale"] is False
    bpy.data.objects["Cube"].location.z += 1
    bpy.context.evaluated_depsgraph_get()
    assert props().stale
    code, out, err = run(addon, "report", "--json", str(tmp_path / "r.json"))
    assert code == 0, err
    assert props().last_analysis_json != first[1], "report kept a stale analysis"
    assert json.loads((tmp_path / "r.json").read_text())["stale"] is False


def test_report_without_any_analysis_analyzes(fresh, addon):
    simple_scene()
    code, out, err = run(addon, "report")
    assert code == 0, err
    assert props().has_results


def test_calibrate_writes_the_given_file(fresh, addon, tmp_path):
    target = tmp_path / "cal" / "c.json"
    code, out, err = run(addon, "calibrate", "--scale", "tiny", "--calibration", str(target), "--json", str(tmp_path / "c.json"))
    assert code == 0, err
    assert target.is_file()
    doc = json.loads((tmp_path / "c.json").read_text())
    assert doc["path"] == str(target) and "bvh" in doc["calibration"]["fits"]


def test_blend_argument_opens_a_saved_file(fresh, addon, tmp_path):
    simple_scene()
    bpy.context.scene.name = "Saved"
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    code, out, err = run(addon, "analyze", "--blend", str(path), "--rays", "1e5", "--json", str(tmp_path / "a.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "a.json").read_text())
    assert doc["scene"] == "Saved" and doc["summary"]["triangles"] == 14
    assert doc["file"] == str(path)


@pytest.mark.parametrize("argv, code, words", [
    (["explode"], 2, "invalid choice"),
    (["analyze", "--rays", "0"], 2, "greater than 0"),
    (["analyze", "--rays", "many"], 2, "not a number"),
    (["analyze", "--frobnicate"], 2, "unrecognized arguments"),
    (["analyze", "--blend", "/nonexistent/x.blend"], 2, "no such file"),
    (["analyze", "--scene", "Nope"], 2, "no such scene"),
    (["analyze", "--candidates", "kd-tree"], 2, "unknown kd-tree"),
    ([], 2, "required"),
])
def test_bad_arguments_exit_2_with_one_line(fresh, addon, argv, code, words):
    add_cube("Cube")
    got, out, err = run(addon, *argv)
    line = one_line(err)
    assert got == code, f"exit {got}, expected {code}: {line}"
    assert words in line and line.startswith("hybrid_raycast"), line


def test_help_exits_0(addon, capsys):
    got, out, err = run(addon, "--help")
    assert got == 0


def test_no_geometry_exits_3(fresh, addon):
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("Empty", None))
    got, out, err = run(addon, "analyze")
    assert got == 3 and "no geometry" in one_line(err)


def test_unwritable_paths_exit_4(fresh, addon, tmp_path):
    add_cube("Cube")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for argv in (["analyze", "--json", str(blocker / "a.json")],
                 ["analyze", "--output", str(blocker / "out")],
                 ["analyze", "--json", str(tmp_path)],
                 ["calibrate", "--scale", "tiny", "--calibration", str(blocker / "c.json")]):
        got, out, err = run(addon, *argv)
        assert got == 4, f"{argv}: exit {got}: {err}"
        assert "unwritable path" in one_line(err)
    assert not props().has_results, "an unwritable --json must fail before analysing"


def test_nan_geometry_exits_5(fresh, addon):
    make_nan(add_cube("Broken"))
    got, out, err = run(addon, "analyze")
    assert got == 5 and "'Broken'" in one_line(err)


def test_trace_without_a_camera_exits_6(fresh, addon):
    add_cube("Cube")
    got, out, err = run(addon, "trace")
    assert got == 6 and "no camera" in one_line(err)
    got, out, err = run(addon, "trace", "--workload", "ao", "--object", "Nope")
    assert got == 6 and "no mesh to bake" in one_line(err)
