"""`-c hybrid_raycast export`: one scene file per frame, checked against Blender's own data."""

import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, addon, fresh, make_nan, run_cli  # noqa: E402,F401

from hybrid_raycast import core  # noqa: E402

pytestmark = pytest.mark.blender


def animated_cube():
    """A 2-unit cube keyframed from x = 0 at frame 1 to x = 40 at frame 5, and a still one."""
    ob = add_cube("Mover", 2.0)
    for f in (1, 5):
        ob.location = (10.0 * (f - 1), 0.0, 0.0)
        ob.keyframe_insert("location", frame=f)
    add_cube("Still", 1.0, (0.0, 5.0, 0.0))
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 5
    scene.frame_set(2)
    return ob


def blender_world_vertices(ob, frame):
    """Blender's own answer: the evaluated object's vertices times its world matrix at ``frame``."""
    bpy.context.scene.frame_set(frame)
    ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
    co = np.array([ev.matrix_world @ v.co for v in ev.data.vertices], np.float64)
    return co.min(axis=0), co.max(axis=0)


def test_export_writes_one_file_per_frame_matching_blender(fresh, addon, tmp_path):
    ob = animated_cube()
    code, out, err = run_cli(addon, "export", "--frames", "1-3,5", "--output", str(tmp_path), "--json", str(tmp_path / "e.json"))
    assert code == 0, err
    names = sorted(p.name for p in tmp_path.glob("*.npz"))
    assert names == ["frame_0001.npz", "frame_0002.npz", "frame_0003.npz", "frame_0005.npz"]
    progress = [x for x in err.splitlines() if x.startswith("hybrid_raycast export: frame ")]
    assert len(progress) == 4 and "(4/4)" in progress[-1] and "frame_0005.npz" in progress[-1], err
    assert bpy.context.scene.frame_current == 2, "the scene's frame is restored"
    expected = {f: blender_world_vertices(ob, f) for f in (1, 2, 3, 5)}
    for f, (lo, hi) in expected.items():
        scene = core.read_scene(tmp_path / f"frame_{f:04d}.npz")
        assert scene.frame == f
        mesh = scene.mesh
        assert mesh.triangle_count == 24 and sorted(mesh.object_names) == ["Mover", "Still"]
        mover = mesh.object_names.index("Mover")
        v = mesh.vertices[np.unique(mesh.triangles[mesh.object_index == mover])]
        assert np.allclose(v.min(axis=0), lo, atol=1e-5) and np.allclose(v.max(axis=0), hi, atol=1e-5), \
            f"frame {f}: exported box {v.min(axis=0)}..{v.max(axis=0)}, Blender {lo}..{hi}"
    assert expected[1][0][0] != expected[5][0][0], "the cube must move, or the test proves nothing"
    doc = json.loads((tmp_path / "e.json").read_text())
    assert [r["frame"] for r in doc["files"]] == [1, 2, 3, 5] and all(r["triangles"] == 24 for r in doc["files"])


def test_export_defaults_to_the_scene_frame_range(fresh, addon, tmp_path):
    animated_cube()
    code, out, err = run_cli(addon, "export", "--output", str(tmp_path))
    assert code == 0, err
    assert len(list(tmp_path.glob("frame_*.npz"))) == 5


@pytest.mark.parametrize("argv, code, words", [
    (["export", "--frames", "1-3"], 2, "needs --output"),
    (["export", "--frames", "3-1", "--output", "{tmp}"], 2, "runs backwards"),
    (["export", "--frames", "one", "--output", "{tmp}"], 2, "--frames 'one'"),
    (["export", "--frames", "1", "--output", "{tmp}/file/sub"], 4, "unwritable path"),
    (["export", "--frames", "1", "--output", "{tmp}", "--save"], 2, "export changes no scene"),
])
def test_export_argument_and_path_errors(fresh, addon, tmp_path, argv, code, words):
    add_cube("Cube")
    (tmp_path / "file").write_text("x")
    got, out, err = run_cli(addon, *[a.format(tmp=tmp_path) for a in argv])
    lines = [x for x in err.strip().splitlines() if x]
    assert got == code and len(lines) == 1 and words in lines[0], (got, err)


def test_export_of_an_empty_or_broken_frame_names_it(fresh, addon, tmp_path):
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("Empty", None))
    got, out, err = run_cli(addon, "export", "--frames", "7", "--output", str(tmp_path))
    assert got == 3 and "frame 7: no geometry" in err
    make_nan(add_cube("Broken"))
    got, out, err = run_cli(addon, "export", "--frames", "2", "--output", str(tmp_path))
    assert got == 5 and "frame 2:" in err and "'Broken'" in err
    assert not list(tmp_path.glob("*.npz")), "nothing is written for a frame that failed"
