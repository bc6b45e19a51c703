"""A small Wavefront OBJ reader: positions and faces only, into a TriangleMesh.

Reads what the test meshes and most exporters write: ``v x y z [w | r g b]`` lines and
``f`` lines whose corners are ``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn`` with 1-based
or negative (relative to the vertices read so far) indices.  Polygons with more than
three corners are fan-triangulated (corner 0, i, i+1), and every triangle remembers
its source face in ``polygon_index`` (0-based, counting ``f`` lines in file order).
``o`` statements name objects (``object_index`` per triangle); everything else
(normals, texture coordinates, materials, groups, lines, curves) is ignored.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .mesh import TriangleMesh

# the "/vt/vn" tail of a face corner: only the position index matters here
_CORNER_TAIL = re.compile(r"/[^\s]*")


def load_obj(path) -> TriangleMesh:
    """Read ``path`` into a TriangleMesh (float32 positions, int32 triangles).

    Raises ValueError naming the line for malformed vertices, zero indices and faces
    with fewer than three corners; indices outside the vertex list raise from
    TriangleMesh with the offending triangle.
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8", errors="replace")
    vlines: list[str] = []
    flines: list[str] = []
    fline_no: list[int] = []
    f_nverts: list[int] = []  # vertices read before each face: the base of negative indices
    f_object: list[int] = []
    names: list[str] = []
    for no, line in enumerate(text.splitlines(), 1):
        if line.startswith("v ") or line.startswith("v\t"):
            vlines.append(line)
        elif line.startswith("f ") or line.startswith("f\t"):
            flines.append(line[2:])
            fline_no.append(no)
            f_nverts.append(len(vlines))
            f_object.append(max(0, len(names) - 1))
        elif line.startswith("o ") or line.startswith("o\t"):
            names.append(line[2:].strip() or f"object{len(names)}")

    vertices = _parse_vertices(vlines, path)
    if not names:
        names = [path.stem]

    if not flines:
        return TriangleMesh(vertices, np.zeros((0, 3), np.int32), object_index=np.zeros(0, np.int32),
                            polygon_index=np.zeros(0, np.int32), object_names=names)

    corners = [_CORNER_TAIL.sub("", f).split() for f in flines]
    counts = np.fromiter(map(len, corners), dtype=np.int64, count=len(corners))
    short = np.flatnonzero(counts < 3)
    if short.size:
        i = int(short[0])
        raise ValueError(f"{path.name}:{fline_no[i]}: face with {counts[i]} corners (needs at least 3)")
    try:
        flat = np.array([c for face in corners for c in face], dtype=np.int64)
    except ValueError as e:
        raise ValueError(f"{path.name}: a face index is not an integer ({e})") from None
    if (flat == 0).any():
        k = int(np.flatnonzero(flat == 0)[0])
        face = int(np.searchsorted(np.cumsum(counts), k, side="right"))
        raise ValueError(f"{path.name}:{fline_no[face]}: vertex index 0 (OBJ indices start at 1)")

    # 1-based -> 0-based; negative indices count back from the vertices read so far
    base = np.repeat(np.asarray(f_nverts, np.int64), counts)
    flat = np.where(flat > 0, flat - 1, base + flat)

    # fan triangulation, vectorised: triangle j of face f is (c0, c_{j+1}, c_{j+2})
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    ntri = counts - 2
    face_of_tri = np.repeat(np.arange(len(counts)), ntri)
    j = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    s = starts[face_of_tri]
    triangles = np.stack([flat[s], flat[s + j + 1], flat[s + j + 2]], axis=1)
    object_index = np.asarray(f_object, np.int32)[face_of_tri]
    return TriangleMesh(vertices, triangles, object_index=object_index,
                        polygon_index=face_of_tri.astype(np.int32), object_names=names)


def _parse_vertices(vlines, path) -> np.ndarray:
    if not vlines:
        return np.zeros((0, 3), np.float32)
    try:
        # extra columns (w, or vertex colours) are dropped
        return np.array([ln.split()[1:4] for ln in vlines], dtype=np.float64).reshape(-1, 3)
    except ValueError:
        for ln in vlines:
            parts = ln.split()[1:4]
            try:
                if len(parts) != 3:
                    raise ValueError
                [float(p) for p in parts]
            except ValueError:
                raise ValueError(f"{path.name}: malformed vertex line {ln.strip()!r}") from None
        raise
