"""All-pairs brute force through the shared kernel: the in-package reference for tests."""

from __future__ import annotations

import numpy as np

from . import proximity
from .accel import Accel
from .intersect import NearestHits, Rays, intersect


class BruteForce(Accel):
    """Tests every ray against every (non-degenerate) triangle, in blocks of pairs.

    Config: ``block_pairs`` (default 2**20): pairs per kernel call, bounds memory.
    """

    kind = "brute"
    chunk_size = 1 << 12

    def __init__(self, mesh, *, block_pairs: int = 1 << 20, **kw):
        self.block_pairs = int(block_pairs)
        super().__init__(mesh, **kw)

    def _build(self):
        self.tris = np.flatnonzero(self.mesh.valid).astype(np.int32)

    def _pairs(self, m):
        per = max(1, self.block_pairs // max(1, m))
        for s in range(0, len(self.tris), per):
            tri = self.tris[s : s + per]
            yield np.repeat(np.arange(m), len(tri)), np.tile(tri, m)

    def _trace_rays(self, rays: Rays):
        tv = self.mesh.tri_vertices
        best = NearestHits(len(rays))
        for r, tri in self._pairs(len(rays)):
            best.update(r, tri, intersect(rays, r, tri, tv, t_hi=best.t(r)))
        return best.finish(rays, tv)

    # the point queries by brute force: the reference the trees are tested against
    def closest(self, points, max_distance=np.inf):
        return proximity.closest_brute(self.mesh, points, max_distance)

    def winding_number(self, points, accuracy=None):
        """The exact sum over every triangle (``accuracy`` is the trees'; ignored)."""
        return proximity.winding_number_brute(self.mesh, points)

    def count_hits(self, origins, directions, tmin=0.0, tmax=np.inf):
        return proximity.count_hits_brute(self.mesh, origins, directions, tmin, tmax)

    def _occluded_rays(self, rays: Rays):
        tv = self.mesh.tri_vertices
        hit = np.zeros(len(rays), bool)
        for r, tri in self._pairs(len(rays)):
            t = intersect(rays, r, tri, tv)
            hit[r[np.isfinite(t)]] = True
        return hit
