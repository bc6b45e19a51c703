"""Scene files: one TriangleMesh (and its frame) in a compressed .npz, for tracing away from Blender.

A scene file holds the arrays of ``TriangleMesh`` as they are (float32 vertices, int32
triangles, object and polygon indices) plus the object names, the frame it was taken at
and a format tag and version, so a reader knows what it opens.  ``np.load`` reads it
with ``allow_pickle=False``: a scene file never runs code.  Writes go to a temporary
file in the same folder and are renamed into place (``os.replace`` is atomic on POSIX and
Windows), so a reader sees the old file or the new one, never half of one.
"""

from __future__ import annotations

import errno
import hashlib
import io
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .mesh import TriangleMesh

FORMAT = "hybrid_raycast.scene"
VERSION = 1
SUFFIX = ".npz"


class SceneFileError(ValueError):
    """A scene file that is not one, is damaged, or was written by a newer version."""


@dataclass
class SceneFile:
    """What ``read_scene`` returns.

    mesh: the TriangleMesh
    frame: the frame it was exported at (None when not given)
    version: the format version it was written with
    digest: SHA-256 of the file's bytes (hex), the identity ``core.distributed`` caches by
    """

    path: Path
    mesh: TriangleMesh
    frame: int | None
    version: int
    digest: str


def save_mesh(mesh: TriangleMesh, path, *, frame: int | None = None) -> Path:
    """Write ``mesh`` (and ``frame``) to ``path`` atomically; returns the path.

    Raises TypeError for something that is not a TriangleMesh, and OSError when the
    folder cannot be written (the target is then left as it was).
    """
    if not isinstance(mesh, TriangleMesh):
        raise TypeError(f"save_mesh() needs a core.TriangleMesh, got {type(mesh).__name__}")
    path = Path(path)
    arrays = {
        "format": np.array(FORMAT),
        "version": np.array(VERSION, np.int32),
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
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
    return path


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


def read_scene(path, *, expect_digest: str | None = None) -> SceneFile:
    """Read a scene file written by ``save_mesh``.

    expect_digest: the SHA-256 the caller saw; a file whose bytes differ now raises
    SceneFileError (it changed in between).
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
            missing = [k for k in ("vertices", "triangles") if k not in z.files]
            if missing:
                raise SceneFileError(f"{path}: damaged scene file (no {' or '.join(missing)} array)")
            names = z["object_names"] if "object_names" in z.files else np.zeros(0, str)
            mesh = TriangleMesh(
                z["vertices"], z["triangles"],
                object_index=z["object_index"] if "object_index" in z.files else None,
                polygon_index=z["polygon_index"] if "polygon_index" in z.files else None,
                object_names=[str(n) for n in names.reshape(-1)],
            )
            frame = int(z["frame"][()]) if "frame" in z.files else None
        except SceneFileError:
            raise
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, TypeError, KeyError) as e:
            raise SceneFileError(f"{path}: damaged scene file ({type(e).__name__}: {e})") from None
    return SceneFile(path=path, mesh=mesh, frame=frame, version=version, digest=digest)


def load_mesh(path) -> TriangleMesh:
    """The TriangleMesh of a scene file (``read_scene`` for the frame and the rest)."""
    return read_scene(path).mesh
