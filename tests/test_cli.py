"""The -c hybrid_raycast command, called as Blender calls it: handler(argv) -> exit code."""

import io
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, addon, fresh, make_nan, props, run_cli, simple_scene  # noqa: E402,F401

pytestmark = pytest.mark.blender


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
    code, out, err = run_cli(addon, "analyze", "--rays", "2e6", "--json", str(tmp_path / "a.json"), "--output", str(tmp_path / "o"))
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
    code, out, err = run_cli(addon, "trace", "--output", str(tmp_path))
    assert code == 0, err
    for stem in ("depth", "normal", "object_id", "plot"):
        assert (tmp_path / f"hybrid_raycast_{stem}.png").is_file(), stem
    doc = json.loads((tmp_path / "hybrid_raycast_trace.json").read_text())
    assert doc["trace"]["rays"] == 48 * 32 and doc["trace"]["workload"] == "CAMERA"
    assert doc["decision"] in {"GRID", "BVH", "EMBREE"}, "trace analyzes first when there is no analysis"
    assert doc["last_trace"]["structure"] == doc["trace"]["structure"].upper()
    # the rays the plan's samples answered are not traced again (Embree never mixes in the grid's
    # answers); for so few rays a sample would cost more than its share of their trace, so none is taken
    plan = doc["trace"]["plan"]
    answered = 0 if doc["trace"]["structure"] == "embree" else plan["workload_samples"]
    assert doc["trace"]["rays_traced_after_plan"] == 48 * 32 - answered, doc["trace"]
    assert plan["samples"] == 0 and (plan["no_sample"] or not plan["grid_built"]), plan


def test_trace_ao_bakes_the_named_object(fresh, addon):
    simple_scene()
    code, out, err = run_cli(addon, "trace", "--workload", "ao", "--object", "Cube", "--ao-samples", "4")
    assert code == 0, err
    assert "HRC AO" in bpy.data.objects["Cube"].data.color_attributes


def test_report_reuses_a_fresh_analysis_and_reanalyzes_a_stale_one(fresh, addon, tmp_path):
    simple_scene()
    run_cli(addon, "analyze")
    first = props().analyzed_at, props().last_analysis_json
    code, out, err = run_cli(addon, "report", "--json", "-")
    assert code == 0, err
    doc = json.loads(out)  # nothing but the JSON on stdout; the messages went to stderr
    assert "hybrid_raycast report: decision" in err
    assert props().last_analysis_json == first[1], "report re-analyzed a fresh analysis"
    assert doc["decision"] == props().decision and doc["stale"] is False
    bpy.data.objects["Cube"].location.z += 1
    bpy.context.evaluated_depsgraph_get()
    assert props().stale
    code, out, err = run_cli(addon, "report", "--json", str(tmp_path / "r.json"))
    assert code == 0, err
    assert props().last_analysis_json != first[1], "report kept a stale analysis"
    assert json.loads((tmp_path / "r.json").read_text())["stale"] is False


def test_report_without_any_analysis_analyzes(fresh, addon):
    simple_scene()
    code, out, err = run_cli(addon, "report")
    assert code == 0, err
    assert props().has_results


def test_calibrate_writes_the_given_file(fresh, addon, tmp_path):
    target = tmp_path / "cal" / "c.json"
    code, out, err = run_cli(addon, "calibrate", "--scale", "tiny", "--calibration", str(target), "--json", str(tmp_path / "c.json"))
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
    code, out, err = run_cli(addon, "analyze", "--blend", str(path), "--rays", "1e5", "--json", str(tmp_path / "a.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "a.json").read_text())
    assert doc["scene"] == "Saved" and doc["summary"]["triangles"] == 14
    assert doc["file"] == str(path)


@pytest.mark.parametrize("argv, code, words", [
    (["explode"], 2, "invalid choice"),
    (["analyze", "--rays", "0"], 2, "greater than 0"),
    (["analyze", "--rays", "-5"], 2, "greater than 0"),
    (["analyze", "--rays", "inf"], 2, "finite"),
    (["analyze", "--rays", "nan"], 2, "finite"),
    (["analyze", "--rays", "1e16"], 2, "at most 1e+15"),
    (["analyze", "--density", "inf"], 2, "finite"),
    (["calibrate", "--save"], 2, "changes no scene"),
    (["analyze", "--save"], 2, "no .blend is loaded"),
    (["analyze", "--save", "/tmp/x.txt"], 2, "not a .blend path"),
    (["analyze", "--rays", "many"], 2, "not a number"),
    (["analyze", "--frobnicate"], 2, "unrecognized arguments"),
    (["analyze", "--blend", "/nonexistent/x.blend"], 2, "no such file"),
    (["analyze", "--scene", "Nope"], 2, "no such scene"),
    (["analyze", "--candidates", "kd-tree"], 2, "unknown kd-tree"),
    ([], 2, "required"),
])
def test_bad_arguments_exit_2_with_one_line(fresh, addon, argv, code, words):
    add_cube("Cube")
    got, out, err = run_cli(addon, *argv)
    line = one_line(err)
    assert got == code, f"exit {got}, expected {code}: {line}"
    assert words in line and line.startswith("hybrid_raycast"), line


def test_help_exits_0(addon, capsys):
    got, out, err = run_cli(addon, "--help")
    assert got == 0


def test_no_geometry_exits_3(fresh, addon):
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("Empty", None))
    got, out, err = run_cli(addon, "analyze")
    assert got == 3 and "no geometry" in one_line(err)


def test_unwritable_paths_exit_4(fresh, addon, tmp_path):
    add_cube("Cube")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for argv in (["analyze", "--json", str(blocker / "a.json")],
                 ["analyze", "--output", str(blocker / "out")],
                 ["analyze", "--json", str(tmp_path)],
                 ["calibrate", "--scale", "tiny", "--calibration", str(blocker / "c.json")]):
        got, out, err = run_cli(addon, *argv)
        assert got == 4, f"{argv}: exit {got}: {err}"
        assert "unwritable path" in one_line(err)
    assert not props().has_results, "an unwritable --json must fail before analysing"


def test_nan_geometry_exits_5(fresh, addon):
    make_nan(add_cube("Broken"))
    got, out, err = run_cli(addon, "analyze")
    assert got == 5 and "'Broken'" in one_line(err)


def test_trace_without_a_camera_exits_6(fresh, addon):
    add_cube("Cube")
    got, out, err = run_cli(addon, "trace")
    assert got == 6 and "no camera" in one_line(err)
    got, out, err = run_cli(addon, "trace", "--workload", "ao", "--object", "Nope")
    assert got == 6 and "no mesh to bake" in one_line(err)


# -- output a program can read ---------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]

_SUBPROCESS = textwrap.dedent("""
    import os, sys
    sys.path.insert(0, {scripts!r})
    import bpy
    from _package import load_addon
    addon = load_addon()
    addon.register()
    bpy.ops.wm.open_mainfile(filepath={blend!r})       # prints "Read blend" (Blender's C printf)
    print("python print before", flush=True)
    sys.stdout.flush(); os.write(1, b"<<<")            # stdout from here on is the command's
    cal = ["--calibration", {cal!r}]
    code = addon.operators.cli.main(["analyze", "--json", "-", "--rays", "1e6", *cal])
    print("between", flush=True)                       # fd 1 restored: main() was not Blender's handler
    sys.argv = ["blender", "-b", {blend!r}, "-c", "hybrid_raycast"]
    code2 = addon.operators.cli.handler(["trace", "--workload", "ao", "--object", "Cube", "--ao-samples", "4",
                                         "--json", "-", "--save", *cal])
    print("after the handler", flush=True)             # Blender exits next: this goes to stderr
    from _bpy_exit import exit_past_bpy                # past bpy 4.2's segfault at exit, with our code
    exit_past_bpy(code * 16 + code2)
""")


def test_json_dash_puts_only_the_json_on_stdout_even_blenders_own_prints(fresh, addon, tmp_path):
    """Blender's C-level prints ("Read blend", "Info: Saved") and the add-on's messages go to
    stderr while a ``--json -`` command runs; stdout holds the JSON and nothing else."""
    simple_scene()
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    script = _SUBPROCESS.format(scripts=str(ROOT / "scripts"), blend=str(blend), cal=str(tmp_path / "absent.json"))
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, f"exit {p.returncode} (analyze*16 + trace)\n{p.stderr[-3000:]}"
    head, sep, tail = p.stdout.partition("<<<")
    assert sep and "Read blend" in head, "the probe did not see Blender's own print on stdout before the command"
    first, between, second = tail.partition("between\n")
    assert between, f"stdout after main() was not restored: {tail[:500]!r}"
    a, t = json.loads(first), json.loads(second)  # each part is one JSON document, nothing else
    assert a["command"] == "analyze" and a["decision"] in {"GRID", "BVH", "EMBREE"}
    assert t["command"] == "trace" and t["trace"]["workload"] == "AO" and t["files"]["blend"] == str(blend)
    assert "after the handler" in p.stderr and "after the handler" not in p.stdout
    assert "Saved" in p.stderr, "Blender's own 'Info: Saved' print should have gone to stderr"
    assert "hybrid_raycast analyze: decision" in p.stderr and "hybrid_raycast: info: traced" in p.stderr


def _decode(path):
    img = bpy.data.images.load(str(path))
    img.colorspace_settings.name = "Non-Color"  # the bytes as written, no sRGB decoding
    w, h = img.size
    a = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(a)
    return a.reshape(h, w, 4)[::-1]  # top row first


def test_trace_json_decodes_the_depth_and_object_id_pngs_like_scene_ray_cast(fresh, addon, tmp_path):
    """A program holding only the PNGs and the JSON recovers each pixel's depth and object:
    compared with Blender's own ``scene.ray_cast`` through the same pixel centres."""
    scene = simple_scene(resolution=(40, 30))
    add_cube("Box", 1.0, (2.2, 0.0, -0.2))
    bpy.context.view_layer.update()
    code, out, err = run_cli(addon, "trace", "--output", str(tmp_path), "--json", str(tmp_path / "t.json"))
    assert code == 0, err
    passes = json.loads((tmp_path / "t.json").read_text())["trace"]["passes"]
    near, far = passes["depth"]["near"], passes["depth"]["far"]
    table = passes["object_ids"]
    assert 0 < near < far and {e["name"] for e in table} == {"Cube", "Ground", "Box"}
    assert [e["index"] for e in table] == list(range(len(table)))
    depth = _decode(tmp_path / "hybrid_raycast_depth.png")
    ids = _decode(tmp_path / "hybrid_raycast_object_id.png")
    colors = np.array([e["color"] for e in table], np.float64)

    from hybrid_raycast.operators.passes import camera_workload

    deps = bpy.context.evaluated_depsgraph_get()
    rays = camera_workload(scene, deps)
    cam = scene.camera.matrix_world
    view = -np.array(cam.to_3x3().col[2])  # the camera looks down its -Z
    checked = wrong_object = 0
    worst_depth = 0.0
    for k in range(0, 40 * 30, 7):
        r, c = divmod(k, 40)
        o, d = rays["origins"][k].astype(np.float64), rays["directions"][k].astype(np.float64)
        ok, loc, _n, _i, ob, _m = scene.ray_cast(deps, o.tolist(), d.tolist(), distance=float(rays["tmax"][k]))
        assert (ids[r, c, 3] > 0.5) == ok, f"pixel ({r}, {c}): hit {ok} in Blender, alpha {ids[r, c, 3]}"
        if not ok:
            continue
        dist = np.abs(colors - ids[r, c, :3]).max(axis=1)
        assert (dist <= 1.5 / 255).sum() == 1, f"pixel ({r}, {c}): colour {ids[r, c, :3]} matches {dist.min()}"
        wrong_object += table[int(dist.argmin())]["name"] != ob.name
        z_ref = float(np.dot(np.array(loc) - o, view))
        z = far - depth[r, c, 0] * (far - near)
        worst_depth = max(worst_depth, abs(z - z_ref))
        checked += 1
    assert checked > 50
    assert wrong_object == 0, f"{wrong_object} of {checked} pixels decode to another object than scene.ray_cast's"
    assert worst_depth <= (far - near) / 255 + 1e-4, f"decoded depth off by {worst_depth} (8-bit step {(far - near) / 255})"


def _ao(ob):
    a = ob.data.color_attributes["HRC AO"]
    v = np.empty(len(a.data) * 4, np.float32)
    a.data.foreach_get("color", v)
    return v.reshape(-1, 4)[:, 0]


def test_trace_ao_save_keeps_the_bake_in_the_loaded_blend_or_a_new_path(fresh, addon, tmp_path):
    simple_scene()
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    code, out, err = run_cli(addon, "trace", "--workload", "ao", "--object", "Cube", "--ao-samples", "8")
    assert code == 0, err
    assert "pass --save" in out, "an unsaved bake should say how to keep it"
    code, out, err = run_cli(addon, "trace", "--workload", "ao", "--object", "Cube", "--ao-samples", "8", "--save")
    assert code == 0, err
    baked = _ao(bpy.data.objects["Cube"])
    other = tmp_path / "sub" / "copy.blend"
    code, out, err = run_cli(addon, "trace", "--workload", "ao", "--object", "Cube", "--ao-samples", "8",
                         "--save", str(other), "--json", str(tmp_path / "t.json"))
    assert code == 0, err
    assert json.loads((tmp_path / "t.json").read_text())["files"]["blend"] == str(other)
    for path in (blend, other):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.wm.open_mainfile(filepath=str(path))
        ob = bpy.data.objects["Cube"]
        assert "HRC AO" in ob.data.color_attributes, f"{path.name} has no bake"
        got = _ao(ob)
        assert got.shape == baked.shape and np.all((got >= 0) & (got <= 1)) and got.max() > 0
        assert np.allclose(got, baked), f"{path.name}: the saved bake differs from the one computed"
    left = sorted(p.name for p in tmp_path.rglob("*@"))
    assert not left, f"Blender's temporary save files were left behind: {left}"


def test_save_to_an_unwritable_place_exits_4_before_any_work(fresh, addon, tmp_path):
    simple_scene()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for target in (blocker / "x.blend", tmp_path):
        got, out, err = run_cli(addon, "analyze", "--save", str(target) if target != tmp_path else str(tmp_path / "d.blend"))
        if target == tmp_path:
            assert got == 0, err  # a fresh path in a writable folder is fine
            continue
        assert got == 4 and "unwritable path" in one_line(err), (got, err)
    (tmp_path / "dir.blend").mkdir()
    got, out, err = run_cli(addon, "analyze", "--save", str(tmp_path / "dir.blend"))
    assert got == 4 and "is a folder" in one_line(err)


def test_files_before_c_are_the_arguments_blender_opened():
    from hybrid_raycast.operators.cli import _files_before_command

    assert _files_before_command(["blender", "-b", "a.blend", "-c", "hybrid_raycast", "analyze", "b.blend"]) == ["a.blend"]
    assert _files_before_command(["blender", "-b", "-P", "s.py", "--python-expr", "x", "-t", "2", "-E", "CYCLES",
                                  "--factory-startup", "f.blend", "--command", "hybrid_raycast"]) == ["f.blend"]
    assert _files_before_command(["blender", "-p", "0", "0", "10", "10", "g.blend", "-c", "x"]) == ["g.blend"]
    assert _files_before_command(["blender", "-b", "-c", "hybrid_raycast", "analyze"]) == []


def test_a_missing_or_non_blend_file_before_c_exits_2_with_one_line(fresh, addon, tmp_path):
    """Blender goes on with the startup scene when the file before -c cannot be opened;
    the command refuses instead of analysing that scene."""
    simple_scene()
    text = tmp_path / "notes.txt"
    text.write_text("not a blend")
    blend = tmp_path / "ok.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_factory_settings(use_empty=True)  # what Blender has after failing to open a file
    for path, words in ((tmp_path / "missing.blend", "no such file"), (text, "not a .blend file")):
        out, err = io.StringIO(), io.StringIO()
        argv = ["blender", "-b", str(path), "-c", "hybrid_raycast", "analyze"]
        got = addon.operators.cli.main(["analyze"], stdout=out, stderr=err, blender_argv=argv)
        line = one_line(err.getvalue())
        assert got == 2 and words in line and str(path) in line, line
    got, out, err = run_cli(addon, "analyze", "--blend", str(text))
    assert got == 2 and "cannot open" in one_line(err), err
    assert not props().has_results, "nothing may be analysed after a bad file"
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    out, err = io.StringIO(), io.StringIO()
    got = addon.operators.cli.main(["analyze"], stdout=out, stderr=err,
                                   blender_argv=["blender", "-b", str(blend), "-c", "hybrid_raycast", "analyze"])
    assert got == 0, err.getvalue()


def test_distance_measures_each_point_against_the_scene_and_writes_them(fresh, addon, tmp_path):
    """A cloud above, inside and beside the cube (and over the ground), as a binary PLY that
    plyfile writes: distances, nearest objects, signs and the npz of every point."""
    plyfile = pytest.importorskip("plyfile")
    simple_scene()
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.5, 0.5, 0.25]])
    v = np.array([tuple(p) for p in pts], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    path = tmp_path / "cloud.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(path))
    code, out, err = run_cli(addon, "distance", "--points", str(path), "--output", str(tmp_path / "o"),
                             "--json", str(tmp_path / "d.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["distance"]["points"] == 4 and doc["distance"]["found"] == 4 and doc["distance"]["inside"] == 2
    assert set(doc["nearest_objects"]) == {"Cube", "Ground"}
    z = np.load(tmp_path / "o" / "hybrid_raycast_distance.npz")
    assert z["distance"] == pytest.approx([1.0, 1.0, 1.0, 0.5], abs=1e-6)
    assert z["signed_distance"] == pytest.approx([1.0, -1.0, 1.0, -0.5], abs=1e-6)
    assert list(z["object_names"][z["object_index"]]) == ["Cube", "Cube", "Ground", "Cube"]
    assert "4 of 4 points within reach, 2 inside" in out


@pytest.mark.parametrize("make, words", [
    (None, "distance needs --points"),
    (lambda p: p.write_text("not a ply\n"), "not a PLY file"),
    (lambda p: None, "no such file"),
])
def test_distance_refuses_a_missing_or_unreadable_points_file_with_exit_2(fresh, addon, tmp_path, make, words):
    simple_scene()
    path = tmp_path / "bad.ply"
    argv = ["distance"]
    if make is not None:
        make(path)
        argv += ["--points", str(path)]
    code, out, err = run_cli(addon, *argv)
    assert code == 2 and words in one_line(err), err
