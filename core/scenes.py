"""Procedural scenes the package generates itself, for calibration and tests.

The paper calibrates its two constants on a set of representative scenes (Hapala et
al. 2011, section 3); these generators stand in for that set without any files.  Each
one takes a target triangle count ``n`` and a ``seed`` and returns a TriangleMesh with
roughly ``n`` triangles (exactly where the construction allows), the same mesh for the
same arguments.  They span what changes a structure's constants: closed smooth
surfaces (sphere, torus), no coherence at all (triangle soup), a flat 2.5D scene
(terrain), an axis-aligned architectural scene (city), many small objects in empty
space (scatter), a small dense object in a huge sparse scene (teapot in a stadium) and
long thin triangles spanning the scene (slivers, the grid's worst case).

Everything is whole-array numpy; a million triangles take well under a second or two.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from .mesh import TriangleMesh

F64 = np.float64


def _rng(seed) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def _mesh(vertices, triangles) -> TriangleMesh:
    return TriangleMesh(np.asarray(vertices, F64).astype(np.float32), np.asarray(triangles, np.int64))


def _concat(parts) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate (vertices, triangles) pairs, offsetting the indices."""
    vs, fs, off = [], [], 0
    for v, f in parts:
        vs.append(np.asarray(v, F64))
        fs.append(np.asarray(f, np.int64) + off)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# -- building blocks -------------------------------------------------------------------

_PHI = (1 + 5 ** 0.5) / 2
_ICO_V = np.array(
    [[-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0],
     [0, -1, _PHI], [0, 1, _PHI], [0, -1, -_PHI], [0, 1, -_PHI],
     [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1]], F64)
_ICO_F = np.array(
    [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
     [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
     [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
     [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], np.int64)


def geodesic_sphere_arrays(frequency: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit geodesic sphere: each icosahedron face split into frequency**2 triangles.

    Shared vertices are merged exactly: a lattice point is identified by its integer
    weights over the 12 icosahedron corners, so the mesh is closed (watertight) and
    outward-facing.  20 * frequency**2 triangles.
    """
    f = max(1, int(frequency))
    # lattice of one face: weights (f-i-j, i, j) on corners (c0, c1, c2)
    i, j = np.meshgrid(np.arange(f + 1), np.arange(f + 1), indexing="ij")
    keep = (i + j) <= f
    i, j = i[keep], j[keep]
    local = -np.ones((f + 1, f + 1), np.int64)
    local[i, j] = np.arange(i.size)
    ui, uj = np.nonzero(np.add.outer(np.arange(f + 1), np.arange(f + 1)) <= f - 1)
    up = np.stack([local[ui, uj], local[ui + 1, uj], local[ui, uj + 1]], axis=1)
    di, dj = np.nonzero(np.add.outer(np.arange(f + 1), np.arange(f + 1)) <= f - 2)
    down = np.stack([local[di + 1, dj], local[di + 1, dj + 1], local[di, dj + 1]], axis=1)
    tri_local = np.concatenate([up, down])
    p = i.size
    w = np.zeros((20, p, 12), np.int32)
    faces = np.arange(20)[:, None]
    w[faces, np.arange(p)[None, :], _ICO_F[:, 0:1]] += (f - i - j)[None, :]
    w[faces, np.arange(p)[None, :], _ICO_F[:, 1:2]] += i[None, :]
    w[faces, np.arange(p)[None, :], _ICO_F[:, 2:3]] += j[None, :]
    w = w.reshape(20 * p, 12)
    keys = np.ascontiguousarray(w).view(np.dtype((np.void, w.dtype.itemsize * 12))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    pts = w[first].astype(F64) @ _ICO_V
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    tris = (tri_local[None, :, :] + (np.arange(20) * p)[:, None, None]).reshape(-1, 3)
    return pts, inverse.reshape(-1)[tris]


def torus_arrays(major: int, minor: int, R: float = 1.0, r: float = 0.35) -> tuple[np.ndarray, np.ndarray]:
    """Closed torus in the xy plane: a (major x minor) quad grid, 2*major*minor triangles."""
    major, minor = max(3, int(major)), max(3, int(minor))
    a = 2 * np.pi * np.arange(major) / major
    b = 2 * np.pi * np.arange(minor) / minor
    A, B = np.meshgrid(a, b, indexing="ij")
    ring = R + r * np.cos(B)
    v = np.stack([ring * np.cos(A), ring * np.sin(A), r * np.sin(B)], axis=-1).reshape(-1, 3)
    ii, jj = np.meshgrid(np.arange(major), np.arange(minor), indexing="ij")
    v00 = ii * minor + jj
    v10 = ((ii + 1) % major) * minor + jj
    v01 = ii * minor + (jj + 1) % minor
    v11 = ((ii + 1) % major) * minor + (jj + 1) % minor
    f = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    return v, f


def _box_arrays(lo, hi, bottom: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (B, 3) lo/hi -> 8B corners and 12B (or 10B without the bottom) triangles."""
    lo = np.asarray(lo, F64).reshape(-1, 3)
    hi = np.asarray(hi, F64).reshape(-1, 3)
    corner = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], F64)  # index x + 2y + 4z
    v = lo[:, None, :] + corner[None] * (hi - lo)[:, None, :]
    quads = [(4, 5, 7, 6), (0, 1, 5, 4), (1, 3, 7, 5), (3, 2, 6, 7), (2, 0, 4, 6)]  # top and four sides
    if bottom:
        quads.append((0, 2, 3, 1))
    t = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))], np.int64)
    f = t[None] + (8 * np.arange(len(lo)))[:, None, None]
    return v.reshape(-1, 3), f.reshape(-1, 3)


def _grid_quads(nu: int, nv: int, wrap_u: bool = False) -> np.ndarray:
    """Triangles of an (nu x nv) vertex grid (row-major, u slow), optionally wrapped in u."""
    cu = nu if wrap_u else nu - 1
    ii, jj = np.meshgrid(np.arange(cu), np.arange(nv - 1), indexing="ij")
    a = ii * nv + jj
    b = ((ii + 1) % nu) * nv + jj
    return np.concatenate([np.stack([a, b, b + 1], -1).reshape(-1, 3), np.stack([a, b + 1, a + 1], -1).reshape(-1, 3)])


# -- the scenes --------------------------------------------------------------------------

def sphere(n: int = 20000, seed=0) -> TriangleMesh:
    """A closed geodesic (subdivided icosahedron) sphere of radius 1, randomly rotated."""
    f = max(1, round((max(n, 20) / 20) ** 0.5))
    v, t = geodesic_sphere_arrays(f)
    return _mesh(v @ _random_rotation(_rng(seed)).T, t)


def torus(n: int = 20000, seed=0) -> TriangleMesh:
    """A closed torus (R = 1, r = 0.35), major resolution twice the minor, randomly rotated."""
    minor = max(3, round((max(n, 72) / 4) ** 0.5))
    v, t = torus_arrays(2 * minor, minor)
    return _mesh(v @ _random_rotation(_rng(seed)).T, t)


def soup(n: int = 20000, seed=0) -> TriangleMesh:
    """Independent random triangles in the unit cube, edges about the mean spacing n**(-1/3)."""
    rng = _rng(seed)
    n = max(1, int(n))
    size = 1.5 * n ** (-1 / 3)
    c = rng.random((n, 1, 3))
    v = c + size * (rng.random((n, 3, 3)) - 0.5)
    return _mesh(v.reshape(-1, 3), np.arange(3 * n).reshape(n, 3))


def terrain(n: int = 20000, seed=0) -> TriangleMesh:
    """A height field over [0, 10]^2: sum of random sinusoid octaves (a flat 2.5D scene)."""
    rng = _rng(seed)
    k = max(2, round((max(n, 2) / 2) ** 0.5) + 1)
    x = np.linspace(0.0, 10.0, k)
    X, Y = np.meshgrid(x, x, indexing="ij")
    Z = np.zeros_like(X)
    for octave in range(6):
        freq = 0.4 * 2 ** octave
        for _ in range(3):
            ang = rng.uniform(0, 2 * np.pi)
            Z += (0.8 / 2 ** octave) * np.sin(freq * (np.cos(ang) * X + np.sin(ang) * Y) + rng.uniform(0, 2 * np.pi))
    v = np.stack([X, Y, Z], -1).reshape(-1, 3)
    return _mesh(v, _grid_quads(k, k))


def city(n: int = 20000, seed=0) -> TriangleMesh:
    """Boxes of lognormal heights on a jittered lot grid over a ground plane (10 triangles a box)."""
    rng = _rng(seed)
    nb = max(1, (int(n) - 2) // 10)
    g = int(np.ceil(nb ** 0.5))
    lot = np.stack(np.meshgrid(np.arange(g), np.arange(g), indexing="ij"), -1).reshape(-1, 2)[:nb].astype(F64)
    foot = rng.uniform(0.3, 0.8, (nb, 2))
    off = rng.random((nb, 2)) * (1 - foot)
    h = np.minimum(rng.lognormal(0.0, 0.8, nb), 12.0)
    lo = np.column_stack([lot + off, np.zeros(nb)])
    hi = np.column_stack([lot + off + foot, h])
    bv, bf = _box_arrays(lo, hi, bottom=False)
    ground = (np.array([[0, 0, 0], [g, 0, 0], [g, g, 0], [0, g, 0]], F64), np.array([[0, 1, 2], [0, 2, 3]]))
    return _mesh(*_concat([ground, (bv, bf)]))


def scatter(n: int = 20000, seed=0) -> TriangleMesh:
    """Small 80-triangle spheres, randomly stretched and placed in a mostly empty unit cube."""
    rng = _rng(seed)
    count = max(1, int(n) // 80)
    sv, sf = geodesic_sphere_arrays(2)
    radius = 0.15 * count ** (-1 / 3)
    scale = radius * rng.uniform(0.3, 1.0, (count, 1, 3))
    rot = np.stack([_random_rotation(rng) for _ in range(min(count, 64))])[np.arange(count) % min(count, 64)]
    centre = rng.random((count, 1, 3))
    v = np.einsum("kij,kvj->kvi", rot, sv[None] * scale) + centre
    f = sf[None] + (len(sv) * np.arange(count))[:, None, None]
    return _mesh(v.reshape(-1, 3), f.reshape(-1, 3))


def stadium(n: int = 20000, seed=0) -> TriangleMesh:
    """Teapot in a stadium: a dense sphere-and-torus object of size ~3 holding ~95% of the
    triangles, inside a sparse open bowl (a floor ring from radius 5 and a wall) of radius 100."""
    rng = _rng(seed)
    n = max(200, int(n))
    dense = int(0.95 * n)
    sv, st = geodesic_sphere_arrays(max(1, round((0.6 * dense / 20) ** 0.5)))
    minor = max(3, round((0.4 * dense / 4) ** 0.5))
    tv, tt = torus_arrays(2 * minor, minor, R=1.5, r=0.3)
    rot = _random_rotation(rng)
    sparse = max(32, n - len(st) - len(tt))
    # the bowl: a (nu x nv) grid over angle (wrapped) and a profile from floor centre up the wall
    nu = max(8, int((sparse / 2) ** 0.5 * 2))
    nv = max(3, sparse // (2 * nu) + 1)
    ang = 2 * np.pi * np.arange(nu) / nu
    s = np.linspace(0.0, 1.0, nv)
    radius = np.where(s < 0.7, 5 + 95 * s / 0.7, 100.0)  # a hole of radius 5 under the object
    height = np.where(s < 0.7, -5.0, -5.0 + 40 * (s - 0.7) / 0.3)
    A, S = np.meshgrid(ang, np.arange(nv), indexing="ij")
    bowl_v = np.stack([radius[S] * np.cos(A), radius[S] * np.sin(A), height[S]], -1).reshape(-1, 3)
    bowl_f = _grid_quads(nu, nv, wrap_u=True)
    return _mesh(*_concat([(sv @ rot.T, st), (tv @ rot.T, tt), (bowl_v, bowl_f)]))


def slivers(n: int = 20000, seed=0, span: float = 1.0) -> TriangleMesh:
    """Long thin triangles: each runs between two random points on the unit cube's
    surface (``span`` scales the length about its midpoint) with a width of ~1e-3."""
    rng = _rng(seed)
    n = max(1, int(n))

    def on_cube_surface(k):
        p = rng.random((k, 3))
        axis = rng.integers(0, 3, k)
        p[np.arange(k), axis] = rng.integers(0, 2, k)
        return p

    a, b = on_cube_surface(n), on_cube_surface(n)
    mid = 0.5 * (a + b)
    a = mid + span * (a - mid)
    b = mid + span * (b - mid)
    side = np.cross(b - a, rng.standard_normal((n, 3)))
    side *= 1e-3 / np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-30)
    c = a + rng.random((n, 1)) * (b - a) + side
    v = np.stack([a, b, c], axis=1).reshape(-1, 3)
    return _mesh(v, np.arange(3 * n).reshape(n, 3))


def clusters(n: int = 20000, seed=0, count: int = 12) -> TriangleMesh:
    """Triangle soup in ``count`` Gaussian clusters of random size (sigma 0.02-0.12) in an
    otherwise empty unit cube: dense pockets in empty space, the case uniform grids handle
    worst (most cells empty, a few overfull)."""
    rng = _rng(seed)
    n = max(1, int(n))
    centre = 0.1 + 0.8 * rng.random((count, 3))
    sigma = np.exp(rng.uniform(np.log(0.02), np.log(0.12), count))
    which = rng.integers(0, count, n)
    c = centre[which] + sigma[which, None] * rng.standard_normal((n, 3))
    size = 0.6 * sigma[which] * (n / count) ** (-1 / 3) * 4
    v = c[:, None, :] + size[:, None, None] * (rng.random((n, 3, 3)) - 0.5)
    return _mesh(v.reshape(-1, 3), np.arange(3 * n).reshape(n, 3))


def sizes(n: int = 20000, seed=0) -> TriangleMesh:
    """Random triangles in the unit cube whose sizes spread over three decades (log-uniform
    edge from 1e-3 to 1): a few large ones overlap many cells and many rays, most are small."""
    rng = _rng(seed)
    n = max(1, int(n))
    edge = np.exp(rng.uniform(np.log(1e-3), 0.0, n))
    c = rng.random((n, 1, 3))
    v = c + edge[:, None, None] * (rng.random((n, 3, 3)) - 0.5)
    return _mesh(v.reshape(-1, 3), np.arange(3 * n).reshape(n, 3))


#: every generator by name: ``SCENES[name](n, seed) -> TriangleMesh``
SCENES = {
    "sphere": sphere,
    "torus": torus,
    "soup": soup,
    "terrain": terrain,
    "city": city,
    "scatter": scatter,
    "stadium": stadium,
    "slivers": slivers,
    "clusters": clusters,
    "sizes": sizes,
}


#: the generators whose triangles have three vertices of their own: soups, not surfaces
#: (``TriangleMesh.is_surface`` False); every other generator's triangles share their vertices
SOUPS = frozenset({"soup", "slivers", "clusters", "sizes"})


def is_surface_scene(name: str) -> bool | None:
    """Whether the calibration scene ``name`` (``generator-size``, ``calibration_set``) is a
    surface, from its generator; None for a name no generator makes."""
    generator = str(name).split("-", 1)[0]
    return None if generator not in SCENES else generator not in SOUPS


def make_scene(name: str, n: int, seed=0) -> TriangleMesh:
    """``SCENES[name](n, seed)`` with a clear error for an unknown name."""
    try:
        gen = SCENES[name]
    except KeyError:
        raise ValueError(f"unknown procedural scene {name!r}; expected one of {', '.join(SCENES)}") from None
    return gen(n, seed)


def _label(n: int) -> str:
    if n >= 1_000_000:
        return f"{n / 1e6:g}M"
    return f"{n / 1000:g}k" if n >= 1000 else str(n)


#: (generator, target triangles[, options]) per calibration scale.  'default' spans ~500
#: to ~1M triangles, each generator at two or three sizes far apart so that the fit sees
#: small and large N.  The slivers there span a tenth of the scene (aspect ~100:1): at
#: full span every ray overlaps most of them and the per-ray cost of any hierarchy is
#: ~N, not log N (its c_R far above the other scenes'), which would swamp the
#: mean; full-span slivers stay a robustness case, not a calibration scene.
_SETS = {
    "tiny": [("sphere", 500), ("torus", 800), ("soup", 600), ("terrain", 1000),
             ("city", 700), ("scatter", 800), ("stadium", 1000), ("slivers", 500, {"span": 0.1})],
    "quick": [("sphere", 2000), ("torus", 30000), ("soup", 8000), ("terrain", 60000),
              ("city", 4000), ("scatter", 16000), ("stadium", 40000), ("slivers", 1000, {"span": 0.1})],
    "default": [("sphere", 500), ("sphere", 20000), ("sphere", 250000),
                ("torus", 5000), ("torus", 40000), ("torus", 300000),
                ("soup", 2000), ("soup", 60000), ("soup", 600000),
                ("terrain", 20000), ("terrain", 1000000),
                ("city", 1000), ("city", 15000), ("city", 120000),
                ("scatter", 10000), ("scatter", 200000),
                ("stadium", 3000), ("stadium", 500000),
                ("slivers", 800, {"span": 0.1}), ("slivers", 5000, {"span": 0.1})],
}
#: 'rich': 'default' plus what it lacks, dense clusters in empty space, sizes spread over
#: three decades, and longer slivers (a third of the scene); not the default, since its fit
#: follows held-out meshes less well (BENCHMARKS.md, "Tried and not kept")
_SETS["rich"] = _SETS["default"] + [("clusters", 3000), ("clusters", 80000), ("clusters", 400000),
                                    ("sizes", 2000), ("sizes", 50000), ("slivers", 2000, {"span": 0.3}),
                                    ("scatter", 1500), ("city", 600000)]
SCALES = tuple(_SETS)


def calibration_set(scale: str = "default", seed: int = 0) -> list[tuple[str, "partial[TriangleMesh]"]]:
    """The calibration scenes as (name, factory) pairs; ``factory()`` makes the mesh.

    Names read ``generator-size`` (``torus-300k``).  Factories are cheap to hold: a mesh
    is generated only when called, so a calibration run keeps one scene in memory at a time.
    """
    try:
        spec = _SETS[scale]
    except KeyError:
        raise ValueError(f"unknown calibration scale {scale!r}; expected one of {', '.join(SCALES)}") from None
    return [(f"{e[0]}-{_label(e[1])}", partial(SCENES[e[0]], e[1], seed, **(e[2] if len(e) > 2 else {}))) for e in spec]


def subdivide(mesh: TriangleMesh) -> TriangleMesh:
    """Midpoint subdivision (each triangle into four, shared edge midpoints merged):
    4x the triangles of the same shape, for larger versions of a real mesh."""
    v = mesh.vertices.astype(F64)
    f = mesh.triangles.astype(np.int64)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    mids = 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])
    inv = inv.reshape(-1)
    t = len(f)
    m01, m12, m20 = (len(v) + inv[k * t:(k + 1) * t] for k in range(3))
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    nf = np.concatenate([np.stack(x, 1) for x in ((a, m01, m20), (m01, b, m12), (m20, m12, c), (m01, m12, m20))])
    return TriangleMesh(np.concatenate([v, mids]).astype(np.float32), nf)
