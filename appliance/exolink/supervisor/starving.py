"""Starved or hung: the kernel's word on a node found late by its heartbeat deadline.

A node whose loop waits for the CPU behind others (runnable, on the run queue) is starved, not
hung: on a full core the h2 reader went 509-598 ms without a beat (deadline 500 ms) while its
thread was runnable (`make bench-board` on a host 2-2.8x slower, docs/performance.md), and each
kill cost a whole re-import on the core that was already full. The kernel counts how long each
thread waited on a run queue (``/proc/<pid>/schedstat``: run time, wait time) and in what
state it is: a loop that blocked (a deadlock, a stop signal, a lock) is not runnable and does not
wait there, one that spins is caught at the node's ``starved_deadline_ms`` however long it
waited. The wait is added when the thread gets the CPU, so a loop kept off it since before the
span shows none: runnable now and on the CPU for at most half the span counts as starved too
(C74: the recorder killed at 30 s, runnable). A kernel without schedstat reads as not starved:
the node is then judged as any late node.
"""

from __future__ import annotations

from dataclasses import dataclass

WAIT_SHARE = 0.25  # of the span looked at: a loop that waited for the CPU this much was starved,
RAN_SHARE = 0.5  # or one runnable now that ran at most this much of it
MIN_SPAN_S = 0.05  # a span shorter than this says nothing


@dataclass(frozen=True, slots=True)
class Sched:
    """A node's main thread (its loop, exolink.runtime) as the scheduler counts it."""

    t: float  # monotonic, when read
    state: str  # R: running or waiting for the CPU; S, D, T: not waiting for it
    run_ns: int  # time on the CPU since the thread began
    wait_ns: int  # time on a run queue, waiting for the CPU, up to its last turn on it


def read(pid: int, t: float) -> Sched | None:
    """The main thread's state and run-queue wait (None: gone, or no schedstat)."""
    try:
        with open(f"/proc/{pid}/schedstat", "rb") as f:
            run, wait = f.read().split()[:2]
        with open(f"/proc/{pid}/stat", "rb") as f:
            state = f.read().rpartition(b")")[2].split()[0].decode()
        return Sched(t, state, int(run), int(wait))
    except (OSError, IndexError, ValueError):
        return None


def starved(mark: Sched | None, now: Sched | None) -> tuple[float, float] | None:
    """Over the span from ``mark`` (read while the node was on time) to ``now``, the shares its
    loop waited for the CPU and ran, if it was starved: runnable now, and it waited at least
    WAIT_SHARE of the span or ran at most RAN_SHARE of it; None: not starved (blocked, or not
    known)."""
    if mark is None or now is None or now.state != "R":
        return None
    span = now.t - mark.t
    if span < MIN_SPAN_S:
        return None
    waited = (now.wait_ns - mark.wait_ns) / 1e9 / span
    ran = (now.run_ns - mark.run_ns) / 1e9 / span
    return (waited, ran) if waited >= WAIT_SHARE or ran <= RAN_SHARE else None
