"""core.pointcloud's per-point fields (incidence, returns, material, class) and material-name
table in every format, read back with readers this project did not write: laspy (LAS),
plyfile (PLY), numpy after the PCD 0.7 header (PCD), np.load (npz), np.fromfile (KITTI).
"""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_raycast.core import pointcloud

plyfile = pytest.importorskip("plyfile", reason="plyfile (test-only) is not installed")
laspy = pytest.importorskip("laspy", reason="laspy (test-only) is not installed")

OBJECTS = ["Ground", "Rock/Big", "Car 2"]
MATERIALS = ["Concrete", "Glass pane", "Métal"]
NEW = ("cos_incidence", "return_index", "return_count", "material_index", "classification")


def _scan(n=400, seed=0):
    rng = np.random.default_rng(seed)
    count = rng.integers(1, 4, n)
    return {"points": rng.normal(0, 20, (n, 3)) + [500.0, -20.0, 3.0], "range": rng.random(n) * 50,
            "intensity": rng.random(n), "ring": rng.integers(0, 32, n), "azimuth": rng.random(n) * 360,
            "time": rng.random(n) + 5.0, "object_index": rng.integers(0, 3, n),
            "instance_index": rng.integers(0, 4, n), "normals": rng.normal(size=(n, 3)),
            "cos_incidence": rng.random(n), "return_index": 1 + (rng.integers(0, 3, n) % count),
            "return_count": count, "material_index": rng.integers(-1, 3, n),
            "classification": np.array([2, 6, 1], np.uint8)[rng.integers(0, 3, n)]}


def _old_scan(n=50):
    """A scan dict from before the new fields existed."""
    return {k: v for k, v in _scan(n).items() if k not in NEW}


def _want(f, k):
    return np.asarray(f[k]).astype(pointcloud.FIELDS[k][0])


# -- a PCD 0.7 reader from the format's description (pointclouds.org, "The PCD File Format") --------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4",
              ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4"}


def _read_pcd(path):
    raw = path.read_bytes()
    head, comments, pos = {}, [], 0
    while True:
        end = raw.index(b"\n", pos)
        line = raw[pos:end].decode("utf-8")
        pos = end + 1
        if line.startswith("#"):
            comments.append(line)
            continue
        key, *values = line.split()
        head[key] = values
        if key == "DATA":
            break
    assert head["DATA"] == ["binary"] and head["VERSION"] == ["0.7"]
    dtype = np.dtype([(name, "<" + _PCD_TYPES[(t, int(size))], (int(c),) if int(c) > 1 else ())
                      for name, size, t, c in zip(head["FIELDS"], head["SIZE"], head["TYPE"], head["COUNT"])])
    n = int(head["POINTS"][0])
    assert int(head["WIDTH"][0]) * int(head["HEIGHT"][0]) == n
    assert len(raw) - pos == n * dtype.itemsize, "the binary data holds exactly POINTS records of the declared sizes"
    return np.frombuffer(raw, dtype, n, pos), comments


# -- every format -----------------------------------------------------------------------------------

def test_las_fills_return_number_count_and_class_natively_and_the_rest_as_extra_bytes(tmp_path):
    f = _scan()
    pointcloud.write_las(tmp_path / "s.las", f, OBJECTS, material_names=MATERIALS)
    las = laspy.read(str(tmp_path / "s.las"))
    assert np.array_equal(np.asarray(las.return_number), f["return_index"]), "return number (byte 14 bits 0-3)"
    assert np.array_equal(np.asarray(las.number_of_returns), f["return_count"]), "number of returns (bits 4-7)"
    assert np.array_equal(np.asarray(las.classification), f["classification"])
    assert np.array_equal(np.asarray(las["cos_incidence"]), _want(f, "cos_incidence"))
    assert np.array_equal(np.asarray(las["material_index"]), f["material_index"])
    by_return = np.bincount(f["return_index"], minlength=16)[1:]
    assert list(las.header.number_of_points_by_return) == list(by_return), "header count of points by return"
    tables = {v.record_id: v.record_data.decode("utf-8").split("\n") for v in las.vlrs if v.user_id == "hybrid_raycast"}
    assert tables == {1: OBJECTS, 2: MATERIALS}, f"name-table VLRs: {tables}"


def test_las_clips_return_number_and_count_to_the_four_bits_they_have(tmp_path):
    f = _scan(20)
    f["return_index"] = np.full(20, 20)
    f["return_count"] = np.full(20, 0)
    pointcloud.write_las(tmp_path / "c.las", f, OBJECTS)
    las = laspy.read(str(tmp_path / "c.las"))
    assert (np.asarray(las.return_number) == 15).all() and (np.asarray(las.number_of_returns) == 1).all()


def test_ply_holds_every_new_field_and_the_material_table(tmp_path):
    f = _scan()
    pointcloud.write_ply(tmp_path / "s.ply", f, OBJECTS, material_names=MATERIALS)
    ply = plyfile.PlyData.read(str(tmp_path / "s.ply"))
    v = ply["vertex"].data
    for k in NEW:
        assert v[k].dtype == np.dtype(pointcloud.FIELDS[k][0]), f"{k}: PLY type {v[k].dtype}"
        assert np.array_equal(v[k], _want(f, k)), k
    table = [c.split(" ", 2) for c in ply.comments if c.startswith("material ")]
    ascii_names = [m.encode("ascii", "backslashreplace").decode() for m in MATERIALS]  # a PLY header is ASCII
    assert [(int(i), name) for _, i, name in table] == list(enumerate(ascii_names))
    assert [name.encode().decode("unicode_escape") for _, _, name in table] == MATERIALS, "the escapes decode back"


def test_pcd_holds_every_field_with_its_declared_size_and_type(tmp_path):
    f = _scan()
    pointcloud.write_pcd(tmp_path / "s.pcd", f, OBJECTS, material_names=MATERIALS)
    rec, comments = _read_pcd(tmp_path / "s.pcd")
    assert np.array_equal(np.c_[rec["x"], rec["y"], rec["z"]], f["points"].astype(np.float32))
    assert np.array_equal(np.c_[rec["normal_x"], rec["normal_y"], rec["normal_z"]], _want(f, "normals"))
    for k in ("range", "intensity", "azimuth", "ring", "time", "object_index", "instance_index", *NEW):
        assert np.array_equal(rec[k], _want(f, k)), k
    assert [c.split(" ", 3)[2:] for c in comments if c.startswith("# material ")] == \
        [[str(i), m] for i, m in enumerate(MATERIALS)]
    assert [c.split(" ", 3)[3] for c in comments if c.startswith("# object ")] == OBJECTS


def test_npz_holds_every_field_and_both_tables(tmp_path):
    f = _scan()
    pointcloud.write_npz(tmp_path / "s.npz", f, OBJECTS, material_names=MATERIALS)
    with np.load(tmp_path / "s.npz", allow_pickle=False) as z:
        for k in pointcloud.FIELDS:
            assert z[k].dtype == np.dtype(pointcloud.FIELDS[k][0]) and np.array_equal(z[k], _want(f, k)), k
        assert list(z["material_names"]) == MATERIALS and list(z["object_names"]) == OBJECTS


def test_kitti_stays_four_float32_per_point(tmp_path):
    f = _scan()
    pointcloud.write_kitti(tmp_path / "s.bin", f, OBJECTS, material_names=MATERIALS)
    a = np.fromfile(tmp_path / "s.bin", np.float32).reshape(-1, 4)
    assert a.shape == (len(f["points"]), 4)
    assert np.array_equal(a, np.c_[f["points"], f["intensity"]].astype(np.float32))


@pytest.mark.parametrize("fmt", pointcloud.FORMATS)
def test_write_passes_the_material_table_to_every_format(tmp_path, fmt):
    path = tmp_path / f"s.{pointcloud.EXTENSIONS[fmt]}"
    pointcloud.write(path, fmt, _scan(30), OBJECTS, material_names=MATERIALS)
    assert path.stat().st_size > 0


# -- older scans --------------------------------------------------------------------------------------

def test_a_scan_without_the_new_fields_gets_their_defaults_in_every_format(tmp_path):
    f = _old_scan()
    n = len(f["points"])
    for fmt in pointcloud.FORMATS:
        pointcloud.write(tmp_path / f"o.{pointcloud.EXTENSIONS[fmt]}", fmt, f, OBJECTS)
    defaults = {"return_index": 1, "return_count": 1, "material_index": -1, "classification": 1}
    v = plyfile.PlyData.read(str(tmp_path / "o.ply"))["vertex"].data
    rec, _ = _read_pcd(tmp_path / "o.pcd")
    with np.load(tmp_path / "o.npz", allow_pickle=False) as z:
        npz = {k: z[k] for k in NEW}
        assert len(z["material_names"]) == 0
    for name, got in (("PLY", v), ("PCD", rec), ("NPZ", npz)):
        assert np.isnan(got["cos_incidence"]).all(), f"{name}: cos_incidence is NaN when unknown"
        for k, d in defaults.items():
            assert (got[k] == d).all(), f"{name}: {k} defaults to {d}"
    las = laspy.read(str(tmp_path / "o.las"))
    assert (np.asarray(las.return_number) == 1).all() and (np.asarray(las.number_of_returns) == 1).all()
    assert (np.asarray(las.classification) == 1).all() and (np.asarray(las["material_index"]) == -1).all()
    assert las.header.point_count == n


def test_a_field_given_as_none_counts_as_left_out(tmp_path):
    f = {**_old_scan(), "cos_incidence": None, "classification": None}
    pointcloud.write_npz(tmp_path / "n.npz", f, OBJECTS)
    with np.load(tmp_path / "n.npz", allow_pickle=False) as z:
        assert np.isnan(z["cos_incidence"]).all() and (z["classification"] == 1).all()
    with pytest.raises(ValueError, match="missing: range"):
        pointcloud.write_npz(tmp_path / "m.npz", {**f, "range": None}, OBJECTS)


def test_a_class_or_return_outside_one_byte_is_refused_not_wrapped(tmp_path):
    for k, bad in (("classification", 256), ("return_index", -1), ("return_count", 300)):
        f = _scan(10)
        f[k] = np.full(10, bad)
        with pytest.raises(ValueError, match=k):
            pointcloud.write(tmp_path / "x.ply", "ply", f, OBJECTS)
    assert not (tmp_path / "x.ply").exists()
