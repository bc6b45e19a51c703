"""Threads tracing one chunk together (``Accel.shares_chunks``: the numpy BVH and grid).

Every thread draws rays from one ``RaySupply`` and refills its own lockstep pool from it,
so the hits must be those of one thread, ray for ray, and every ray must be traced once.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from hybrid_raycast import core
from hybrid_raycast.core import accel
from hybrid_raycast.core.accel import RaySupply
from hybrid_raycast.core.scenes import torus_arrays


def _mesh():
    v, t = torus_arrays(48, 24)
    return core.TriangleMesh(v, t)


def _rays(mesh, m, seed):
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds()
    o = rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo), (m, 3))
    return o, rng.normal(size=(m, 3))


def _assert_same(got, want, what):
    for field in ("triangle", "t", "u", "v"):
        a, b = getattr(got, field), getattr(want, field)
        bad = np.flatnonzero(a != b)
        assert not len(bad), (f"{what}: {len(bad)} rays differ in {field}, first ray {bad[0]}: "
                              f"{field} {a[bad[0]]!r} against {b[bad[0]]!r}")


def test_ray_supply_hands_out_every_ray_exactly_once_to_concurrent_takers():
    supply = RaySupply(100_003)
    got = [[] for _ in range(4)]

    def take(out):
        while supply.left:
            s = supply.take(37)
            out.extend(range(s.start, s.stop))

    threads = [threading.Thread(target=take, args=(g,)) for g in got]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    rays = np.sort(np.concatenate([np.asarray(g, np.int64) for g in got]))
    assert np.array_equal(rays, np.arange(100_003)), "some ray was handed out twice or never"
    assert supply.take(5) == slice(100_003, 100_003), "an exhausted supply must hand out nothing"


@pytest.mark.parametrize("kind, config", [("bvh", {"batch": 64}), ("grid", {"pool": 50})])
def test_threads_sharing_a_chunk_give_one_threads_hits_and_occlusion(monkeypatch, kind, config):
    # MIN_SPLIT lowered so that small chunks (about 1,700 rays, pools of 50-64 rays refilled
    # many times) are shared by all three threads
    monkeypatch.setattr(accel, "MIN_SPLIT", 100)
    mesh = _mesh()
    o, d = _rays(mesh, 5000, seed=3)
    one = core.build(mesh, kind, threads=1, **config)
    many = core.build(mesh, kind, threads=3, chunk_size=1700, **config)
    assert many._workers(1700) == 3, "set-up: the chunk is not shared by three threads"
    _assert_same(many.trace(o, d), one.trace(o, d), f"{kind}, 3 threads sharing chunks of 1,700 rays")
    brute = core.build(mesh, "brute")
    _assert_same(one.trace(o, d), brute.trace(o, d), f"{kind}, 1 thread against brute force")
    got, want = many.occluded(o, d, 0.0, 0.6), brute.occluded(o, d, 0.0, 0.6)
    assert 0.1 < want.mean() < 0.9, f"set-up: {want.mean():.2f} of the rays are occluded"
    bad = np.flatnonzero(got != want)
    assert not len(bad), f"{kind}: occluded differs from brute force on {len(bad)} rays, first {bad[:5]}"


def test_bvh_counters_count_every_ray_once_when_threads_share_a_chunk(monkeypatch):
    monkeypatch.setattr(accel, "MIN_SPLIT", 100)
    mesh = _mesh()
    o, d = _rays(mesh, 3000, seed=4)
    bvh = core.build(mesh, "bvh", threads=3, chunk_size=3000, batch=64)
    bvh.trace(o, d)
    taken = [c[0] for c in bvh._counters]
    assert len(taken) == 3 and sum(taken) == 3000, f"rays per thread {taken}: not the 3,000 rays once each"
    assert bvh.stats()["last_rays"] == 3000
