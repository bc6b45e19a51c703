"""Ray batches for tests, benchmarks and the cost model.

Every generator returns ``(origins, directions)`` as (M, 3) float32 arrays, takes its
randomness from an explicit ``seed`` (an int or a ``numpy.random.Generator``) and
touches no global state.
"""

from __future__ import annotations

import numpy as np

from .mesh import TriangleMesh

F32 = np.float32


def _rng(seed) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def unit_sphere(m: int, rng: np.random.Generator) -> np.ndarray:
    """(m, 3) float64 directions uniform on the unit sphere (normalised Gaussians)."""
    d = rng.standard_normal((m, 3))
    n = np.linalg.norm(d, axis=1)
    bad = n < 1e-12  # probability ~0, but a zero direction would be rejected later
    while bad.any():
        d[bad] = rng.standard_normal((int(bad.sum()), 3))
        n = np.linalg.norm(d, axis=1)
        bad = n < 1e-12
    return d / n[:, None]


def padded_bounds(mesh_or_bounds, pad: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) float64 of a mesh or a (lo, hi) pair, widened by ``pad`` times the
    diagonal on every side (so a flat scene still gets a box with volume)."""
    if isinstance(mesh_or_bounds, TriangleMesh):
        lo, hi = mesh_or_bounds.bounds()
    else:
        lo, hi = mesh_or_bounds
    lo = np.asarray(lo, np.float64).reshape(3)
    hi = np.asarray(hi, np.float64).reshape(3)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (lo > hi).any():
        raise ValueError(f"bounds must be finite with lo <= hi, got lo={lo}, hi={hi}")
    diag = float(np.linalg.norm(hi - lo))
    scale = max(np.abs(lo).max(), np.abs(hi).max())
    # a point (or empty) scene: pad by something relative to where it is, or 1
    margin = pad * diag if diag > 0 else pad * (scale if scale > 0 else 1.0)
    return lo - margin, hi + margin


def uniform_rays(mesh_or_bounds, m: int, seed=0, pad: float = 0.01):
    """The paper's distribution: origins uniform in the (padded) scene box, directions
    uniform on the sphere (Hapala et al. 2011, section 4).

    mesh_or_bounds: a TriangleMesh or a (lo, hi) pair of 3-vectors.
    """
    rng = _rng(seed)
    lo, hi = padded_bounds(mesh_or_bounds, pad)
    m = int(m)
    o = lo + rng.random((m, 3)) * (hi - lo)
    d = unit_sphere(m, rng)
    return o.astype(F32), d.astype(F32)


#: the Halton bases of a quasi-random ray's five coordinates: the origin's x, y and z, then
#: the direction's cosine of the polar angle and its azimuth (``quasi_uniform_rays``)
HALTON_BASES = (2, 3, 5, 7, 11)


def _digit_by_digit(i: np.ndarray, base: int) -> np.ndarray:
    """``radical_inverse`` one digit at a time (its tables)."""
    out = np.zeros(i.shape)
    scale = 1.0
    while i.any():
        scale /= base
        i, digit = np.divmod(i, base)
        out += scale * digit
    return out


#: {base: (base ** j, the radical inverses of 0 .. base ** j - 1)}, j digits at a time
_DIGIT_TABLES: dict[int, tuple[int, np.ndarray]] = {}


def radical_inverse(i, base: int) -> np.ndarray:
    """The van der Corput sequence: the base-``base`` digits of the non-negative integers
    ``i`` mirrored about the radix point, as float64 in [0, 1) (3 in base 2 is 0.11 = 0.75).

    Mirrors j digits at a time from a table of the first ``base ** j`` <= 4,096 values, far
    fewer numpy calls than one digit at a time (which made ``quasi_uniform_rays`` cost
    several times ``uniform_rays``)."""
    i = np.array(i, np.int64)
    if (i < 0).any():
        raise ValueError("radical_inverse takes non-negative integers")
    if base not in _DIGIT_TABLES:
        size = base
        while size * base <= 4096:
            size *= base
        _DIGIT_TABLES[base] = (size, _digit_by_digit(np.arange(size), base))
    size, table = _DIGIT_TABLES[base]
    out = np.zeros(i.shape)
    scale = 1.0
    while i.any():
        i, low = np.divmod(i, size)
        out += scale * table[low]
        scale /= size
    return out


def quasi_uniform_rays(mesh_or_bounds, m: int, seed=0, pad: float = 0.01):
    """The paper's distribution (``uniform_rays``) from a randomized Halton sequence.

    The five coordinates of ray i (origin in the padded box; direction by the cosine of
    its polar angle and its azimuth, which are uniform on the sphere) are point
    ``start + i`` of the Halton sequence in ``HALTON_BASES``, shifted modulo 1 by one
    random vector (Cranley and Patterson 1976), with ``start`` random too.  Every ray is
    uniform, so a mean over the rays estimates the paper's mean without bias; the rays
    cover the box and the sphere more evenly than independent ones, so the mean of K of
    them moves less between seeds.  A plan's sample rays (``core.plan``), whose counts'
    spread is the break-even's: on real meshes the break-even moves less between seeds
    than on independent uniform rays (BENCHMARKS.md, "Calibration and plan repeatability").
    """
    rng = _rng(seed)
    lo, hi = padded_bounds(mesh_or_bounds, pad)
    m = int(m)
    start = int(rng.integers(0, 1 << 30))
    index = np.arange(start, start + m, dtype=np.int64)
    u = np.stack([radical_inverse(index, b) for b in HALTON_BASES], axis=1)
    u = (u + rng.random(len(HALTON_BASES))) % 1.0
    o = lo + u[:, :3] * (hi - lo)
    z = 1.0 - 2.0 * u[:, 3]
    phi = 2.0 * np.pi * u[:, 4]
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return o.astype(F32), d.astype(F32)


def camera_rays(origin, look_at, up, fov_deg: float, width: int, height: int):
    """Primary rays of a pinhole camera through pixel centres, row-major from the top row.

    ``fov_deg`` spans the larger image dimension (Blender's sensor fit 'AUTO').
    Directions are unit length; every origin is ``origin``.
    """
    eye = np.asarray(origin, np.float64).reshape(3)
    fwd = np.asarray(look_at, np.float64).reshape(3) - eye
    up = np.asarray(up, np.float64).reshape(3)
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise ValueError(f"image size must be at least 1x1, got {width}x{height}")
    if not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
    if np.linalg.norm(fwd) == 0:
        raise ValueError("look_at equals the camera origin")
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-12 * max(1.0, np.linalg.norm(up)):
        raise ValueError("up is parallel to the viewing direction")
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    half = np.tan(np.radians(fov_deg) / 2)
    aspect = width / height
    sx, sy = (half, half / aspect) if width >= height else (half * aspect, half)
    x = ((np.arange(width) + 0.5) / width * 2 - 1) * sx
    y = (1 - (np.arange(height) + 0.5) / height * 2) * sy
    X, Y = np.meshgrid(x, y)  # (height, width): row-major, top row first
    d = fwd + X.reshape(-1, 1) * right + Y.reshape(-1, 1) * true_up
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape)
    return np.ascontiguousarray(o, dtype=F32), d.astype(F32)


def hemisphere_rays(points, normals, m_per_point: int, seed=0, cosine: bool = True):
    """Rays leaving each point into the hemisphere around its normal (for ambient occlusion).

    Point i owns rays ``i*m_per_point`` to ``(i+1)*m_per_point - 1``.  With ``cosine``
    the directions are cosine-weighted (Malley's method), else uniform over the
    hemisphere.  Origins are the points themselves: pass ``tmin`` > 0 to the trace
    to step off the surface.  Normals need not be unit length but must not be zero.
    """
    rng = _rng(seed)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    if p.shape != n.shape:
        raise ValueError(f"points {p.shape} and normals {n.shape} differ in shape")
    ln = np.linalg.norm(n, axis=1)
    if (ln == 0).any() or not np.isfinite(ln).all():
        bad = np.flatnonzero((ln == 0) | ~np.isfinite(ln))
        raise ValueError(f"{bad.size} normals are zero or not finite, first at point {bad[:5].tolist()}")
    n = n / ln[:, None]
    k = int(m_per_point)
    total = len(p) * k
    # an orthonormal frame per point (Duff et al., JCGT 2017, "Building an orthonormal basis, revisited")
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t2 = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    u1 = rng.random(total)
    u2 = rng.random(total)
    phi = 2 * np.pi * u2
    if cosine:
        r = np.sqrt(u1)
        z = np.sqrt(np.maximum(0.0, 1 - u1))
    else:
        z = u1
        r = np.sqrt(np.maximum(0.0, 1 - z * z))
    idx = np.repeat(np.arange(len(p)), k)
    d = (r * np.cos(phi))[:, None] * t1[idx] + (r * np.sin(phi))[:, None] * t2[idx] + z[:, None] * n[idx]
    return p[idx].astype(F32), d.astype(F32)
