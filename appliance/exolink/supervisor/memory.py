"""The supervisor's resident memory: read from /proc, and given back to the kernel after a burst."""

from __future__ import annotations

import ctypes
import os
from typing import Any

TRIM_PERIOD_S = 10.0
TRIM_GROWTH_MB = 8.0
PAGE_SIZE = os.sysconf("SC_PAGE_SIZE")


class MemoryTrim:
    """Gives back to the kernel what glibc keeps after a burst (``malloc_trim``).

    A flood of queries (three clients queueing 3000 status queries each) left the supervisor
    ~20 MB larger for good: Zenoh's and Python's threads allocate in glibc arenas, which keep
    freed memory; malloc_trim(0) gave it back (75 -> 53 MB). It is called only when the
    resident size grew by TRIM_GROWTH_MB since the last call, looked at every TRIM_PERIOD_S
    (one read of /proc/self/statm), so a steady supervisor never pays for the walk of its
    heap (4.5 ms for 100k free chunks on x86)."""

    def __init__(self) -> None:
        self.trims = 0
        self._next = 0.0
        self._base: float | None = None
        try:
            self._trim: Any = ctypes.CDLL(None).malloc_trim
        except (OSError, AttributeError):  # not glibc
            self._trim = None

    def check(self, now: float) -> None:
        if self._trim is None or now < self._next:
            return
        self._next = now + TRIM_PERIOD_S
        rss = rss_mb()
        if self._base is None:
            self._base = rss
        elif rss > self._base + TRIM_GROWTH_MB:
            self._trim(0)
            self.trims += 1
            self._base = rss_mb()


def rss_mb() -> float:
    """This process' resident size in MiB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE_SIZE / 2**20
