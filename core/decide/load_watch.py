"""Watching the machine's load while measuring: the share of the CPU other processes took
(``OthersShare``), rounds of measurements taken again when it was too high
(``interleaved``), passes over many scenes so that every scene sees the machine's drift
alike (``in_passes``), and the notes a calibration or a measurement gives about it.

A shared machine's speed drifts from second to second and over minutes; the lowest
priority alone does not keep a measurement clean, since other work still runs in the
cores' idle moments (BENCHMARKS.md, "Calibration and plan repeatability").
"""

from __future__ import annotations

import os
import time

#: a round of measurements is taken again when other processes used more than this share
#: of the machine's CPU time while it ran (``OthersShare``); with nothing else running the
#: share stays near zero
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
    (the counters advance in clock ticks)."""

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
        # the counters advance in clock ticks, so each end rounds: clip to what a share can be
        self.share = min(1.0, max(0.0, others / (wall * (os.cpu_count() or 1))))
        return False


def _process_seconds() -> float:
    t = os.times()
    return t.user + t.system


def interleaved(jobs: dict, repeats: int, *, quiet: float | None = None, retries: int = QUIET_RETRIES,
                shares: list | None = None, first_round: int = 0) -> dict[str, list]:
    """Run every job ``repeats`` times, interleaved (round r runs the jobs in an order
    rotated by ``first_round`` + r), and return each job's results in run order.

    On a shared machine the time of one run drifts from second to second;
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
    the next pass starts.  The machine's speed drifts over minutes (a scene measured in one
    slow minute would have every build and trace of it slow); in passes, each scene's
    medians span the whole run, so the calibration and the evaluation's truths, both
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
