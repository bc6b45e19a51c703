"""core.returns: beam footprints, multiple returns, weather and dropout.  No Blender needed.

Expected values are worked out by hand from the lidar equation in the module doc:
P = w * rho * cos * min(1, (reference / r)^2) * factor * exp(-2 * 3.912 / visibility * r).
"""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_raycast.core import returns as rt
from hybrid_raycast.core import sensors

LIDAR = sensors.RotatingLidar(range_min=0.5, range_max=100.0)


def _measure(ray, r, *, beams, samples, returns, cos=None, rho=None, factor=None, sensor=LIDAR, frame=0):
    e = len(r)
    _, weights = rt.beam_offsets(returns.beam_divergence, samples)
    ones = np.ones(e)
    return rt.measure_returns(np.asarray(ray, np.int64), np.asarray(r, float),
                              ones if cos is None else cos, ones if rho is None else rho,
                              ones if factor is None else factor, beams=beams, samples=samples,
                              weights=weights, sensor=sensor, returns=returns, frame=frame)


# -- footprint -------------------------------------------------------------------------------------

AWKWARD = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-0.0, -0.0, 1.0], [-0.0, 0.0, -1.0],
                    [1e-300, -0.0, -1.0], [1.0, -0.0, 0.0], [-0.0, -1.0, 0.0], [3.0, -4.0, 12.0]])


def _directions():
    rng = np.random.default_rng(5)
    return np.vstack([AWKWARD, rng.normal(size=(200, 3))])


def test_basis_is_right_handed_orthonormal_for_any_direction_including_poles_and_negative_zero():
    d = _directions()
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    b1, b2 = rt.orthonormal_basis(d)
    for name, x, y, want in [("b1.b1", b1, b1, 1), ("b2.b2", b2, b2, 1), ("b1.b2", b1, b2, 0),
                             ("b1.d", b1, u, 0), ("b2.d", b2, u, 0)]:
        err = np.abs(np.einsum("ij,ij->i", x, y) - want)
        assert err.max() < 1e-12, f"{name} off by {err.max():.1e} for direction {d[err.argmax()]}"
    assert np.allclose(np.cross(b1, b2), u, atol=1e-12), "b1 x b2 must be the direction"


@pytest.mark.parametrize("samples", [1, 2, 3, 7, 16])
def test_sub_rays_lie_within_half_the_divergence_and_average_to_the_beam(samples):
    d = _directions()
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    divergence = 3.0  # mrad full angle
    sub, weights = rt.beam_directions(d, divergence, samples)
    assert sub.shape == (len(d) * samples, 3) and sub.dtype == np.float64
    assert np.allclose(np.linalg.norm(sub, axis=1), 1.0, atol=1e-14)
    beam = np.repeat(u, samples, axis=0)  # beam-major: rows i*S .. i*S+S-1 belong to beam i
    angle = np.arctan2(np.linalg.norm(np.cross(beam, sub), axis=1), np.einsum("ij,ij->i", beam, sub))
    assert angle.max() <= 0.5e-3 * divergence * (1 + 1e-9), f"sub-ray {angle.argmax()} at {angle.max():.3e} rad"
    mean = sub.reshape(len(d), samples, 3).mean(axis=1)
    off = np.arctan2(np.linalg.norm(np.cross(u, mean), axis=1), np.einsum("ij,ij->i", u, mean))
    assert off.max() < 1e-9, f"mean sub-ray of beam {off.argmax()} is {off.max():.2e} rad off its axis"
    assert weights.shape == (samples,) and abs(weights.sum() - 1.0) < 1e-15


def test_one_sample_or_zero_divergence_gives_the_beam_itself():
    d = _directions()
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    sub, w = rt.beam_directions(d, 2.0, 1)
    assert np.allclose(sub, u, atol=1e-15) and w.tolist() == [1.0]
    sub, w = rt.beam_directions(d, 0.0, 4)
    assert np.allclose(sub, np.repeat(u, 4, axis=0), atol=1e-15) and np.allclose(w, 0.25)


def test_offsets_spread_over_the_disc_with_equal_weights():
    offsets, weights = rt.beam_offsets(2.0, 64)
    radius = np.hypot(offsets[:, 0], offsets[:, 1])
    assert radius.max() < 1e-3 and np.allclose(weights, 1 / 64)
    # equal areas: a quarter of the points within half the radius (a quarter of the area)
    assert abs((radius < 0.5e-3).mean() - 0.25) <= 1 / 64


# -- multiple returns ------------------------------------------------------------------------------

def _edge(mode, near_rho=1.0):
    """One beam of 8 sub-rays: 4 hit a wall at 10 m, 4 a wall at 20 m (cos 1, reference 10 m).
    Near: 4 * 1/8 * near_rho * 1 = 0.5 near_rho; far: 4 * 1/8 * (10/20)^2 = 0.125."""
    ray = np.arange(8)
    r = np.where(ray < 4, 10.0, 20.0)
    rho = np.where(ray < 4, near_rho, 1.0)
    return _measure(ray, r, beams=1, samples=8, rho=rho,
                    returns=sensors.Returns(mode=mode, beam_divergence=2.0, beam_samples=8))


def test_dual_return_on_an_edge_reports_both_walls_each_with_half_the_intensity():
    m = _edge("DUAL")
    assert len(m) == 2
    assert m.true_range.tolist() == [10.0, 20.0] and m.range.tolist() == [10.0, 20.0]
    assert m.return_index.tolist() == [1, 2] and m.return_count.tolist() == [2, 2]
    assert m.return_index.dtype == np.uint8 and m.return_count.dtype == np.uint8
    # a full return is 1.0 at 10 m and 0.25 at 20 m; each wall fills half the footprint
    assert np.allclose(m.intensity, [0.5, 0.125]) and m.intensity.dtype == np.float32
    assert m.echo.tolist() == [0, 4], "representative: the lowest echo index among equal powers"
    assert m.beam.tolist() == [0, 0] and not m.false.any()


@pytest.mark.parametrize("mode, want", [("FIRST", 10.0), ("LAST", 20.0), ("STRONGEST", 10.0)])
def test_first_last_and_strongest_pick_their_wall(mode, want):
    m = _edge(mode)
    assert m.true_range.tolist() == [want] and m.return_index.tolist() == [1] and m.return_count.tolist() == [1]


def test_dual_reports_one_return_when_the_strongest_is_the_last():
    m = _edge("DUAL", near_rho=0.1)  # near 0.05 < far 0.125
    assert m.true_range.tolist() == [20.0] and m.return_count.tolist() == [1]
    assert _edge("STRONGEST", near_rho=0.1).true_range.tolist() == [20.0]


def test_echoes_closer_than_the_range_resolution_merge_into_a_power_weighted_return():
    ret = sensors.Returns(reference_range=100.0, beam_samples=2, range_resolution=0.1)
    # powers 0.5 * 1 = 0.5 at 10.00 m and 0.5 * 0.5 = 0.25 at 10.05 m (falloff 1 within 100 m)
    m = _measure([1, 0], [10.05, 10.0], beams=1, samples=2, cos=np.array([0.5, 1.0]), returns=ret)
    assert len(m) == 1 and m.return_count.tolist() == [1]
    assert m.true_range[0] == pytest.approx((0.5 * 10.0 + 0.25 * 10.05) / 0.75, abs=1e-12)
    assert m.intensity[0] == pytest.approx(0.75, abs=1e-7)
    assert m.echo.tolist() == [1], "the representative is the more powerful echo (input index 1)"
    apart = _measure([1, 0], [10.05, 10.0], beams=1, samples=2, cos=np.array([0.5, 1.0]),
                     returns=sensors.Returns(reference_range=100.0, range_resolution=0.04, mode="DUAL"))
    assert apart.true_range.tolist() == [10.0, 10.05], "0.05 m apart with a 0.04 m resolution: two returns"


def test_echoes_outside_the_range_window_are_not_detected():
    ret = sensors.Returns(mode="DUAL", beam_samples=2, reference_range=100.0)
    m = _measure([0, 1, 2, 3], [0.3, 30.0, 101.0, 40.0], beams=2, samples=2, returns=ret)
    assert m.beam.tolist() == [0, 1] and m.true_range.tolist() == [30.0, 40.0]


def test_reflectivity_and_transmitted_factor_scale_the_intensity():
    m = _measure([0, 1], [5.0, 8.0], beams=2, samples=1, rho=np.array([0.4, 1.0]),
                 factor=np.array([1.0, 0.3]), returns=sensors.Returns())
    assert np.allclose(m.intensity, [0.4, 0.3])


def test_fog_attenuates_intensity_by_the_two_way_koschmieder_extinction():
    ret = sensors.Returns(visibility=1000.0, reference_range=10.0)
    m = _measure([0], [50.0], beams=1, samples=1, returns=ret)
    # (10 / 50)^2 * exp(-2 * 3.912 / 1000 * 50) = 0.04 * exp(-0.3912) = 0.04 * 0.6762449
    assert m.intensity[0] == pytest.approx(0.04 * 0.6762449, rel=1e-6)
    clear = _measure([0], [50.0], beams=1, samples=1, returns=sensors.Returns())
    assert clear.intensity[0] == pytest.approx(0.04, rel=1e-6), "clear air: no extinction"


# -- weather, noise and dropout --------------------------------------------------------------------

def test_false_returns_hit_the_requested_share_of_beams_near_the_sensor():
    n = 100_000
    ret = sensors.Returns(false_return_rate=0.3, false_return_range=5.0, false_return_intensity=0.05, seed=11)
    m = _measure([], [], beams=n, samples=1, returns=ret)
    share = len(np.unique(m.beam)) / n
    assert abs(share - 0.3) < 0.01, f"{share:.4f} of beams have a false return"
    assert len(m) == len(np.unique(m.beam)), "at most one false return per beam"
    assert m.false.all() and (m.echo == -1).all() and np.all(m.intensity == np.float32(0.05))
    assert m.true_range.min() >= LIDAR.range_min and m.true_range.max() <= 5.0


def test_a_false_return_competes_with_the_real_echo():
    n = 2000
    ret = sensors.Returns(false_return_rate=0.5, mode="FIRST", seed=2)
    ray = np.arange(n)
    first = _measure(ray, np.full(n, 50.0), beams=n, samples=1, returns=ret)
    assert first.false.any() and len(first) == n, "FIRST: the near false return replaces the wall"
    assert np.all(first.true_range[first.false] <= 5.0) and np.all(first.true_range[~first.false] == 50.0)
    last = _measure(ray, np.full(n, 50.0), beams=n, samples=1, returns=sensors.Returns(
        false_return_rate=0.5, mode="LAST", seed=2))
    assert not last.false.any() and len(last) == n


def _noisy(frame):
    ret = sensors.Returns(noise_sigma=0.05, seed=4, mode="DUAL", false_return_rate=0.2,
                          dropoff_general_rate=0.1, dropoff_zero_intensity=0.5, beam_samples=2)
    ray = np.arange(2000)
    r = np.where(ray % 2 == 0, 10.0, 30.0)
    return _measure(ray, r, beams=1000, samples=2, returns=ret, frame=frame)


def test_same_seed_and_frame_repeat_exactly_and_another_frame_differs():
    a, b, c = _noisy(3), _noisy(3), _noisy(4)
    for f in ("beam", "echo", "range", "true_range", "intensity", "return_index", "return_count", "false"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f"{f} differs between two runs of frame 3"
    assert len(a) != len(c) or not np.array_equal(a.range, c.range), "frames 3 and 4 gave the same returns"


def test_general_dropout_drops_about_half_at_rate_one_half():
    n = 100_000
    m = _measure(np.arange(n), np.full(n, 5.0), beams=n, samples=1,
                 returns=sensors.Returns(dropoff_general_rate=0.5, seed=1))
    assert abs(len(m) / n - 0.5) < 0.01, f"kept {len(m) / n:.4f}"


def test_intensity_dropout_is_linear_below_the_limit_and_off_above_it():
    n = 100_000
    ret = sensors.Returns(dropoff_intensity_limit=0.5, dropoff_zero_intensity=1.0, seed=1, reference_range=10.0)
    # cos 0.25 -> intensity 0.25, dropped with 1 * (1 - 0.25 / 0.5) = 0.5; cos 0.8 -> never dropped
    cos = np.where(np.arange(n) % 2 == 0, 0.25, 0.8)
    m = _measure(np.arange(n), np.full(n, 5.0), beams=n, samples=1, cos=cos, returns=ret)
    weak = (m.beam % 2 == 0).sum() / (n / 2)
    assert abs(weak - 0.5) < 0.015, f"kept {weak:.4f} of the 0.25-intensity returns"
    assert (m.beam % 2 == 1).sum() == n // 2, "returns above the intensity limit are never dropped"


def test_one_thin_ray_strongest_mode_equals_sensors_measure_with_noise():
    sensor = sensors.RotatingLidar(range_min=0.0, range_max=100.0)
    rng = np.random.default_rng(9)
    n = 50_000
    t = rng.uniform(0.0, 120.0, n)
    t[:50] = rng.uniform(0.0, 0.05, 50)          # noise may put these behind the sensor
    t[rng.random(n) < 0.2] = np.inf              # misses
    hit = np.isfinite(t)
    cos = rng.random(n)
    ret = sensors.Returns(noise_sigma=0.05, seed=3, drop_below=0.01)
    keep, r, inten = sensors.measure(t, hit, cos, sensor, ret, frame=7)
    ray = np.flatnonzero(hit)
    m = rt.measure_returns(ray, t[ray], cos[ray], np.ones(len(ray)), np.ones(len(ray)), beams=n, samples=1,
                           weights=np.ones(1), sensor=sensor, returns=ret, frame=7)
    assert 0 < keep[:50].sum() < 50, "the test must exercise ranges made negative by noise"
    assert np.array_equal(m.beam, np.flatnonzero(keep)), "different beams kept"
    assert np.array_equal(m.range, r[keep]), "noisy ranges differ"
    assert np.array_equal(m.intensity, inten[keep]), "intensities differ"
    assert np.array_equal(m.true_range, t[keep]) and np.array_equal(m.echo, np.searchsorted(ray, m.beam))
    assert (m.return_index == 1).all() and (m.return_count == 1).all()


def test_empty_echoes_give_no_returns():
    m = _measure([], [], beams=4, samples=2, returns=sensors.Returns(noise_sigma=0.1, mode="DUAL"))
    assert len(m) == 0 and m.beam.dtype == np.int64 and m.intensity.dtype == np.float32


# -- settings and inputs ---------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, name", [
    ({"beam_divergence": -1.0}, "beam_divergence"),
    ({"beam_samples": 0}, "beam_samples"),
    ({"beam_samples": 0.5}, "beam_samples"),
    ({"visibility": 0.0}, "visibility"),
    ({"visibility": -10.0}, "visibility"),
    ({"range_resolution": 0.0}, "range_resolution"),
    ({"false_return_rate": 1.5}, "false_return_rate"),
    ({"dropoff_general_rate": -0.1}, "dropoff_general_rate"),
    ({"max_bounces": -1}, "max_bounces"),
    ({"mode": "TRIPLE"}, "mode"),
])
def test_bad_returns_settings_raise_errors_naming_the_setting(kwargs, name):
    with pytest.raises(ValueError, match=name):
        sensors.Returns(**kwargs)


def test_unknown_mode_lists_the_valid_modes():
    with pytest.raises(ValueError, match="STRONGEST, FIRST, LAST, DUAL"):
        sensors.Returns(mode="strongest")
    assert sensors.RETURN_MODES == ("STRONGEST", "FIRST", "LAST", "DUAL")
    assert sensors.Returns(visibility=float("inf")).visibility == float("inf")


def test_bad_echo_inputs_raise_clear_errors():
    ret = sensors.Returns()
    with pytest.raises(ValueError, match="ray must lie in"):
        _measure([0, 4], [1.0, 2.0], beams=2, samples=2, returns=ret)
    with pytest.raises(ValueError, match="range_ must have shape"):
        rt.measure_returns([0], [1.0, 2.0], [1.0], [1.0], [1.0], beams=1, samples=1, weights=[1.0],
                           sensor=LIDAR, returns=ret)
    with pytest.raises(ValueError, match="weights"):
        rt.measure_returns([0], [1.0], [1.0], [1.0], [1.0], beams=1, samples=2, weights=[1.0],
                           sensor=LIDAR, returns=ret)
    with pytest.raises(ValueError, match="reflectivity"):
        rt.measure_returns([0], [1.0], [1.0], [1.5], [1.0], beams=1, samples=1, weights=[1.0],
                           sensor=LIDAR, returns=ret)
    with pytest.raises(ValueError, match="beams"):
        rt.measure_returns([], [], [], [], [], beams=0, samples=1, weights=[1.0], sensor=LIDAR, returns=ret)
    with pytest.raises(ValueError, match="directions"):
        rt.beam_directions([[0.0, 0.0, 0.0]], 1.0, 4)
