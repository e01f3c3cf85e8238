"""Starved or hung: the kernel's word on a node found late by its heartbeat deadline.

A node whose loop waits for the CPU behind others (runnable, on the run queue) is starved, not
hung: on a full core the h2 reader went 509-598 ms without a beat (deadline 500 ms) while its
thread was runnable (`make bench-board` on a host 2-2.8x slower, docs/performance.md), and each
kill cost a whole re-import on the core that was already full. The kernel counts how long each
thread waited on a run queue (``/proc/<pid>/schedstat``, second field): a loop that blocked
(a deadlock, a stop signal, a lock) does not wait there, one that spins is caught at the node's
``starved_deadline_ms`` however long it waited. A kernel without schedstat reads as not starved:
the node is then judged as any late node.
"""

from __future__ import annotations

from dataclasses import dataclass

WAIT_SHARE = 0.25  # of the span looked at: a loop that waited for the CPU this much was starved
MIN_SPAN_S = 0.05  # a span shorter than this says nothing


@dataclass(frozen=True, slots=True)
class Sched:
    """A node's main thread (its loop, exolink.runtime) as the scheduler counts it."""

    t: float  # monotonic, when read
    state: str  # R: running or waiting for the CPU; S, D, T: not waiting for it
    wait_ns: int  # time on a run queue, waiting for the CPU, since the thread began


def read(pid: int, t: float) -> Sched | None:
    """The main thread's state and run-queue wait (None: gone, or no schedstat)."""
    try:
        with open(f"/proc/{pid}/schedstat", "rb") as f:
            wait_ns = int(f.read().split()[1])
        with open(f"/proc/{pid}/stat", "rb") as f:
            state = f.read().rpartition(b")")[2].split()[0].decode()
    except (OSError, IndexError, ValueError):
        return None
    return Sched(t, state, wait_ns)


def waited_share(mark: Sched | None, now: Sched | None) -> float | None:
    """The share of the span from ``mark`` (taken while the node was on time) to ``now`` its
    loop waited for the CPU, if it was starved: runnable now and waiting at least WAIT_SHARE
    of it; None: not starved (blocked, or not known)."""
    if mark is None or now is None or now.state != "R":
        return None
    span = now.t - mark.t
    if span < MIN_SPAN_S:
        return None
    share = (now.wait_ns - mark.wait_ns) / 1e9 / span
    return share if share >= WAIT_SHARE else None
