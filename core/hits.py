"""Hits: the result of a trace, one entry per ray."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Hits:
    """Nearest hits of a ray batch.

    t: (M,) float32, +inf on a miss, in units of the given direction
    triangle: (M,) int32, -1 on a miss
    u, v: (M,) float32 barycentrics, p = (1-u-v) v0 + u v1 + v v2 (0 on a miss)
    """

    t: np.ndarray
    triangle: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def __len__(self):
        return len(self.t)

    @property
    def hit(self) -> np.ndarray:
        return self.triangle >= 0

    @classmethod
    def empty(cls, m: int) -> "Hits":
        return cls(
            t=np.full(m, np.inf, np.float32),
            triangle=np.full(m, -1, np.int32),
            u=np.zeros(m, np.float32),
            v=np.zeros(m, np.float32),
        )

    def points(self, origins, directions) -> np.ndarray:
        """(M, 3) float64 world hit points (NaN on a miss)."""
        t = np.where(self.hit, self.t, np.nan).astype(np.float64)
        return np.asarray(origins, np.float64) + t[:, None] * np.asarray(directions, np.float64)
