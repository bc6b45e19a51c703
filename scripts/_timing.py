"""Timing of a block of code, for the benchmarks."""

import statistics
import time


def median_time(fn, runs, clock=time.perf_counter):
    """Median over ``runs`` calls of ``fn`` of the time ``clock`` measures: wall time by
    default; ``time.process_time`` gives process CPU time, steadier than wall time when
    other jobs share the cores."""
    ts = []
    for _ in range(runs):
        t0 = clock()
        fn()
        ts.append(clock() - t0)
    return statistics.median(ts)
