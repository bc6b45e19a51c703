"""core.distributed on a real 2-worker LocalCluster (processes, one thread each).

Properties: the dask arrays hold exactly the hits of a local trace with the same structure;
each worker process builds a structure once, not once per block; kind='auto' decides on the
client and the workers build that kind; a worker killed mid-run costs nothing but time;
a missing or damaged scene file is a clear error before any task runs.
"""

import logging
import os
import sys

import numpy as np
import pytest

da = pytest.importorskip("dask.array", reason="dask is not installed (pip install .[dask])")
distributed = pytest.importorskip("distributed", reason="distributed is not installed (pip install .[dask])")

from _package import importable_by_workers  # noqa: E402

from hybrid_raycast import core  # noqa: E402
from hybrid_raycast.core import distributed as hd  # noqa: E402

COMPUTE_TIMEOUT = 120  # seconds: a hung cluster fails the test instead of the suite


@pytest.fixture(scope="module")
def client():
    """One cluster for the module: starting one costs a few seconds."""
    importable_by_workers()
    import cloudpickle

    # the killed-worker test ships a function of this module; workers cannot import tests/
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.CRITICAL)
    c = distributed.Client(cluster)
    try:
        c.wait_for_workers(2, timeout=60)
        yield c
    finally:
        c.close()
        cluster.close()
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def soup(seed, t=3000, objects=3):
    """Random triangles in a unit box, spread over a few named objects."""
    rng = np.random.default_rng(seed)
    centre = rng.random((t, 1, 3))
    v = (centre + 0.05 * rng.normal(size=(t, 3, 3))).reshape(-1, 3).astype(np.float32)
    return core.TriangleMesh(v, np.arange(3 * t).reshape(t, 3), object_index=rng.integers(0, objects, t),
                             polygon_index=np.arange(t), object_names=[f"obj{i}" for i in range(objects)])


def rays(mesh, m, seed, rows):
    o, d = core.uniform_rays(mesh, m, seed=seed)
    return o, d, da.from_array(o, chunks=(rows, 3)), da.from_array(d, chunks=(rows, 3))


def gather(client, r):
    futures = client.compute([getattr(r, f) for f in hd.FIELDS])
    return {name: f.result(timeout=COMPUTE_TIMEOUT) for name, f in zip(hd.FIELDS, futures)}


def assert_same_as_local(got, mesh, kind, o, d, tmin=0.0, tmax=np.inf):
    ref = core.build(mesh, kind).trace(o, d, tmin, tmax)
    for name in ("t", "triangle", "u", "v"):
        a, b = got[name], getattr(ref, name)
        bad = np.flatnonzero(a != b)
        assert bad.size == 0, f"{kind}: {name} differs from a local trace at {bad.size} rays, first {bad[:5].tolist()}"
    expect = np.where(ref.hit, mesh.object_index[np.maximum(ref.triangle, 0)], -1)
    assert np.array_equal(got["object_index"], expect), f"{kind}: object_index is not the hit triangle's object"
    assert ref.hit.sum() > len(o) // 10, "too few hits for the comparison to mean much"


def stats(client):
    return client.run(hd.worker_stats)


@pytest.mark.parametrize("kind", ["grid", "bvh"])
def test_hits_are_identical_to_a_local_trace_of_the_same_structure(client, tmp_path, kind):
    mesh = soup(1)
    path = core.save_mesh(mesh, tmp_path / "scene.npz")
    o, d, do, dd = rays(mesh, 8_000, 2, 1_000)
    tmin = np.random.default_rng(3).random(len(o)).astype(np.float32) * 0.1
    r = hd.trace(path, do, dd, kind=kind, tmin=tmin, tmax=5.0)
    assert r.kind == kind and r.plan is None
    assert r.t.chunks == do.chunks[:1], "results are chunked like the rays"
    assert_same_as_local(gather(client, r), mesh, kind, o, d, tmin, 5.0)


def test_each_worker_builds_once_not_once_per_block(client, tmp_path):
    client.run(hd.clear_worker_cache)
    mesh = soup(4)
    path = core.save_mesh(mesh, tmp_path / "once.npz")
    o, d, do, dd = rays(mesh, 8_000, 5, 500)  # 16 blocks over 2 workers
    r = hd.trace(path, do, dd, kind="bvh")
    got = gather(client, r)
    again = gather(client, hd.trace(path, do, dd, kind="bvh"))  # a second trace reuses the structures
    assert all(np.array_equal(got[f], again[f]) for f in hd.FIELDS)
    label = f"{r.scene.label()}:bvh"
    seen = stats(client)
    blocks = {w: s["blocks"].get(label, 0) for w, s in seen.items()}
    builds = {w: s["builds"].get(label, 0) for w, s in seen.items()}
    assert sum(blocks.values()) == 2 * 16, f"every block traced once per trace: {blocks}"
    assert all(builds[w] == 1 for w in seen if blocks[w]), f"one build per worker that traced: builds {builds}, blocks {blocks}"
    assert max(blocks.values()) > 1, f"some worker traced several blocks with its one structure: {blocks}"
    for w, s in seen.items():
        if blocks[w]:
            wall, cpu = s["trace_s"][label], s["trace_cpu_s"][label]
            assert s["build_s"][label] > 0 and 0 < cpu <= wall * 1.05 + 0.01, f"one thread's CPU within its wall time: {s}"


def test_auto_decides_once_on_the_client_and_workers_build_that_kind(client, tmp_path):
    mesh = soup(6)
    path = core.save_mesh(mesh, tmp_path / "auto.npz")
    o, d, do, dd = rays(mesh, 6_000, 7, 1_500)
    cal, _ = core.load_or_default(None)
    r = hd.trace(path, do, dd, kind="auto", calibration=cal)
    assert r.plan is not None and r.plan.expected_rays == len(o), "the whole array's length is the ray budget"
    assert r.kind == r.plan.chosen
    got = gather(client, r)
    built = {k for s in stats(client).values() for k in s["builds"] if k.startswith(r.scene.label())}
    assert built == {f"{r.scene.label()}:{r.kind}"}, f"workers built {built}, the plan chose {r.kind}"
    assert_same_as_local(got, mesh, r.kind, o, d)
    few = hd.trace(path, do, dd, kind="auto", expected_rays=10)
    assert few.plan.expected_rays == 10 and few.kind != "bvh", "ten rays never pay for a numpy BVH"
    assert few.kind == "grid" or not few.plan.grid_built, "Embree for ten rays only where it builds faster"
    none = hd.trace(path, do[:0], dd[:0])
    assert none.kind == "grid" and none.plan is None and gather(client, none)["t"].shape == (0,)


def test_trace_frames_traces_each_frame_in_its_own_scene(client, tmp_path):
    meshes = [soup(10 + i, t=1500) for i in range(3)]
    paths = [core.save_mesh(m, tmp_path / f"frame_{i:04d}.npz", frame=i) for i, m in enumerate(meshes)]
    batches = [rays(m, 3_000 + 500 * i, 20 + i, 1_000) for i, m in enumerate(meshes)]
    results = hd.trace_frames(paths, [b[2] for b in batches], [b[3] for b in batches], kind="grid")
    assert len(results) == 3
    for mesh, (o, d, _, _), r in zip(meshes, batches, results):
        got = r.compute()  # DistributedHits.compute: all five arrays through the default client
        assert_same_as_local(got, mesh, "grid", o, d)
        assert np.array_equal(r.hit.compute(), got["triangle"] >= 0)
    auto = hd.trace_frames(paths, [b[2] for b in batches], [b[3] for b in batches])
    assert auto[0].plan.expected_rays == 3_000 and len({r.kind for r in auto}) == 1, "one decision for every frame"


def _die_once(block, marker, victim, block_info=None):
    """Kill this worker process the first time block ``victim`` is computed."""
    if block_info[0]["chunk-location"][0] == victim and not os.path.exists(marker):
        open(marker, "w").close()
        os._exit(1)
    return block


def test_a_worker_killed_mid_run_is_recomputed_and_the_result_is_complete(client, tmp_path):
    mesh = soup(30)
    path = core.save_mesh(mesh, tmp_path / "kill.npz")
    o, d, do, dd = rays(mesh, 6_000, 31, 500)  # 12 blocks; the worker dies on block 9
    marker = tmp_path / "killed"
    before = set(client.scheduler_info()["workers"])
    doomed = do.map_blocks(_die_once, marker=str(marker), victim=9, dtype=do.dtype)
    got = gather(client, hd.trace(path, doomed, dd, kind="bvh"))
    assert marker.exists(), "the worker was not killed: the test proved nothing"
    assert_same_as_local(got, mesh, "bvh", o, d)
    client.wait_for_workers(2, timeout=60)
    after = set(client.scheduler_info()["workers"])
    assert before - after, "a worker process died, so one address must have been replaced by the nanny's restart"


def test_missing_or_damaged_scene_file_fails_on_the_client_naming_it(client, tmp_path):
    mesh = soup(40, t=100)
    _, _, do, dd = rays(mesh, 1_000, 41, 500)
    with pytest.raises(FileNotFoundError, match="absent.npz"):
        hd.trace(tmp_path / "absent.npz", do, dd, kind="grid")
    (tmp_path / "junk.npz").write_bytes(b"not a scene")
    with pytest.raises(core.SceneFileError, match="junk.npz"):
        hd.trace(tmp_path / "junk.npz", do, dd, kind="bvh")
    good = core.save_mesh(mesh, tmp_path / "good.npz")
    with pytest.raises(FileNotFoundError, match="frame_0002.npz"):
        hd.trace_frames([good, tmp_path / "frame_0002.npz"], [do, do], [dd, dd], kind="grid")


def test_a_scene_file_changed_after_trace_is_refused_by_the_workers(client, tmp_path):
    path = core.save_mesh(soup(50, t=200), tmp_path / "moving.npz")
    _, _, do, dd = rays(soup(50, t=200), 2_000, 51, 1_000)
    r = hd.trace(path, do, dd, kind="grid")
    core.save_mesh(soup(51, t=200), path)  # another scene under the same name
    with pytest.raises(core.SceneFileError, match="moving.npz: the file changed"):
        gather(client, r)


def test_bad_arguments_are_clear_errors(tmp_path):
    path = core.save_mesh(soup(60, t=10), tmp_path / "s.npz")
    o = da.zeros((10, 3), chunks=(5, 3))
    with pytest.raises(TypeError, match="origins must be a dask array"):
        hd.trace(path, np.zeros((10, 3)), o)
    with pytest.raises(ValueError, match=r"directions must have shape \(M, 3\)"):
        hd.trace(path, o, da.zeros((10, 2), chunks=(5, 2)))
    with pytest.raises(ValueError, match="kind must be"):
        hd.trace(path, o, o, kind="octree")
    with pytest.raises(ValueError, match=r"tmin must be a scalar or have shape \(10,\)"):
        hd.trace(path, o, o, kind="grid", tmin=np.zeros(3))
    with pytest.raises(ValueError, match="one entry per frame"):
        hd.trace_frames([path, path], [o], [o])


def test_without_dask_the_error_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "dask.array", None)
    with pytest.raises(ImportError, match=r"pip install 'hybrid_raycast\[dask\]'"):
        hd.trace(tmp_path / "s.npz", None, None)


@pytest.mark.parametrize("kind", ["bvh", "grid"])
def test_closest_on_the_cluster_equals_a_local_search(client, tmp_path, kind):
    mesh = soup(11)
    path = core.save_mesh(mesh, tmp_path / "near.npz")
    pts = np.random.default_rng(3).uniform(-0.2, 1.2, size=(5000, 3))
    got = hd.closest(path, da.from_array(pts, chunks=(1250, 3)), kind=kind, max_distance=0.3).compute(
        timeout=COMPUTE_TIMEOUT)
    want = core.build(mesh, kind).closest(pts, max_distance=0.3)
    assert np.array_equal(got["triangle"], want.triangle) and np.array_equal(got["distance"], want.distance)
    assert np.array_equal(got["points"], want.points, equal_nan=True)
    assert (~want.found).any() and want.found.any(), "some points are past max_distance, some not"
    found = want.found
    assert np.array_equal(got["object_index"][found], mesh.object_index[want.triangle[found]])
    assert (got["object_index"][~found] == -1).all()


def test_closest_refuses_bad_arguments_before_any_task(tmp_path):
    path = core.save_mesh(soup(12, t=50), tmp_path / "s.npz")
    pts = da.zeros((10, 3), chunks=(5, 3))
    with pytest.raises(ValueError, match="max_distance must be positive"):
        hd.closest(path, pts, max_distance=0)
    with pytest.raises(ValueError, match="kind must be one of"):
        hd.closest(path, pts, kind="octree")
    with pytest.raises(TypeError, match="points must be a dask array"):
        hd.closest(path, np.zeros((10, 3)))
    with pytest.raises(FileNotFoundError):
        hd.closest(tmp_path / "missing.npz", pts)



# -- instanced scene files (version 2): bottoms per mesh digest, reused across frames ------------

def blob(rng, t):
    """Random triangles around the origin (object space), about one unit across."""
    centre = rng.uniform(-0.5, 0.5, (t, 1, 3))
    return core.TriangleMesh((centre + 0.08 * rng.normal(size=(t, 3, 3))).reshape(-1, 3).astype(np.float32),
                             np.arange(3 * t).reshape(t, 3), polygon_index=np.arange(t))


def placements(rng, which):
    """Row-major 4x4 matrices (rounded to float32, as Blender's), instance 1 mirrored."""
    mats = np.tile(np.eye(4), (len(which), 1, 1))
    for i in range(len(which)):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        scale = np.array([-1.2 if i == 1 else 1.0 + 0.2 * i, 0.8, 1.1])
        mats[i, :3, :3] = q * np.abs(np.linalg.det(q)) @ np.diag(scale)
        mats[i, :3, 3] = rng.uniform(0, 1.5, 3)
    return mats.astype(np.float32).astype(np.float64)


def instanced_frames(tmp_path, seed=70):
    """Frame 1, and frame 2 with instance 3 moved: two meshes placed six times, saved as
    version-2 files; (paths, flat meshes)."""
    rng = np.random.default_rng(seed)
    meshes = [blob(rng, 300), blob(rng, 200)]
    which = np.array([0, 0, 1, 1, 0, 1])
    objects = np.array([0, 1, 2, 2, 0, 1])
    first = placements(rng, which)
    second = first.copy()
    second[3, :3, 3] += (0.6, -0.3, 0.2)
    paths = [core.meshio.save_scene(tmp_path / f"frame_{f:04d}.npz", meshes, which, m, objects, ["a", "b", "c"], frame=f)
             for f, m in ((1, first), (2, second))]
    return paths, [core.load_mesh(p) for p in paths]


def assert_close_to_flat(got, flat, o, d, what):
    """As a float64 brute-force trace of the flat mesh: hit/miss and the global triangle, but
    for near-ties (a ray through an edge); t within float32 rounding of the scene's scale."""
    ref = core.build(flat, "brute").trace(o, d)
    tri, t = got["triangle"], got["t"]
    scale = float(np.abs(flat.vertices).max())
    hit = tri >= 0
    flips = np.flatnonzero(hit != ref.hit)
    assert flips.size <= max(2, len(o) // 500), f"{what}: hit/miss differs at {flips.size} rays, first {flips[:5].tolist()}"
    both = hit & ref.hit
    other = np.flatnonzero(both & (tri != ref.triangle))
    assert np.allclose(t[other], ref.t[other], rtol=0, atol=1e-4 * scale), \
        f"{what}: another triangle at {other.size} rays, not all near-ties, first {other[:5].tolist()}"
    same = both & (tri == ref.triangle)
    assert other.size <= max(2, len(o) // 500) and same.sum() > len(o) // 8, f"{what}: {same.sum()} same hits of {len(o)}"
    assert np.allclose(t[same], ref.t[same], rtol=1e-5, atol=1e-5 * scale), f"{what}: t differs beyond float32 rounding"
    for name in ("u", "v"):
        assert np.allclose(got[name][same], getattr(ref, name)[same], atol=1e-3), f"{what}: {name} differs"
    assert np.array_equal(got["object_index"][hit], flat.object_index[tri[hit]]) and (got["object_index"][~hit] == -1).all()


def test_instanced_frames_on_the_cluster_equal_flat_traces_and_build_each_bottom_once_per_worker(client, tmp_path):
    client.run(hd.clear_worker_cache)
    paths, flats = instanced_frames(tmp_path)
    o, d = core.uniform_rays(flats[0], 4_000, seed=71)
    do, dd = da.from_array(o, chunks=(1_000, 3)), da.from_array(d, chunks=(1_000, 3))
    results = hd.trace_frames(paths, [do, do], [dd, dd], kind="bvh")
    got = [gather(client, r) for r in results]
    for i, (g, flat) in enumerate(zip(got, flats)):
        assert_close_to_flat(g, flat, o, d, f"frame {i + 1}")
    assert not np.array_equal(got[0]["triangle"], got[1]["triangle"]), "the move must change some hits"
    for w, s in stats(client).items():
        built = sum(s["bottom_builds"].get(f"{r.scene.label()}:bvh", 0) for r in results)
        tops = sum(s["builds"].get(f"{r.scene.label()}:bvh", 0) for r in results)
        reused = sum(s["bottom_reuses"].get(f"{r.scene.label()}:bvh", 0) for r in results)
        assert built <= 2, f"worker {w} built {built} bottoms for 2 unique meshes over 2 frames: {s}"
        assert built + reused == 2 * tops, f"worker {w}: every top level takes its 2 bottoms: {s}"


def test_a_later_frame_with_unchanged_meshes_builds_no_bottom(tmp_path):
    """In this process (the synchronous scheduler), so the counters are certain."""
    hd.clear_worker_cache()
    paths, flats = instanced_frames(tmp_path, seed=72)
    o, d = core.uniform_rays(flats[0], 2_000, seed=73)
    do, dd = da.from_array(o, chunks=(500, 3)), da.from_array(d, chunks=(500, 3))
    labels = []
    for path, flat in zip(paths, flats):
        r = hd.trace(path, do, dd, kind="bvh")
        assert_close_to_flat(r.compute(scheduler="synchronous"), flat, o, d, path.name)
        labels.append(f"{r.scene.label()}:bvh")
    s = hd.worker_stats()
    assert s["bottom_builds"].get(labels[0]) == 2 and labels[0] not in s["bottom_reuses"], s
    assert labels[1] not in s["bottom_builds"] and s["bottom_reuses"].get(labels[1]) == 2, \
        f"frame 2 moved an instance only: its top level alone is built: {s}"
    assert s["builds"][labels[1]] == 1 and len(s["bottoms_cached"]) == 2, s
    # a mesh whose content changes gets a new bottom; the other is still reused
    f2 = core.read_scene(paths[1]).instances
    changed = [f2.meshes[0], core.TriangleMesh(f2.meshes[1].vertices * np.float32(1.1), f2.meshes[1].triangles,
                                               polygon_index=f2.meshes[1].polygon_index)]
    p3 = core.meshio.save_scene(tmp_path / "frame_0003.npz", changed, f2.instance_mesh, f2.matrices,
                                f2.instance_object, f2.object_names, frame=3)
    r = hd.trace(p3, do, dd, kind="bvh")
    assert_close_to_flat(r.compute(scheduler="synchronous"), core.load_mesh(p3), o, d, p3.name)
    s = hd.worker_stats()
    label = f"{r.scene.label()}:bvh"
    assert s["bottom_builds"].get(label) == 1 and s["bottom_reuses"].get(label) == 1, s
    # point queries on an instanced file search the flat mesh
    pts = np.random.default_rng(74).uniform(0, 3, (500, 3))
    near = hd.closest(paths[0], da.from_array(pts, chunks=(250, 3))).compute(scheduler="synchronous")
    want = core.build(flats[0], "bvh").closest(pts)
    assert np.array_equal(near["triangle"], want.triangle) and np.array_equal(near["distance"], want.distance)
    hd.clear_worker_cache()
