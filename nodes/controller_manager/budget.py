"""A controller's update, judged: its own CPU against its budget (the thread's CPU clock, less
the garbage collector's share and one step of the clock) and the values it may write."""

from __future__ import annotations

import gc
import math
import threading
import time
from typing import Any

import structlog
from exolink.nodes.controller_manager.slots import Slot

log = structlog.get_logger()


class GcClock:
    """CPU seconds each thread spent in the garbage collector (gc.callbacks), so a controller's
    budget counts its own work: a collection falls in whichever update allocates past the
    threshold, and a controller must not be stopped for an overrun that was the collector's."""

    def __init__(self) -> None:
        self.spent: dict[int, float] = {}
        self._start: dict[int, float] = {}
        self.runs = [0, 0, 0]  # collections per generation
        self.longest_s = [0.0, 0.0, 0.0]  # the longest of each (CPU): a stall of the loop

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        tid = threading.get_ident()
        if phase == "start":
            self._start[tid] = time.thread_time()
        elif (t0 := self._start.pop(tid, None)) is not None:
            took = time.thread_time() - t0
            self.spent[tid] = self.spent.get(tid, 0.0) + took
            g = info.get("generation", 0)
            self.runs[g] += 1
            if took > self.longest_s[g]:
                self.longest_s[g] = took

    def of_this_thread(self) -> float:
        return self.spent.get(threading.get_ident(), 0.0)

    def counters(self) -> dict[str, list[float]]:
        return {"runs": list(self.runs), "longest_ms": [round(t * 1e3, 2) for t in self.longest_s]}


GC_CLOCK = GcClock()
gc.callbacks.append(GC_CLOCK)


def cpu_clock_step(spin_s: float = 0.05) -> float:
    """The smallest step of this thread's CPU clock, measured once. Where the kernel accounts CPU
    in ticks (User-Mode Linux: 10 ms) an update that straddles a tick reads a whole tick; a
    budget is then judged on what was surely used (the reading less one step), so a controller
    is never stopped for a tick it only touched. On the board's kernel the step is ~1 us."""
    t0 = t = time.thread_time()
    end = time.perf_counter() + spin_s
    while t == t0 and time.perf_counter() < end:
        t = time.thread_time()
    return t - t0 if t > t0 else spin_s


CPU_STEP_S = cpu_clock_step()


def overran(slot: Slot, cpu: float, period_s: float) -> str | None:
    """Why an update over its budget stops the controller: a second one in a row, or one
    longer than the update period (that cycle itself late). One alone is counted: a
    thread's CPU clock also takes the interrupts served while it ran, and stopping a gait
    for one would put a walking patient's joints in the safe action for nothing."""
    budget = f"{slot.budget_s * 1e3:g} ms"
    last, slot.overran_last = slot.overran_last, cpu
    if cpu > period_s:
        return (
            f"overran its budget: {cpu * 1e3:.3f} ms CPU > {budget}, longer than the "
            f"update period ({period_s * 1e3:g} ms)"
        )
    if last:
        return (
            f"overran its budget twice in a row: {last * 1e3:.3f} and {cpu * 1e3:.3f} ms "
            f"CPU > {budget}"
        )
    log.warning("controller_overran", controller=slot.name, cpu_ms=round(cpu * 1e3, 3))
    return None


def check_values(slot: Slot, values: Any) -> str | None:
    """What is wrong with an update's values (None: nothing): only interfaces it claimed, and
    finite numbers (three for a board's gains)."""
    if not isinstance(values, dict):
        return f"update returned {type(values).__name__}, not a dict of interface values"
    for k, v in values.items():
        if k not in slot.claims:
            return f"wrote {k}, which it did not claim"
        if k.endswith("/gains") and k.startswith("maccepa"):
            if not (isinstance(v, tuple | list) and len(v) == 3 and all(map(_finite, v))):
                return f"wrote {k} = {v!r}, not three finite numbers (kp, ki, kd)"
        elif not _finite(v):
            return f"wrote {k} = {v!r}, not a finite number"
    return None


def _finite(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
