"""Starved or hung: the kernel's word on a node found late by its heartbeat deadline.

A node whose loop waits for the CPU behind others (runnable, on the run queue) is starved, not
hung: on a full core the h2 reader went 509-598 ms without a beat (deadline 500 ms) while its
thread was runnable (`make bench-board` on a host 2-2.8x slower, docs/performance.md), and each
kill cost a whole re-import on the core that was already full. The kernel counts how long each
thread waited on a run queue (``/proc/<pid>/task/<tid>/schedstat``: run time, wait time) and in
what state it is: a loop that blocked (a deadlock, a stop signal, a lock) is not runnable and does
not wait there, one that spins is caught at the node's ``starved_deadline_ms`` however long it
waited. The wait is added when the thread gets the CPU, so a loop kept off it since before the
span shows none: runnable now and on the CPU for at most half the span counts as starved too
(C74: the recorder killed at 30 s, runnable). A loop asleep while a thread of its own process is
runnable waits for that thread (the GIL, a lock, a channel it fills: C76 killed the pattern
player asleep in a futex and the recorder in a pipe read, the core full): starved when the
process's threads together waited a quarter of the span (the rule "ran at most half" is not
used there: an asleep loop runs little either way). A kernel without schedstat reads as not
starved: the node is then judged as any late node.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field

from exolink.supervisor.osproc import thread_state

WAIT_SHARE = 0.25  # of the span looked at: a loop that waited for the CPU this much was starved,
RAN_SHARE = 0.5  # or one runnable now that ran at most this much of it
MIN_SPAN_S = 0.05  # a span shorter than this says nothing


@dataclass(frozen=True, slots=True)
class Sched:
    """A node's main thread (its loop, exolink.runtime) as the scheduler counts it, and its
    process's other threads."""

    t: float  # monotonic, when read
    state: str  # R: running or waiting for the CPU; S, D, T: not waiting for it; ?: not read
    run_ns: int  # time on the CPU since the thread began
    wait_ns: int  # time on a run queue, waiting for the CPU, up to its last turn on it
    others: Mapping[int, tuple[int, int]] = field(default_factory=dict)  # tid -> (run, wait)
    other_runnable: bool = False  # one of them was runnable (read only when the loop sleeps)


class Threads:
    """The scheduler's counts of one process's threads, from their ``schedstat`` files kept
    open and read again with one ``pread`` each (opening them every time took ~3 system calls
    a thread: 167 us of x86 CPU a look at a node of 8 threads, a look at each graced node a
    second). The files of threads that ended are closed at the next look; ``close`` at the
    process's end or its respawn."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self._fds: dict[int, int] = {}  # tid -> its open schedstat

    def read(self, t: float, states: bool = False) -> Sched | None:
        """The main thread's state and run-queue wait, and its siblings' (None: gone, or no
        schedstat). ``states``: whether a sibling is runnable too, when the main thread sleeps
        (a late node: the on-time mark needs only the counts)."""
        pid = self.pid
        try:
            tids = {int(tid) for tid in os.listdir(f"/proc/{pid}/task")}
            state = thread_state(pid) if states else "?"
        except (OSError, IndexError, ValueError):
            self.close()
            return None
        for tid in self._fds.keys() - tids:
            os.close(self._fds.pop(tid))
        counts: dict[int, tuple[int, int]] = {}
        for tid in tids:
            try:
                if (fd := self._fds.get(tid)) is None:
                    fd = self._fds[tid] = os.open(f"/proc/{pid}/task/{tid}/schedstat", os.O_RDONLY)
                fields = os.pread(fd, 128, 0).split()
                counts[tid] = int(fields[0]), int(fields[1])
            except (OSError, IndexError, ValueError):
                if (fd := self._fds.pop(tid, None)) is not None:
                    os.close(fd)  # a thread that ended meanwhile
        if pid not in counts:
            return None
        main = counts.pop(pid)
        runnable = states and state == "S" and any(_runnable(pid, tid) for tid in counts)
        return Sched(t, state, main[0], main[1], counts, runnable)

    def close(self) -> None:
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()


def _runnable(pid: int, tid: int) -> bool:
    try:
        return thread_state(pid, tid) == "R"
    except (OSError, IndexError):
        return False


def read(pid: int, t: float, states: bool = False) -> Sched | None:
    """``Threads(pid).read`` once (its files closed after)."""
    threads = Threads(pid)
    try:
        return threads.read(t, states)
    finally:
        threads.close()


def starved(mark: Sched | None, now: Sched | None) -> tuple[float, float] | None:
    """Over the span from ``mark`` (read while the node was on time) to ``now``, the shares its
    loop waited for the CPU and ran, if it was starved: runnable now, and it waited at least
    WAIT_SHARE of the span or ran at most RAN_SHARE of it; or asleep while a thread of its
    process is runnable, and the threads together waited WAIT_SHARE (shares then of the whole
    process); None: not starved (blocked, or not known)."""
    if mark is None or now is None:
        return None
    span = now.t - mark.t
    if span < MIN_SPAN_S:
        return None
    if now.state == "R":
        waited = (now.wait_ns - mark.wait_ns) / 1e9 / span
        ran = (now.run_ns - mark.run_ns) / 1e9 / span
        return (waited, ran) if waited >= WAIT_SHARE or ran <= RAN_SHARE else None
    if now.state != "S" or not now.other_runnable:
        return None
    run_ns, wait_ns = now.run_ns - mark.run_ns, now.wait_ns - mark.wait_ns
    for tid, (run, wait) in now.others.items():
        was = mark.others.get(tid, (0, 0))  # a thread begun since the mark: all of it
        run_ns, wait_ns = run_ns + run - was[0], wait_ns + wait - was[1]
    waited, ran = wait_ns / 1e9 / span, run_ns / 1e9 / span
    return (waited, ran) if waited >= WAIT_SHARE else None
