"""core.motion: sweep blocks, block counts from a skew tolerance, and pose interpolation."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_raycast.core import motion


def _rz(angle, t=(0.0, 0.0, 0.0)):
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = t
    return m


def _random_rotations(n, seed=0):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(n, 3, 3)))
    return q * np.sign(np.linalg.det(q))[:, None, None]


def test_quaternions_round_trip_every_rotation_including_half_turns():
    r = np.concatenate([_random_rotations(200), np.stack([_rz(np.pi)[:3, :3], np.diag([1.0, -1.0, -1.0]),
                                                          np.diag([-1.0, 1.0, -1.0]), np.eye(3)])])
    back = motion.quaternion_to_matrix(motion.matrix_to_quaternion(r))
    assert np.abs(back - r).max() < 1e-12, "a rotation changed through its quaternion"


def test_interpolated_poses_follow_a_constant_turn_and_a_straight_path_exactly():
    """A sensor turning at a constant rate while moving in a straight line: slerp and a linear
    translation between two samples give the pose at any time between them."""
    a, b = _rz(0.0, (0.0, 0.0, 1.0)), _rz(1.2, (3.0, -1.0, 1.0))
    t = np.linspace(0.0, 1.0, 11)
    out = motion.interpolate_poses([0.0, 1.0], np.stack([a, b]), t)
    for ti, p in zip(t, out):
        want = _rz(1.2 * ti, (3.0 * ti, -ti, 1.0))
        assert np.abs(p - want).max() < 1e-12, f"pose at t={ti} off by {np.abs(p - want).max():.2e}"


def test_interpolation_picks_the_samples_around_each_time():
    times = [0.0, 0.5, 1.0]
    poses = np.stack([_rz(0.0), _rz(0.1, (1.0, 0.0, 0.0)), _rz(1.0, (1.0, 4.0, 0.0))])
    out = motion.interpolate_poses(times, poses, [0.25, 0.75, 0.5])
    assert np.allclose(out[0], _rz(0.05, (0.5, 0.0, 0.0)))
    assert np.allclose(out[1], _rz(0.55, (1.0, 2.0, 0.0)))
    assert np.allclose(out[2], poses[1])
    with pytest.raises(ValueError, match="increase"):
        motion.interpolate_poses([0.0, 0.0], poses[:2], [0.0])


def test_block_count_holds_every_point_within_the_tolerance():
    assert motion.blocks_for(1.0, 0.01, 1800) == 100  # 1 m over the sweep, 1 cm a block
    assert motion.blocks_for(0.0, 0.01, 1800) == 1
    assert motion.blocks_for(1.0, 0.01, 64) == 64  # capped
    assert motion.blocks_for(np.inf, 0.01, 64) == 64  # unknown motion (the topology changed)
    with pytest.raises(ValueError, match="tolerance"):
        motion.blocks_for(1.0, 0.0, 10)


def test_sweep_blocks_cut_the_firing_times_into_equal_slices():
    t = np.arange(1800) / 18000.0  # a 10 Hz turn in 1,800 steps
    block, mids = motion.sweep_blocks(t, 0.1, 4)
    assert np.bincount(block).tolist() == [450] * 4
    assert np.allclose(mids, [0.0125, 0.0375, 0.0625, 0.0875])
    assert (np.abs(t - mids[block]) <= 0.0125 + 1e-12).all()
    one, mid = motion.sweep_blocks(t, 0.1, 1)
    assert (one == 0).all() and mid.tolist() == [0.05]


@pytest.mark.parametrize("kwargs,word", [({"motion": "ROLLING"}, "motion"), ({"tolerance": 0.0}, "tolerance"),
                                         ({"tolerance": float("nan")}, "tolerance"), ({"blocks": -1}, "blocks"),
                                         ({"max_blocks": 0}, "max_blocks")])
def test_bad_sweep_settings_raise_errors_naming_the_setting(kwargs, word):
    with pytest.raises(ValueError, match=word):
        motion.Sweep(**kwargs)
