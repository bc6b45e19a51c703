"""LiDAR returns of beams with a footprint: divergence, multiple returns, weather, dropout.

A beam is a cone of full angle ``beam_divergence`` (milliradians), sampled by
``beam_samples`` sub-rays (``beam_offsets``, ``beam_directions``).  The caller casts the
sub-rays, follows glass and mirrors itself, and hands ``measure_returns`` one *echo* per
surface a sub-ray met.  Units: metres, radians (milliradians for the divergence setting),
intensities and powers in [0, 1] relative to a perpendicular white target at
``reference_range``.

The received power of an echo at range r (the lidar equation for a Lambertian target, as
``sensors.measure``, times the share of the beam and the two-way atmospheric loss):

    P = w * rho * |cos(incidence)| * min(1, (reference_range / r)^2) * f * exp(-2 alpha r)

with w the sub-ray's share of the footprint (``weights``), rho the material's
reflectivity, f the share of the sub-ray's power reaching the surface (1 for the first
surface, the transmitted share behind glass) and alpha = 3.912 / visibility the extinction
coefficient of Koschmieder's law (visibility is where the contrast of a black target falls
to 2 %, ln 50 = 3.912; Koschmieder 1924, "Theorie der horizontalen Sichtweite").

Per beam the echoes are sorted by range and single-linkage clustered: consecutive echoes
closer than ``range_resolution`` are one return (the receiver cannot separate the pulses).
A return's range is the power-weighted mean of its echoes, its intensity the sum of their
powers clipped to [0, 1], so a return from half the footprint has about half the intensity
of a full one.  ``mode`` picks which returns are reported (``sensors.RETURN_MODES``).

Weather and dropout, each from its own random stream keyed by (seed, frame) so a frame
repeats exactly: false returns (rain, fog backscatter near the sensor) with probability
``false_return_rate`` per beam, Gaussian range noise, and CARLA's dropout
(docs: "sensor.lidar.ray_cast"; ``ARayCastLidar::PostprocessDetection`` in CARLA's
RayCastLidar.cpp keeps a point of intensity I <= limit with probability
1 - zero_intensity * (1 - I / limit)), here applied per return together with the general
rate.  Echoes whose true range is outside [range_min, range_max] are not detected and
dropped (a blind-zone hit is a miss, not a see-through).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sensors import Returns, _count, _number

__all__ = ["Measured", "beam_offsets", "orthonormal_basis", "beam_directions", "measure_returns"]

#: the golden angle pi (3 - sqrt 5): successive Vogel spiral points turn by it
_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def beam_offsets(divergence_mrad, samples):
    """Angular offsets of a beam's sub-rays from its axis, and their shares of its power.

    Parameters
    ----------
    divergence_mrad : float >= 0
        Full cone angle in milliradians; the offsets lie in a disc of radius half of it.
    samples : int >= 1

    Returns
    -------
    offsets : (S, 2) float64
        Radians along the two basis vectors perpendicular to the beam (``orthonormal_basis``).
        A point-symmetric Vogel sunflower spiral (Vogel 1979, "A better way to construct the
        sunflower head"): for odd S a centre point standing for the central disc of area
        pi R^2 / S; the other points in pairs +-p_k, p_k at squared radius
        R^2 (c + (1 - c) (k + 0.5) / m) (m pairs, c the centre's share of the area), turned by
        k golden angles, so every point stands for an equal area of the disc.  The pairs make
        the mean offset zero (a flat target is seen centred on the axis) where a plain spiral
        of few points leans to one side; all lie strictly inside radius R.  S = 1 is the axis.
    weights : (S,) float64
        1 / S each (equal areas of a uniform footprint), summing to 1.
    """
    divergence_mrad = _number(divergence_mrad, "beam_divergence", low=0.0)
    samples = _count(samples, "beam_samples")
    m = samples // 2
    centre = samples % 2
    c = centre / samples
    k = np.arange(m, dtype=np.float64)
    radius = 0.5e-3 * divergence_mrad * np.sqrt(c + (1.0 - c) * (k + 0.5) / max(m, 1))
    phi = k * _GOLDEN_ANGLE
    pairs = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    offsets = np.zeros((samples, 2))
    offsets[centre::2] = pairs
    offsets[centre + 1::2] = -pairs
    return offsets, np.full(samples, 1.0 / samples)


def _unit_directions(directions):
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {d.shape}")
    norm = np.linalg.norm(d, axis=1)
    if not (np.isfinite(norm).all() and (norm > 0).all()):
        raise ValueError("directions must be finite and non-zero")
    return d / norm[:, None]


def orthonormal_basis(directions):
    """Two unit vectors perpendicular to each direction and to each other.

    Duff et al. 2017, "Building an orthonormal basis, revisited" (JCGT 6(1)): branch-free
    and accurate for every direction, +-Z included; copysign puts -0.0 with the negative
    branch, so (0, 0, -0.0) never divides by zero.

    Parameters
    ----------
    directions : (N, 3) array_like, finite and non-zero (normalised here)

    Returns
    -------
    b1, b2 : (N, 3) float64
        (b1, b2, d) is a right-handed orthonormal frame for each unit direction d.
    """
    d = _unit_directions(directions)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    sign = np.copysign(1.0, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    b1 = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    b2 = np.stack([b, sign + y * y * a, -y], axis=1)
    return b1, b2


def beam_directions(directions, divergence_mrad, samples):
    """The sub-rays of every beam.

    Parameters
    ----------
    directions : (N, 3) array_like
        Beam axes, finite and non-zero (need not be unit).
    divergence_mrad : float >= 0
        Full cone angle in milliradians.
    samples : int >= 1

    Returns
    -------
    sub : (N * S, 3) float64 unit vectors, beam-major
        Rows i*S .. i*S + S - 1 are beam i's sub-rays, in ``beam_offsets`` order: the axis d
        turned by the offset's angle r towards cos(phi) b1 + sin(phi) b2, i.e.
        d cos(r) + (cos(phi) b1 + sin(phi) b2) sin(r), exactly at angle r from d.
    weights : (S,) float64
        Each sub-ray's share of its beam's power (``beam_offsets``).
    """
    d = _unit_directions(directions)
    offsets, weights = beam_offsets(divergence_mrad, samples)
    b1, b2 = orthonormal_basis(d)
    r = np.hypot(offsets[:, 0], offsets[:, 1])
    # sin(r) / r times the offset gives (cos(phi), sin(phi)) sin(r), and is 1 on the axis
    scale = np.divide(np.sin(r), r, out=np.ones_like(r), where=r > 0)
    c1, c2 = offsets[:, 0] * scale, offsets[:, 1] * scale
    sub = (d[:, None, :] * np.cos(r)[None, :, None]
           + c1[None, :, None] * b1[:, None, :] + c2[None, :, None] * b2[:, None, :]).reshape(-1, 3)
    sub /= np.linalg.norm(sub, axis=1, keepdims=True)
    return sub, weights


@dataclass
class Measured:
    """The reported returns of one frame, R of them, sorted by beam then measured range.

    beam: (R,) int64 beam index; echo: (R,) int64 the representative echo (the most powerful
    of the return's echoes; ties: the lowest index) as an index into ``measure_returns``'s
    inputs, -1 for a false return; range: (R,) float64 measured range (with noise), metres;
    true_range: (R,) float64 the power-weighted mean of the echoes' true ranges; intensity:
    (R,) float32 in [0, 1]; return_index: (R,) uint8 1-based rank by range among the beam's
    reported returns; return_count: (R,) uint8 how many the beam reports; false: (R,) bool
    True for a rain / fog false return.
    """

    beam: np.ndarray
    echo: np.ndarray
    range: np.ndarray
    true_range: np.ndarray
    intensity: np.ndarray
    return_index: np.ndarray
    return_count: np.ndarray
    false: np.ndarray

    def __len__(self):
        return len(self.beam)


def _echo_array(value, name, e):
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (e,):
        raise ValueError(f"{name} must have shape ({e},) like ray, got {a.shape}")
    return a


def _fraction(a, name):
    if a.size and not ((a >= 0) & (a <= 1)).all():
        raise ValueError(f"{name} must lie in [0, 1]")


def _block_starts(keys):
    """Indices where a run of equal values begins in the sorted (R,) ``keys``."""
    new = np.ones(len(keys), bool)
    new[1:] = keys[1:] != keys[:-1]
    return np.flatnonzero(new)


def measure_returns(ray, range_, cos_incidence, reflectivity, factor, *, beams, samples, weights,
                    sensor, returns: Returns, frame: int = 0) -> Measured:
    """Returns of one frame from the echoes of its sub-rays (module doc for the physics).

    Parameters
    ----------
    ray : (E,) integer
        Index of the sub-ray of each echo, in ``beam_directions`` order (beam = ray // samples).
    range_ : (E,) float
        True range along the beam's unit direction, metres; for an echo seen through glass
        or in a mirror, the total path length.
    cos_incidence : (E,) float
        |cos| of the angle between sub-ray and surface normal.
    reflectivity : (E,) float in [0, 1]
        The material's (1 when none says otherwise).
    factor : (E,) float in [0, 1]
        Share of the sub-ray's power reaching the surface (1 for the first surface).
    beams, samples : int >= 1
        N beams of S sub-rays each.
    weights : (S,) float
        Each sub-ray's share of its beam's power (``beam_directions``).
    sensor : has ``range_min`` and ``range_max`` (metres)
    returns : sensors.Returns
    frame : int
        With ``returns.seed``, keys the random streams: noise (seed, frame), false returns
        (seed, frame, 1), dropout (seed, frame, 2), frame taken modulo 2**32.

    Returns
    -------
    Measured
        With one sub-ray per beam, no false returns, mode STRONGEST, reflectivity and factor
        1 and clear air, the kept beams, noisy ranges and intensities equal ``sensors.measure``'s
        for the same seed and frame: the first reported return of every beam takes the
        beam's entry of one normal draw per beam (all N, in beam order, as ``measure``), the
        other returns (DUAL) draws after those, in beam-then-range order.
    """
    if not isinstance(returns, Returns):
        raise TypeError(f"returns must be a sensors.Returns, got {type(returns).__name__}")
    beams, samples = _count(beams, "beams"), _count(samples, "samples")
    ray = np.asarray(ray)
    if ray.ndim != 1:
        raise ValueError(f"ray must have shape (E,), got {ray.shape}")
    if ray.size and not np.issubdtype(ray.dtype, np.integer):
        raise TypeError(f"ray must hold integer sub-ray indices, got dtype {ray.dtype}")
    ray = ray.astype(np.int64)
    e = len(ray)
    if e and (ray.min() < 0 or ray.max() >= beams * samples):
        raise ValueError(f"ray must lie in [0, beams * samples = {beams * samples}), "
                         f"got values in [{ray.min()}, {ray.max()}]")
    r = _echo_array(range_, "range_", e)
    cos = np.abs(_echo_array(cos_incidence, "cos_incidence", e))
    rho = _echo_array(reflectivity, "reflectivity", e)
    share = _echo_array(factor, "factor", e)
    _fraction(rho, "reflectivity")
    _fraction(share, "factor")
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (samples,) or not (np.isfinite(w).all() and (w >= 0).all()):
        raise ValueError(f"weights must be ({samples},) finite and non-negative, got shape {w.shape}")
    lo, hi = float(sensor.range_min), float(sensor.range_max)
    key = (returns.seed, int(frame) & 0xFFFFFFFF)

    # -- echo power; echoes outside the range window are not detected
    inside = (r >= lo) & (r <= hi)
    every = bool(inside.all())  # the common case: no copies of the echoes
    idx = np.arange(e) if every else np.flatnonzero(inside)
    sel = slice(None) if every else idx
    r = r[sel]
    alpha = 3.912 / returns.visibility  # Koschmieder; 0 for clear air (inf)
    with np.errstate(divide="ignore"):
        falloff = np.minimum(1.0, (returns.reference_range / r) ** 2)  # r = 0: 1
    power = (w[0] if samples == 1 else w[ray[sel] % samples]) * rho[sel] * cos[sel] * falloff * share[sel]
    if alpha > 0:  # clear air attenuates nothing: exp(0) = 1
        power = power * np.exp(-2.0 * alpha * r)
    beam = ray[sel] // samples
    echo = idx
    tie = idx  # representative ties go to the lowest echo index, false returns after all

    # -- false returns: at most one per beam, from their own stream
    if returns.false_return_rate > 0:
        top = min(hi, returns.false_return_range)
        if top < lo:
            raise ValueError(f"false_return_range ({returns.false_return_range:g}) must not be below the "
                             f"sensor's range_min ({lo:g})")
        rng = np.random.default_rng(key + (1,))
        fb = np.flatnonzero(rng.random(beams) < returns.false_return_rate)
        beam = np.concatenate([beam, fb])
        r = np.concatenate([r, rng.uniform(lo, top, len(fb))])
        power = np.concatenate([power, np.full(len(fb), returns.false_return_intensity)])
        echo = np.concatenate([echo, np.full(len(fb), -1, np.int64)])
        tie = np.concatenate([tie, e + fb])

    # -- cluster each beam's echoes along range
    if len(beam) and (np.diff(beam) > 0).all():
        # at most one echo a beam, in beam order (one sub-ray, nothing passed on, no false
        # return): every echo is its own return, whatever the mode
        s_beam, s_true, s_echo = beam, r, echo
        intensity = np.clip(power, 0.0, 1.0).astype(np.float32)
        return _report(s_beam, s_true, s_echo, intensity, beams, returns, key, ordered=True)
    order = np.lexsort((tie, r, beam))
    beam, r, power, echo, tie = beam[order], r[order], power[order], echo[order], tie[order]
    n = len(beam)
    start = np.ones(n, bool)
    start[1:] = (beam[1:] != beam[:-1]) | (np.diff(r) >= returns.range_resolution)
    cid = np.cumsum(start) - 1
    starts = np.flatnonzero(start)
    c = len(starts)
    psum = np.bincount(cid, power, c)
    # weighted mean as an offset from the cluster's first range: exact for one echo
    r0 = r[starts]
    dr = r - r0[cid]
    num = np.where(psum > 0, np.bincount(cid, power * dr, c), np.bincount(cid, dr, c))
    den = np.where(psum > 0, psum, np.diff(np.append(starts, n)))
    c_range = r0 + num / np.maximum(den, np.finfo(np.float64).tiny)
    # representative: the most powerful echo of each cluster (lexsort keeps clusters in blocks)
    rep = np.lexsort((tie, -power, cid))[starts]
    c_echo = echo[rep]
    c_beam = beam[starts]
    c_int = np.clip(psum, 0.0, 1.0)

    # -- the returns the mode reports (clusters are in beam-then-range order)
    first = _block_starts(c_beam)
    last = np.append(first[1:] - 1, c - 1) if c else first
    if returns.mode == "FIRST":
        sel = first
    elif returns.mode == "LAST":
        sel = last
    else:
        strongest = np.lexsort((np.arange(c), -c_int, c_beam))[first]  # ties: nearest
        sel = strongest if returns.mode == "STRONGEST" else np.union1d(strongest, last)
    sel = np.sort(sel)
    s_beam, s_true, s_int = c_beam[sel], c_range[sel], c_int[sel]
    s_echo = c_echo[sel]
    return _report(s_beam, s_true, s_echo, s_int.astype(np.float32), beams, returns, key)


def _report(s_beam, s_true, s_echo, intensity, beams, returns, key, ordered=False) -> Measured:
    """Noise, dropout and ranks of the selected returns (sorted by beam, then true range);
    ``ordered``: at most one a beam, so the order by measured range is the same."""
    sel = s_beam  # one row per selected return

    # -- range noise: one draw per beam in beam order (as sensors.measure), then the extras
    measured = s_true.copy()
    keep = np.ones(len(sel), bool)
    if returns.noise_sigma > 0:
        rng = np.random.default_rng(key)
        lead = np.zeros(len(sel), bool)
        lead[_block_starts(s_beam)] = True
        per_beam = rng.normal(0.0, returns.noise_sigma, beams)
        noise = np.empty(len(sel))
        noise[lead] = per_beam[s_beam[lead]]
        noise[~lead] = rng.normal(0.0, returns.noise_sigma, int((~lead).sum()))
        measured += noise
        keep &= measured > 0  # a noisy range cannot put the point behind the sensor

    # -- dropout (CARLA's three parameters), then the intensity floor
    g, limit, zero = returns.dropoff_general_rate, returns.dropoff_intensity_limit, returns.dropoff_zero_intensity
    if g > 0 or zero > 0:
        u = np.random.default_rng(key + (2,)).random((len(sel), 2))
        slope = (1.0 - intensity / limit) if limit > 0 else np.ones(len(sel))
        p_int = np.where(intensity > limit, 0.0, zero * slope)
        keep &= ~((u[:, 0] < g) | (u[:, 1] < p_int))
    if returns.drop_below > 0:
        keep &= intensity >= returns.drop_below

    # -- the reported returns, by beam then measured range, ranked within their beam
    k = np.flatnonzero(keep)
    if not ordered:
        k = k[np.lexsort((measured[k], s_beam[k]))]
    out_beam = s_beam[k]
    if ordered:
        rank = count = np.ones(len(k), np.uint8)
    else:
        heads = _block_starts(out_beam)
        counts = np.diff(np.append(heads, len(k)))
        block = np.repeat(np.arange(len(heads)), counts)
        rank = (np.arange(len(k)) - heads[block] + 1).astype(np.uint8)
        count = counts[block].astype(np.uint8)
    return Measured(
        beam=out_beam.astype(np.int64),
        echo=s_echo[k].astype(np.int64),
        range=measured[k],
        true_range=s_true[k],
        intensity=intensity[k],
        return_index=rank,
        return_count=count,
        false=s_echo[k] < 0,
    )
