"""Measuring: timing a structure as a caller would, the calibration run, and the true
break-even of the paper's evaluation.

Timings: ``time.perf_counter`` around builds and traces, each batch traced as ``trace``
runs it (``time_trace``).  The default 1,048,576 rays per scene (one chunk) fill both threads of
every structure, so the per-ray constants are a large workload's (see ``RAYS_PER_SCENE``).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

from ..accel import LOCKSTEP_CHUNK, Accel
from ..factory import build
from ..mesh import TriangleMesh
from .calfile import Calibration
from .work import Work, grid_work, traversal_counts
from .cost import DEFAULT_MODEL, DEFAULT_SPREAD, Measurement, SceneRecord, break_even, fit, fit_counts, nlog2n

#: rays per scene for each calibration scale.  A structure's time per ray falls with the
#: batch's size: lockstep traversal ends in steps over the rays still in flight when the
#: batch runs out (two threads' pools of them), a cost the same for any batch.  Measured on
#: 2026-12-02 (3 interleaved repeats, 2 threads; sphere and city at 200k triangles, the
#: Stanford bunny): 524,288 rays cost 1.06-1.13x per ray what 1M rays do for the grid,
#: 0.95-1.13x for the BVH, and the held-out report, whose truths trace 1M rays, found the
#: calibration's grid and BVH times per ray +9-10% high (median) when it measured 524,288.
#: The default measures one full chunk of the lockstep tracers (``LOCKSTEP_CHUNK``, also
#: api.CHUNK), so the constants are a large workload's, the ones a break-even of 10^5-10^6
#: rays is about
RAYS_PER_SCENE = {"tiny": 2000, "quick": 20000, "default": LOCKSTEP_CHUNK, "rich": LOCKSTEP_CHUNK}
#: sample sizes K at which calibration times the grid on each scene, to correct a plan's
#: K-ray sample for the fixed per-batch cost of lockstep traversal (see grid_sample_ratio)
SAMPLE_LADDER = (1024, 2048, 4096, 8192, 16384, 32768, 65536)
#: the least number of rays the grid's large-workload time per ray is measured on when
#: samples are timed (whatever the scale's rays per scene): the default scale's batch
GRID_LARGE_RAYS = LOCKSTEP_CHUNK
#: passes of a calibration over all its scenes, each pass building and tracing every
#: structure of every scene once (interleaved); a record keeps its scene's medians (on this
#: 2-core VM one trace moves by 20-40% between runs).  With 3 repeats back to back, two
#: calibrations in a row stated the grid's time per ray at 40 cells 16-19% apart and the
#: BVH's build at 1M triangles 12% apart; with 5 back to back, the BVH's time per ray at
#: 1,024 triangles 15%; with 5 passes, every constant within 6.7% (median 1.7%; the
#: report's repeatability row, issue 14)
CALIBRATION_REPEATS = 5
#: the part of a calibration's progress bar for generating the scenes and timing the grid's
#: samples, before the passes of builds and traces (about that share of its time)
SETUP_SHARE = 0.1
#: what each calibration scale measures and costs, for the add-on's settings, its Calibrate
#: operator and the CLI (one text for all three); the full set's minutes are measured on
#: this project's 2-core reference machine (``scripts/ship_calibration.py`` prints its duration;
#: 'tiny' took 128 s and 'quick' 157 s there, each with SMALL_BUILDS builds of its small scenes)
FULL_CALIBRATION_MINUTES = 11
SCALE_NOTES = {
    "tiny": "About 2 minutes on 2 cores: 8 scenes of 500-1,000 triangles; rough constants (for tests)",
    "quick": "About 3 minutes on 2 cores: 8 scenes, so constants can differ between runs",
    "default": (f"About {FULL_CALIBRATION_MINUTES} minutes on 2 cores: 20 scenes, {RAYS_PER_SCENE['default']:,} rays "
                f"each, {CALIBRATION_REPEATS} passes over them; the constants the add-on ships"),
}
#: sample rays on which calibration counts the grid's per-ray work, as a plan does on its K
#: (``work.DEFAULT_SAMPLES``): the counts are means over the rays, the same for any K but
#: for their noise
WORK_SAMPLES = 16384


# -- measuring ---------------------------------------------------------------------------------

def time_trace(accel: Accel, origins, directions, tmin=0.0, tmax=np.inf):
    """Trace and time a batch as a caller would: (Hits, seconds).

    The batch runs exactly as ``accel.trace`` runs it (its chunks, its threads).  Splitting
    a small batch over the threads does not make it cost what a large workload does: with
    a few thousand rays per thread the numpy calls of the two threads contend for the GIL
    and the time per ray doubled (measured on the real meshes at K = 16,384).  A plan
    corrects its small sample with ``Calibration.grid_sample_ratio`` instead.
    """
    t0 = time.perf_counter()
    hits = accel.trace(origins, directions, tmin, tmax)
    return hits, time.perf_counter() - t0


def measure(mesh: TriangleMesh, kind: str, origins, directions, *, threads=None, config=None,
            builds: int | None = None) -> Measurement:
    """Build ``kind`` over ``mesh`` and trace the rays through it: one Measurement.

    A plan's structure is built once, and builds repeated back to back are not like it:
    they reuse the memory the previous one freed, and a median of up to nine of them put a
    20k-triangle scene's numpy BVH build at 34-38 ms where single builds took 48-68 ms
    (issue 14; the held-out break-even error rose from 12-14% to 23% with it).  So a large
    scene's build is timed once.  A small scene's (``builds_per_measurement``) is timed
    several times, each build after its own ``settle_before_build``, which makes the later
    ones like the first (sphere-20k's numpy BVH 31.3-31.8 ms and Embree 3.3-3.5 ms by
    position, ``scripts/small_build_study.py --order``), and the median one is kept.
    ``builds`` overrides that count (1 where only the trace is wanted)."""
    return _measure(mesh, kind, origins, directions, threads, config, builds)[0]


#: scenes of at most this many triangles (``cost.N_REF``) have each measured build of a
#: fitted structure timed ``SMALL_BUILDS`` times, each after its own ``settle_before_build``,
#: and the median kept.  Their builds take 0.5-15 ms (Embree) and 4-120 ms (numpy BVH), and on
#: this VM the CPU time of one such build moves by up to 1.8x with the host's load: one
#: calibration's five passes put sphere-20k's Embree build at 3.8-7.4 ms and sphere-500's at
#: 1.2-2.8 ms.  Over 25 settled builds of each small calibration scene, the median of 5
#: builds varied by 11-36% (Embree) and 7-15% (BVH), p10-p90 over resamples, the median of 25
#: by 4-20% and 2-9%; two calibrations in a row stated Embree's build at 1,024 triangles
#: 16.1% (report R) and 24.2% apart, and at 16,384 15.0% (issue 14).  Settling costs ~0.16 s
#: a build; larger scenes' builds, 20 ms to 1.3 s, spread far less and keep one
SMALL_SCENE = 65_536
SMALL_BUILDS = 5


def builds_per_measurement(triangles: int, kind: str) -> int:
    """How many timed builds one measurement of ``kind`` on a ``triangles``-triangle scene
    takes: ``SMALL_BUILDS`` for a small scene's fitted structure, else one.  The grid's
    build is timed once: no constant is fitted to it (a plan times its own grid)."""
    return SMALL_BUILDS if triangles <= SMALL_SCENE and kind != "grid" else 1


def _measure(mesh, kind, origins, directions, threads, config, builds=None) -> tuple[Measurement, Accel]:
    """``measure``, and the structure it built (the last, when it built several)."""
    cfg = dict(config or {})
    if threads is not None:
        cfg.setdefault("threads", threads)
    timed, accel = [], None
    for _ in range(max(1, int(builds or builds_per_measurement(mesh.triangle_count, kind)))):
        accel = None  # the previous build's memory goes before the next one settles
        settle_before_build(mesh.triangle_count)
        k0 = _kernel_usage()
        accel = build(mesh, kind, **cfg)
        k1 = _kernel_usage()
        timed.append((float(accel.build_time), k0, k1))
    # the median build (an odd count's middle one) with its own kernel figures
    build_time, k0, k1 = sorted(timed, key=lambda t: t[0])[len(timed) // 2]
    _, dt = time_trace(accel, origins, directions)
    faults, system, cpu = (None, None, None) if k0 is None else (k1[0] - k0[0], k1[1] - k0[1], k1[2] - k0[2])
    return Measurement(build_time, float(dt), int(len(origins)), int(accel.threads), faults, system, cpu), accel


#: seconds the process rests between the page warming and each timed build, so that every
#: build starts as a user's does (after an Analyze click, a script's first ``api.cast``),
#: never in the fast state of a build that follows other work within a few ms.  Embree
#: builds over all hardware threads, and its small builds ran 1.7-2x faster back to back
#: than after a rest; the calibration and the truths met both states at random (BENCHMARKS.md,
#: "Embree's small builds after a rest"; scripts/build_rest_study.py).  Well below the
#: seconds after which the VM's host takes freed memory back, so the warming still holds.
IDLE_BEFORE_BUILD = 0.05


#: seconds the main thread spins on one core right after the rest, just before each timed
#: build, so that every build follows the same work whatever ran before it.  On a VM that packs
#: its vCPUs (this project's Firecracker kernel, ``sched_vcpu_pack``), Embree's build ran on
#: about one thread after a two-thread trace, even after the rest, and on two after one-thread
#: work or nothing: homer, rocker-arm and stanford-bunny's builds 3-12 of 12 on one thread
#: after a trace, 0-4 otherwise, 1.4-1.9x slower on one.  The calibration and the truths met
#: both at random (the jobs' order rotates by pass).  After 100 ms of spinning: 0 of 12 on one
#: thread after any of five kinds of work, each mesh's medians within 4% of each other; 20 ms
#: was not enough (homer and rocker-arm 11-12 of 12 on one thread after a trace).  Every build
#: is then timed in the two-thread state, the one a machine that does not pack its vCPUs
#: should always give (not measured: there is no such machine here); on this VM a plan's own
#: build right after its sample trace still ran on one thread for homer 7-10 of 12 times,
#: rocker-arm 4-7, stanford-bunny 0 (BENCHMARKS.md, "Every timed build after the same work";
#: ``scripts/build_rest_study.py --before`` and ``--plan``).
BUSY_BEFORE_BUILD = 0.1


def spin(seconds: float) -> None:
    """Keep this thread busy for ``seconds`` (no sleeping, no other thread)."""
    t = time.perf_counter()
    while time.perf_counter() - t < seconds:
        pass


def settle_before_build(triangles: int) -> None:
    """What comes right before every timed build: the scene's share of memory written
    (``warm_pages``), the rest (``IDLE_BEFORE_BUILD``), then one thread busy
    (``BUSY_BEFORE_BUILD``)."""
    warm_pages(warm_bytes(triangles))
    time.sleep(IDLE_BEFORE_BUILD)
    spin(BUSY_BEFORE_BUILD)


#: memory written just before each timed build (``warm_pages``), per triangle and at least /
#: at most: above the largest build's fresh pages (the numpy BVH's peak is ~310 bytes a
#: triangle at 1M triangles; Embree's first build at 1M took 156 huge pages, ~310 MB)
WARM_BYTES_PER_TRIANGLE = 512
WARM_MIN_BYTES = 16 << 20
WARM_MAX_BYTES = 1 << 30


def warm_bytes(triangles: int) -> int:
    """How much memory ``_measure`` writes before building over ``triangles``: 512 bytes a
    triangle, 16 MiB to 1 GiB, and at most an eighth of the memory free now."""
    n = min(WARM_MAX_BYTES, max(WARM_MIN_BYTES, WARM_BYTES_PER_TRIANGLE * int(triangles)))
    try:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return n
    return int(max(0, min(n, free // 8)))


def warm_pages(nbytes: int) -> None:
    """Write one byte in every 4 KiB of ``nbytes`` of fresh memory and free it, so a build
    right after takes pages the machine has just used.

    On a virtual machine whose host takes back the memory its guest leaves free (the
    balloon's free page reporting, on this project's Firecracker VM), memory a process
    freed and left idle for a couple of seconds is handed back to the host, and the next
    process to touch it waits for the host to supply every page again.  Measured here,
    writing 512 MB after an idle gap: 36-73 ms after idling 0-1 s, 1.2-1.5 s after 3-10 s,
    all of it system time.  So a build's time depended on
    how long the machine had rested before it, not on the scene: two calibrations in a row
    gave the numpy BVH's build at 1M triangles 1,254 and 901 ms (the first's system time
    341 ms, the second's 0) and Embree's 165 and 373 ms (system 20 and 253 ms).  With the
    pages written just before it, the BVH build at 1M triangles took 53-74 ms of system
    time where it took 175-373 ms without, and Embree's 11-18 ms where it took 33-185 ms
    after an idle gap.  The pages the kernel hands out next are the ones freed last, so the
    build gets memory that is already backed; on a machine without such a host it costs
    the pages' zeroing, ~40 ms for the 512 MB of a 1M-triangle scene, and changes nothing
    else (BENCHMARKS.md, twelfth session).
    """
    n = int(nbytes)
    if n <= 0:
        return
    a = np.empty(n, dtype=np.uint8)
    a[::4096] = 1
    del a


#: a build whose CPU seconds over its wall seconds (``Measurement.build_parallelism``) are
#: below this kept about one thread busy.  Embree builds on every hardware thread; on this
#: project's 2-vCPU VM a build after a rest ran on about one (1.0-1.2) or on two (1.8-1.9),
#: and little in between (BENCHMARKS.md, "Embree's builds on one thread or two")
ONE_THREAD = 1.3


def _kernel_usage() -> tuple[int, float, float] | None:
    """(minor page faults, system CPU seconds, user + system CPU seconds) of this process so
    far, all its threads (None where there is no ``resource`` module: Windows)."""
    try:
        import resource
    except ImportError:
        return None
    r = resource.getrusage(resource.RUSAGE_SELF)
    return int(r.ru_minflt), float(r.ru_stime), float(r.ru_utime + r.ru_stime)


def unavailable_reason(kind: str) -> str | None:
    """Why ``kind`` cannot be built here (one line), or None when it can."""
    from .. import embree

    if kind == "embree" and not embree.embree_available():
        why = getattr(embree, "embree_unavailable_reason", None)
        return (why() if why is not None else None) or "embreex is not installed"
    return None


def available_kinds(kinds) -> tuple[tuple[str, ...], list[str]]:
    """The kinds that can be built here, and a note for each one that cannot."""
    keep, notes = [], []
    for k in kinds:
        why = unavailable_reason(k)
        if why:
            notes.append(f"{k} skipped: {why}")
        else:
            keep.append(k)
    return tuple(keep), notes


def prepare_mesh(mesh: TriangleMesh):
    """Compute the mesh's cached arrays before timing, so no structure pays for them."""
    mesh.tri_vertices
    mesh.valid


def warm_up(kinds, *, threads=None, configs=None):
    """Build and trace each kind once on a tiny scene, untimed: the first build of a kind
    in a process pays one-off costs (Embree starts its threads, ~10 ms measured here)."""
    from ..rays import uniform_rays
    from ..scenes import sphere

    warm = sphere(80)
    prepare_mesh(warm)
    o, d = uniform_rays(warm, 64, seed=0)
    for kind in kinds:
        measure(warm, kind, o, d, threads=threads, config=(configs or {}).get(kind), builds=1)


#: a round of measurements is taken again when other processes used more than this share
#: of the machine's CPU time while it ran (``OthersShare``).  On this 2-core VM two
#: calibrations in a row, with other work at the lowest priority running beside them part
#: of the time, gave builds a median 13% and times per ray 11% apart (issue 14): the lowest
#: priority alone does not keep a measurement clean, as the others still run in the cores'
#: idle moments.  With nothing else running the share stays below 1%
QUIET_SHARE = 0.10
#: how a calibration's note that its measurements stayed disturbed ends (``quiet_notes``)
BUSY_ADVICE = "calibrate again on a quiet machine"
#: how many times a disturbed round is taken again before the least disturbed one is kept
#: (a calibration on a machine that stays busy takes up to 1 + this times as long)
QUIET_RETRIES = 2


def _cpu_times() -> tuple[float, float] | None:
    """(busy, total) CPU seconds of the whole machine since boot, from /proc/stat (None
    where there is none): busy counts steal (time the hypervisor gave to other machines)."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            v = [int(x) for x in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    if len(v) < 8:
        return None
    hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    total = sum(v)  # user nice system idle iowait irq softirq steal
    return (total - v[3] - v[4]) / hz, total / hz


class OthersShare:
    """The share of the machine's CPU time that other processes (and the hypervisor's
    other guests) took while the ``with`` block ran: machine busy time minus this
    process's, over the block's wall time times the cores.  ``share`` is None where the
    machine's counters cannot be read (not Linux) or the block was too short to resolve
    (the counters tick every 10 ms)."""

    MIN_WALL = 0.2  # seconds: below this a tick's rounding is more than a few % of the figure

    def __enter__(self):
        self._m0, self._p0, self._w0 = _cpu_times(), _process_seconds(), time.perf_counter()
        self.share = None
        return self

    def __exit__(self, *exc):
        wall = time.perf_counter() - self._w0
        m1 = _cpu_times()
        if self._m0 is None or m1 is None or wall < self.MIN_WALL:
            return False
        others = (m1[0] - self._m0[0]) - (_process_seconds() - self._p0)
        # the counters tick every 10 ms, so each end rounds: clip to what a share can be
        self.share = min(1.0, max(0.0, others / (wall * (os.cpu_count() or 1))))
        return False


def _process_seconds() -> float:
    t = os.times()
    return t.user + t.system


def interleaved(jobs: dict, repeats: int, *, quiet: float | None = None, retries: int = QUIET_RETRIES,
                shares: list | None = None, first_round: int = 0) -> dict[str, list]:
    """Run every job ``repeats`` times, interleaved (round r runs the jobs in an order
    rotated by ``first_round`` + r), and return each job's results in run order.

    On a shared machine the time of one run drifts by 20-40% from second to second;
    interleaving spreads that drift over every job alike, so the medians of the runs
    compare fairly and their spread says how repeatable each figure is.

    quiet: a share of the machine (``OthersShare``); a round during which other processes
    took more is run again, up to ``retries`` times, and the least disturbed take is kept.
    shares: a list that receives (share of the round kept, takes) per round (share None
    where it could not be read)."""
    names = list(jobs)
    out = {k: [] for k in names}
    for r in range(first_round, first_round + max(1, int(repeats))):
        order = [names[(i + r) % len(names)] for i in range(len(names))]
        best, takes = None, 0
        for takes in range(1, 2 + (max(0, int(retries)) if quiet is not None else 0)):
            with OthersShare() as busy:
                got = {k: jobs[k]() for k in order}
            if best is None or (busy.share is not None and (best[0] is None or busy.share < best[0])):
                best = (busy.share, got)
            if quiet is None or busy.share is None or busy.share <= quiet:
                break
        for k in names:
            out[k].append(best[1][k])
        if shares is not None:
            shares.append((best[0], takes))
    return out


def in_passes(scene_jobs, passes: int, *, quiet: float | None = None, shares: list | None = None) -> list[dict]:
    """Run every scene's jobs ``passes`` times as passes over all the scenes: pass r runs
    each scene's jobs once, interleaved (``interleaved``, its order rotated by r), before
    the next pass starts.  On this 2-core VM the machine's speed drifts over minutes (a
    scene measured in one slow minute had every build and trace of it slow); in passes, each
    scene's medians span the whole run, so the calibration and the evaluation's truths, both
    measured this way, see the same drift.

    scene_jobs: one callable per scene, ``make(r)`` -> that scene's {name: job} for pass r
    (made per pass, so what a pass needs, such as its rays, is freed after it).
    quiet: ``interleaved``'s, for every round.  shares: one list per scene, each receiving
    its rounds' (share, takes) (``interleaved``).
    Returns one {name: [result of each pass]} per scene."""
    runs = [{} for _ in scene_jobs]
    for r in range(max(1, int(passes))):
        for i, make in enumerate(scene_jobs):
            got = interleaved(make(r), 1, quiet=quiet, shares=None if shares is None else shares[i], first_round=r)
            for k, v in got.items():
                runs[i].setdefault(k, []).extend(v)
    return runs


@dataclass
class BreakEven:
    """Measured break-even of each hierarchical structure against the grid on one scene.

    ``R_C[k] = T_B^k / (t_G - t_k)`` with measured times (inf where t_G <= t_k), the same
    formula as the estimate (the grid's build is sunk), so the two compare directly.
    measurements: each structure's median build time and median trace time over the
    interleaved repeats; R_C_repeats: R_C of each repeat on its own, whose spread is the
    measurement's own repeatability (``repeatability``).
    """

    triangles: int
    rays: int
    measurements: dict[str, Measurement]
    R_C: dict[str, float]
    repeats: int = 1
    R_C_repeats: dict[str, list] = field(default_factory=dict)
    #: every repeat's Measurement per kind
    runs: dict[str, list] = field(default_factory=dict)
    #: the last structure built of each kind (not serialised), for callers that go on using it
    structures: dict = field(default_factory=dict, repr=False)
    #: what the measurement noticed (rounds taken again while other processes were busy)
    notes: list = field(default_factory=list)

    def repeatability(self, kind: str) -> float:
        """(max - min) / median of the repeats' R_C, in percent (NaN with fewer than two
        finite repeats): how far the truth itself moves between runs."""
        v = [x for x in self.R_C_repeats.get(kind, []) if math.isfinite(x)]
        if len(v) < 2:
            return math.nan
        return 100.0 * (max(v) - min(v)) / float(np.median(v))


def measure_break_even(mesh: TriangleMesh, rays, kinds=("grid", "bvh"), *, threads=None, configs=None, seed=0,
                       repeats: int = 1, quiet: float | None = None) -> BreakEven:
    """Really build every structure in ``kinds`` (which must include 'grid') and trace
    ``rays`` through each: the true break-even R_C of the paper's evaluation.

    rays: (origins, directions), or a count of the paper's uniform random rays (from ``seed``).
    configs: optional {kind: config dict} passed to ``build``.
    repeats: builds and traces of every structure, interleaved (``interleaved``); the
    break-even is taken from the medians.
    quiet: a round during which other processes took more than this share of the CPU is
    taken again (``interleaved``; ``QUIET_SHARE`` is calibration's); ``notes`` say so.
    ``measure_break_evens`` measures several scenes in passes."""
    return measure_break_evens([(mesh, rays)], kinds, threads=threads, configs=configs, seed=seed, repeats=repeats,
                               quiet=quiet)[0]


def measure_break_evens(scenes, kinds=("grid", "bvh"), *, threads=None, configs=None, seed=0, repeats: int = 1,
                        quiet: float | None = None, progress=None) -> list[BreakEven]:
    """``measure_break_even`` of every (mesh, rays) in ``scenes``, in ``repeats`` passes over
    all of them (``in_passes``), as calibration measures its scenes: the truths and the
    constants they are compared with then see the machine's drift alike.  A count of rays
    is made again from ``seed`` in each pass (1M rays are 48 MB a scene).  Each
    BreakEven's ``structures`` are those of the last pass (earlier passes' are freed after
    their trace, as ``measure`` frees its own).  progress: ``callback(fraction, message)``
    before each scene's round.  ``break_even_jobs`` gives the same jobs to run in other
    passes (``calibrate(beside=...)``)."""
    jobs, finish = break_even_jobs(scenes, kinds, threads=threads, configs=configs, seed=seed, passes=repeats,
                                   progress=progress)
    shares = [[] for _ in jobs]
    return finish(in_passes(jobs, repeats, quiet=quiet, shares=shares), shares, quiet)


def break_even_jobs(scenes, kinds=("grid", "bvh"), *, threads=None, configs=None, seed=0, passes: int = 1,
                    progress=None):
    """The jobs of ``measure_break_evens``: (scene_jobs, finish), ``scene_jobs`` one
    ``in_passes`` callable per scene and ``finish(runs, shares, quiet)`` the BreakEvens from
    ``in_passes``' results (``shares`` its per-scene lists)."""
    from ..rays import uniform_rays

    if "grid" not in kinds:
        raise ValueError("measure_break_even needs 'grid' among the kinds (the break-even is against the grid)")
    scenes = list(scenes)
    passes = max(1, int(passes))
    for mesh, _ in scenes:
        prepare_mesh(mesh)
    warm_up(kinds, threads=threads, configs=configs)
    kept = [{} for _ in scenes]

    def scene_jobs(i):
        mesh, rays = scenes[i]

        def make(r):
            if progress is not None:
                progress((r + i / len(scenes)) / passes, f"pass {r + 1}/{passes}, scene {i + 1}/{len(scenes)}")
            o, d = uniform_rays(mesh, int(rays), seed=seed) if isinstance(rays, (int, np.integer)) else rays

            def job(kind):
                def run():
                    m, acc = _measure(mesh, kind, o, d, threads, (configs or {}).get(kind))
                    if r == passes - 1:
                        kept[i][kind] = acc
                    return m
                return run

            return {k: job(k) for k in kinds}
        return make

    def finish(all_runs, shares, quiet) -> list[BreakEven]:
        out = []
        for i, runs in enumerate(all_runs):
            meas = {k: median_measurement(v) for k, v in runs.items()}
            g = meas["grid"].per_ray
            rc = {k: break_even(m.build_time, g, m.per_ray) for k, m in meas.items() if k != "grid"}
            rc_rep = {k: [break_even(h.build_time, gg.per_ray, h.per_ray) for h, gg in zip(runs[k], runs["grid"])]
                      for k in kinds if k != "grid"}
            n_rays = next(iter(runs.values()))[0].rays
            out.append(BreakEven(scenes[i][0].triangle_count, n_rays, meas, rc, len(runs["grid"]), rc_rep, runs,
                                 kept[i], notes=quiet_notes(shares[i], quiet)))
        return out

    return [scene_jobs(i) for i in range(len(scenes))], finish


def _grid_samples(mesh, ladder, threads, config, seed) -> dict[int, float]:
    """The grid's time per ray on fresh uniform samples of each size in ``ladder`` (what a
    plan's K-sample costs per ray).

    Each sample is traced as ``plan`` traces it: first thing through a grid just built.
    A grid's first traces can cost more than later ones (freshly allocated memory is
    faulted in; measured up to 2x on 800k triangles), and a sample timed after the large
    batch would miss that."""
    from ..rays import uniform_rays

    samples = {}
    for k in ladder:
        o, d = uniform_rays(mesh, int(k), seed=seed + int(k))
        samples[int(k)] = measure(mesh, "grid", o, d, threads=threads, config=config, builds=1).per_ray
    return samples


def sample_work(mesh, k: int, *, threads=None, config=None, seed=0) -> Work:
    """The grid's per-ray work counts on K uniform sample rays, as ``plan`` counts them
    (quasi-random, ``rays.quasi_uniform_rays``)."""
    from ..rays import quasi_uniform_rays

    cfg = dict(config or {})
    if threads is not None:
        cfg.setdefault("threads", threads)
    grid = build(mesh, "grid", **cfg)
    o, d = quasi_uniform_rays(mesh, int(k), seed=seed)
    before = grid.traversal_work()
    t = grid.trace(o, d).t
    return grid_work(grid, o, d, t, traversal=traversal_counts(before, grid.traversal_work()))


def quiet_notes(shares, quiet: float | None) -> list[str]:
    """What ``interleaved``'s (share, takes) per round say about other processes' use of
    the CPU (``OthersShare``), as notes for a calibration or a measurement; none when
    nothing was checked (quiet None)."""
    if not shares or quiet is None:
        return []
    seen = [x for x, _ in shares if x is not None]
    if not seen:
        return ["other processes' share of the CPU could not be read here (no /proc/stat): "
                "calibrate on a quiet machine"]
    out = []
    again = [n for _, n in shares if n > 1]
    if again:
        out.append(f"{len(again)} of {len(shares)} measurement rounds were taken again ({sum(again) - len(again)} "
                   f"retakes): other processes took more than {quiet:.0%} of the CPU while they ran")
    loud = [(x, n) for x, n in shares if x is not None and x > quiet]
    if loud:
        out.append(f"{len(loud)} of {len(shares)} rounds stayed busier than that after {max(n for _, n in loud) - 1} "
                   f"retakes (up to {max(x for x, _ in loud):.0%} of the CPU taken by others): their times may be "
                   f"slow; {BUSY_ADVICE}")
    return out


def median_measurement(runs) -> Measurement:
    """Median build time, trace time and build page faults, system time and CPU time (each
    where every run has it) of repeated Measurements of one structure."""
    def med(name, cast=float):
        v = [getattr(m, name) for m in runs]
        return None if any(x is None for x in v) else cast(np.median(v))

    return Measurement(med("build_time"), med("trace_time"), runs[0].rays, runs[0].threads,
                       med("build_faults", lambda x: int(round(x))), med("build_system"), med("build_cpu"))


def _size_hint(factory) -> float:
    """Expected work of a scene for the progress fraction: N log2 N of its size."""
    if isinstance(factory, TriangleMesh):
        return nlog2n(factory.triangle_count)
    args = getattr(factory, "args", ())
    n = args[0] if args and isinstance(args[0], (int, np.integer)) else 10000
    return nlog2n(n)


def calibrate(
    scenes=None,
    kinds=("bvh", "embree"),
    *,
    scale: str = "default",
    rays_per_scene: int | None = None,
    progress=None,
    threads: int | None = None,
    grid: bool = True,
    configs: dict | None = None,
    model: str = DEFAULT_MODEL,
    spread=DEFAULT_SPREAD,
    seed: int = 0,
    sample_ladder=SAMPLE_LADDER,
    repeats: int = CALIBRATION_REPEATS,
    work_samples: int = WORK_SAMPLES,
    quiet: float | None = QUIET_SHARE,
    beside=None,
) -> Calibration:
    """Measure every structure in ``kinds`` on each scene and fit the model.

    scenes: (name, factory-or-TriangleMesh) pairs; default ``scenes.calibration_set(scale)``.
    rays_per_scene: M, the paper's uniform random rays per scene (default by scale).
    progress: ``callback(fraction in [0, 1], message)``, called before each structure.
    threads: passed to every structure (None: each structure's default).
    grid: also measure the grid per scene: its time per ray on the calibration rays and on
    samples of each size in ``sample_ladder``, which give ``Calibration.grid_sample_ratio``
    (the grid's constants are not fitted: a plan measures the grid on its own scene).
    configs: optional {kind: config dict} passed to ``build``.
    repeats: passes over all the scenes (``CALIBRATION_REPEATS``), each building and tracing
    every structure of every scene once, so a scene's medians span the whole run.
    quiet: a round of a scene's measurements during which other processes took more than
    this share of the machine's CPU is taken again (``interleaved``; None: never); the
    calibration's notes say how many were, and the largest share in the rounds kept.
    beside: (scene_jobs, done): other scenes' ``in_passes`` jobs, run in the same passes
    after the calibration's own scenes (an evaluation's truths: the constants and the
    truths then come from the same minutes of the machine); ``done(runs, shares)`` gets
    their results when the passes end.
    """
    from .. import scenes as scene_lib
    from ..rays import uniform_rays

    t_start = time.perf_counter()
    if scenes is None:
        scenes = scene_lib.calibration_set(scale)
    else:
        scale = "custom"
    scenes = list(scenes)
    if not scenes:
        raise ValueError("calibrate needs at least one scene")
    m_rays = int(rays_per_scene or RAYS_PER_SCENE.get(scale, RAYS_PER_SCENE["default"]))
    if m_rays < 1:
        raise ValueError(f"rays_per_scene must be at least 1, got {m_rays}")
    fitted, notes = available_kinds(kinds)
    if not fitted:
        raise ValueError(f"none of the structures {tuple(kinds)} can be built here: {'; '.join(notes)}")
    measured = (("grid",) if grid and "grid" not in fitted else ()) + fitted
    weights = np.array([_size_hint(f) for _, f in scenes])
    done = np.concatenate([[0.0], np.cumsum(weights)]) / weights.sum()

    warm_up(measured, threads=threads, configs=configs)
    passes = max(1, int(repeats))

    def report(frac, msg):
        if progress is not None:
            progress(float(frac), msg)

    # first every scene once: generated, its grid samples and work counts measured; then the
    # repeats as passes over all scenes, so each scene's medians come from the whole run and
    # not from one minute of it: the machine's speed drifts over minutes, and two calibrations
    # in a row measured the small scenes minutes apart in different states (the BVH's time
    # per ray at 1,024 triangles 15% apart with repeats back to back).  The meshes stay; a
    # scene's rays are made again from their seed in each pass (24 MB a scene otherwise kept)
    records, plans = [], []
    for i, (name, factory) in enumerate(scenes):
        report(SETUP_SHARE * done[i], f"scene {i + 1}/{len(scenes)}: generating {name}")
        mesh = factory if isinstance(factory, TriangleMesh) else factory()
        prepare_mesh(mesh)
        rec = SceneRecord(name, mesh.triangle_count, m_rays)
        rays = {}  # kind: (ray count, seed) of the rays it is timed on
        for kind in measured:
            rays[kind] = (m_rays, seed + i)
            if kind == "grid":
                report(SETUP_SHARE * done[i], f"scene {i + 1}/{len(scenes)}: {name} ({mesh.triangle_count:,} triangles), "
                                              f"grid samples")
                cfg = (configs or {}).get(kind)
                gseed = seed + 7919 * (i + 1)
                rec.grid_samples = _grid_samples(mesh, sample_ladder, threads, cfg, gseed)
                rec.work = sample_work(mesh, work_samples, threads=threads, config=cfg, seed=gseed + 1).to_dict()
                if sample_ladder and m_rays < GRID_LARGE_RAYS:
                    # the ratio needs a large workload's time per ray: the 'tiny' and 'quick'
                    # scales' few rays per scene would themselves be a small batch
                    rays[kind] = (GRID_LARGE_RAYS, gseed)
        records.append(rec)
        plans.append((mesh, rays))
        del mesh  # plans holds it until the passes end

    def job(mesh, kind, o, d, frac, msg):
        def run():  # progress before every structure, so a cancel waits for one trace at most
            report(frac, msg)
            return measure(mesh, kind, o, d, threads=threads, config=(configs or {}).get(kind))
        return run

    def scene_jobs(i):
        rec, (mesh, rays) = records[i], plans[i]

        def make(r):
            frac = SETUP_SHARE + (1.0 - SETUP_SHARE) * (r + done[i]) / passes
            head = f"pass {r + 1}/{passes}, scene {i + 1}/{len(scenes)}: {rec.name} ({rec.triangles:,} triangles)"
            made = {key: uniform_rays(mesh, key[0], seed=key[1]) for key in set(rays.values())}
            return {k: job(mesh, k, *made[rays[k]], frac, f"{head}, {k}") for k in measured}
        return make

    others = list(beside[0]) if beside is not None else []
    per_scene = [[] for _ in range(len(records) + len(others))]
    runs = in_passes([scene_jobs(i) for i in range(len(records))] + others, passes, quiet=quiet, shares=per_scene)
    if beside is not None:
        beside[1](runs[len(records):], per_scene[len(records):])
    runs, per_scene = runs[: len(records)], per_scene[: len(records)]
    shares = [x for got in per_scene for x in got]
    plans.clear()  # the scenes' meshes
    for rec, got in zip(records, runs):
        rec.kinds = {k: median_measurement(v) for k, v in got.items()}
        rec.passes = {k: list(v) for k, v in got.items()}
    notes += quiet_notes(shares, quiet)
    fits = fit(records, fitted, model=model, spread=spread)
    counts = fit_counts(records, ("grid",) + tuple(fitted), spread)
    duration = time.perf_counter() - t_start
    if progress is not None:
        progress(1.0, f"calibrated {', '.join(fits)} on {len(records)} scenes in {duration:.1f} s")
    return Calibration(
        fits=fits, scenes=records, model=model, spread=tuple(spread), rays_per_scene=m_rays, scale=scale,
        threads=threads, duration_s=duration, created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        source="measured", notes=notes, counts=counts,
    )
