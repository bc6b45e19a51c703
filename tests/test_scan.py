"""Sensor scans in Blender: api.scan against scene.ray_cast, per-frame files, the operator and the CLI."""

from __future__ import annotations

import io
import json
import math
import os

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")
plyfile = pytest.importorskip("plyfile", reason="plyfile (test-only) is not installed")
laspy = pytest.importorskip("laspy", reason="laspy (test-only) is not installed")

from blender_scenes import add_cube, add_plane, addon, fresh  # noqa: E402,F401

pytestmark = pytest.mark.blender


def scene_with_sensor(animated=True):
    """A ground, a cube, two collection instances of a box, a cube moving along x over
    frames 1-10, and an Empty sensor 1 m above the ground, turned and tilted."""
    scene = bpy.context.scene
    add_plane("Ground", 60.0, z=0.0, location=(0.0, 0.0, -1.0))
    add_cube("Cube", 2.0, (6.0, 1.0, 0.0))
    coll = bpy.data.collections.new("Props")
    box = add_cube("Box", 1.0)
    scene.collection.objects.unlink(box)
    coll.objects.link(box)
    for i, loc in enumerate([(-5.0, 3.0, 0.0), (-4.0, -6.0, 0.5)]):
        inst = bpy.data.objects.new(f"Props.{i}", None)
        inst.instance_type = "COLLECTION"
        inst.instance_collection = coll
        inst.location = loc
        scene.collection.objects.link(inst)
    mover = add_cube("Mover", 1.5, (0.0, 5.0, 0.0))
    if animated:
        scene.frame_start, scene.frame_end = 1, 10
        mover.location = (-6.0, 5.0, 0.0)
        mover.keyframe_insert("location", frame=1)
        mover.location = (6.0, 5.0, 0.0)
        mover.keyframe_insert("location", frame=10)
    sensor = bpy.data.objects.new("Lidar", None)
    sensor.location = (0.3, -0.2, 0.5)
    sensor.rotation_euler = (math.radians(4.0), 0.0, math.radians(30.0))
    scene.collection.objects.link(sensor)
    scene.frame_set(scene.frame_start)
    bpy.context.view_layer.update()
    return scene, sensor


def ray_cast_reference(scene, sensor, result, every=5):
    """scene.ray_cast along every ``every``-th ray of the sensor's pattern: (ray, hit, location,
    normal, object)."""
    from mathutils import Vector

    dg = bpy.context.evaluated_depsgraph_get()
    model, _ = addon_scan().sensor_model(sensor)
    pose = result.sensor_matrix
    d = model.pattern().directions @ pose[:3, :3].T
    o = Vector(pose[:3, 3].tolist())
    out = []
    for i in range(0, len(d), every):
        ok, loc, nrm, _face, ob, _m = scene.ray_cast(dg, o, Vector(d[i].tolist()), distance=model.range_max)
        out.append((i, ok, np.array(loc), np.array(nrm), ob.original if ok else None))
    return out


_ADDON = {}


def addon_scan():
    return _ADDON["pkg"].operators.scan


@pytest.fixture(autouse=True)
def _remember(addon):
    _ADDON["pkg"] = addon


def test_scan_points_normals_and_objects_equal_scene_ray_cast(fresh, addon):
    scene, sensor = scene_with_sensor()
    r = addon.api.scan(sensor)
    assert len(r) > 1000 and r.rays == 16 * 1800
    by_ray = {int(k): j for j, k in enumerate(r.ray)}
    checked = 0
    for i, ok, loc, nrm, ob in ray_cast_reference(scene, sensor, r):
        j = by_ray.get(i)
        dist = np.linalg.norm(loc - r.sensor_matrix[:3, 3]) if ok else np.inf
        if not ok or dist < 0.5:  # a miss, or in the blind zone: no point
            assert j is None, f"ray {i}: Blender found nothing (or a blind-zone hit), the scan has a point"
            continue
        assert j is not None, f"ray {i}: Blender hit {ob.name} at {loc}, the scan has no point"
        assert np.allclose(r.points[j], loc, atol=1e-4), f"ray {i}: {r.points[j]} vs {loc}"
        assert np.allclose(r.normals[j], nrm, atol=1e-4), f"ray {i}: normal {r.normals[j]} vs {nrm}"
        assert r.objects[r.object_index[j]] == ob, f"ray {i}: {r.object_names[r.object_index[j]]} vs {ob.name}"
        assert np.isclose(r.range[j], dist, atol=1e-4)
        checked += 1
    assert checked > 500
    hit_names = set(r.object_names[np.unique(r.object_index)])
    assert {"Ground", "Cube", "Box", "Mover"} <= hit_names
    # the two instances of Box are told apart
    box = np.flatnonzero(r.object_names == "Box")[0]
    assert len(np.unique(r.instance_index[r.object_index == box])) == 2


def test_scan_at_a_frame_sees_that_frame_and_leaves_the_timeline_alone(fresh, addon):
    scene, sensor = scene_with_sensor()
    scene.frame_set(3)
    mover = bpy.data.objects["Mover"]
    r8 = addon.api.scan(sensor, frame=8)
    assert scene.frame_current == 3, "the scene is back at its frame"
    scene.frame_set(8)
    ref = ray_cast_reference(scene, sensor, r8, every=3)
    by_ray = {int(k): j for j, k in enumerate(r8.ray)}
    on_mover = [(i, loc) for i, ok, loc, _n, ob in ref if ok and ob == mover]
    assert on_mover, "the moving cube is in view at frame 8"
    for i, loc in on_mover:
        j = by_ray[i]
        assert r8.object_names[r8.object_index[j]] == "Mover" and np.allclose(r8.points[j], loc, atol=1e-4)
    fps = scene.render.fps / scene.render.fps_base
    assert r8.time.min() >= (8 - 1) / fps and r8.time.max() < (8 - 1) / fps + 0.1, "time: frame time + sweep"


def test_sensor_space_is_the_world_scan_seen_from_the_sensor(fresh, addon):
    _scene, sensor = scene_with_sensor()
    w = addon.api.scan(sensor)
    s = addon.api.scan(sensor, space="SENSOR")
    pose = w.sensor_matrix
    assert np.allclose(s.points, (w.points - pose[:3, 3]) @ pose[:3, :3], atol=1e-6)
    assert np.allclose(np.linalg.norm(s.points, axis=1), s.range, atol=1e-6)
    assert np.allclose(s.normals, w.normals @ pose[:3, :3], atol=1e-5)


def test_range_noise_statistics_against_the_noise_free_scan(fresh, addon):
    _scene, sensor = scene_with_sensor(animated=False)
    sensor.hybrid_raycast_sensor.preset = "OS1_64"
    s = sensor.hybrid_raycast_sensor
    s.noise_sigma, s.seed = 0.0, 0
    clean = addon.api.scan(sensor)
    s.noise_sigma = 0.03
    noisy = addon.api.scan(sensor)
    again = addon.api.scan(sensor)
    common, a, b = np.intersect1d(clean.ray, noisy.ray, return_indices=True)
    err = noisy.range[b] - clean.range[a]
    assert len(err) > 20_000
    assert abs(err.mean()) < 5 * 0.03 / np.sqrt(len(err)), f"mean range error {err.mean():.2e}"
    assert abs(err.std() / 0.03 - 1) < 0.03, f"sigma {err.std():.4f} vs 0.03"
    # the noisy point stays on its ray
    d = (noisy.points - noisy.sensor_matrix[:3, 3]) / noisy.range[:, None]
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.array_equal(noisy.range, again.range), "seeded: a scan repeats"


def test_depth_camera_rays_fill_blenders_camera_frame(fresh, addon):
    from mathutils import Vector

    scene, _ = scene_with_sensor(animated=False)
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    cam.data.lens, cam.data.shift_x, cam.data.shift_y = 35.0, 0.1, -0.05
    scene.collection.objects.link(cam)
    s = cam.hybrid_raycast_sensor
    s.kind, s.width, s.height = "DEPTH", 64, 48
    model, _ = addon.operators.scan.sensor_model(cam, scene)
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 48, 100
    frame = [Vector(v) for v in cam.data.view_frame(scene=scene)]  # top-right, bottom-right, bottom-left, top-left
    z = -frame[0].z
    corners = {(64, 0): frame[0], (64, 48): frame[1], (0, 48): frame[2], (0, 0): frame[3]}
    for (u, v), c in corners.items():
        ray = np.array([(u - model.cx) / model.fx, -(v - model.cy) / model.fy, -1.0]) * z
        assert np.allclose(ray, np.array(c), atol=1e-5), f"pixel corner {(u, v)}: {ray} vs Blender's {tuple(c)}"


def test_bad_settings_raise_value_error_in_scripts(fresh, addon):
    _scene, sensor = scene_with_sensor()
    s = sensor.hybrid_raycast_sensor
    s.range_min, s.range_max = 50.0, 10.0
    with pytest.raises(ValueError, match="range_min"):
        addon.api.scan(sensor)
    s.range_min, s.range_max = 0.5, 100.0
    with pytest.raises(ValueError, match="space"):
        addon.api.scan(sensor, space="CAMERA")
    with pytest.raises(TypeError, match="sensor_object"):
        addon.api.scan("Lidar")
    s.kind = "DEPTH"
    with pytest.raises(ValueError, match="camera"):
        addon.api.scan(sensor)


# -- files: the operator, cancellation, the CLI -------------------------------------------------

def test_operator_writes_one_complete_file_per_frame_equal_to_api_scan(fresh, addon, tmp_path):
    scene, sensor = scene_with_sensor()
    bpy.data.objects["Ground"]["classification"] = 2
    s = sensor.hybrid_raycast_sensor
    s.directory, s.file_format, s.use_scene_range, s.frame_start, s.frame_end = str(tmp_path), "LAS", False, 2, 4
    for ob in list(bpy.context.view_layer.objects):
        ob.select_set(False)
    bpy.context.view_layer.objects.active = sensor
    assert bpy.ops.hybrid_raycast.scan() == {"FINISHED"}
    names = sorted(os.listdir(tmp_path))
    assert names == ["Lidar_00002.las", "Lidar_00003.las", "Lidar_00004.las"]
    las = laspy.read(str(tmp_path / "Lidar_00003.las"))
    ref = addon.api.scan(sensor, frame=3)
    assert las.header.point_count == len(ref)
    assert np.abs(np.c_[las.x, las.y, las.z] - ref.points).max() <= 1e-4
    assert np.array_equal(np.asarray(las.ring), ref.ring)
    ground = np.asarray(las.object_index) == list(ref.object_names).index("Ground")
    assert (np.asarray(las.classification)[ground] == 2).all() and (np.asarray(las.classification)[~ground] == 1).all()
    s.file_format = "PLY"
    assert bpy.ops.hybrid_raycast.scan() == {"FINISHED"}
    ply = plyfile.PlyData.read(str(tmp_path / "Lidar_00004.ply"))
    ref = addon.api.scan(sensor, frame=4)
    v = ply["vertex"].data
    assert np.array_equal(np.c_[v["x"], v["y"], v["z"]], ref.points)
    assert np.array_equal(v["object_index"], ref.object_index)
    assert [c.split(" ", 2)[2] for c in ply.comments if c.startswith("object ")] == list(ref.object_names)


def test_a_kitti_scan_writes_a_bin_per_frame_and_every_frames_pose(fresh, addon, tmp_path):
    scene, sensor = scene_with_sensor()
    scan = addon.operators.scan
    result = addon.operators.jobs.run_sync(
        scan.scan_job(scene, addon.operators.jobs.Job(), sensor, frames=(2, 4), directory=str(tmp_path), fmt="kitti"))
    assert sorted(os.listdir(tmp_path)) == ["Lidar_00002.bin", "Lidar_00003.bin", "Lidar_00004.bin", "poses.txt"]
    assert len(result["files"]) == 3
    poses = np.loadtxt(tmp_path / "poses.txt").reshape(-1, 3, 4)
    for i, frame in enumerate((2, 3, 4)):
        ref = addon.api.scan(sensor, frame=frame)
        k = np.fromfile(tmp_path / f"Lidar_{frame:05d}.bin", np.float32).reshape(-1, 4)
        # the job's first frame traces flat while it plans, later scans with the two-level scene: the
        # same hits to float32 rounding of the object-space ray (core/twolevel.py)
        assert len(k) == len(ref.points), f"frame {frame}: {len(k)} points written, {len(ref.points)} scanned"
        assert np.allclose(k[:, :3], ref.points, rtol=0, atol=1e-4) and np.allclose(k[:, 3], ref.intensity, atol=1e-5)
        assert np.allclose(poses[i], ref.sensor_matrix[:3], rtol=0, atol=1e-8)
    pcd = scan.write_scan(addon.api.scan(sensor, frame=2), tmp_path / "one.pcd", "pcd")
    assert pcd.read_bytes().startswith(b"# .PCD v0.7")


def test_a_scan_stopped_between_frames_leaves_finished_files_complete_and_no_partial_file(fresh, addon, tmp_path):
    scene, sensor = scene_with_sensor()
    scan = addon.operators.scan
    job = addon.operators.jobs.Job()
    written = []
    gen = scan.scan_job(scene, job, sensor, frames=(1, 10), directory=str(tmp_path), fmt="ply", written=written)
    for _ in range(3):
        next(gen)
    job.cancel_event.set()  # Esc, as the modal operator sets it
    with pytest.raises(addon.operators.jobs.Cancelled):
        next(gen)
    gen.close()
    assert scene.frame_current == 1, "the timeline is back where it was"
    assert sorted(os.listdir(tmp_path)) == ["Lidar_00001.ply", "Lidar_00002.ply"]
    for p in written:
        assert len(plyfile.PlyData.read(str(p))["vertex"].data) > 1000


def run_cli(addon, *argv):
    out, err = io.StringIO(), io.StringIO()
    code = addon.operators.cli.main(list(argv), stdout=out, stderr=err)
    return code, out.getvalue(), err.getvalue()


def test_cli_scan_writes_every_frame_and_exits_0(fresh, addon, tmp_path):
    scene_with_sensor()
    code, out, err = run_cli(addon, "scan", "--sensor", "Lidar", "--frames", "1-3", "--output", str(tmp_path),
                             "--format", "npz", "--space", "sensor", "--json", str(tmp_path / "scan.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "scan.json").read_text())
    assert doc["structure"] in ("grid", "bvh", "embree") and doc["structures"]["parts"], doc
    assert all(p["kind"] in ("grid", "bvh", "embree", "mixed") for p in doc["structures"]["parts"])
    files = sorted(p for p in os.listdir(tmp_path) if p.endswith(".npz"))
    assert files == ["Lidar_00001.npz", "Lidar_00002.npz", "Lidar_00003.npz"]
    z = np.load(tmp_path / files[1])
    assert np.allclose(np.linalg.norm(z["points"], axis=1), z["range"], atol=1e-6), "sensor space"


@pytest.mark.parametrize("argv,code,words", [
    (["scan", "--frames", "1-3"], 2, "--sensor"),
    (["scan", "--sensor", "Nope"], 2, "no object"),
    (["scan", "--sensor", "Lidar", "--frames", "5-40"], 2, "outside the scene's frame range 1-10"),
    (["scan", "--sensor", "Lidar", "--frames", "abc"], 2, "--frames"),
    (["scan", "--sensor", "Lidar", "--format", "xyz"], 2, "--format"),
])
def test_cli_scan_bad_arguments_exit_2_with_one_line(fresh, addon, tmp_path, argv, code, words):
    scene_with_sensor()
    argv = argv + ["--output", str(tmp_path / "out")]
    got, _out, err = run_cli(addon, *argv)
    lines = [x for x in err.strip().splitlines() if x]
    assert got == code and len(lines) == 1 and words in lines[0], (got, lines)
    assert not any(p.suffix in (".ply", ".las", ".npz") for p in (tmp_path / "out").glob("*")) \
        if (tmp_path / "out").exists() else True


def test_cli_scan_bad_sensor_settings_exit_2_and_unwritable_output_exits_4(fresh, addon, tmp_path):
    _scene, sensor = scene_with_sensor()
    sensor.hybrid_raycast_sensor.range_min = 200.0
    code, _o, err = run_cli(addon, "scan", "--sensor", "Lidar", "--frames", "1", "--output", str(tmp_path))
    assert code == 2 and "range_min (200) must be below range_max (100)" in err and len(err.strip().splitlines()) == 1
    sensor.hybrid_raycast_sensor.range_min = 0.5
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _o, err = run_cli(addon, "scan", "--sensor", "Lidar", "--frames", "1", "--output", str(blocker / "sub"))
    assert code == 4 and "unwritable" in err and len(err.strip().splitlines()) == 1


def test_readme_sensor_scan_example_runs_as_written(fresh, addon, monkeypatch):
    import re
    import sys
    import types
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    start = text.index("## Sensor scans")
    blocks = re.findall(r"```python\n(.*?)```", text[start:text.index("\n## ", start + 3)], flags=re.S)
    assert blocks and all("api.scan" in b for b in blocks)
    for name in ("bl_ext", "bl_ext.user_default"):
        mod = types.ModuleType(name)
        mod.__path__ = []
        monkeypatch.setitem(sys.modules, name, mod)
    monkeypatch.setitem(sys.modules, "bl_ext.user_default.hybrid_raycast", addon)
    scene, _sensor = scene_with_sensor()
    scene.frame_set(2)
    ns = {}
    for block in blocks:
        exec(compile(block, "README.md sensor scan block", "exec"), ns)
    r = ns["r"]
    assert r.frame == 12 and scene.frame_current == 2 and len(r) > 1000
    assert np.allclose(np.linalg.norm(r.points, axis=1), r.range, atol=1e-6), "SENSOR space as the README says"


class _Layout:
    """A stand-in for bpy.types.UILayout that checks every property and operator drawn."""

    def __init__(self, seen):
        self.seen = seen

    def __getattr__(self, name):
        return lambda *a, **k: self

    def __setattr__(self, name, value):
        object.__setattr__(self, name, value)

    def prop(self, data, name, **_k):
        assert name in data.bl_rna.properties, f"panel draws a missing property {name!r}"
        self.seen.add(name)
        return self

    def operator(self, idname, **_k):
        cat, op = idname.split(".")
        assert hasattr(getattr(bpy.ops, cat), op), f"panel calls a missing operator {idname}"
        self.seen.add(idname)
        return self


@pytest.mark.parametrize("kind", ["ROTATING", "AREA", "DEPTH"])
def test_scan_panel_draws_existing_settings_and_the_scan_button(fresh, addon, kind):
    import types

    _scene, sensor = scene_with_sensor(animated=False)
    sensor.hybrid_raycast_sensor.kind = kind
    sensor.hybrid_raycast_sensor.use_scene_range = False
    seen = set()
    panel = types.SimpleNamespace(layout=_Layout(seen))
    ctx = types.SimpleNamespace(active_object=sensor)
    addon.ui.scan_panel.VIEW3D_PT_hybrid_raycast_scan.draw(panel, ctx)
    assert "hybrid_raycast.scan" in seen and "range_max" in seen and "frame_end" in seen
    assert {"ROTATING": "channels", "AREA": "h_fov", "DEPTH": "width"}[kind] in seen


def test_cli_scan_motion_and_returns_override_the_sensor_for_the_run_only(fresh, addon, tmp_path):
    import json

    _scene, sensor = scene_with_sensor()
    s = sensor.hybrid_raycast_sensor
    s.channels, s.azimuth_steps = 8, 360
    code, out, err = run_cli(addon, "scan", "--sensor", "Lidar", "--frames", "2-3", "--output", str(tmp_path),
                             "--format", "npz", "--motion", "sweep", "--returns", "DUAL", "--beam-samples", "4",
                             "--beam-divergence", "3", "--json", str(tmp_path / "scan.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "scan.json").read_text())
    assert (doc["motion"], doc["returns"], doc["beam_samples"], doc["beam_divergence"]) == ("SWEEP", "DUAL", 4, 3.0)
    assert "(SWEEP, DUAL returns)" in out
    z = np.load(tmp_path / "Lidar_00002.npz")
    assert len(z["return_count"]) == len(z["range"]) > 1000
    assert set(np.unique(z["return_count"])) <= {1, 2} and (z["return_index"] <= z["return_count"]).all()
    assert (z["return_count"] == 2).any(), "a 3 mrad beam over the cube's edges gives dual returns"
    # the sensor's own settings are back
    assert (s.motion, s.returns, s.beam_samples, s.beam_divergence) == ("FRAME", "STRONGEST", 1, 0.0)


def test_cli_scan_puts_the_sensor_settings_back_after_an_error(fresh, addon, tmp_path):
    _scene, sensor = scene_with_sensor()
    s = sensor.hybrid_raycast_sensor
    s.range_min = 200.0  # no sensor: the job refuses it after the overrides are set
    code, _o, err = run_cli(addon, "scan", "--sensor", "Lidar", "--frames", "1", "--output", str(tmp_path),
                            "--motion", "sweep", "--returns", "last", "--beam-samples", "2")
    assert code == 2 and "range_min" in err
    assert (s.motion, s.returns, s.beam_samples) == ("FRAME", "STRONGEST", 1)


@pytest.mark.parametrize("argv,words", [
    (["--returns", "triple"], "--returns"),
    (["--motion", "rolling"], "--motion"),
    (["--beam-samples", "0"], "--beam-samples"),
    (["--beam-samples", "65"], "--beam-samples"),
    (["--beam-samples", "2.5"], "--beam-samples"),
    (["--beam-divergence", "-1"], "--beam-divergence"),
    (["--beam-divergence", "nan"], "--beam-divergence"),
])
def test_cli_scan_bad_motion_returns_and_beam_options_exit_2_naming_the_option(fresh, addon, tmp_path, argv, words):
    scene_with_sensor()
    code, _out, err = run_cli(addon, "scan", "--sensor", "Lidar", "--frames", "1", "--output", str(tmp_path / "out"),
                              *argv)
    lines = [x for x in err.strip().splitlines() if x]
    assert code == 2 and len(lines) == 1 and words in lines[0], (code, lines)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("samples", [1, 3])
def test_sub_rays_of_channels_firing_together_equal_each_beam_rotated_alone(addon, samples):
    """A spinning sensor's beams grouped by firing time take one product per time
    (``scan._sub_rays``): the same origins and directions, to rounding, as every beam
    rotated by its own pose (the path a pattern in any order takes)."""
    scan = addon.operators.scan
    rng = np.random.default_rng(4)
    t, group = 5, 4
    q, _ = np.linalg.qr(rng.normal(size=(t, 3, 3)))
    origin = rng.normal(size=(t, 3))
    at = np.repeat(np.arange(t), group)
    rows = rng.normal(size=(t * group * samples, 3))
    o, d = scan._sub_rays(q, origin, at, rows, samples)
    want_d = np.einsum("bij,bsj->bsi", q[at], rows.reshape(-1, samples, 3)).reshape(-1, 3)
    assert np.allclose(d, want_d, rtol=0, atol=1e-14) and np.array_equal(o, np.repeat(origin[at], samples, axis=0))
    order = rng.permutation(len(at))  # the same beams out of time order: the per-beam path
    o2, d2 = scan._sub_rays(q, origin, at[order], rows.reshape(-1, samples, 3)[order].reshape(-1, 3), samples)
    assert np.array_equal(d2, want_d.reshape(-1, samples, 3)[order].reshape(-1, 3))
    assert np.array_equal(o2, o.reshape(-1, samples, 3)[order].reshape(-1, 3))
