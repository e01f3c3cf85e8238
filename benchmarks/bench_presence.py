"""The operator's presence: how long a gait goes on after the laptop holding it is lost.

An attached ``exolink pattern start`` (a real CLI process) holds motion and plays the gait; the
process is then frozen (SIGSTOP: a Wi-Fi drop or a hung laptop, no TCP close) or killed
(SIGKILL: the TCP link closes), and an independent listener on the bus times the first disable
frame from that moment, and counts the position frames in between. Before the keep-alive was the
application's own, a frozen laptop kept the gait going ~12 s (Zenoh's 10 s session lease, then
operator_lost_ms); the goal is within operator_lost_ms + 1 s.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from typing import Any

from benchmarks.harness import EXOLINK, Appliance, DrainedBus, motion_nodes, pct
from exolink.protocol import h2

LOST_MS = 2000  # watchdog.operator_lost_ms, as shipped
PLAYER = {
    "name": "pattern_player",
    "plugin": "pattern_player",
    "critical": True,
    "params": {"speed": 10, "selected": ["r_hip", "r_knee", "l_hip", "l_knee"]},
}


def _trial(app: Appliance, bus: DrainedBus, sig: int) -> tuple[float, int] | None:
    """(s from the signal to the first disable frame, position frames in between)."""
    end = time.monotonic() + 15
    while not app.call("watchdog", {"action": "arm"}).get("ok"):
        if time.monotonic() > end:
            return None
        time.sleep(0.2)
    holder = subprocess.Popen(
        [*EXOLINK, "pattern", "start", "--at", app.at],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        running = bus.wait_for(_position, 15)
        if running is None:
            return None
        time.sleep(0.5)
        bus.clear()
        t0 = time.time()
        os.kill(holder.pid, sig)
        frames = bus.collect(LOST_MS / 1000 + 3)
        decoded = [(m.timestamp, h2.decode(m)) for m in frames]
        first = next((t for t, f in decoded if _mode(f) == 4), None)
        if first is None:
            return None
        moved = sum(1 for t, f in decoded if _mode(f) == 1 and t < first)
        return first - t0, moved
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()


def _mode(f: Any) -> int | None:
    return f.mode if isinstance(f, h2.JointControl) else None


def _position(m: Any) -> bool:
    return _mode(h2.decode(m)) == 1


def run(quick: bool) -> dict[str, Any]:
    trials = 3 if quick else 8
    app = Appliance.sim(nodes=motion_nodes(PLAYER))
    bus = DrainedBus(app.group)
    out: dict[str, Any] = {"operator_lost_ms": LOST_MS, "trials": trials}
    try:
        for name, sig in (("frozen_sigstop", signal.SIGSTOP), ("killed_sigkill", signal.SIGKILL)):
            got = [r for r in (_trial(app, bus, sig) for _ in range(trials)) if r is not None]
            out[name] = {
                "to_first_disable_frame_ms": pct([t for t, _ in got], 1e3),
                "position_frames_meanwhile": pct([float(n) for _, n in got], 1.0, 0),
                "measured": len(got),
            }
    finally:
        bus.close()
        app.close()
    return out
