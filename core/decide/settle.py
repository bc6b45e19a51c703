"""What comes right before every timed build, so that each starts in the same state a
user's build does: the scene's share of memory written, a short rest, then one thread busy.

On a virtual machine that takes back the memory its guest leaves free, and packs its vCPUs,
the time of a build otherwise depends on what the machine did just before it, not on the
scene (BENCHMARKS.md, "Measurement protocol and model terms").
"""

from __future__ import annotations

import os
import time

import numpy as np

#: seconds the process rests between the page warming and each timed build, so that every
#: build starts as a user's does (after an Analyze click, a script's first ``api.cast``),
#: never in the fast state of a build that follows other work within a few ms (Embree builds
#: over all hardware threads).  Well below the seconds after which a VM's host takes freed
#: memory back, so the warming still holds
IDLE_BEFORE_BUILD = 0.05
#: seconds the main thread spins on one core right after the rest, just before each timed
#: build, so that every build follows the same work whatever ran before it: on a VM that packs
#: its vCPUs, Embree's build after a two-thread trace runs on about one thread, and after a
#: spin of this length on two, whatever came before
BUSY_BEFORE_BUILD = 0.1
#: memory written just before each timed build (``warm_pages``), per triangle and at least /
#: at most: above the largest build's fresh pages (the numpy BVH's peak and Embree's first
#: build are each about 310 bytes a triangle)
WARM_BYTES_PER_TRIANGLE = 512
WARM_MIN_BYTES = 16 << 20
WARM_MAX_BYTES = 1 << 30


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


def warm_bytes(triangles: int) -> int:
    """How much memory ``settle_before_build`` writes before building over ``triangles``: 512 bytes a
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

    On a virtual machine whose host takes back the memory its guest leaves free (a
    balloon's free page reporting), memory a process freed and left idle for a couple of
    seconds goes back to the host, and the next process to touch it waits for the host to
    supply every page again, in system time: a build's time would depend on how long the
    machine had rested before it.  The pages the kernel hands out next are the ones freed
    last, so the build gets memory that is already backed; on a machine without such a host
    this costs the pages' zeroing and changes nothing else (BENCHMARKS.md, "Measurement
    protocol and model terms").
    """
    n = int(nbytes)
    if n <= 0:
        return
    a = np.empty(n, dtype=np.uint8)
    a[::4096] = 1
    del a

