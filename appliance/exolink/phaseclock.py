"""CPU time of a node loop's phases, sampled every few iterations.

On the board every process shares one core, often saturated, so wall-clock profiles (cProfile,
the manager's ``overhead_us``) measure the waits for the CPU, not the work. This thread's CPU
clock does not advance while the thread is preempted: a phase's figure is its own cost, however
busy the core. Reading that clock is a system call (no vDSO for per-thread clocks; tens of
microseconds under TCG), so only one iteration in ``every`` is timed and the sum is divided by
the sampled count.
"""

from __future__ import annotations

import time
from typing import Any


class PhaseClock:
    """``start()`` at the top of each iteration, ``mark(phase)`` after each phase: the CPU the
    thread used since the previous mark is added to that phase, on sampled iterations only.

    ``walls``: also each phase's longest wall time, every iteration (the monotonic clock, no
    system call), since the last ``counters()``: where a loop that missed its deadline spent
    the time, which the CPU figures cannot say (the h2 reader went 509 ms without a beat with
    CPU 0 mostly idle, H65 in docs/performance.md)."""

    def __init__(self, every: int = 8, walls: bool = False) -> None:
        if every < 1:
            raise ValueError(f"PhaseClock every must be >= 1, got {every}")
        self.every = every
        self.iterations = 0
        self.sampled = 0
        self.on = False
        self._last = 0.0
        self._spent: dict[str, float] = {}
        self.walls = walls
        self._wall_last = 0.0
        self._wall_max: dict[str, float] = {}

    def start(self) -> None:
        self.iterations += 1
        self.on = self.iterations % self.every == 0
        if self.walls:
            self._wall_last = time.monotonic()
        if self.on:
            self.sampled += 1
            self._last = time.thread_time()

    def mark(self, phase: str) -> None:
        if self.walls:
            now = time.monotonic()
            if now - self._wall_last > self._wall_max.get(phase, 0.0):
                self._wall_max[phase] = now - self._wall_last
            self._wall_last = now
        if self.on:
            now = time.thread_time()
            self._spent[phase] = self._spent.get(phase, 0.0) + now - self._last
            self._last = now

    def counters(self) -> dict[str, Any]:
        """Mean CPU per iteration of each phase (us) over the sampled iterations, and the sums
        (``us_sum``), from which two readings give a window's own means (``window``); with
        ``walls``, each phase's longest wall time (ms, ``wall_max_ms``) since the last reading."""
        n = self.sampled
        out = {
            "iterations": self.iterations,
            "sampled": n,
            "every": self.every,
            "us_per_iteration": {k: round(v / n * 1e6, 1) for k, v in self._spent.items()}
            if n
            else {},
            "us_sum": {k: round(v * 1e6) for k, v in self._spent.items()},
        }
        if self.walls:  # the longest since the last reading, then from scratch
            out["wall_max_ms"] = {k: round(v * 1e3, 1) for k, v in self._wall_max.items()}
            self._wall_max = {}
        return out


def window(before: dict[str, Any], after: dict[str, Any]) -> dict[str, Any]:
    """Mean CPU per iteration of each phase between two ``counters()`` readings."""
    n = after["sampled"] - before["sampled"]
    if n <= 0:
        return {"iterations": 0, "us_per_iteration": {}}
    was = before["us_sum"]
    return {
        "iterations": after["iterations"] - before["iterations"],
        "us_per_iteration": {
            k: round((v - was.get(k, 0)) / n, 1) for k, v in after["us_sum"].items()
        },
    }
