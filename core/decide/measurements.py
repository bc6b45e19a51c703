"""Measuring: timing a structure as a caller would, and the calibration run.

Timings: ``time.perf_counter`` around builds and traces, each batch traced as ``trace``
runs it (``time_trace``); each timed build after ``settle.settle_before_build``, each round
of measurements watched for other processes' load (``load_watch``).  The default scale
traces one full chunk per scene, so the per-ray constants are a large workload's (see
``RAYS_PER_SCENE``).  ``truth`` measures the evaluation's true break-evens the same way.
"""

from __future__ import annotations

import time
from datetime import datetime, timezone

import numpy as np

from ..accel import LOCKSTEP_CHUNK, Accel
from ..factory import available_kinds, build
from ..mesh import TriangleMesh
from .calfile import Calibration
from .cost import DEFAULT_MODEL, DEFAULT_SPREAD, Measurement, SceneRecord, fit, fit_counts, nlog2n
from .load_watch import QUIET_SHARE, in_passes, quiet_notes
from .points import calibrate_points
from .settle import settle_before_build
from .work import Work, grid_work, traversal_counts

#: rays per scene for each calibration scale.  A structure's time per ray falls with the
#: batch's size: lockstep traversal ends in steps over the rays still in flight when the
#: batch runs out (two threads' pools of them), a cost the same for any batch.  The default
#: measures one full chunk of the lockstep tracers (``LOCKSTEP_CHUNK``, also ``api.CHUNK``),
#: so the constants are a large workload's, the ones a break-even of 10^5-10^6 rays is about
#: (BENCHMARKS.md, "Calibration and plan repeatability")
RAYS_PER_SCENE = {"tiny": 2000, "quick": 20000, "default": LOCKSTEP_CHUNK, "rich": LOCKSTEP_CHUNK}
#: sample sizes K at which calibration times the grid on each scene, to correct a plan's
#: K-ray sample for the fixed per-batch cost of lockstep traversal (see grid_sample_ratio)
SAMPLE_LADDER = (1024, 2048, 4096, 8192, 16384, 32768, 65536)
#: the least number of rays the grid's large-workload time per ray is measured on when
#: samples are timed (whatever the scale's rays per scene): the default scale's batch
GRID_LARGE_RAYS = LOCKSTEP_CHUNK
#: passes of a calibration over all its scenes, each pass building and tracing every
#: structure of every scene once (interleaved); a record keeps its scene's medians, since
#: one trace moves between runs on a shared machine and fewer passes left two calibrations
#: in a row further apart (BENCHMARKS.md, "Calibration and plan repeatability")
CALIBRATION_REPEATS = 5
#: what a scale changes of ``calibrate``'s defaults (an argument given to ``calibrate`` wins).
#: 'tiny' checks that calibrating, saving and using a calibration work (tests, a first try):
#: one pass, two sample sizes, the grid's reference and its work counts on small batches, one
#: build per measurement and no settling, so it takes seconds and its constants are rough
SCALE_SETTINGS = {"tiny": {"repeats": 1, "sample_ladder": (1024, 4096), "grid_large_rays": 8192, "small_builds": 1,
                           "work_samples": 2048, "settle": False}}
#: the part of a calibration's progress bar for generating the scenes and timing the grid's
#: samples, before the passes of builds and traces (about that share of its time)
SETUP_SHARE = 0.1
#: what each calibration scale measures and costs, for the add-on's settings, its Calibrate
#: operator and the CLI (one text for all three); the minutes are those of the 2-core
#: reference machine (``scripts/ship_calibration.py`` prints a calibration's duration)
FULL_CALIBRATION_MINUTES = 12
SCALE_NOTES = {
    "tiny": "Seconds: 8 scenes of 500-1,000 triangles, one pass; rough constants that check the set-up (tests)",
    "quick": "About 3 minutes on 2 cores: 8 scenes, so constants can differ between runs",
    "default": (f"About {FULL_CALIBRATION_MINUTES} minutes on 2 cores: 20 scenes, {RAYS_PER_SCENE['default']:,} rays "
                f"each, {CALIBRATION_REPEATS} passes over them, and the point queries; the constants the add-on ships"),
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
    and the time per ray rises.  A plan corrects its small sample with
    ``Calibration.grid_sample_ratio`` instead.
    """
    t0 = time.perf_counter()
    hits = accel.trace(origins, directions, tmin, tmax)
    return hits, time.perf_counter() - t0


def measure(mesh: TriangleMesh, kind: str, origins, directions, *, threads=None, config=None,
            builds: int | None = None, settle: bool = True) -> Measurement:
    """Build ``kind`` over ``mesh`` and trace the rays through it: one Measurement.

    A plan's structure is built once, and builds repeated back to back are not like it:
    they reuse the memory the previous one freed and run faster than a user's single build
    does.  So a large scene's build is timed once.  A small scene's
    (``builds_per_measurement``) is timed several times, each build after its own
    ``settle_before_build``, which makes the later ones like the first, and the median one
    is kept (BENCHMARKS.md, "Calibration and plan repeatability").
    ``builds`` overrides that count (1 where only the trace is wanted); ``settle=False``
    skips the settling (the 'tiny' scale, whose constants are rough anyway)."""
    return measure_and_keep(mesh, kind, origins, directions, threads, config, builds, settle)[0]


#: scenes of at most this many triangles (``cost.N_REF``) have each measured build of a
#: fitted structure timed ``SMALL_BUILDS`` times, each after its own ``settle_before_build``,
#: and the median kept: their builds take milliseconds, and the CPU time of one such build
#: moves with the host's load far more than a large scene's does, which keeps one
SMALL_SCENE = 65_536
SMALL_BUILDS = 5


def builds_per_measurement(triangles: int, kind: str) -> int:
    """How many timed builds one measurement of ``kind`` on a ``triangles``-triangle scene
    takes: ``SMALL_BUILDS`` for a small scene's fitted structure, else one.  The grid's
    build is timed once: no constant is fitted to it (a plan times its own grid)."""
    return SMALL_BUILDS if triangles <= SMALL_SCENE and kind != "grid" else 1


def measure_and_keep(mesh, kind, origins, directions, threads=None, config=None, builds=None,
                     settle: bool = True) -> tuple[Measurement, Accel]:
    """``measure``, and the structure it built (the last, when it built several), for
    callers that go on using it (``truth``)."""
    cfg = dict(config or {})
    if threads is not None:
        cfg.setdefault("threads", threads)
    timed, accel = [], None
    for _ in range(max(1, int(builds or builds_per_measurement(mesh.triangle_count, kind)))):
        accel = None  # the previous build's memory goes before the next one settles
        if settle:
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


#: a build whose CPU seconds over its wall seconds (``Measurement.build_parallelism``) are
#: below this kept about one thread busy.  Embree builds on every hardware thread; on a
#: 2-vCPU VM a build ran on about one thread or on two, and little in between
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


def warm_up(kinds, *, threads=None, configs=None):
    """Build and trace each kind once on a tiny scene, untimed: the first build of a kind
    in a process pays one-off costs (Embree starts its threads); untimed, so not settled."""
    from ..rays import uniform_rays
    from ..scenes import sphere

    warm = sphere(80)
    warm.prepare()
    o, d = uniform_rays(warm, 64, seed=0)
    for kind in kinds:
        measure(warm, kind, o, d, threads=threads, config=(configs or {}).get(kind), builds=1, settle=False)


def _grid_samples(mesh, ladder, threads, config, seed, settle=True) -> dict[int, float]:
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
        samples[int(k)] = measure(mesh, "grid", o, d, threads=threads, config=config, builds=1, settle=settle).per_ray
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
    sample_ladder=None,
    repeats: int | None = None,
    grid_large_rays: int | None = None,
    small_builds: int | None = None,
    work_samples: int | None = None,
    settle: bool | None = None,
    quiet: float | None = QUIET_SHARE,
    beside=None,
    points: bool = True,
) -> Calibration:
    """Measure every structure in ``kinds`` on each scene and fit the model.

    scenes: (name, factory-or-TriangleMesh) pairs; default ``scenes.calibration_set(scale)``.
    rays_per_scene: M, the paper's uniform random rays per scene (default by scale).
    progress: ``callback(fraction in [0, 1], message)``, called before each structure.
    threads: passed to every structure (None: each structure's default).
    grid: also measure the grid per scene: its time per ray on the calibration rays and on
    samples of each size in ``sample_ladder``, which give ``Calibration.grid_sample_ratio``
    (the grid's constants are not fitted: a plan measures the grid on its own scene); its
    large-workload time per ray on at least ``grid_large_rays`` rays.
    configs: optional {kind: config dict} passed to ``build``.
    repeats: passes over all the scenes (``CALIBRATION_REPEATS``), each building and tracing
    every structure of every scene once, so a scene's medians span the whole run.
    small_builds: timed builds of a small scene's fitted structure (``SMALL_BUILDS``).
    work_samples: rays the grid's work is counted on (``WORK_SAMPLES``).
    settle: settle before every timed build (``settle.settle_before_build``; default True).
    sample_ladder, repeats, grid_large_rays, small_builds, work_samples, settle: None takes
    the scale's (``SCALE_SETTINGS``), else the module's defaults.
    quiet: a round of a scene's measurements during which other processes took more than
    this share of the machine's CPU is taken again (``interleaved``; None: never); the
    calibration's notes say how many were, and the largest share in the rounds kept.
    points: also measure the point queries on the scenes (``points.calibrate_points``) for
    their decision.
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
    given = {"sample_ladder": sample_ladder, "repeats": repeats, "grid_large_rays": grid_large_rays,
             "small_builds": small_builds, "work_samples": work_samples, "settle": settle}
    setting = {"sample_ladder": SAMPLE_LADDER, "repeats": CALIBRATION_REPEATS, "grid_large_rays": GRID_LARGE_RAYS,
               "small_builds": SMALL_BUILDS, "work_samples": WORK_SAMPLES, "settle": True,
               **SCALE_SETTINGS.get(scale, {})}
    setting.update({k: v for k, v in given.items() if v is not None})
    sample_ladder, grid_large_rays = tuple(setting["sample_ladder"]), int(setting["grid_large_rays"])
    repeats, small_builds = int(setting["repeats"]), int(setting["small_builds"])
    work_samples, settle = int(setting["work_samples"]), bool(setting["settle"])
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
    # not from one minute of it (the machine's speed drifts over minutes).  The meshes stay;
    # a scene's rays are made again from their seed in each pass (24 MB a scene otherwise kept)
    records, plans = [], []
    for i, (name, factory) in enumerate(scenes):
        report(SETUP_SHARE * done[i], f"scene {i + 1}/{len(scenes)}: generating {name}")
        mesh = factory if isinstance(factory, TriangleMesh) else factory()
        mesh.prepare()
        rec = SceneRecord(name, mesh.triangle_count, m_rays)
        rays = {}  # kind: (ray count, seed) of the rays it is timed on
        for kind in measured:
            rays[kind] = (m_rays, seed + i)
            if kind == "grid":
                report(SETUP_SHARE * done[i], f"scene {i + 1}/{len(scenes)}: {name} ({mesh.triangle_count:,} triangles), "
                                              f"grid samples")
                cfg = (configs or {}).get(kind)
                gseed = seed + 7919 * (i + 1)
                rec.grid_samples = _grid_samples(mesh, sample_ladder, threads, cfg, gseed, settle)
                rec.work = sample_work(mesh, work_samples, threads=threads, config=cfg, seed=gseed + 1).to_dict()
                if sample_ladder and m_rays < grid_large_rays:
                    # the ratio needs a large workload's time per ray: the 'quick' scale's
                    # few rays per scene would themselves be a small batch
                    rays[kind] = (grid_large_rays, gseed)
        records.append(rec)
        plans.append((mesh, rays))
        del mesh  # plans holds it until the passes end

    def job(mesh, kind, o, d, frac, msg):
        def run():  # progress before every structure, so a cancel waits for one trace at most
            report(frac, msg)
            builds = small_builds if builds_per_measurement(mesh.triangle_count, kind) > 1 else 1
            return measure(mesh, kind, o, d, threads=threads, config=(configs or {}).get(kind), builds=builds,
                           settle=settle)
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
    point_model = {}
    if points:
        point_model = calibrate_points([(rec.name, mesh) for rec, (mesh, _) in zip(records, plans)], threads=threads,
                                       progress=lambda f, msg: report(0.99, msg)).to_dict()
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
        source="measured", notes=notes, counts=counts, points=point_model,
    )
