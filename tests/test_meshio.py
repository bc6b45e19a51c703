"""Scene files: save_mesh/load_mesh keep every array bit for bit; bad files are clear errors;
an instanced (version-2) file stores each mesh once and gives the flat mesh the extraction would."""

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
    assert scene.frame == 17 and scene.version == meshio.FLAT_VERSION == 1
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
    assert meshio.check_scene(good) == meshio.FLAT_VERSION
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


# -- version 2: instanced scenes -----------------------------------------------------------------

def _rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _matrix(rot=np.eye(3), scale=(1.0, 1.0, 1.0), move=(0.0, 0.0, 0.0)):
    """A 4x4 row-major object-to-world matrix, rounded to float32 as Blender's are."""
    m = np.eye(4)
    m[:3, :3] = rot @ np.diag(scale)
    m[:3, 3] = move
    return m.astype(np.float32).astype(np.float64)


def instanced(seed=0, copies=(4, 3), mirrored=1):
    """Two object-space meshes placed ``copies`` times each, the first ``mirrored`` placements
    of mesh 0 with a negative scale; names 'A', 'B', 'C' (an object per instance, cycling)."""
    rng = np.random.default_rng(seed)
    meshes = []
    for k, t in enumerate((40, 25)):
        v = rng.normal(size=(2 * t, 3)).astype(np.float32)
        meshes.append(core.TriangleMesh(v, rng.integers(0, len(v), (t, 3)), polygon_index=np.arange(t) // 2 + 10 * k))
    which = np.repeat(np.arange(len(copies)), copies)
    mats = []
    for i, k in enumerate(which):
        scale = (-1.5, 1.0, 0.5) if (k == 0 and i < mirrored) else (1.0 + 0.3 * i, 1.0, 2.0)
        mats.append(_matrix(_rotation(rng.normal(size=3), rng.uniform(0, 6)), scale, rng.uniform(-20, 20, 3)))
    return meshes, which, np.array(mats), np.arange(len(which)) % 3, ["A", "B", "C"]


def flat_by_hand(meshes, which, mats, objects, names):
    """An independent flat mesh: instance by instance, world = v @ A^T + b in float32, a
    mirrored instance's corners swapped [0, 2, 1], consecutive global numbering."""
    verts, tris, obj, poly, nv = [], [], [], [], 0
    for k, m, o in zip(which, mats, objects):
        mesh = meshes[k]
        a32, b32 = m[:3, :3].astype(np.float32), m[:3, 3].astype(np.float32)
        verts.append(mesh.vertices @ a32.T + b32)
        t = mesh.triangles + nv
        tris.append(t[:, [0, 2, 1]] if np.linalg.det(m[:3, :3]) < 0 else t)
        obj.append(np.full(mesh.triangle_count, o))
        poly.append(mesh.polygon_index)
        nv += len(mesh.vertices)
    return core.TriangleMesh(np.vstack(verts), np.vstack(tris), np.concatenate(obj), np.concatenate(poly), names)


def test_instanced_file_stores_each_mesh_once_and_gives_the_flat_mesh(tmp_path):
    meshes, which, mats, objects, names = instanced(copies=(30, 20), mirrored=2)
    path = meshio.save_scene(tmp_path / "i.npz", meshes, which, mats, objects, names, frame=4)
    with np.load(path, allow_pickle=False) as z:
        assert z["mesh_vertices"].shape == (sum(len(m.vertices) for m in meshes), 3), "each mesh's vertices once"
        assert z["mesh_triangles"].shape == (sum(m.triangle_count for m in meshes), 3), "each mesh's triangles once"
        assert z["instance_matrix"].shape == (50, 4, 4) and z["instance_matrix"].dtype == np.float64
    f = core.read_scene(path)
    assert f.version == meshio.INSTANCED_VERSION == 2 and f.frame == 4
    want = flat_by_hand(meshes, which, mats, objects, names)
    _same(want, f.mesh)
    _same(want, core.load_mesh(path))
    assert np.array_equal(f.mesh.instance_index, np.repeat(np.arange(50), [meshes[k].triangle_count for k in which]))
    inst = f.instances
    assert inst.mirrored.sum() == 2 and np.array_equal(inst.matrices, mats) and np.array_equal(inst.instance_mesh, which)
    assert inst.digests == [meshio.mesh_digest(m) for m in meshes] and len(set(inst.digests)) == 2
    flat_size = core.save_mesh(want, tmp_path / "flat.npz").stat().st_size
    assert path.stat().st_size * 4 < flat_size, f"50 instances of 2 meshes: {path.stat().st_size} bytes, flat {flat_size}"


def test_instanced_numbering_follows_tri_base_and_the_digest_follows_content(tmp_path):
    meshes, which, mats, objects, names = instanced(seed=1, copies=(2, 2))
    counts = np.array([meshes[k].triangle_count for k in which])
    order = np.array([2, 0, 3, 1])  # the instances' ranges in this order
    base = np.empty(4, np.int64)
    base[order] = np.concatenate([[0], np.cumsum(counts[order])[:-1]])
    got = core.read_scene(meshio.save_scene(tmp_path / "b.npz", meshes, which, mats, objects, names, base)).mesh
    _same(flat_by_hand(meshes, which[order], mats[order], objects[order], names), got)
    moved = core.TriangleMesh(meshes[0].vertices + np.float32(1), meshes[0].triangles, polygon_index=meshes[0].polygon_index)
    assert meshio.mesh_digest(moved) != meshio.mesh_digest(meshes[0])
    with pytest.raises(ValueError, match="tile"):
        meshio.save_scene(tmp_path / "x.npz", meshes, which, mats, objects, names, base + 1)


def test_instanced_flat_mesh_equals_the_extractions_assembly(tmp_path):
    """The same data through operators/extract.py's _assemble (what a version-1 export writes)."""
    pytest.importorskip("bpy", reason="operators.extract imports with the add-on (bpy)")
    from types import SimpleNamespace

    from hybrid_raycast.operators import extract

    meshes, which, mats, objects, names = instanced(seed=2, copies=(3, 2), mirrored=2)
    groups = [SimpleNamespace(co=m.vertices, tris=m.triangles, poly=m.polygon_index,
                              where=list(np.flatnonzero(which == k)), entries=list(objects[which == k]),
                              matrices=mats[which == k].astype(np.float32).transpose(0, 2, 1).copy())
              for k, m in enumerate(meshes)]
    want = extract._assemble(groups, names)
    got = core.read_scene(meshio.save_scene(tmp_path / "e.npz", meshes, which, mats, objects, names)).mesh
    _same(want, got)


def test_damaged_or_inconsistent_instanced_files_are_scene_file_errors(tmp_path):
    meshes, which, mats, objects, names = instanced(seed=3)
    good = meshio.save_scene(tmp_path / "good.npz", meshes, which, mats, objects, names)
    with np.load(good, allow_pickle=False) as z:
        arrays = dict(z)
    for what, change in [("digest", lambda a: a.__setitem__("mesh_digest", a["mesh_digest"][::-1].copy())),
                         ("offsets", lambda a: a.__setitem__("mesh_vertex_start", a["mesh_vertex_start"] + 1)),
                         ("mesh_index", lambda a: a.__setitem__("instance_mesh", a["instance_mesh"] + 5)),
                         ("no_matrix", lambda a: a.pop("instance_matrix"))]:
        bad = dict(arrays)
        change(bad)
        with open(tmp_path / f"{what}.npz", "wb") as f:
            np.savez(f, **bad)
        with pytest.raises(core.SceneFileError, match=f"{what}.npz: damaged") as e:
            core.load_mesh(tmp_path / f"{what}.npz")
        assert "\n" not in str(e.value)
