"""Motion within a sensor sweep: where the sensor is at each firing, and how the sweep is cut.

A rotating LiDAR takes 1 / rotation_rate seconds to turn once; a scene and a sensor that
move during the turn give a *skewed* scan (the rolling-shutter effect every driving data
set shows).  A SWEEP scan (``operators/scan.py``) evaluates the scene at a few times of the
sweep, cuts the rays into *blocks* of consecutive firing times, and traces each block
against the scene at its own time:

- ``sweep_blocks(times, duration, count)``: which block each ray falls in, and each block's
  scene time (its middle), for ``count`` equal slices of ``[0, duration)``.
- ``blocks_for(displacement, tolerance, cap)``: how many blocks keep every scene point
  within ``tolerance`` of its path over one block, when the largest displacement of any
  point over the sweep is ``displacement`` (motion taken as uniform over the sweep: a point
  moves at most ``displacement / count`` within one block, so half that from the block's
  middle, and a skew measured across blocks is off by at most ``tolerance``; a motion that
  turns back within one sweep is underestimated).
- ``interpolate_poses(sample_times, poses, times)``: the sensor's pose at every ray's own
  firing time, from poses evaluated at a few times: translation linear, rotation by
  quaternion slerp (Shoemake 1985), so ego motion is exact up to the curvature of the
  path between samples, however coarse the blocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MOTIONS", "Sweep", "sweep_blocks", "blocks_for", "interpolate_poses", "matrix_to_quaternion", "quaternion_to_matrix"]


#: 'FRAME': every ray sees the scene and the sensor of the frame; 'SWEEP': each block of
#: firing times sees them at its own time
MOTIONS = ("FRAME", "SWEEP")


@dataclass
class Sweep:
    """How a scan treats time within one sensor sweep.

    motion: one of ``MOTIONS``; tolerance: metres, the largest distance a scene point may
    move within one block (sets the block count when ``blocks`` is 0); blocks: a fixed
    block count (0: from ``tolerance``); max_blocks: the most blocks an automatic count takes.
    """

    motion: str = "FRAME"
    tolerance: float = 0.01
    blocks: int = 0
    max_blocks: int = 256

    def __post_init__(self):
        if self.motion not in MOTIONS:
            raise ValueError(f"motion must be one of {', '.join(MOTIONS)}, got {self.motion!r}")
        if isinstance(self.tolerance, bool) or not isinstance(self.tolerance, (int, float, np.floating)) \
                or not math.isfinite(self.tolerance) or not self.tolerance > 0:
            raise ValueError(f"sweep tolerance must be a positive length in metres, got {self.tolerance!r}")
        for name in ("blocks", "max_blocks"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (0 if name == "blocks" else 1):
                raise ValueError(f"sweep {name} must be a whole number of at least "
                                 f"{0 if name == 'blocks' else 1}, got {v!r}")
        self.tolerance, self.blocks, self.max_blocks = float(self.tolerance), int(self.blocks), int(self.max_blocks)


def blocks_for(displacement: float, tolerance: float, cap: int) -> int:
    """Blocks so that no point moves more than ``tolerance`` within one block:
    ceil(displacement / tolerance), at least 1 and at most ``cap``."""
    if not tolerance > 0 or not math.isfinite(tolerance):
        raise ValueError(f"tolerance must be a positive length, got {tolerance!r}")
    cap = max(1, int(cap))
    if not math.isfinite(displacement):
        return cap
    return int(min(cap, max(1, math.ceil(displacement / tolerance - 1e-9))))


def sweep_blocks(times: np.ndarray, duration: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(block (M,) int64 in [0, count), middle (count,) float64 seconds) of rays fired at
    ``times`` (seconds from the start of the sweep, in ``[0, duration)``)."""
    times = np.asarray(times, dtype=np.float64)
    count = max(1, int(count))
    if duration <= 0 or count == 1:
        return np.zeros(len(times), np.int64), np.array([duration / 2.0 if duration > 0 else 0.0])
    block = np.clip(np.floor(times * (count / duration)).astype(np.int64), 0, count - 1)
    return block, (np.arange(count) + 0.5) * (duration / count)


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(K, 4) unit quaternions (w, x, y, z) of (K, 3, 3) rotation matrices (Shepperd's
    method: the largest of the four squared components is taken first, for stability)."""
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3, 3)
    tr = np.trace(r, axis1=1, axis2=2)
    diag = np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    which = np.argmax(diag, axis=1)
    q = np.empty((len(r), 4))
    for k in range(4):  # four cases, each whole-array
        m = which == k
        if not m.any():
            continue
        a = r[m]
        if k == 0:
            s = np.sqrt(1.0 + tr[m]) * 2.0
            q[m] = np.stack([0.25 * s, (a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s,
                             (a[:, 1, 0] - a[:, 0, 1]) / s], axis=1)
        else:
            i = k - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            s = np.sqrt(1.0 + a[:, i, i] - a[:, j, j] - a[:, l, l]) * 2.0
            out = np.empty((len(a), 4))
            out[:, 0] = (a[:, l, j] - a[:, j, l]) / s
            out[:, 1 + i] = 0.25 * s
            out[:, 1 + j] = (a[:, j, i] + a[:, i, j]) / s
            out[:, 1 + l] = (a[:, l, i] + a[:, i, l]) / s
            q[m] = out
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotation matrices of (K, 4) quaternions (w, x, y, z), normalised first."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)


def _slerp(q0: np.ndarray, q1: np.ndarray, f: np.ndarray) -> np.ndarray:
    dot = np.einsum("ij,ij->i", q0, q1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)  # the shorter arc
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-6
    s = np.sin(theta)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(small, 1.0 - f, np.sin((1.0 - f) * theta) / s)
        b = np.where(small, f, np.sin(f * theta) / s)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def interpolate_poses(sample_times, poses, times) -> np.ndarray:
    """(M, 4, 4) poses at ``times`` from (K, 4, 4) rigid ``poses`` (no scale) at increasing
    ``sample_times``: translation linear, rotation slerped, between the two samples around
    each time.  Outside [first, last] sample time the end pair extrapolates the translation
    linearly and the rotation stays at the end sample (callers sample the sweep's two ends)."""
    st = np.asarray(sample_times, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    t = np.asarray(times, dtype=np.float64)
    if len(st) != len(poses) or len(st) == 0:
        raise ValueError(f"interpolate_poses: {len(st)} sample times for {len(poses)} poses")
    if len(st) > 1 and not (np.diff(st) > 0).all():
        raise ValueError("interpolate_poses: sample times must increase")
    out = np.zeros((len(t), 4, 4))
    out[:, 3, 3] = 1.0
    if len(st) == 1:
        out[:] = poses[0]
        return out
    i = np.clip(np.searchsorted(st, t, side="right") - 1, 0, len(st) - 2)
    f = (t - st[i]) / (st[i + 1] - st[i])
    p0, p1 = poses[i, :3, 3], poses[i + 1, :3, 3]
    out[:, :3, 3] = p0 + f[:, None] * (p1 - p0)
    q = matrix_to_quaternion(poses[:, :3, :3])
    out[:, :3, :3] = quaternion_to_matrix(_slerp(q[i], q[i + 1], np.clip(f, 0.0, 1.0)))
    return out
