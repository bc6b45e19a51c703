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
