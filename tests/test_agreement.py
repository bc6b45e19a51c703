"""Every structure against the independent float64 reference, and the numpy ones hit for hit.

- numpy structures (brute, grid, bvh) vs tests/reference.py: the same triangle on every
  ray the reference calls unambiguous (no edge/vertex grazing within 1e-5 barycentric,
  no near tie, not in a triangle's plane), and relative t error < 1e-5;
- grid == bvh == brute on every ray, grazing ones included: one kernel, so bit-identical;
- Embree: hit/miss and triangle on unambiguous rays, t within a looser tolerance (it
  works in float32 from the ray origin); its disagreement rate is printed (pytest -s).

Real meshes come from ../shared/scenes (skipped when absent).  Brute force is slow, so
on the real meshes it traces a subset of the rays, bounded by a pair budget.
"""

from functools import lru_cache

import numpy as np
import pytest

from conftest import real_scene_paths
from hybrid_raycast import core
from hybrid_raycast.core.rays import radical_inverse
from reference import (
    NUMPY_KINDS,
    describe_ray,
    kind_params,
    reference_for_mesh,
    terrain,
    triangle_soup,
    uv_sphere,
    vertex_and_edge_targets,
)

REAL_RAYS = 1500
BRUTE_PAIRS = 1_500_000  # brute force on a real mesh traces at most this many (ray, triangle) pairs
T_RTOL = 1e-5
EMBREE_T_TOL = 1e-5  # relative to the ray's scale: |o| / |d| + t


def _procedural(name):
    if name == "soup":
        v, t = triangle_soup(300, seed=11)
    elif name == "sphere":
        v, t = uv_sphere(14, 20, radius=3.0, center=(0.5, -0.25, 0.125))
    elif name == "terrain":
        v, t = terrain(20, seed=5)
    return core.TriangleMesh(v, t)


PROCEDURAL = ("soup", "sphere", "terrain")


@lru_cache(maxsize=None)
def _scene(name):
    """(mesh, origins, directions, tmin, tmax, reference) for a named scene, computed once."""
    if name in PROCEDURAL:
        mesh = _procedural(name)
        o, d = core.uniform_rays(mesh, 1500, seed=7)
        # plus rays aimed exactly at vertices and edge midpoints (grazing on purpose), and
        # a band of tmin/tmax so the interval is exercised too
        targets = vertex_and_edge_targets(mesh.vertices, mesh.triangles)
        rng = np.random.default_rng(8)
        targets = targets[rng.choice(len(targets), min(len(targets), 500), replace=False)]
        o2, _ = core.uniform_rays(mesh, len(targets), seed=9)
        o = np.vstack([o, o2])
        d = np.vstack([d, (targets - o2.astype(np.float64)).astype(np.float32)])
        d[np.all(d == 0, axis=1)] = [0, 0, 1]
        m = len(o)
        tmin = np.where(rng.random(m) < 0.2, rng.uniform(0, 2, m), 0.0)
        tmax = np.where(rng.random(m) < 0.2, tmin + rng.uniform(0, 4, m), np.inf)
    else:
        mesh = core.load_obj(name)
        o, d = core.uniform_rays(mesh, REAL_RAYS, seed=7)
        tmin, tmax = 0.0, np.inf
    ref = reference_for_mesh(mesh, o, d, tmin, tmax)
    return mesh, o, d, tmin, tmax, ref


def _subset_for(kind, mesh, m):
    """Rays a structure traces: all, except brute force on big meshes (a pair budget)."""
    if kind != "brute":
        return np.arange(m)
    k = max(32, BRUTE_PAIRS // max(1, mesh.triangle_count))
    return np.arange(min(m, k))


@lru_cache(maxsize=None)
def _trace(kind, name):
    mesh, o, d, tmin, tmax, _ = _scene(name)
    idx = _subset_for(kind, mesh, len(o))
    lo = tmin if np.ndim(tmin) == 0 else tmin[idx]
    hi = tmax if np.ndim(tmax) == 0 else tmax[idx]
    return idx, core.build(mesh, kind).trace(o[idx], d[idx], lo, hi)


SCENES = list(PROCEDURAL) + [str(p) for p in real_scene_paths()]
SCENE_IDS = list(PROCEDURAL) + [p.stem for p in real_scene_paths()]


def _check_against_reference(kind, name, t_tol):
    mesh, o, d, _, _, ref = _scene(name)
    idx, h = _trace(kind, name)
    amb = ref.ambiguous[idx]
    rt = ref.triangle[idx]
    bad = np.flatnonzero((h.triangle != rt) & ~amb)
    if bad.size:
        i = bad[0]
        r = idx[i]
        pytest.fail(
            f"{kind} on {SCENE_IDS[SCENES.index(name)]}: {bad.size} of {(~amb).sum()} unambiguous rays pick a "
            f"different triangle; first {describe_ray(r, o, d)}: expected triangle {rt[i]} at t={ref.t[r]!r}, "
            f"got {h.triangle[i]} at t={float(h.t[i])!r}"
        )
    both = (h.triangle == rt) & (rt >= 0) & ~amb
    err = np.abs(h.t[both].astype(np.float64) - ref.t[idx][both])
    scale = t_tol(o[idx][both], d[idx][both], ref.t[idx][both])
    worst = np.argmax(err / scale) if err.size else None
    if worst is not None and err[worst] > scale[worst]:
        r = idx[np.flatnonzero(both)[worst]]
        pytest.fail(f"{kind}: t error {err[worst]:.3g} exceeds {scale[worst]:.3g} on {describe_ray(r, o, d)}: "
                    f"reference t={ref.t[r]!r}, got {float(h.t[idx == r][0])!r}")
    return idx, h, amb


@pytest.mark.parametrize("name", SCENES, ids=SCENE_IDS)
@pytest.mark.parametrize("kind", kind_params(NUMPY_KINDS))
def test_numpy_structure_matches_float64_reference_on_unambiguous_rays(kind, name):
    _check_against_reference(kind, name, lambda o, d, t: T_RTOL * np.abs(t))


@pytest.mark.parametrize("name", SCENES, ids=SCENE_IDS)
@pytest.mark.parametrize("kind", kind_params(("embree",)))
def test_embree_matches_float64_reference_loosely(kind, name):
    def tol(o, d, t):
        ray_scale = np.abs(o.astype(np.float64)).max(axis=1) / np.abs(d.astype(np.float64)).max(axis=1)
        return EMBREE_T_TOL * (ray_scale + np.abs(t))

    idx, h, amb = _check_against_reference(kind, name, tol)
    _, o, d, _, _, ref = _scene(name)
    diff_tri = h.triangle != ref.triangle[idx]
    diff_hit = h.hit != ref.hit[idx]
    print(f"\n[embree vs reference] {SCENE_IDS[SCENES.index(name)]}: {len(idx)} rays, "
          f"{amb.sum()} ambiguous; triangle differs on {diff_tri.sum()} "
          f"({100 * diff_tri.mean():.3f}%), hit/miss differs on {diff_hit.sum()} ({100 * diff_hit.mean():.3f}%)")


@pytest.mark.parametrize("name", SCENES, ids=SCENE_IDS)
def test_grid_bvh_and_brute_agree_bit_for_bit_on_every_ray(name):
    kinds = NUMPY_KINDS
    mesh, o, d, _, _, ref = _scene(name)
    results = {k: _trace(k, name) for k in kinds}
    for a in kinds:
        for b in kinds:
            if a >= b:
                continue
            ia, ha = results[a]
            ib, hb = results[b]
            common, pa, pb = np.intersect1d(ia, ib, return_indices=True)
            for field in ("triangle", "t"):
                x, y = getattr(ha, field)[pa], getattr(hb, field)[pb]
                w = np.flatnonzero(x != y)
                if w.size:
                    r = common[w[0]]
                    pytest.fail(
                        f"{a} and {b} differ in {field} on {w.size} of {len(common)} rays; first "
                        f"{describe_ray(r, o, d)} (ambiguous for the reference: {bool(ref.ambiguous[r])}): "
                        f"{a} triangle {ha.triangle[pa][w[0]]} t={float(ha.t[pa][w[0]])!r}, "
                        f"{b} triangle {hb.triangle[pb][w[0]]} t={float(hb.t[pb][w[0]])!r}"
                    )


@pytest.mark.parametrize("kind", kind_params(NUMPY_KINDS + ("embree",)))
def test_occluded_agrees_with_trace_on_procedural_scenes(kind):
    for name in PROCEDURAL:
        mesh, o, d, tmin, tmax, _ = _scene(name)
        idx, h = _trace(kind, name)
        lo = tmin if np.ndim(tmin) == 0 else tmin[idx]
        hi = tmax if np.ndim(tmax) == 0 else tmax[idx]
        occ = core.build(mesh, kind).occluded(o[idx], d[idx], lo, hi)
        w = np.flatnonzero(occ != h.hit)
        assert w.size == 0, (f"{kind} on {name}: occluded != trace().hit on {w.size} rays; first "
                             f"{describe_ray(idx[w[0]], o, d)}: occluded {occ[w[0]]}, trace triangle {h.triangle[w[0]]}")


def test_reference_flags_grazing_rays_as_ambiguous_and_plain_rays_not():
    """The reference itself: a ray through a shared edge is ambiguous, one through the middle is not."""
    mesh = core.TriangleMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [1, 3, 2]])
    o = np.array([[0.5, 0.5, 1], [0.25, 0.25, 1], [0.5, 0.5 - 1e-7, 1], [2, 2, 1], [1 + 1e-7, 0.5, 1]], float)
    d = np.array([[0, 0, -1]] * 5, float)
    ref = reference_for_mesh(mesh, o, d)
    assert ref.ambiguous.tolist() == [True, False, True, False, True], ref.ambiguous.tolist()
    assert ref.triangle[1] == 0 and ref.t[1] == 1.0
    assert ref.triangle[3] == -1


# -- what the agreement tests stand on: the OBJ reader and the ray generators -------------------

def test_load_obj_reads_every_corner_format_negative_indices_and_ngons(tmp_path):
    p = tmp_path / "mixed.obj"
    p.write_text(
        "# comment\n"
        "o first\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0 1.0\n"  # a w component is ignored
        "vt 0 0\nvn 0 0 1\n"
        "f 1 2 3\n"
        "f 1/1 3/1 4/1\n"
        "o second\n"
        "v 0 0 1 0.5 0.5 0.5\nv 1 0 1\nv 1 1 1\nv 0 1 1\nv 0.5 1.5 1\n"  # vertex colours ignored
        "f 5//1 6//1 7//1 8//1\n"  # a quad
        "f -5/1/1 -4/1/1 -3/1/1 -1/1/1 -2/1/1\n"  # a pentagon with negative indices
        "l 1 2\n"
    )
    m = core.load_obj(p)
    assert m.vertices.shape == (9, 3) and m.vertices.dtype == np.float32
    expected = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [4, 5, 6], [4, 6, 8], [4, 8, 7]]
    assert m.triangles.tolist() == expected, m.triangles.tolist()
    assert m.polygon_index.tolist() == [0, 1, 2, 2, 3, 3, 3]
    assert m.object_index.tolist() == [0, 0, 1, 1, 1, 1, 1] and m.object_names == ["first", "second"]


def test_load_obj_rejects_index_zero_and_short_faces_naming_the_line(tmp_path):
    p = tmp_path / "bad.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 0 1 2\n")
    with pytest.raises(ValueError, match=r"bad.obj:5: vertex index 0"):
        core.load_obj(p)
    p.write_text("v 0 0 0\nv 1 0 0\nf 1 2\n")
    with pytest.raises(ValueError, match=r"bad.obj:3: face with 2 corners"):
        core.load_obj(p)
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n")
    with pytest.raises(ValueError, match="outside"):
        core.load_obj(p)


@pytest.mark.parametrize("path", real_scene_paths(), ids=[p.stem for p in real_scene_paths()])
def test_load_obj_matches_trimesh_on_the_real_meshes(path):
    trimesh = pytest.importorskip("trimesh")
    m = core.load_obj(path)
    # trimesh, unprocessed, keeps the file's vertices (for files without texture seams)
    try:
        t = trimesh.load(path, process=False, force="mesh", maintain_order=True, skip_materials=True)
    except ImportError as e:  # e.g. PIL for a file with texture coordinates
        pytest.skip(f"trimesh cannot load {path.name} here: {e}")
    if len(t.vertices) != len(m.vertices):
        pytest.skip(f"trimesh split vertices ({len(t.vertices)} vs {len(m.vertices)}): not comparable")
    np.testing.assert_allclose(m.vertices, t.vertices, rtol=1e-6, atol=1e-6)
    # the same triangles as sets of corners (fan order may differ)
    a = np.sort(np.sort(m.triangles, axis=1), axis=0)
    b = np.sort(np.sort(np.asarray(t.faces), axis=1), axis=0)
    assert a.shape == b.shape and (a == b).all(), f"{path.name}: triangles differ from trimesh's"


def _assert_papers_distribution(rays, mean_tol: float, moment_tol: float):
    """Checks a generator of the paper's rays (``rays(bounds, m, seed=...)``) on a box flat
    in y: float32 arrays, origins in the padded box (which has volume), unit directions
    whose means and second moments are within the tolerances of the sphere's, and the
    seed deciding the rays.  Returns the 20,000 rays of seed 5 and the box."""
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([3.0, 0.0, 4.0])  # flat in y
    o, d = rays((lo, hi), 20000, seed=5)
    assert o.dtype == np.float32 and d.dtype == np.float32 and o.shape == d.shape == (20000, 3)
    pad = 0.01 * np.linalg.norm(hi - lo)
    assert (o >= lo - pad - 1e-5).all() and (o <= hi + pad + 1e-5).all()
    assert o[:, 1].max() - o[:, 1].min() > pad, "a flat box still gets padded volume"
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-6)
    assert np.abs(d.mean(axis=0)).max() < mean_tol, f"directions not uniform: mean {d.mean(axis=0)}"
    assert np.abs((d ** 2).mean(axis=0) - 1 / 3).max() < moment_tol
    o2, d2 = rays((lo, hi), 20000, seed=5)
    assert (o == o2).all() and (d == d2).all(), "the same seed must give the same rays"
    assert not (rays((lo, hi), 10, seed=6)[1] == d[:10]).all()
    return o, d, (lo, hi)


def test_uniform_rays_have_explicit_dtypes_fill_the_padded_box_and_cover_the_sphere():
    _assert_papers_distribution(core.uniform_rays, 0.03, 0.02)


def test_radical_inverse_mirrors_the_digits_about_the_radix_point():
    np.testing.assert_array_equal(radical_inverse(np.arange(6), 2), [0, 0.5, 0.25, 0.75, 0.125, 0.625])
    np.testing.assert_allclose(radical_inverse(np.arange(1, 6), 3), [1 / 3, 2 / 3, 1 / 9, 4 / 9, 7 / 9])
    assert radical_inverse(np.array([1 << 40]), 2)[0] == 2.0 ** -41
    with pytest.raises(ValueError, match="non-negative"):
        radical_inverse(np.array([-1]), 2)


def _hits_sphere(o, d, centre, radius):
    """Whether the half-lines o + t d (t >= 0, d unit) meet the ball, in float64."""
    oc = centre - o.astype(np.float64)
    along = (oc * d).sum(axis=1)
    gap2 = (oc * oc).sum(axis=1) - along ** 2
    inside = (oc * oc).sum(axis=1) <= radius ** 2
    return inside | ((along > 0) & (gap2 <= radius ** 2))


def test_quasi_uniform_rays_are_the_papers_distribution_and_their_means_move_less_between_seeds():
    o, d, (lo, hi) = _assert_papers_distribution(core.quasi_uniform_rays, 0.01, 0.01)
    np.testing.assert_allclose(o.mean(axis=0), (lo + hi) / 2, atol=0.01)
    # the share of rays that meet a ball inside a unit box: the same mean as independent
    # rays, with a smaller spread over seeds (what a plan's break-even inherits)
    box, centre = (np.zeros(3), np.ones(3)), np.full(3, 0.5)
    share = {f: np.array([_hits_sphere(*f(box, 2048, seed=s), centre, 0.25).mean() for s in range(40)])
             for f in (core.uniform_rays, core.quasi_uniform_rays)}
    rnd, qmc = share[core.uniform_rays], share[core.quasi_uniform_rays]
    assert abs(qmc.mean() - rnd.mean()) < 3 * np.hypot(rnd.std(), qmc.std()) / np.sqrt(40)
    assert qmc.std() < 0.75 * rnd.std(), f"quasi-random spread {qmc.std():.4f} vs independent {rnd.std():.4f}"


def test_camera_rays_are_row_major_from_the_top_with_fov_across_the_larger_side():
    o, d = core.camera_rays((0, 0, 0), (0, 0, -1), (0, 1, 0), 90.0, 5, 3)
    assert o.shape == d.shape == (15, 3) and d.dtype == np.float32
    d = d.reshape(3, 5, 3)
    np.testing.assert_allclose(d[1, 2], [0, 0, -1], atol=1e-7)  # centre pixel looks at look_at
    assert d[0, 2, 1] > 0 > d[2, 2, 1], "row 0 is the top row"
    assert d[1, 0, 0] < 0 < d[1, 4, 0], "columns run left to right"
    # pixel centres at +-(1 - 1/5) of the half-width: tan(45 deg) * 0.8
    np.testing.assert_allclose(d[1, 4, 0] / -d[1, 4, 2], 0.8, rtol=1e-6)
    _, dt = core.camera_rays((0, 0, 0), (0, 0, -1), (0, 1, 0), 90.0, 3, 5)  # portrait
    dt = dt.reshape(5, 3, 3)
    np.testing.assert_allclose(dt[0, 1, 1] / -dt[0, 1, 2], 0.8, rtol=1e-6)


def test_hemisphere_rays_stay_above_the_surface_and_are_cosine_weighted():
    pts = np.array([[0, 0, 0], [1, 2, 3.0]])
    nrm = np.array([[0, 0, 1.0], [-1, -1, 0.0]])
    o, d = core.hemisphere_rays(pts, nrm, 5000, seed=1)
    assert o.shape == d.shape == (10000, 3) and o.dtype == np.float32
    n = np.repeat(nrm / np.linalg.norm(nrm, axis=1, keepdims=True), 5000, axis=0)
    cos = (d * n).sum(axis=1)
    assert (cos >= -1e-6).all(), "a direction points below the surface"
    assert abs(cos.mean() - 2 / 3) < 0.02, f"mean cosine {cos.mean()}, expected 2/3 for cosine weighting"
    _, du = core.hemisphere_rays(pts, nrm, 5000, seed=1, cosine=False)
    assert abs((du * n).sum(axis=1).mean() - 0.5) < 0.02
    with pytest.raises(ValueError, match="zero"):
        core.hemisphere_rays(pts, np.zeros((2, 3)), 3)
