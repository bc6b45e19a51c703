"""core.sensors (ray patterns, returns physics, presets) and core.pointcloud (PLY, LAS, npz files).

No Blender needed.  Files are read back with the independent readers plyfile and laspy.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from hybrid_raycast.core import atomic, pointcloud, sensors

plyfile = pytest.importorskip("plyfile", reason="plyfile (test-only) is not installed")
laspy = pytest.importorskip("laspy", reason="laspy (test-only) is not installed")


# -- patterns -----------------------------------------------------------------------------------

def _elev_az(d):
    return np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1))), np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360


def test_rotating_lidar_fires_every_channel_at_every_azimuth_step():
    lidar = sensors.RotatingLidar(channels=5, fov_up=10.0, fov_down=-20.0, azimuth_steps=8, rotation_rate=20.0)
    p = lidar.pattern()
    assert len(p) == 40
    assert np.allclose(np.linalg.norm(p.directions, axis=1), 1.0)
    elev, az = _elev_az(p.directions)
    assert np.allclose(elev, np.array([-20.0, -12.5, -5.0, 2.5, 10.0])[p.ring], atol=1e-9), "elevation of each ring"
    assert np.allclose(np.sort(np.unique(np.round(az, 9))), np.arange(8) * 45.0)
    assert np.allclose(az, p.azimuth, atol=1e-4), "azimuth field is the firing direction"
    # one turn takes 1/20 s: the last firing is one step before the end of the turn
    assert p.time.min() == 0.0 and np.isclose(p.time.max(), 7 / 8 / 20.0)
    assert np.allclose(p.time, p.azimuth / 360.0 / 20.0, atol=1e-6), "firing time follows the azimuth"


def test_explicit_elevations_override_channels_and_fov():
    p = sensors.RotatingLidar(elevations=(-3.0, 7.5, 1.0), azimuth_steps=4).pattern()
    elev, _ = _elev_az(p.directions)
    assert np.allclose(elev, np.array([-3.0, 7.5, 1.0])[p.ring])


def test_area_scanner_covers_its_field_of_view_symmetrically():
    a = sensors.AreaScanner(h_fov=60.0, v_fov=20.0, h_steps=7, v_steps=5)
    p = a.pattern()
    elev, az = _elev_az(p.directions)
    az = np.where(az > 180, az - 360, az)
    half_cell_h, half_cell_v = 60.0 / 7 / 2, 20.0 / 5 / 2
    assert np.isclose(az.max(), 30.0 - half_cell_h) and np.isclose(az.min(), -30.0 + half_cell_h)
    assert np.isclose(elev.max(), 10.0 - half_cell_v) and np.isclose(elev.min(), -10.0 + half_cell_v)
    assert (np.diff(p.ring) >= 0).all() and p.ring.max() == 4
    assert (elev[p.ring == 0] > elev[p.ring == 4].max()).all(), "row 0 is the top row"


def test_depth_camera_rays_pass_through_pixel_centres():
    cam = sensors.DepthCamera(width=4, height=3, fx=2.0, fy=2.0, cx=2.0, cy=1.5)
    d = cam.pattern().directions.reshape(3, 4, 3)
    # pixel (u=0, v=0) centre is (0.5, 0.5): x = (0.5-2)/2, y = -(0.5-1.5)/2, z = -1
    want = np.array([-0.75, 0.5, -1.0])
    assert np.allclose(d[0, 0], want / np.linalg.norm(want))
    assert (d[..., 2] < 0).all(), "a Blender camera looks along -Z"


def test_camera_intrinsics_follow_blenders_sensor_fit():
    k = sensors.camera_intrinsics(50.0, 36.0, 24.0, "AUTO", 1920, 1080)
    assert np.isclose(k["fx"], 50 / 36 * 1920) and k["cx"] == 960 and k["cy"] == 540
    k = sensors.camera_intrinsics(50.0, 36.0, 24.0, "AUTO", 1080, 1920)  # portrait: fit the height
    assert np.isclose(k["fy"], 50 / 36 * 1920)
    k = sensors.camera_intrinsics(50.0, 36.0, 24.0, "VERTICAL", 1920, 1080)
    assert np.isclose(k["fy"], 50 / 24 * 1080)


@pytest.mark.parametrize("cls,kwargs,words", [
    (sensors.RotatingLidar, {"channels": 0}, "channels"),
    (sensors.RotatingLidar, {"azimuth_steps": 0}, "azimuth_steps"),
    (sensors.RotatingLidar, {"range_min": 50.0, "range_max": 10.0}, "range_min (50) must be below range_max (10)"),
    (sensors.RotatingLidar, {"fov_up": -20.0, "fov_down": 10.0}, "fov_down"),
    (sensors.RotatingLidar, {"elevations": ()}, "elevations"),
    (sensors.RotatingLidar, {"rotation_rate": 0.0}, "rotation_rate"),
    (sensors.AreaScanner, {"h_steps": 0}, "h_steps"),
    (sensors.AreaScanner, {"v_fov": 0.0}, "v_fov"),
    (sensors.DepthCamera, {"width": 0}, "width"),
    (sensors.DepthCamera, {"fx": -1.0}, "fx"),
    (sensors.Returns, {"noise_sigma": -0.1}, "noise_sigma"),
    (sensors.Returns, {"drop_below": 2.0}, "drop_below"),
])
def test_bad_sensor_settings_raise_one_line_naming_the_setting(cls, kwargs, words):
    with pytest.raises(ValueError) as e:
        cls(**kwargs)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_every_preset_builds_and_cites_a_source():
    for key, p in sensors.PRESETS.items():
        s = p.sensor()
        assert len(s.pattern()) > 0, key
        assert any(w in p.description for w in ("Manual", "datasheet", "Guide")), f"{key}: no source named"
    os1 = sensors.PRESETS["OS1_64"].sensor()
    assert len(os1.pattern()) == 64 * 2048


#: the channel count each rotating preset's description states
PRESET_CHANNELS = {"VLP16": 16, "OS1_64": 64, "PANDAR_XT16": 16, "RS_LIDAR_16": 16}


def test_every_rotating_preset_fires_the_channel_count_its_source_states():
    rotating = {k for k, p in sensors.PRESETS.items() if p.kind == "ROTATING"}
    assert rotating == set(PRESET_CHANNELS), f"add the new presets' channel counts: {rotating ^ set(PRESET_CHANNELS)}"
    for key, n in PRESET_CHANNELS.items():
        p = sensors.PRESETS[key]
        s = p.sensor()
        pat = s.pattern()
        assert s.channels == n and len(np.unique(pat.ring)) == n, f"{key}: {s.channels} channels, want {n}"
        assert len(pat) == n * s.azimuth_steps, key
        assert str(n) in p.description, f"{key}: the description does not state {n} channels"


# -- returns ------------------------------------------------------------------------------------

def test_range_limits_drop_blind_zone_and_far_hits():
    lidar = sensors.RotatingLidar(range_min=1.0, range_max=10.0)
    t = np.array([0.5, 1.0, 5.0, 10.0, 10.5, np.inf])
    hit = np.isfinite(t)
    keep, r, _ = sensors.measure(t, hit, np.ones(6), lidar, sensors.Returns())
    assert keep.tolist() == [False, True, True, True, False, False]
    assert np.array_equal(r[keep], t[keep]), "no noise: the range is the true range"


def test_range_noise_has_the_requested_mean_and_sigma_and_repeats_per_seed_and_frame():
    lidar = sensors.RotatingLidar(range_min=0.1, range_max=100.0)
    n, sigma = 200_000, 0.05
    t = np.full(n, 20.0)
    ret = sensors.Returns(noise_sigma=sigma, seed=7)
    keep, r, _ = sensors.measure(t, np.ones(n, bool), np.ones(n), lidar, ret, frame=3)
    err = r[keep] - 20.0
    # mean within 5 standard errors; sample sigma within 1.5 % (its standard error is ~0.16 %)
    assert abs(err.mean()) < 5 * sigma / np.sqrt(n), f"mean error {err.mean():.2e}"
    assert abs(err.std() / sigma - 1) < 0.015, f"sigma {err.std():.5f} vs {sigma}"
    again = sensors.measure(t, np.ones(n, bool), np.ones(n), lidar, ret, frame=3)[1]
    other = sensors.measure(t, np.ones(n, bool), np.ones(n), lidar, ret, frame=4)[1]
    assert np.array_equal(r, again), "same seed and frame: same noise"
    assert not np.array_equal(r, other), "another frame: other noise"


def test_intensity_is_cosine_times_inverse_square_beyond_the_reference_and_weak_returns_drop():
    lidar = sensors.RotatingLidar(range_min=0.1, range_max=100.0)
    t = np.array([5.0, 10.0, 20.0, 20.0, 40.0])
    cos = np.array([1.0, 0.5, 1.0, 0.5, 1.0])
    _, _, inten = sensors.measure(t, np.ones(5, bool), cos, lidar, sensors.Returns(reference_range=10.0))
    assert np.allclose(inten, [1.0, 0.5, 0.25, 0.125, 0.0625])
    keep, _, _ = sensors.measure(t, np.ones(5, bool), cos, lidar, sensors.Returns(reference_range=10.0, drop_below=0.2))
    assert keep.tolist() == [True, True, True, False, False]


# -- files --------------------------------------------------------------------------------------

def _fields(n=500, seed=0):
    rng = np.random.default_rng(seed)
    return {"points": rng.normal(0, 30, (n, 3)) + [1.2e4, -3.4e3, 12.0], "range": rng.random(n) * 50,
            "intensity": rng.random(n), "ring": rng.integers(0, 64, n), "azimuth": rng.random(n) * 360,
            "time": rng.random(n) + 100.0, "object_index": rng.integers(0, 3, n),
            "instance_index": rng.integers(0, 5, n), "normals": rng.normal(size=(n, 3))}


NAMES = ["Ground", "Rock/Big", "Car 2"]


def test_ply_reads_back_with_plyfile_field_for_field(tmp_path):
    f = _fields()
    pointcloud.write_ply(tmp_path / "s.ply", f, NAMES)
    ply = plyfile.PlyData.read(str(tmp_path / "s.ply"))
    v = ply["vertex"].data
    assert ply.text is False, "binary PLY"
    assert np.array_equal(np.c_[v["x"], v["y"], v["z"]], f["points"])
    assert np.array_equal(np.c_[v["nx"], v["ny"], v["nz"]], f["normals"].astype(np.float32))
    for k in ("range", "intensity", "azimuth"):
        assert np.array_equal(v[k], f[k].astype(np.float32)), k
    for k in ("ring", "object_index", "instance_index", "time"):
        assert np.array_equal(v[k], f[k]), k
    table = [c.split(" ", 2) for c in ply.comments if c.startswith("object ")]
    assert [(int(i), name) for _, i, name in table] == list(enumerate(NAMES))


def test_las_reads_back_with_laspy(tmp_path):
    f = _fields()
    cls = np.array([2, 6, 1], np.uint8)[f["object_index"]]
    f["classification"] = cls
    pointcloud.write_las(tmp_path / "s.las", f, NAMES)
    las = laspy.read(str(tmp_path / "s.las"))
    assert (las.header.version.major, las.header.version.minor) == (1, 4) and las.header.point_format.id == 6
    assert las.header.point_count == len(f["points"])
    assert las.header.global_encoding.wkt, "LAS 1.4 point format 6 needs the WKT bit"
    xyz = np.c_[las.x, las.y, las.z]
    assert np.abs(xyz - f["points"]).max() <= pointcloud.LAS_SCALE / 2 + 1e-9, "coordinates within half a unit"
    assert np.array_equal(np.asarray(las.classification), cls)
    assert np.array_equal(np.asarray(las.gps_time), f["time"])
    want = f["intensity"].astype(np.float32).astype(np.float64)  # the scan keeps intensity as float32
    assert np.abs(np.asarray(las.intensity) / 65535 - want).max() <= 0.5 / 65535 + 1e-9
    for k in ("range", "azimuth"):
        assert np.array_equal(np.asarray(las[k]), f[k].astype(np.float32)), k
    for k in ("ring", "object_index", "instance_index"):
        assert np.array_equal(np.asarray(las[k]), f[k]), k
    assert np.array_equal(np.c_[las.normal_x, las.normal_y, las.normal_z], f["normals"].astype(np.float32))
    names = [v for v in las.vlrs if v.user_id == "hybrid_raycast"][0]
    assert names.record_data.decode().split("\n") == NAMES
    assert np.allclose([las.header.mins, las.header.maxs], [xyz.min(0), xyz.max(0)])


def test_empty_scans_write_valid_files(tmp_path):
    f = {k: v[:0] for k, v in _fields().items()}
    pointcloud.write_ply(tmp_path / "e.ply", f, [])
    pointcloud.write_las(tmp_path / "e.las", f, [])
    assert len(plyfile.PlyData.read(str(tmp_path / "e.ply"))["vertex"].data) == 0
    assert laspy.read(str(tmp_path / "e.las")).header.point_count == 0


def test_npz_holds_every_field_and_the_names(tmp_path):
    f = _fields()
    pointcloud.write_npz(tmp_path / "s.npz", f, NAMES)
    z = np.load(tmp_path / "s.npz")
    assert list(z["object_names"]) == NAMES
    for k in f:
        assert np.array_equal(z[k], np.asarray(f[k]).astype(pointcloud.FIELDS[k][0])), k


def test_an_interrupted_write_leaves_the_old_file_and_no_partial_file(tmp_path):
    path = tmp_path / "frame.ply"
    pointcloud.write_ply(path, _fields(seed=1), NAMES)
    before = path.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with atomic.atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(b"ply\nhalf")
            raise KeyboardInterrupt
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["frame.ply"], "no temporary file left behind"


def test_bad_fields_are_refused_before_any_file_is_made(tmp_path):
    f = _fields()
    f["ring"] = f["ring"][:-1]
    with pytest.raises(ValueError, match="ring"):
        pointcloud.write(tmp_path / "x.ply", "ply", f, NAMES)
    with pytest.raises(ValueError, match="format"):
        pointcloud.write(tmp_path / "x.xyz", "xyz", _fields(), NAMES)
    assert os.listdir(tmp_path) == []
