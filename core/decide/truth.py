"""The true break-even of the paper's evaluation: every structure really built and run on
the same rays, interleaved and in passes over the scenes as calibration measures its own
(``load_watch.in_passes``), so the truths and the constants they are compared with see the
machine's drift alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..mesh import TriangleMesh
from .cost import Measurement, break_even
from .load_watch import in_passes, quiet_notes
from .measurements import measure_and_keep, median_measurement, warm_up


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
        mesh.prepare()
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
                    m, acc = measure_and_keep(mesh, kind, o, d, threads, (configs or {}).get(kind))
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
