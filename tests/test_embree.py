"""core/embree.py: Embree through embreex behind the common interface.

What embreex cannot do itself (tnear, degenerate triangles, index mapping) is
emulated by the wrapper; these tests pin that emulation down.
"""

import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from hybrid_raycast import core
from reference import describe_ray, kind_missing_reason

needs_embree = pytest.mark.skipif(kind_missing_reason("embree") is not None,
                                  reason=str(kind_missing_reason("embree")))


def _layers():
    """Three parallel squares (two triangles each) at z = 1, 2, 3, with degenerate
    triangles interleaved so Embree's primID differs from the mesh's index."""
    tris = []
    for z in (1.0, 2.0, 3.0):
        tris.append([[0, 0, z], [0, 0, z], [1, 0, z]])  # degenerate
        tris.append([[-2, -2, z], [2, -2, z], [2, 2, z]])
        tris.append([[-2, -2, z], [2, 2, z], [-2, 2, z]])
    tris = np.array(tris, np.float64)
    return core.TriangleMesh(tris.reshape(-1, 3), np.arange(len(tris) * 3).reshape(-1, 3))


def test_importing_core_does_not_import_embreex():
    code = ("import sys, types; p = types.ModuleType('hybrid_raycast'); p.__path__ = [sys.argv[1]]; "
            "sys.modules['hybrid_raycast'] = p; from hybrid_raycast import core; "
            "core.build(core.TriangleMesh([[0,0,0],[1,0,0],[0,1,0]], [[0,1,2]]), 'brute'); "
            "assert 'embreex' not in sys.modules, 'core imported embreex eagerly'; print('ok')")
    r = subprocess.run([sys.executable, "-c", code, str(ROOT)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_build_without_embreex_raises_a_clear_runtime_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "embreex", None)  # makes "import embreex" fail
    for name in [k for k in sys.modules if k.startswith("embreex.")]:
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(RuntimeError, match="embreex is not installed"):
        core.build(_layers(), "embree")


def test_embree_available_agrees_with_importability():
    try:
        import embreex  # noqa: F401
        importable = True
    except ImportError:
        importable = False
    assert core.embree_available() == importable


def test_embree_unavailable_reason_names_the_platform_without_a_wheel(monkeypatch):
    from hybrid_raycast.core import embree

    assert (embree.embree_unavailable_reason() is None) == core.embree_available()
    monkeypatch.setattr(embree, "embree_available", lambda: False)
    why = embree.embree_unavailable_reason
    assert why("Darwin", "arm64", (3, 11)) == "embreex has no wheel for macOS arm64"
    assert why("Darwin", "x86_64", (3, 13)) == "embreex has no wheel for macOS x64"
    assert why("Linux", "aarch64", (3, 11)) == "embreex has no wheel for Linux arm64"
    assert why("Windows", "ARM64", (3, 13)) == "embreex has no wheel for Windows arm64"
    assert why("Linux", "x86_64", (3, 12)) == "embreex has no wheel for Python 3.12"
    # where a wheel exists (the packages for linux-x64 and windows-x64 carry it), only its absence is left
    assert why("Linux", "x86_64", (3, 11)) == why("Windows", "AMD64", (3, 13)) == "embreex is not installed"


@needs_embree
def test_embree_maps_primitive_ids_back_past_degenerate_triangles():
    mesh = _layers()
    acc = core.build(mesh, "embree")
    o = np.array([[0.5, -0.5, 0.0], [-0.5, 0.5, 0.0], [0.5, -0.5, 4.0], [-0.5, 0.5, 4.0]])
    d = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0], [0, 0, -1.0]])
    h = acc.trace(o, d)
    assert h.triangle.tolist() == [1, 2, 7, 8], f"got {h.triangle.tolist()}, expected [1, 2, 7, 8]"
    np.testing.assert_allclose(h.t, [1, 1, 1, 1], rtol=1e-6)
    assert acc.stats()["embree_triangles"] == 6 and acc.stats()["robust"] is True


@needs_embree
def test_embree_honours_tmin_exclusive_and_tmax_inclusive():
    acc = core.build(_layers(), "embree")
    o = np.tile([0.5, -0.5, 0.0], (7, 1))
    d = np.tile([0.0, 0.0, 2.0], (7, 1))  # unnormalised: the layers are at t = 0.5, 1, 1.5
    tmin = np.array([0.0, 0.5, 0.6, 0.0, 0.0, 1.0, 1.5])
    tmax = np.array([np.inf, np.inf, np.inf, 0.5, 0.49, 1.0, np.inf])
    h = acc.trace(o, d, tmin, tmax)
    exp_tri = [1, 4, 4, 1, -1, -1, -1]
    exp_t = [0.5, 1.0, 1.0, 0.5, np.inf, np.inf, np.inf]
    assert h.triangle.tolist() == exp_tri, f"triangles {h.triangle.tolist()}, expected {exp_tri}"
    np.testing.assert_allclose(h.t, exp_t, rtol=1e-6)
    assert acc.occluded(o, d, tmin, tmax).tolist() == [t >= 0 for t in exp_tri]


@needs_embree
def test_embree_skips_a_hit_exactly_at_the_ray_start():
    acc = core.build(_layers(), "embree")
    # origins exactly on the z = 1 layer (t = 0 there; the convention excludes t = tmin)
    o = np.array([[0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.25, -0.25, 2.0]])
    d = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]])
    h = acc.trace(o, d)
    assert h.triangle.tolist() == [4, -1, 7], f"got {h.triangle.tolist()}, expected [4, -1, 7]"
    np.testing.assert_allclose(h.t[[0, 2]], [1.0, 1.0], rtol=1e-5)
    assert acc.occluded(o, d).tolist() == [True, False, True]
    # the same with tmin > 0 putting the start exactly on a layer
    h = acc.trace(np.zeros((1, 3)) + [0.5, -0.5, 0], [[0, 0, 1.0]], tmin=2.0)
    assert h.triangle.tolist() == [7] and abs(h.t[0] - 3) < 1e-5, f"{h.triangle.tolist()} t={h.t.tolist()}"


@needs_embree
def test_embree_barycentrics_follow_the_project_convention():
    rng = np.random.default_rng(0)
    tris = rng.uniform(-3, 3, (50, 3, 3))
    mesh = core.TriangleMesh(tris.reshape(-1, 3), np.arange(150).reshape(-1, 3))
    w = rng.dirichlet([3, 3, 3], 50)
    target = np.einsum("nk,nkj->nj", w, tris)
    o = rng.uniform(-3, 3, (50, 3))
    he = core.build(mesh, "embree").trace(o, target - o)
    hb = core.build(mesh, "brute").trace(o, target - o)
    same = (he.triangle == hb.triangle) & hb.hit
    assert same.mean() > 0.95, f"only {same.mean():.0%} of rays agree on the triangle"
    np.testing.assert_allclose(he.u[same], hb.u[same], atol=1e-4, err_msg="u is the weight of corner 1")
    np.testing.assert_allclose(he.v[same], hb.v[same], atol=1e-4, err_msg="v is the weight of corner 2")


@needs_embree
def test_embree_results_do_not_depend_on_chunking():
    mesh = _layers()
    o, d = core.uniform_rays(mesh, 300, seed=1)
    a = core.build(mesh, "embree").trace(o, d)
    b = core.build(mesh, "embree", chunk_size=7).trace(o, d)
    w = np.flatnonzero((a.triangle != b.triangle) | (a.t != b.t))
    assert w.size == 0, f"chunk_size changes {describe_ray(w[0], o, d)}: {a.triangle[w[0]]} vs {b.triangle[w[0]]}"


@needs_embree
def test_embree_build_time_includes_the_commit():
    rng = np.random.default_rng(2)
    tris = rng.uniform(-1, 1, (20000, 3, 3))
    acc = core.build(core.TriangleMesh(tris.reshape(-1, 3), np.arange(60000).reshape(-1, 3)), "embree")
    assert acc.scene.is_committed, "the Embree scene must be committed (its BVH built) by build()"
    assert acc.build_time > 0


@needs_embree
@pytest.mark.parametrize("threads", [1, 2])
def test_concurrent_traces_on_one_structure_match_a_single_thread_trace(threads):
    """embreex releases the GIL in its ray loop, so two Python threads really trace one
    scene at once: each must get exactly the hits its rays get when traced alone."""
    import threading

    from hybrid_raycast.core import scenes

    mesh = scenes.make_scene("city", 20000, seed=3)
    acc = core.build(mesh, "embree", threads=threads, chunk_size=8192)
    batches = []
    for seed in (1, 2):
        o, d = core.uniform_rays(mesh, 60_000, seed=seed)
        tmin = np.where(np.arange(len(o)) % 3 == 0, np.float32(0.05), np.float32(0))  # moved and fresh rays
        batches.append((o, d, tmin))
    alone = [acc.trace(o, d, tmin) for o, d, tmin in batches]
    alone_occ = [acc.occluded(o, d, tmin) for o, d, tmin in batches]
    start = threading.Barrier(2)
    got = [[], []]

    def worker(i):
        o, d, tmin = batches[i]
        start.wait()
        for _ in range(3):
            got[i].append((acc.trace(o, d, tmin), acc.occluded(o, d, tmin)))

    workers = [threading.Thread(target=worker, args=(i,)) for i in range(2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    for i in range(2):
        assert len(got[i]) == 3, f"thread {i} did not finish its traces"
        for run, (h, occ) in enumerate(got[i]):
            for f in ("t", "triangle", "u", "v"):
                a, b = getattr(h, f), getattr(alone[i], f)
                bad = np.flatnonzero(~((a == b) | (np.isnan(a) & np.isnan(b))))
                assert bad.size == 0, f"thread {i} run {run}: {f} differs from the lone trace at rays {bad[:5].tolist()}"
            bad = np.flatnonzero(occ != alone_occ[i])
            assert bad.size == 0, f"thread {i} run {run}: occluded differs at rays {bad[:5].tolist()}"


@needs_embree
@pytest.mark.parametrize("threads,chunk_size", [(1, 7000), (2, 7000), (2, 1 << 16)])
def test_chunk_by_chunk_validation_gives_the_whole_batch_paths_hits_and_errors(threads, chunk_size):
    """EmbreeAccel validates each chunk inside its pool task and writes into one output;
    the hits, the occluded flags and the error messages must be those of the base class's
    whole-batch path (prepare_rays on every ray, then chunks, then concatenation)."""
    from hybrid_raycast.core import scenes
    from hybrid_raycast.core.accel import Accel

    mesh = scenes.make_scene("city", 20000, seed=3)
    acc = core.build(mesh, "embree", threads=threads, chunk_size=chunk_size)
    o, d = core.uniform_rays(mesh, 30_000, seed=5)
    n = len(o)
    tmin = np.where(np.arange(n) % 3 == 0, np.float32(0.05), np.float32(0))
    tmax = np.where(np.arange(n) % 5 == 0, np.float32(0.5), np.float32(np.inf))
    cases = {"defaults": (o, d), "tmin": (o, d, tmin), "tmin and tmax": (o, d, tmin, tmax),
             "float64, scalars": (o.astype(np.float64), d.astype(np.float64), 0.01, 3.0),
             "one (3,) ray": (o[0], d[0]), "no rays": (o[:0], d[:0])}
    for name, args in cases.items():
        got, want = acc.trace(*args), Accel.trace(acc, *args)
        for f in ("t", "triangle", "u", "v"):
            a, b = getattr(got, f), getattr(want, f)
            assert a.dtype == b.dtype and a.shape == b.shape, f"{name}: {f} is {a.dtype}{a.shape}, want {b.dtype}{b.shape}"
            bad = np.flatnonzero(a.view(np.uint32) != b.view(np.uint32))
            assert bad.size == 0, f"{name}: {f} differs from the whole-batch path at rays {bad[:5].tolist()}"
        occ, occ_want = acc.occluded(*args), Accel.occluded(acc, *args)
        bad = np.flatnonzero(occ != occ_want)
        assert bad.size == 0, f"{name}: occluded differs from the whole-batch path at rays {bad[:5].tolist()}"
    bad_o = o.copy()
    bad_o[[7, n - 3]] = np.nan  # in the first and the last chunk
    bad_d = d.copy()
    bad_d[n // 2] = 0.0
    for name, args in {"NaN origins": (bad_o, d), "zero direction": (o, bad_d),
                       "tmin > tmax": (o, d, np.where(np.arange(n) == n - 1, 5.0, 0.0), 1.0),
                       "shapes differ": (o, d[:10]), "tmin of the wrong length": (o, d, np.zeros(3))}.items():
        for fn in ("trace", "occluded"):
            with pytest.raises(ValueError) as whole:
                getattr(Accel, fn)(acc, *args)
            with pytest.raises(ValueError) as chunked:
                getattr(acc, fn)(*args)
            assert str(chunked.value) == str(whole.value), f"{name}, {fn}: {chunked.value!r} != {whole.value!r}"


@needs_embree
def test_direct_fill_builds_the_same_structure_as_embreex_copy():
    """The geometry filled through Embree's C API (two numpy copies) and through embreex's
    own element-by-element copy give bit-identical hits, past degenerate triangles too."""
    rng = np.random.default_rng(5)
    tris = rng.uniform(-1, 1, (3000, 3, 3))
    tris[::97, 2] = tris[::97, 1]  # degenerate: Embree's primID must be mapped back
    mesh = core.TriangleMesh(tris.reshape(-1, 3), np.arange(tris.size // 3).reshape(-1, 3))
    direct, copied = core.build(mesh, "embree"), core.build(mesh, "embree", direct_fill=False)
    assert (direct.stats()["fill"], copied.stats()["fill"]) == ("direct", "embreex")
    o, d = core.uniform_rays(mesh, 20000, seed=3)
    a, b = direct.trace(o, d), copied.trace(o, d)
    assert a.hit.mean() > 0.3
    for field in ("t", "triangle", "u", "v"):
        w = np.flatnonzero(getattr(a, field) != getattr(b, field))
        assert w.size == 0, f"{field} differs at {describe_ray(w[0], o, d)}"
    assert np.array_equal(direct.occluded(o, d, 0.0, 0.5), copied.occluded(o, d, 0.0, 0.5))


@needs_embree
def test_direct_fill_refuses_a_scene_it_cannot_vouch_for():
    """The handles are read only from an embreex scene made with the device given, and
    confirmed by Embree; anything else leaves the scene untouched (the build then uses
    embreex's copy)."""
    from embreex import rtcore, rtcore_scene

    from hybrid_raycast.core.embree import _DirectFill

    direct = _DirectFill.get()
    assert direct is not None, f"no usable libembree4 next to embreex ({_DirectFill.library_path()})"
    device, other = rtcore.EmbreeDevice(), rtcore.EmbreeDevice()
    scene = rtcore_scene.EmbreeScene(device)
    assert direct.handles(scene, device) is not None
    tri = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float32)
    for args in ((scene, other), (object(), device), (scene, object())):
        assert direct.handles(*args) is None
        assert direct.fill(*args, tri, np.array([[0, 1, 2]])) is False
    one = np.array([[0.2, 0.2, 0.0]], np.float32)
    assert scene.run(one, np.array([[0, 0, 1]], np.float32))[0] == -1, "a refused fill must write nothing"
    assert direct.fill(scene, device, tri, np.array([[0, 1, 2]])) is True
    assert scene.run(one, np.array([[0, 0, 1]], np.float32))[0] == 0
