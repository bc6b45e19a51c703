"""Peak memory of a block of code, for the benchmarks (Linux: /proc/self; elsewhere None)."""

import ctypes
import gc
import tracemalloc


def _proc_status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    return None


_libc = None


def trim():
    """Collect garbage and hand freed heap back to the OS, so a later peak is not hidden
    by the allocator reusing pages that are already resident."""
    global _libc
    gc.collect()
    try:
        _libc = _libc or ctypes.CDLL("libc.so.6")
        _libc.malloc_trim(0)
    except OSError:
        pass


class PeakMemory:
    """Peak extra memory of a block: RSS high-water mark (Linux) and tracemalloc's peak
    (``traced=False``: RSS only; tracemalloc slows code that allocates per element, such
    as embreex's geometry copy, by 10x or more)."""

    def __init__(self, traced=True):
        self.trace_python = traced
        self.traced = None

    def __enter__(self):
        trim()
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # reset VmHWM to the current RSS
            self.rss0 = _proc_status("VmRSS")
        except OSError:
            self.rss0 = None
        if self.trace_python:
            tracemalloc.start()
        return self

    def __exit__(self, *exc):
        if self.trace_python:
            self.traced = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
        self.hwm = _proc_status("VmHWM") if self.rss0 is not None else None
        self.rss = None if self.hwm is None else max(0, self.hwm - self.rss0)
        return False
