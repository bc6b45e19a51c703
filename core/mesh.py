"""TriangleMesh: world-space triangles as numpy arrays, validated once."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(eq=False)
class TriangleMesh:
    """Triangles in world space.

    vertices:  (V, 3) float32
    triangles: (T, 3) int32 indices into ``vertices``
    object_index: (T,) int32, per triangle the index into ``object_names`` (optional)
    polygon_index: (T,) int32, per triangle the source polygon of its object (optional)
    object_names: names of the source objects (optional)
    instance_index: (T,) int32, per triangle the placement (instance) it belongs to (optional)

    Construction validates shapes, indices and finiteness and raises ``ValueError``
    with a message that says what is wrong and where.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    object_index: np.ndarray | None = None
    polygon_index: np.ndarray | None = None
    object_names: list[str] = field(default_factory=list)
    instance_index: np.ndarray | None = None

    def __post_init__(self):
        v = np.asarray(self.vertices)
        f = np.asarray(self.triangles)
        if v.size == 0:
            v = v.reshape(0, 3)
        if f.size == 0:
            f = f.reshape(0, 3)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"triangles must have shape (T, 3), got {f.shape}")
        if not np.issubdtype(v.dtype, np.number) or np.issubdtype(v.dtype, np.complexfloating):
            raise ValueError(f"vertices must be real numbers, got dtype {v.dtype}")
        if f.size and not np.issubdtype(f.dtype, np.integer):
            if np.issubdtype(f.dtype, np.floating) and np.all(np.mod(f, 1) == 0):
                f = f.astype(np.int64)
            else:
                raise ValueError(f"triangles must be integer indices, got dtype {f.dtype}")
        with np.errstate(over="ignore", invalid="ignore"):  # overflow to inf is reported below
            v32 = np.ascontiguousarray(v, dtype=np.float32)
        bad = ~np.isfinite(v32).all(axis=1)
        if bad.any():
            where = np.flatnonzero(bad)
            raise ValueError(
                f"{where.size} of {len(v32)} vertices are NaN or infinite (or overflow float32), "
                f"first at vertex index {where[:5].tolist()}"
            )
        if f.size:
            lo, hi = int(f.min()), int(f.max())
            if lo < 0 or hi >= len(v32):
                badt = np.flatnonzero(((f < 0) | (f >= len(v32))).any(axis=1))
                raise ValueError(
                    f"{badt.size} triangles index vertices outside 0..{len(v32) - 1} "
                    f"(indices from {lo} to {hi}), first at triangle {badt[:5].tolist()}"
                )
        self.vertices = v32
        self.triangles = np.ascontiguousarray(f, dtype=np.int32)
        T = len(self.triangles)
        for name in ("object_index", "polygon_index", "instance_index"):
            a = getattr(self, name)
            if a is not None:
                a = np.ascontiguousarray(a, dtype=np.int32)
                if a.shape != (T,):
                    raise ValueError(f"{name} must have shape ({T},), got {a.shape}")
                setattr(self, name, a)
        self.object_names = list(self.object_names)
        self._tri_vertices = None
        self._valid = None
        self._bounds = None

    # -- derived arrays (computed once, on demand) ---------------------------------
    @property
    def triangle_count(self) -> int:
        return int(len(self.triangles))

    @property
    def tri_vertices(self) -> np.ndarray:
        """(T, 3, 3) float32: the corners of each triangle, contiguous for fast gathers."""
        if self._tri_vertices is None:
            self._tri_vertices = np.ascontiguousarray(self.vertices[self.triangles])
        return self._tri_vertices

    @property
    def valid(self) -> np.ndarray:
        """(T,) bool: False for degenerate (zero-area in float64) triangles, which never hit."""
        if self._valid is None:
            # the cross product by columns (np.cross's products and differences, so the same
            # zeros; exact here: float32 differences multiply exactly in float64), and no
            # row-wise reduce over 3 columns, which costs several times more
            tv = self.tri_vertices
            a = [tv[:, 1, k].astype(np.float64) - tv[:, 0, k] for k in range(3)]
            b = [tv[:, 2, k].astype(np.float64) - tv[:, 0, k] for k in range(3)]
            self._valid = ((a[1] * b[2] - a[2] * b[1] != 0.0) | (a[2] * b[0] - a[0] * b[2] != 0.0)
                           | (a[0] * b[1] - a[1] * b[0] != 0.0))
        return self._valid

    def prepare(self) -> "TriangleMesh":
        """Compute the cached arrays every structure reads (``tri_vertices``, ``valid``), so
        that a timed build does not pay for them; returns the mesh."""
        self.tri_vertices
        self.valid
        return self

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) float32 of the vertices that triangles use; zeros for an empty mesh.

        Computed once, like the other derived arrays: a column reduction over every corner
        is costly on a large mesh, and every ``plan()`` on a cached scene would pay it
        again for its uniform sample box.  Copies are returned, so a caller cannot change it."""
        if self._bounds is None:
            if self.triangle_count == 0:
                self._bounds = (np.zeros(3, np.float32), np.zeros(3, np.float32))
            else:
                used = self.tri_vertices.reshape(-1, 3)
                # one strided pass per column: numpy's axis-0 reduction over 3 columns runs
                # its inner loop 3 wide, an order of magnitude slower (BENCHMARKS.md, "Scans")
                self._bounds = (np.array([used[:, k].min() for k in range(3)], np.float32),
                                np.array([used[:, k].max() for k in range(3)], np.float32))
        return self._bounds[0].copy(), self._bounds[1].copy()

    def areas(self) -> np.ndarray:
        """(T,) float64 triangle areas."""
        tv = self.tri_vertices.astype(np.float64)
        return 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)

    def surface_area(self) -> float:
        return float(self.areas().sum())

    def is_surface(self) -> bool:
        """Whether the triangles share their vertices as a surface's do (no more vertices
        than triangles; a closed mesh has about half as many), not a soup of separate
        triangles with three each.  A plan may build a hierarchy at once, without a sample,
        only for a surface (``decide.rule.regret_bound``)."""
        return 0 < len(self.vertices) <= self.triangle_count

    def nbytes(self) -> int:
        return int(self.vertices.nbytes + self.triangles.nbytes)

    def __repr__(self):
        return f"TriangleMesh({len(self.vertices)} vertices, {self.triangle_count} triangles, {len(self.object_names)} objects)"


def unit_normals(tri_vertices) -> np.ndarray:
    """(T, 3) float32 unit geometric normals, cross(v1 - v0, v2 - v0) / |...| in float64, of
    (T, 3, 3) triangle corners (NaN for a degenerate triangle)."""
    tv = np.asarray(tri_vertices, np.float64)
    n = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        return (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32)


def place(vertices, triangles, column_major, vertex_base, out_vertices=None, out_triangles=None):
    """k placements of one mesh in world space, as Blender places it: (world vertices (k, V, 3)
    float32, triangles (k, T, 3) int32, mirrored (k,) bool).

    column_major: (k, 4, 4) float32 matrices as ``object_instances.foreach_get('matrix_world')``
    reads them (``[:, :3, :3]`` is A^T, ``[:, 3, :3]`` the translation b); world = v A^T + b in
    float32, one batched product, so every caller rounds alike.  vertex_base: (k,) the index
    of each placement's first vertex in the caller's vertex array.  A mirrored placement
    (det A < 0, in float64) has two corners of every triangle swapped, [0, 2, 1], so the
    winding stays as the mesh's.  ``out_vertices`` / ``out_triangles``: arrays to fill."""
    k, nv, nt = len(column_major), len(vertices), len(triangles)
    w = out_vertices if out_vertices is not None else np.empty((k, nv, 3), np.float32)
    np.matmul(vertices, column_major[:, :3, :3], out=w)
    w += column_major[:, None, 3, :3]
    t = out_triangles if out_triangles is not None else np.empty((k, nt, 3), np.int32)
    np.add(triangles, np.asarray(vertex_base).astype(np.int32)[:, None, None], out=t)
    mirrored = np.linalg.det(column_major[:, :3, :3].astype(np.float64)) < 0
    if mirrored.any():
        t[mirrored] = t[mirrored][:, :, [0, 2, 1]]
    return w, t, mirrored
