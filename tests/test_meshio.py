"""Scene files: save_mesh/load_mesh keep every array bit for bit; bad files are clear errors."""

import os
import zipfile

import numpy as np
import pytest

from hybrid_raycast import core
from hybrid_raycast.core import meshio


def _mesh(seed=0, t=50, with_tables=True):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(3 * t, 3)).astype(np.float32)
    f = rng.integers(0, len(v), size=(t, 3))
    if not with_tables:
        return core.TriangleMesh(v, f)
    return core.TriangleMesh(v, f, object_index=rng.integers(0, 3, t), polygon_index=np.arange(t) // 2,
                             object_names=["Cube", "Suzanne.001", "Ünïcode → name"])


def _same(a, b):
    assert np.array_equal(a.vertices, b.vertices) and a.vertices.dtype == b.vertices.dtype == np.float32
    assert np.array_equal(a.triangles, b.triangles) and b.triangles.dtype == np.int32
    for name in ("object_index", "polygon_index"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or np.array_equal(x, y), name
    assert a.object_names == b.object_names


def test_round_trip_keeps_arrays_names_and_frame(tmp_path):
    mesh = _mesh()
    path = core.save_mesh(mesh, tmp_path / "f.npz", frame=17)
    scene = core.read_scene(path)
    _same(mesh, scene.mesh)
    assert scene.frame == 17 and scene.version == meshio.VERSION
    _same(mesh, core.load_mesh(path))


def test_round_trip_without_tables_and_empty_mesh(tmp_path):
    for mesh in (_mesh(with_tables=False), core.TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), int))):
        path = core.save_mesh(mesh, tmp_path / "g.npz")
        back = core.read_scene(path)
        _same(mesh, back.mesh)
        assert back.frame is None


def test_a_real_mesh_traces_identically_after_a_round_trip(tmp_path):
    mesh = core.load_obj(_real_mesh_path())
    back = core.load_mesh(core.save_mesh(mesh, tmp_path / "m.npz"))
    o, d = core.uniform_rays(mesh, 4000, seed=3)
    a, b = core.build(mesh, "grid").trace(o, d), core.build(back, "grid").trace(o, d)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.triangle, b.triangle)


def _real_mesh_path():
    from conftest import SCENES

    p = SCENES / "cow.obj"
    if not p.is_file():
        pytest.skip(f"{p} not found")
    return p


def test_missing_file_is_file_not_found_naming_it(tmp_path):
    p = tmp_path / "nope.npz"
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        core.load_mesh(p)
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        meshio.check_scene(p)


@pytest.mark.parametrize("what", ["garbage", "empty", "npy", "foreign_npz", "truncated", "newer", "folder", "flipped"])
def test_wrong_or_damaged_files_are_scene_file_errors_naming_the_file(tmp_path, what):
    good = core.save_mesh(_mesh(t=2000), tmp_path / "good.npz")
    p = tmp_path / f"{what}.npz"
    if what == "garbage":
        p.write_bytes(b"this is not a zip archive at all" * 10)
    elif what == "empty":
        p.write_bytes(b"")
    elif what == "npy":
        with open(p, "wb") as f:
            np.save(f, np.arange(4))
    elif what == "foreign_npz":
        with open(p, "wb") as f:
            np.savez(f, vertices=np.zeros((3, 3)), triangles=np.zeros((1, 3), int))
    elif what == "truncated":
        p.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    elif what == "newer":
        with open(p, "wb") as f:
            np.savez(f, format=np.array(meshio.FORMAT), version=np.array(meshio.VERSION + 1))
    elif what == "folder":
        p.mkdir()
    elif what == "flipped":  # one byte changed inside the compressed vertex data: a CRC/zlib error
        data = bytearray(good.read_bytes())
        info = zipfile.ZipFile(good).getinfo("vertices.npy")
        at = info.header_offset + 30 + len(info.filename) + info.compress_size // 2
        data[at] ^= 0xFF
        p.write_bytes(bytes(data))
    with pytest.raises(core.SceneFileError, match=f"{what}.npz") as e:
        core.load_mesh(p)
    assert isinstance(e.value, ValueError) and "\n" not in str(e.value)


def test_header_check_reads_only_the_header_and_rejects_foreign_files(tmp_path):
    good = core.save_mesh(_mesh(), tmp_path / "good.npz")
    assert meshio.check_scene(good) == meshio.VERSION
    with open(tmp_path / "foreign.npz", "wb") as f:
        np.savez(f, a=np.zeros(3))
    with pytest.raises(core.SceneFileError, match="foreign.npz.*not a scene file"):
        meshio.check_scene(tmp_path / "foreign.npz")


def test_a_changed_file_is_refused_when_its_digest_is_expected(tmp_path):
    p = core.save_mesh(_mesh(seed=1), tmp_path / "s.npz")
    digest = meshio.file_digest(p)
    assert core.read_scene(p, expect_digest=digest).digest == digest
    core.save_mesh(_mesh(seed=2), p)
    with pytest.raises(core.SceneFileError, match="s.npz: the file changed"):
        core.read_scene(p, expect_digest=digest)


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    p = core.save_mesh(_mesh(seed=1), tmp_path / "s.npz", frame=1)
    before = p.read_bytes()

    def half_then_fail(f, **arrays):
        f.write(b"PK\x03\x04 half an archive")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", half_then_fail)
    with pytest.raises(OSError, match="No space left"):
        core.save_mesh(_mesh(seed=2), p, frame=2)
    assert p.read_bytes() == before, "the old file must stay whole"
    assert sorted(os.listdir(tmp_path)) == ["s.npz"], "no temporary file may be left behind"
    assert core.read_scene(p).frame == 1


def test_save_needs_a_triangle_mesh(tmp_path):
    with pytest.raises(TypeError, match="TriangleMesh"):
        core.save_mesh({"vertices": []}, tmp_path / "x.npz")
