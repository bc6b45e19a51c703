"""core.pointcloud.read_points, the distance command's input, on files that other programs'
writers made (plyfile, laspy, numpy), and a clear error on what it cannot read."""

import numpy as np
import pytest

from hybrid_raycast.core import pointcloud as pc

PTS = np.random.default_rng(0).uniform(-5, 5, (50, 3))


@pytest.mark.parametrize("text", [True, False])
def test_ply_ascii_and_binary_from_plyfile(tmp_path, text):
    plyfile = pytest.importorskip("plyfile")
    v = np.array([tuple(p) + (7,) for p in PTS], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1")])
    faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    path = tmp_path / "a.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(faces, "face")],
                    text=text, byte_order=">" if not text else "=").write(str(path))
    assert np.allclose(pc.read_points(path), PTS, rtol=0, atol=1e-12)


@pytest.mark.parametrize("fmt, version", [(3, "1.2"), (6, "1.4")])
def test_las_from_laspy(tmp_path, fmt, version):
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=fmt, version=version)
    header.scales, header.offsets = [0.001] * 3, [1.0, -2.0, 3.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = PTS.T
    las.write(str(tmp_path / "a.las"))
    assert np.abs(pc.read_points(tmp_path / "a.las") - PTS).max() <= 0.0005 + 1e-9


def test_numpy_files(tmp_path):
    np.save(tmp_path / "a.npy", PTS)
    np.savez(tmp_path / "b.npz", points=PTS)
    np.savez(tmp_path / "c.npz", x=PTS[:, 0], y=PTS[:, 1], z=PTS[:, 2])
    for name in ("a.npy", "b.npz", "c.npz"):
        assert np.array_equal(pc.read_points(tmp_path / name), PTS), name


def test_what_it_cannot_read_is_an_error_naming_the_file(tmp_path):
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    (tmp_path / "b.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n"
                                     b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 12)
    (tmp_path / "c.las").write_bytes(b"LASF" + b"\0" * 300)
    np.savez(tmp_path / "d.npz", other=PTS)
    np.save(tmp_path / "e.npy", PTS[:, :2])
    for name, words in (("a.xyz", "unknown points format"), ("b.ply", "ends before its 10 vertices"),
                        ("c.las", "ends before"), ("d.npz", "no 'points' array"), ("e.npy", r"not \(N, 3\)"),
                        ("missing.ply", "no such file")):
        with pytest.raises(pc.PointFileError, match=words) as e:
            pc.read_points(tmp_path / name)
        assert name in str(e.value)


def scan_fields(n=40, seed=1):
    rng = np.random.default_rng(seed)
    return {"points": rng.uniform(-50, 50, (n, 3)), "range": rng.uniform(1, 90, n).astype(np.float32),
            "intensity": rng.uniform(0, 1, n).astype(np.float32), "ring": rng.integers(0, 64, n).astype(np.uint16),
            "azimuth": rng.uniform(0, 360, n).astype(np.float32), "time": rng.uniform(0, 0.1, n),
            "object_index": rng.integers(0, 3, n).astype(np.int32),
            "instance_index": rng.integers(0, 3, n).astype(np.int32),
            "normals": rng.normal(size=(n, 3)).astype(np.float32)}


def read_pcd(path):
    """A few lines from the PCD 0.7 specification: ASCII header up to DATA, a packed binary body."""
    raw = open(path, "rb").read()
    head, body, comments = {}, 0, []
    for line in raw.split(b"\n"):
        body += len(line) + 1
        text = line.decode("ascii")
        if text.startswith("#"):
            comments.append(text)
            continue
        key, *vals = text.split()
        head[key] = vals
        if key == "DATA":
            break
    assert head["DATA"] == ["binary"] and head["VERSION"] == ["0.7"]
    code = {"F": "f", "U": "u", "I": "i"}
    dt = np.dtype([(n, "<" + code[t] + s) for n, s, t in zip(head["FIELDS"], head["SIZE"], head["TYPE"])])
    n = int(head["POINTS"][0])
    assert int(head["WIDTH"][0]) * int(head["HEIGHT"][0]) == n
    return np.frombuffer(raw[body:body + n * dt.itemsize], dt), comments


def test_pcd_and_kitti_read_back_by_their_specifications(tmp_path):
    f = scan_fields()
    names = ["Ground", "Wall one", "Car"]
    pc.write(tmp_path / "a.pcd", "pcd", f, names)
    rec, comments = read_pcd(tmp_path / "a.pcd")
    assert np.array_equal(np.c_[rec["x"], rec["y"], rec["z"]], f["points"].astype(np.float32))
    for k in ("intensity", "range", "azimuth", "ring", "time", "object_index", "instance_index"):
        assert np.array_equal(rec[k], f[k]), k
    assert np.array_equal(np.c_[rec["normal_x"], rec["normal_y"], rec["normal_z"]], f["normals"])
    assert [c.split(" ", 3)[3] for c in comments if c.startswith("# object ")] == names
    pc.write(tmp_path / "a.bin", "kitti", f, names)
    k = np.fromfile(tmp_path / "a.bin", np.float32).reshape(-1, 4)
    assert np.array_equal(k[:, :3], f["points"].astype(np.float32)) and np.array_equal(k[:, 3], f["intensity"])
    poses = [np.eye(4), np.array([[0, -1, 0, 5], [1, 0, 0, -2], [0, 0, 1, 1.5], [0, 0, 0, 1]], float)]
    pc.write_poses(tmp_path / "poses.txt", poses)
    back = np.loadtxt(tmp_path / "poses.txt").reshape(-1, 3, 4)
    assert np.array_equal(back, np.stack(poses)[:, :3])
    assert pc.EXTENSIONS["kitti"] == "bin" and set(pc.EXTENSIONS) == set(pc.FORMATS)
