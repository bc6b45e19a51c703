"""core.all_hits: every hit along each ray equals a float64 brute force listing of all
intersections, sorted by ray then t, one hit per point at shared edges and vertices."""

import numpy as np
import pytest

from hybrid_raycast import core
from reference import icosphere, kind_params, uv_sphere


def brute_all(mesh, o, d, tmin=0.0, tmax=np.inf):
    """float64 Moller-Trumbore over every (ray, triangle) pair; hits at one point once."""
    tv = mesh.tri_vertices.astype(np.float64)[mesh.valid]
    v0, e1, e2 = tv[:, 0], tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]
    out = []
    for i in range(len(o)):
        oi, di = o[i].astype(np.float64), d[i].astype(np.float64)
        p = np.cross(di, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = oi - v0
            u = np.einsum("ij,ij->i", s, p) * inv
            q = np.cross(s, e1)
            v = (q @ di) * inv
            t = np.einsum("ij,ij->i", e2, q) * inv
        ok = (det != 0) & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > tmin) & (t <= tmax)
        ts = np.sort(t[ok])
        keep = np.ones(len(ts), bool)
        keep[1:] = np.diff(ts) > 1e-5 * np.maximum(1.0, ts[1:])
        out.append(ts[keep])
    return out


@pytest.mark.parametrize("kind", kind_params(["grid", "bvh", "embree", "brute"]))
def test_all_hits_match_a_float64_brute_force(kind):
    spheres = [uv_sphere(12, 16, 1.0, c) for c in ((0, 0, 0), (3, 0.2, 0), (6, -0.1, 0.1))]
    verts = np.concatenate([s[0] for s in spheres])
    offs = np.cumsum([0] + [len(s[0]) for s in spheres[:-1]])
    tris = np.concatenate([s[1] + k for s, k in zip(spheres, offs)])
    mesh = core.TriangleMesh(verts, tris)
    rng = np.random.default_rng(4)
    m = 400
    o = np.stack([np.full(m, -3.0), rng.uniform(-1, 1, m), rng.uniform(-1, 1, m)], axis=1)
    d = np.stack([np.ones(m), rng.normal(0, 0.02, m), rng.normal(0, 0.02, m)], axis=1)
    acc = core.build(mesh, kind)
    ray, t, tri, u, v = core.all_hits(acc, o, d, max_hits=16)
    assert np.all(np.diff(ray) >= 0), "not sorted by ray"
    same = ray[1:] == ray[:-1]
    assert np.all(t[1:][same] > t[:-1][same]), "not sorted by t within a ray, or a repeated hit"
    ref = brute_all(mesh, o.astype(np.float32), d.astype(np.float32))
    wrong = []
    for i in range(m):
        got = t[ray == i].astype(np.float64)
        if len(got) != len(ref[i]) or not np.allclose(got, ref[i], rtol=1e-5, atol=1e-5):
            wrong.append((i, got.tolist(), ref[i].tolist()))
    assert not wrong, f"{len(wrong)} rays differ from brute force, first {wrong[:3]}"
    assert sum(len(r) for r in ref) > m, "rays should cross several surfaces"
    # max_hits caps, nearest first
    ray2, t2, *_ = core.all_hits(acc, o, d, max_hits=2)
    assert np.bincount(ray2, minlength=m).max() <= 2
    for i in range(0, m, 37):
        assert np.allclose(t2[ray2 == i], t[ray == i][:2])


@pytest.mark.parametrize("kind", kind_params(["grid", "bvh", "embree"]))
def test_a_ray_through_shared_edges_and_vertices_counts_each_surface_once(kind):
    v, f = icosphere(2)
    mesh = core.TriangleMesh(v, f)
    acc = core.build(mesh, kind)
    # from the centre toward each vertex: through a vertex shared by 5 or 6 triangles
    dirs = mesh.vertices.astype(np.float64)
    o = np.zeros_like(dirs)
    ray, t, *_ = core.all_hits(acc, o, dirs, max_hits=8)
    counts = np.bincount(ray, minlength=len(dirs))
    assert np.all(counts == 1), f"rays through a vertex of a closed sphere hit {sorted(set(counts.tolist()))} times"
    # from outside through the centre: in and out, twice each direction's vertex
    ray, t, *_ = core.all_hits(acc, -3 * dirs, dirs, max_hits=8)
    assert np.all(np.bincount(ray, minlength=len(dirs)) == 2)


def test_max_hits_must_be_positive():
    mesh = core.TriangleMesh(np.eye(3), [[0, 1, 2]])
    with pytest.raises(ValueError, match="max_hits"):
        core.all_hits(core.build(mesh, "brute"), [[0, 0, 0]], [[1, 1, 1]], max_hits=0)
