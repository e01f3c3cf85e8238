"""Watchdog reaction times: kill -9 -> first disable frame, SIGSTOP -> trip, crash -> publishing
again; and the resident memory of the whole appliance."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

from benchmarks.harness import Appliance, DrainedBus, pct, pss_mb
from exolink import messaging
from exolink.protocol import h2

NODES = [
    {"name": "simulator", "plugin": "simulator"},
    {
        "name": "h2_reader",
        "plugin": "h2_reader",
        "critical": True,
        "restart": {"max_restarts": 1000, "backoff_initial_ms": 50, "backoff_max_ms": 50},
    },
    {
        "name": "pattern_player",
        "plugin": "pattern_player",
        "critical": True,
        "restart": {"max_restarts": 1000, "backoff_initial_ms": 50, "backoff_max_ms": 50},
    },  # killed per SIGSTOP trial: the default deadline
    {
        "name": "controller_manager",
        "plugin": "controller_manager",
        "critical": True,
        "heartbeat_deadline_ms": 50,  # the motion node, as in the shipped configs
        "restart": {"max_restarts": 1000, "backoff_initial_ms": 50, "backoff_max_ms": 50},
    },
]


def is_disable(m: Any) -> bool:
    f = h2.decode(m)
    return isinstance(f, h2.JointControl) and f.mode == 4


def run(quick: bool) -> dict[str, Any]:
    trials = 20
    app = Appliance.sim(nodes=NODES)
    bus = DrainedBus(app.group)
    js_times: list[float] = []
    lock = threading.Lock()

    def on_js(_s: Any) -> None:
        with lock:
            js_times.append(time.time())

    key = messaging.topic_key(0, "h2", "joint_states", "sensor_msgs/msg/JointState")
    sub = app.session.declare_subscriber(key, on_js)  # type: ignore[union-attr]
    kill_to_disable, kill_to_publish = [], []
    try:
        time.sleep(1)
        nodes = app.call("status")["nodes"]
        rss = {n["name"]: n.get("rss_mb") for n in nodes}
        # All nodes spawned at once share the cores: spawn-to-first-heartbeat vs the start grace.
        cold_start = {n["name"]: n.get("start_s") for n in nodes}
        rss["supervisor"] = _rss(app.proc.pid)
        pss = {n["name"]: pss_mb(n["pid"]) for n in nodes if n.get("pid")}
        pss["supervisor"] = pss_mb(app.proc.pid)
        if zygote := app.call("status").get("zygote_pid"):
            pss["zygote"] = pss_mb(zygote)  # the pre-imported runtime the nodes fork from
        for _ in range(trials):
            pid = app.node("h2_reader")["pid"]
            bus.clear()
            t0 = time.time()
            os.kill(pid, signal.SIGKILL)
            m = bus.wait_for(is_disable, 2)
            if m is not None:
                kill_to_disable.append(m.timestamp - t0)
            end = time.monotonic() + 15
            while time.monotonic() < end:
                with lock:
                    after = [t for t in js_times if t > t0 + 0.02]
                if after:
                    kill_to_publish.append(after[0] - t0)
                    break
                time.sleep(0.005)
            time.sleep(0.3)
        stop_to_trip = _sigstop_trials(app, bus, "pattern_player", 5 if quick else 10)
        motion_stop_to_trip = _sigstop_trials(app, bus, "controller_manager", 10 if quick else 30)
        silence_to_trip = []
        for _ in range(5 if quick else 10):
            time.sleep(1.5)  # the simulator streams again
            app.arm_and_hold()
            bus.clear()
            time.sleep(0.05)  # a few angle frames queued: the last one marks the silence start
            app.call("sim/fault", {"fault": "silent", "duration_s": 1.0})
            m = bus.wait_for(_disable_after_silence(last := [0.0]), 3)
            if m is not None and last[0]:
                silence_to_trip.append(m.timestamp - last[0])
        read_lag = app.call("status")["watchdog"]["read_lag_max_ms"]
    finally:
        sub.undeclare()
        bus.close()
        app.close()
    return {
        "kill9_to_first_disable_frame_ms": pct(kill_to_disable, 1e3),
        "kill9_to_restarted_reader_publishing_ms": pct(kill_to_publish, 1e3),
        "restart_backoff_ms": 50,
        "sigstop_to_disable_frame_ms": pct(stop_to_trip, 1e3),
        "heartbeat_deadline_ms": 500,
        # a motion node (liveness every cycle over its own pipe, 50 ms deadline): SIGSTOP -> the
        # first disable frame seen by an independent listener on the bus
        "sigstop_motion_node_to_disable_frame_ms": pct(motion_stop_to_trip, 1e3),
        "motion_node_deadline_ms": 50,
        # last joint-angle frame on the bus -> first disable frame (limit 100 ms + detection)
        "h2_silence_to_disable_frame_ms": pct(silence_to_trip, 1e3),
        "h2_silence_limit_ms": 100,
        # arrival -> read by the watchdog, worst over the whole run: margin a busy CPU eats
        "watchdog_read_lag_max_ms": read_lag,
        "cold_start_to_first_heartbeat_s": cold_start,
        "rss_mb": rss,
        "rss_total_mb": round(sum(v for v in rss.values() if v), 1),
        "pss_mb": pss,
        "pss_total_mb": round(sum(v for v in pss.values() if v), 1),
    }


def _sigstop_trials(app: Appliance, bus: DrainedBus, node: str, trials: int) -> list[float]:
    out = []
    for _ in range(trials):
        end = time.monotonic() + 10
        while app.node(node)["heartbeat_age_s"] is None and time.monotonic() < end:
            time.sleep(0.05)  # the killed node is back
        app.arm_and_hold()
        pid = app.node(node)["pid"]
        bus.clear()
        t0 = time.time()
        os.kill(pid, signal.SIGSTOP)
        m = bus.wait_for(is_disable, 3)
        with contextlib.suppress(ProcessLookupError):  # the supervisor kills a hung node
            os.kill(pid, signal.SIGCONT)
        if m is not None:
            out.append(m.timestamp - t0)
        time.sleep(0.3)
    return out


def _disable_after_silence(last: list[float]) -> Callable[[Any], bool]:
    """Matches the first disable frame, keeping the last angle frame's timestamp before it."""

    def pred(m: Any) -> bool:
        if m.arbitration_id == h2.JOINT_ANGLES:
            last[0] = m.timestamp
            return False
        return is_disable(m)

    return pred


def _rss(pid: int) -> float:
    with open(f"/proc/{pid}/statm") as f:
        return round(int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20, 1)
