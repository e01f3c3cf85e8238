"""Which kernel work ran in the guest's workqueues, and how long each item held its CPU.

Why: at the pattern's stop a ``kworker/0`` thread held CPU 0 for ~0.5 s (J68's timeline) and
the h2 reader missed its deadline; a thread's CPU ticks cannot say which work it ran. The
kernel's ``workqueue_execute_start`` / ``_end`` tracepoints name each work item's function; the
trace clock is CLOCK_MONOTONIC, the journal's ``-o short-monotonic`` clock, so the longest
items can be read beside the manager's ``timer_left`` and the watchdog's trips.
"""

from __future__ import annotations

import re
from typing import Any

TRACEFS = "/sys/kernel/tracing"
EVENTS = ("workqueue/workqueue_execute_start", "workqueue/workqueue_execute_end")

# One line of the trace: "<comm>-<pid> [cpu] flags <t>: <event>: work struct <p>: function <f>"
LINE = re.compile(
    r"^\s*(?P<comm>.+?)-(?P<pid>\d+)\s+\[(?P<cpu>\d+)\].*?\s(?P<t>\d+\.\d+):\s+"
    r"workqueue_execute_(?P<edge>start|end):\s+work struct\s+(?P<work>\S+?):?\s"
    r"(?:function\s+(?P<fn>\S+))?"
)


def arm_command(buffer_kb: int = 8192) -> str:
    """Shell (as root, in the guest) that clears the trace and starts the two tracepoints on
    the monotonic clock, ``buffer_kb`` per CPU (a minute of work items fits in far less)."""
    on = " ".join(f"echo 1 > events/{e}/enable;" for e in EVENTS)
    return (
        f"mountpoint -q {TRACEFS} || mount -t tracefs nodev {TRACEFS}; cd {TRACEFS} && "
        f"echo 0 > tracing_on && echo mono > trace_clock && echo {buffer_kb} > buffer_size_kb && "
        f"echo > trace && {on} echo 1 > tracing_on"
    )


def stop_command() -> str:
    """Shell that stops tracing and prints the trace (to read after the load)."""
    return f"cd {TRACEFS} && echo 0 > tracing_on && cat trace"


def items(text: str) -> list[dict[str, Any]]:
    """The work items that started and ended in the trace: thread, CPU, function, start (the
    monotonic clock, s) and duration (ms), in start order. An item still running at the
    trace's end, or begun before it, is left out."""
    open_: dict[str, tuple[float, str, str, int]] = {}
    out: list[dict[str, Any]] = []
    for line in text.splitlines():
        m = LINE.match(line)
        if m is None:
            continue
        key = m["pid"]  # one worker thread runs one item at a time
        t = float(m["t"])
        if m["edge"] == "start":
            open_[key] = (t, m["fn"] or m["work"], m["comm"].strip(), int(m["cpu"]))
            continue
        began = open_.pop(key, None)
        if began is None:
            continue
        t0, fn, comm, cpu = began
        out.append({"t": t0, "ms": (t - t0) * 1e3, "fn": fn, "thread": comm, "cpu": cpu})
    return sorted(out, key=lambda i: i["t"])


def summarize(work: list[dict[str, Any]], top: int = 20) -> dict[str, Any]:
    """Per function: count, total and longest ms, the functions by total; and the ``top``
    longest items with their start time (to put beside the journal's)."""
    by_fn: dict[str, dict[str, Any]] = {}
    for i in work:
        s = by_fn.setdefault(i["fn"], {"n": 0, "total_ms": 0.0, "max_ms": 0.0})
        s["n"] += 1
        s["total_ms"] += i["ms"]
        s["max_ms"] = max(s["max_ms"], i["ms"])
    ranked = sorted(by_fn.items(), key=lambda kv: -kv[1]["total_ms"])
    return {
        "items": len(work),
        "functions": {
            fn: {k: round(v, 2) if isinstance(v, float) else v for k, v in s.items()}
            for fn, s in ranked[:top]
        },
        "longest": [
            {**i, "t": round(i["t"], 4), "ms": round(i["ms"], 2)}
            for i in sorted(work, key=lambda i: -i["ms"])[:top]
        ],
    }
