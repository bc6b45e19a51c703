"""Scene files: a scene (and its frame) in a compressed .npz, for tracing away from Blender.

Two forms, told apart by the format version:

- version 1, flat (``save_mesh``): the arrays of one world-space ``TriangleMesh`` as they
  are (float32 vertices, int32 triangles, object and polygon indices);
- version 2, instanced (``save_scene``): each unique mesh once, in its object space, with a
  SHA-256 of its arrays, and per instance the mesh it places, its 4x4 object-to-world
  matrix, its object and its global triangle base.  ``SceneFile.mesh`` assembles the flat
  world-space mesh on demand, laid out and rounded as the extraction's flat mesh
  (``operators/extract.py``, ``_assemble``), so a version-2 file of a scene gives the
  same ``TriangleMesh`` as a version-1 file of it; ``core.distributed`` builds one bottom
  level per mesh digest instead and reuses it across frames.

Both hold the object names, the frame it was taken at and a format tag and version, so a
reader knows what it opens.  ``np.load`` reads a file with ``allow_pickle=False``: a scene
file never runs code.  Writes go to a temporary file in the same folder and are renamed
into place (``os.replace`` is atomic on POSIX and Windows), so a reader sees the old file
or the new one, never half of one.
"""

from __future__ import annotations

import errno
import hashlib
import io
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .mesh import TriangleMesh, place

FORMAT = "hybrid_raycast.scene"
#: the flat form (``save_mesh``)
FLAT_VERSION = 1
#: the instanced form (``save_scene``)
INSTANCED_VERSION = 2
#: the newest version this reads
VERSION = INSTANCED_VERSION
SUFFIX = ".npz"

_INT32_MAX = np.iinfo(np.int32).max


class SceneFileError(ValueError):
    """A scene file that is not one, is damaged, or was written by a newer version."""


def mesh_digest(mesh: TriangleMesh) -> str:
    """SHA-256 (hex) of an object-space mesh's arrays: its sizes, then the bytes of its
    vertices (little-endian float32), triangles (int32) and polygon indices (int32, when
    present).  Equal digests mean equal arrays, so a bottom level built over one serves
    the other (``core.distributed`` keys its bottoms by it)."""
    h = hashlib.sha256()
    poly = mesh.polygon_index
    h.update(f"{len(mesh.vertices)} {mesh.triangle_count} {poly is not None}\n".encode())
    h.update(np.ascontiguousarray(mesh.vertices, "<f4"))
    h.update(np.ascontiguousarray(mesh.triangles, "<i4"))
    if poly is not None:
        h.update(np.ascontiguousarray(poly, "<i4"))
    return h.hexdigest()


@dataclass(eq=False)
class InstancedScene:
    """Unique object-space meshes placed by matrices: what a version-2 scene file holds.

    Parameters
    ----------
    meshes : sequence of TriangleMesh, or of (vertices, triangles[, polygon_index]) tuples
        The K unique meshes in their object space: vertices (V_k, 3) float32, triangles
        (T_k, 3) int32, polygon_index (T_k,) int32 or None (kept only when every mesh has
        one; their object_index and names are not used).  Stored as TriangleMesh.
    instance_mesh : (I,) int
        The mesh each instance places, 0..K-1.  Stored int32.
    matrices : (I, 4, 4) float
        Object-to-world matrices, row-major as Blender's ``matrix_world`` (``p_world = M @
        [p, 1]``), bottom row (0, 0, 0, 1).  Stored float64.
    instance_object : (I,) int
        Each instance's index into ``object_names`` (the flat mesh's ``object_index``).
        Stored int32.
    object_names : sequence of str
    tri_base : (I,) int, optional
        The global index of each instance's triangle 0; the instances' ranges
        [tri_base, tri_base + T) tile 0..T-1 (T: the scene's triangles) exactly once.
        Default: consecutive in instance order.  Stored int64.

    ``digests`` (K hex strings, ``mesh_digest``) and ``triangle_count`` are derived.
    Raises ValueError (the first bad instance named) for shapes that do not fit, an index
    out of range, a non-finite matrix or one whose bottom row is not (0, 0, 0, 1), or
    ranges that do not tile.
    """

    meshes: list
    instance_mesh: np.ndarray
    matrices: np.ndarray
    instance_object: np.ndarray
    object_names: list = field(default_factory=list)
    tri_base: np.ndarray | None = None

    def __post_init__(self):
        self.meshes = [m if isinstance(m, TriangleMesh) else _object_mesh(*m) for m in self.meshes]
        if any(m.polygon_index is None for m in self.meshes):  # kept only when every mesh has them
            self.meshes = [m if m.polygon_index is None else TriangleMesh(m.vertices, m.triangles)
                           for m in self.meshes]
        self.object_names = [str(n) for n in self.object_names]
        k = len(self.meshes)
        im = _ints(self.instance_mesh, "instance_mesh")
        n = len(im)
        if im.size and (im.min() < 0 or im.max() >= k):
            bad = np.flatnonzero((im < 0) | (im >= k))[0]
            raise ValueError(f"instance {bad} places mesh {im[bad]}, outside 0..{k - 1}")
        self.instance_mesh = im.astype(np.int32)
        m = np.asarray(self.matrices, np.float64)
        if m.shape != (n, 4, 4):
            raise ValueError(f"matrices must have shape ({n}, 4, 4), got {m.shape}")
        bad = np.flatnonzero(~np.isfinite(m).all(axis=(1, 2)) | (m[:, 3] != (0.0, 0.0, 0.0, 1.0)).any(axis=1))
        if bad.size:
            raise ValueError(f"instance {bad[0]}: its matrix is not finite or its bottom row is not (0, 0, 0, 1)")
        self.matrices = np.ascontiguousarray(m)
        obj = _ints(self.instance_object, "instance_object")
        if obj.shape != (n,):
            raise ValueError(f"instance_object must have shape ({n},), got {obj.shape}")
        if obj.size and (obj.min() < 0 or obj.max() >= len(self.object_names)):
            bad = np.flatnonzero((obj < 0) | (obj >= len(self.object_names)))[0]
            raise ValueError(f"instance {bad}: object {obj[bad]} is outside the {len(self.object_names)} object names")
        self.instance_object = obj.astype(np.int32)
        counts = self._counts()
        if self.tri_base is None:
            base = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64) if n else np.zeros(0, np.int64)
        else:
            base = _ints(self.tri_base, "tri_base").astype(np.int64)
            if base.shape != (n,):
                raise ValueError(f"tri_base must have shape ({n},), got {base.shape}")
            order = np.argsort(base, kind="stable")
            want = np.concatenate([[0], np.cumsum(counts[order])[:-1]]) if n else np.zeros(0, np.int64)
            bad = np.flatnonzero(base[order] != want)
            if bad.size:
                raise ValueError(f"tri_base: instance {order[bad[0]]} starts at {base[order[bad[0]]]}, not at "
                                 f"{want[bad[0]]}: the instances' triangle ranges must tile 0..T-1 once")
        self.tri_base = base
        self.triangle_count = int(counts.sum())
        self.digests = [mesh_digest(mesh) for mesh in self.meshes]
        self._flat = None

    def _counts(self) -> np.ndarray:
        """(I,) int64 triangles of each instance."""
        sizes = np.array([mesh.triangle_count for mesh in self.meshes], np.int64)
        return sizes[self.instance_mesh] if len(self.instance_mesh) else np.zeros(0, np.int64)

    @property
    def instance_count(self) -> int:
        return int(len(self.instance_mesh))

    def _column_major32(self) -> np.ndarray:
        """(I, 4, 4) float32 matrices laid out as the extraction reads Blender's
        (column-major rows: ``m[:, :3, :3]`` is A^T, ``m[:, 3, :3]`` the translation)."""
        return np.ascontiguousarray(self.matrices.astype(np.float32).transpose(0, 2, 1))

    @property
    def mirrored(self) -> np.ndarray:
        """(I,) bool: det(A) < 0 (of the float32 matrix, in float64), where the flat mesh
        swaps two corners of every triangle to keep the winding."""
        if not self.instance_count:
            return np.zeros(0, bool)
        return np.linalg.det(self._column_major32()[:, :3, :3].astype(np.float64)) < 0

    def flat(self) -> TriangleMesh:
        """The world-space TriangleMesh, made once: instance i's triangles at global
        indices tri_base[i]..+T, its vertices in the same order, ``world = v @ A^T + b``
        in float32 (``core.mesh.place``, as the extraction places them, so the rounding is
        the same), a mirrored instance's corners swapped [0, 2, 1]; object_index,
        polygon_index (when every mesh has one) and instance_index per triangle.  ValueError
        when the vertices pass the int32 range of triangle indices."""
        if self._flat is not None:
            return self._flat
        n = self.instance_count
        nv_of = np.array([len(m.vertices) for m in self.meshes], np.int64)
        nv_i = nv_of[self.instance_mesh] if n else np.zeros(0, np.int64)
        nv = int(nv_i.sum())
        if nv > _INT32_MAX:
            raise ValueError(f"the scene has {nv} vertices, more than int32 triangle indices can address")
        order = np.argsort(self.tri_base, kind="stable")  # vertices laid out in global triangle order
        vbase = np.empty(n, np.int64)
        vbase[order] = np.concatenate([[0], np.cumsum(nv_i[order])[:-1]]) if n else np.zeros(0, np.int64)
        nt = self.triangle_count
        vertices = np.empty((nv, 3), np.float32)
        triangles = np.empty((nt, 3), np.int32)
        object_index = np.empty(nt, np.int32)
        instance_index = np.empty(nt, np.int32)
        with_poly = all(m.polygon_index is not None for m in self.meshes)
        polygon_index = np.empty(nt, np.int32) if with_poly else None
        cm = self._column_major32()
        for k, mesh in enumerate(self.meshes):  # a loop per unique mesh; its instances batched
            idx = np.flatnonzero(self.instance_mesh == k)
            V, T = len(mesh.vertices), mesh.triangle_count
            if not idx.size:
                continue
            w, t, _ = place(mesh.vertices, mesh.triangles, np.ascontiguousarray(cm[idx]), vbase[idx])
            vertices[(vbase[idx][:, None] + np.arange(V)).reshape(-1)] = w.reshape(-1, 3)
            rows = (self.tri_base[idx][:, None] + np.arange(T)).reshape(-1)
            triangles[rows] = t.reshape(-1, 3)
            object_index[rows] = np.repeat(self.instance_object[idx], T)
            instance_index[rows] = np.repeat(idx.astype(np.int32), T)
            if with_poly:
                polygon_index[rows] = np.tile(mesh.polygon_index, idx.size)
        self._flat = TriangleMesh(vertices, triangles, object_index, polygon_index, list(self.object_names),
                                  instance_index=instance_index)
        return self._flat


def _ints(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be a 1-D integer array, got shape {a.shape} dtype {a.dtype}")
    return a


def _object_mesh(vertices, triangles, polygon_index=None) -> TriangleMesh:
    return TriangleMesh(vertices, triangles, polygon_index=polygon_index)


class SceneFile:
    """What ``read_scene`` returns.

    path: the file
    mesh: the flat world-space TriangleMesh (of a version-2 file: assembled on first use,
        ``InstancedScene.flat``)
    frame: the frame it was exported at (None when not given)
    version: the format version it was written with (1 flat, 2 instanced)
    digest: SHA-256 of the file's bytes (hex), the identity ``core.distributed`` caches by
    instances: the ``InstancedScene`` of a version-2 file (meshes, matrices, digests, ...),
        None for version 1
    """

    def __init__(self, path: Path, mesh: TriangleMesh | None, frame: int | None, version: int, digest: str,
                 instances: InstancedScene | None = None):
        self.path, self.frame, self.version, self.digest = path, frame, version, digest
        self.instances = instances
        self._mesh = mesh

    @property
    def mesh(self) -> TriangleMesh:
        if self._mesh is None:
            self._mesh = self.instances.flat()
        return self._mesh

    def __repr__(self):
        what = f"{self.instances.instance_count} instances of {len(self.instances.meshes)} meshes" \
            if self.instances is not None else f"{self._mesh.triangle_count} triangles"
        return f"<SceneFile {self.path.name} v{self.version} frame={self.frame} {what}>"


def _write(path: Path, arrays: dict) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
    return path


def save_mesh(mesh: TriangleMesh, path, *, frame: int | None = None) -> Path:
    """Write ``mesh`` (and ``frame``) to ``path`` atomically, flat (version 1); returns the path.

    Raises TypeError for something that is not a TriangleMesh, and OSError when the
    folder cannot be written (the target is then left as it was).
    """
    if not isinstance(mesh, TriangleMesh):
        raise TypeError(f"save_mesh() needs a core.TriangleMesh, got {type(mesh).__name__}")
    path = Path(path)
    arrays = {
        "format": np.array(FORMAT),
        "version": np.array(FLAT_VERSION, np.int32),
        "vertices": mesh.vertices,
        "triangles": mesh.triangles,
        "object_names": np.array(list(mesh.object_names), dtype=str),
    }
    if mesh.object_index is not None:
        arrays["object_index"] = mesh.object_index
    if mesh.polygon_index is not None:
        arrays["polygon_index"] = mesh.polygon_index
    if frame is not None:
        arrays["frame"] = np.array(int(frame), np.int64)
    return _write(path, arrays)


def save_scene(path, meshes, instance_mesh, matrices, instance_object, object_names, tri_base=None, *,
               frame: int | None = None) -> Path:
    """Write an instanced scene (version 2) to ``path`` atomically: each mesh once; returns the path.

    meshes, instance_mesh, matrices, instance_object, object_names, tri_base: as
    ``InstancedScene`` (shapes and dtypes there); ``meshes`` may also be an
    ``InstancedScene``, the rest then left out.  The file holds the meshes end to end
    (``mesh_vertices`` (sum V, 3) float32, ``mesh_triangles`` (sum T, 3) int32 local
    indices, ``mesh_polygon_index`` (sum T,) int32 when every mesh has one, and the
    ``mesh_vertex_start`` / ``mesh_triangle_start`` (K + 1,) int64 offsets), ``mesh_digest``
    (K,), and per instance ``instance_mesh`` int32, ``instance_matrix`` (I, 4, 4) float64,
    ``instance_object`` int32 and ``instance_tri_base`` int64.
    Raises ValueError for arrays that do not fit (``InstancedScene``) and OSError when the
    folder cannot be written (the target is then left as it was).
    """
    s = meshes if isinstance(meshes, InstancedScene) else InstancedScene(
        list(meshes), instance_mesh, matrices, instance_object, list(object_names), tri_base)
    vstart = np.concatenate([[0], np.cumsum([len(m.vertices) for m in s.meshes])]).astype(np.int64)
    tstart = np.concatenate([[0], np.cumsum([m.triangle_count for m in s.meshes])]).astype(np.int64)
    arrays = {
        "format": np.array(FORMAT),
        "version": np.array(INSTANCED_VERSION, np.int32),
        "object_names": np.array(s.object_names, dtype=str),
        "mesh_vertices": np.concatenate([m.vertices for m in s.meshes]) if s.meshes else np.zeros((0, 3), np.float32),
        "mesh_vertex_start": vstart,
        "mesh_triangles": np.concatenate([m.triangles for m in s.meshes]) if s.meshes else np.zeros((0, 3), np.int32),
        "mesh_triangle_start": tstart,
        "mesh_digest": np.array(s.digests, dtype=str),
        "instance_mesh": s.instance_mesh,
        "instance_matrix": s.matrices,
        "instance_object": s.instance_object,
        "instance_tri_base": s.tri_base,
    }
    if s.meshes and all(m.polygon_index is not None for m in s.meshes):
        arrays["mesh_polygon_index"] = np.concatenate([m.polygon_index for m in s.meshes])
    if frame is not None:
        arrays["frame"] = np.array(int(frame), np.int64)
    return _write(Path(path), arrays)


def _missing(path: Path) -> FileNotFoundError:
    return FileNotFoundError(errno.ENOENT, "no scene file", str(path))


def _open(path: Path, source):
    """The NpzFile of ``source`` (the path, or its bytes in a BytesIO), lazily: arrays are
    read when asked for."""
    try:
        z = np.load(source, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise SceneFileError(f"{path}: not a scene file (not an .npz archive: {e})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise SceneFileError(f"{path}: not a scene file (a single .npy array, not an .npz archive)")
    return z


def _header(path: Path, z) -> int:
    try:
        fmt = str(z["format"][()]) if "format" in z.files else None
        version = int(z["version"][()]) if "version" in z.files else None
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, TypeError) as e:
        raise SceneFileError(f"{path}: damaged scene file header ({e})") from None
    if fmt != FORMAT or version is None:
        raise SceneFileError(f"{path}: not a scene file (an .npz without the '{FORMAT}' tag; "
                             f"it holds {', '.join(z.files[:8]) or 'nothing'})")
    if version > VERSION or version < 1:
        raise SceneFileError(f"{path}: scene file format version {version}; this version reads up to {VERSION}")
    return version


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise _missing(path) from None
    except IsADirectoryError:
        raise SceneFileError(f"{path}: is a folder, not a scene file") from None
    except OSError as e:
        raise SceneFileError(f"{path}: cannot read ({e.strerror or e})") from None


def check_scene(path) -> int:
    """Open ``path`` far enough to know it is a scene file this version reads: the format
    version.  Reads the header only (cheap); FileNotFoundError or SceneFileError otherwise."""
    path = Path(path)
    if not path.exists():
        raise _missing(path)
    if path.is_dir():
        raise SceneFileError(f"{path}: is a folder, not a scene file")
    with _open(path, path) as z:
        return _header(path, z)


def file_digest(path) -> str:
    """SHA-256 (hex) of the file's bytes; FileNotFoundError naming the file when missing."""
    return hashlib.sha256(_read_bytes(Path(path))).hexdigest()


def _need(path: Path, z, names) -> None:
    missing = [k for k in names if k not in z.files]
    if missing:
        raise SceneFileError(f"{path}: damaged scene file (no {' or '.join(missing)} array)")


def _read_flat(path: Path, z) -> TriangleMesh:
    _need(path, z, ("vertices", "triangles"))
    names = z["object_names"] if "object_names" in z.files else np.zeros(0, str)
    return TriangleMesh(
        z["vertices"], z["triangles"],
        object_index=z["object_index"] if "object_index" in z.files else None,
        polygon_index=z["polygon_index"] if "polygon_index" in z.files else None,
        object_names=[str(n) for n in names.reshape(-1)],
    )


def _read_instanced(path: Path, z) -> InstancedScene:
    _need(path, z, ("mesh_vertices", "mesh_vertex_start", "mesh_triangles", "mesh_triangle_start", "mesh_digest",
                    "instance_mesh", "instance_matrix", "instance_object", "instance_tri_base"))
    verts, tris = z["mesh_vertices"], z["mesh_triangles"]
    vs, ts = z["mesh_vertex_start"].astype(np.int64), z["mesh_triangle_start"].astype(np.int64)
    poly = z["mesh_polygon_index"] if "mesh_polygon_index" in z.files else None
    stored = [str(d) for d in z["mesh_digest"].reshape(-1)]
    k = len(stored)
    if vs.shape != (k + 1,) or ts.shape != (k + 1,) or vs[0] != 0 or ts[0] != 0 or (np.diff(vs) < 0).any() \
            or (np.diff(ts) < 0).any() or vs[-1] != len(verts) or ts[-1] != len(tris) \
            or (poly is not None and len(poly) != len(tris)):
        raise SceneFileError(f"{path}: damaged scene file (the mesh offsets do not fit the {k} meshes' arrays)")
    meshes = [TriangleMesh(verts[vs[i]:vs[i + 1]], tris[ts[i]:ts[i + 1]],
                           polygon_index=None if poly is None else poly[ts[i]:ts[i + 1]]) for i in range(k)]
    names = z["object_names"] if "object_names" in z.files else np.zeros(0, str)
    s = InstancedScene(meshes, z["instance_mesh"], z["instance_matrix"], z["instance_object"],
                       [str(n) for n in names.reshape(-1)], z["instance_tri_base"])
    bad = [i for i, (a, b) in enumerate(zip(s.digests, stored)) if a != b]
    if bad:
        raise SceneFileError(f"{path}: damaged scene file (mesh {bad[0]}'s arrays do not match its digest)")
    return s


def read_scene(path, *, expect_digest: str | None = None) -> SceneFile:
    """Read a scene file written by ``save_mesh`` (version 1) or ``save_scene`` (version 2).

    expect_digest: the SHA-256 the caller saw; a file whose bytes differ now raises
    SceneFileError (it changed in between).  A version-2 file's meshes are checked against
    their digests.
    Raises FileNotFoundError when ``path`` does not exist and SceneFileError (a ValueError,
    one line naming the file) when it is not a scene file, is damaged, or is newer.
    """
    path = Path(path)
    data = _read_bytes(path)
    digest = hashlib.sha256(data).hexdigest()
    if expect_digest is not None and digest != expect_digest:
        raise SceneFileError(f"{path}: the file changed since it was first read (SHA-256 {digest[:12]}..., "
                             f"expected {expect_digest[:12]}...)")
    with _open(path, io.BytesIO(data)) as z:
        version = _header(path, z)
        try:
            if version == FLAT_VERSION:
                mesh, instances = _read_flat(path, z), None
            else:
                mesh, instances = None, _read_instanced(path, z)
            frame = int(z["frame"][()]) if "frame" in z.files else None
        except SceneFileError:
            raise
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, TypeError, KeyError) as e:
            raise SceneFileError(f"{path}: damaged scene file ({type(e).__name__}: {e})") from None
    return SceneFile(path=path, mesh=mesh, frame=frame, version=version, digest=digest, instances=instances)


def load_mesh(path) -> TriangleMesh:
    """The flat TriangleMesh of a scene file of either version (``read_scene`` for the
    frame, the instances and the rest)."""
    return read_scene(path).mesh
