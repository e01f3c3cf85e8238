"""The bench's nominal load and what a laptop measures of it; the same for the guest and native.

Load: the H2 stream at 100 Hz and one MACCEPA board from the simulator node (pinned to CPU 1),
maccepa_bridge, timing_monitor, the recorder recording, and the pattern at speed 10 on four joints
while armed, started and held by the CLI; one laptop subscriber counts joint_states.
Everything else of the appliance is confined to CPU 0.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from exolink import messaging, phaseclock

log = structlog.get_logger("bench-board")

SIMULATOR_CPU = 1
# The laptop takes joint_states one message per sample, as a ROS 2 tool or Foxglove does
# (--laptop-one-by-one), instead of as bundles, as exolink's own client does: the board then
# puts every message for it (~100 samples/s more through its router).
ONE_BY_ONE = False
# A PID controller on this joint during the window (bench-board --pid JOINT), or none.
PID_JOINT = ""
# The manager's cycles_per_update for the run (bench-board --cycles-per-update N), or the config's:
# 1 runs a feedback controller at 100 Hz where board.yaml ships 2.
MANAGER_CYCLES: int | None = None
HANDSHAKE_S = 60.0
PATTERN_JOINTS = ["r_hip", "r_knee", "l_hip", "l_knee"]
PATTERN_SPEED = 10
TIMING_QUERY = {"id": 70, "byte0": 1, "dlc": 6}  # r_hip's set-points (H2 joint control)
# The H2 stand-in's angle frames on the bus (kernel times): whether a silence trip was a real gap.
ANGLES_QUERY = {"id": 110, "expected_ms": 10}


# Watchdog timings: "stock" is board.yaml's (only start_grace_ms is raised: imports under TCG);
# "relaxed" widens the node heartbeat deadline (and, on the guest, systemd's WatchdogSec) so a
# CPU too slow for the stock ones still reaches a steady state whose CPU shares can be compared,
# and the controller manager's update budget (2 ms: the gait's trajectory update took 5.0 ms of
# CPU under TCG, ~37 us on x86, and was deactivated for it at its first cycle on the proxy) and
# its H2 silence limit to the watchdog's (50 -> 100 ms): the simulator's stream, cyclic in the
# guest kernel on CPU 1, has gaps of 50-100 ms when the host deschedules that vCPU (the h2
# reader counted ~260 missing frames per id in a window), and the manager stopped the gait for
# them (the run of ff87565: "no H2 joint angles for 50 ms" in the window's first seconds).
TIMINGS = {
    "stock": {"heartbeat_deadline_ms": 500, "pulse_silence_ms": 100, "systemd_watchdog_s": None},
    "relaxed": {
        "heartbeat_deadline_ms": 5000,
        "pulse_silence_ms": 100,
        "systemd_watchdog_s": 60,
        "update_budget_ms": 8.0,
        "h2_timeout_ms": 100,
    },
}


SIM_DEADLINE_MS = 3000
SIM_UPDATE_CYCLES = 4  # the simulator's models step every 40 ms on the proxy (see below)


def bench_config(
    base: dict[str, Any],
    can: dict[str, Any],
    start_grace_ms: int,
    timings: str,
    without: tuple[str, ...] = (),
) -> dict[str, Any]:
    """The appliance config under test: ``base`` (the image's appliance.yaml or board.yaml) with
    the bench's bus, a simulated trigger, the simulator node on CPU 1, one MACCEPA board (read by
    the h2 reader, or by the bridge for a config without ``maccepa_boards``), the timing monitor
    on and the watchdog ``timings`` (TIMINGS, every node's own deadline included)
    with the given start grace. ``without``: non-critical nodes left off (what the rest needs
    when CPU 0 is saturated); a critical one is refused, since nothing arms without it."""
    cfg = json.loads(json.dumps(base))  # deep copy
    names = {n["name"]: n for n in cfg.get("nodes", [])}
    for name in without:
        if name not in names:
            raise ValueError(f"--without {name}: no such node in the config ({', '.join(names)})")
        if names[name].get("critical"):
            raise ValueError(f"--without {name}: a critical node (the watchdog would not arm)")
    cfg["can"] = can
    cfg["trigger"] = {"source": "simulated", "sim_period_s": 0}
    wd = cfg.setdefault("watchdog", {})
    wd.update(
        heartbeat_deadline_ms=TIMINGS[timings]["heartbeat_deadline_ms"],
        pulse_silence_ms=TIMINGS[timings]["pulse_silence_ms"],
        start_grace_ms=start_grace_ms,
        maccepa_boards=[0],
    )
    nodes = [n for n in cfg.get("nodes", []) if n.get("plugin") != "simulator"]
    # The board is read where the config reads boards: by the h2 reader when its params name
    # maccepa_boards (board.yaml since the bus is read in one process), else by the bridge.
    in_reader = any(
        n["plugin"] == "h2_reader" and "maccepa_boards" in (n.get("params") or {}) for n in nodes
    )
    for n in nodes:
        if n["plugin"] == "timing_monitor" or (n["plugin"] == "maccepa_bridge" and not in_reader):
            n["enabled"] = True
        if n["name"] in without:
            n["enabled"] = False
        if n["plugin"] == "maccepa_bridge":
            n["params"] = {**n.get("params", {}), "boards": [0]}
        if n["plugin"] == "h2_reader" and in_reader:
            n["params"] = {**n.get("params", {}), "maccepa_boards": [0]}
        if n["plugin"] == "timing_monitor":
            n["params"] = {**n.get("params", {}), "ids": [70, 110]}
        if n["plugin"] == "recorder":
            n["params"] = {**n.get("params", {}), "autostart": True}
        if n["plugin"] == "controller_manager":
            for key in ("update_budget_ms", "h2_timeout_ms"):
                if key in TIMINGS[timings]:
                    n["params"] = {**n.get("params", {}), key: TIMINGS[timings][key]}
            if MANAGER_CYCLES is not None:
                n["params"] = {**n.get("params", {}), "cycles_per_update": MANAGER_CYCLES}
        if timings == "relaxed" and n.get("heartbeat_deadline_ms"):
            # a node's own deadline (the motion nodes' 50 ms) relaxed too: on a saturated CPU
            # the supervisor SIGKILLed the pattern player every few seconds (seen this stop);
            # a longer one (the observers') stays
            relaxed = TIMINGS[timings]["heartbeat_deadline_ms"]
            n["heartbeat_deadline_ms"] = max(n["heartbeat_deadline_ms"], relaxed)
            if n.get("leased_deadline_ms"):  # never under its own (the config refuses that)
                n["leased_deadline_ms"] = max(n["leased_deadline_ms"], relaxed)
        if (n.get("priority") or {}).get("cpus"):
            raise ValueError(f"node {n['name']} sets cpus: the bench keeps it on CPU 0")
    simulator = {
        "name": "simulator",
        "plugin": "simulator",
        "priority": {"cpus": [SIMULATOR_CPU]},
        # The hardware's stand-in, judged as loosely as hardware that sends on its own timer:
        # its frames are the kernel's, and on a slow host (calibration 295-454 ms) its Python
        # stalled 501 ms at the window's start, it was hung-killed, and its ops with it, so the
        # H2 fell silent and the watchdog tripped (B64, C64): a failure of the bench, not of
        # the appliance.
        "heartbeat_deadline_ms": SIM_DEADLINE_MS,
        # and starved, not hung, on a full CPU 1 (C73: killed while runnable; its restart
        # re-imports on the same CPU): judged again up to ten times that
        "starved_deadline_ms": 10 * SIM_DEADLINE_MS,
        # The hardware's stand-in, not the appliance: on TCG it could not step its models every
        # 10 ms, and CPU 1 full made its kernel timers late (H2 gaps the appliance took for
        # silence). The kernel still sends every frame every 10 ms (udp_multicast: ignored).
        "params": {"maccepa_boards": [0], "update_cycles": SIM_UPDATE_CYCLES},
    }
    cfg["nodes"] = [simulator, *nodes]
    return cfg


def enabled_nodes(cfg: dict[str, Any]) -> set[str]:
    return {n["name"] for n in cfg["nodes"] if n.get("enabled", True)}


def beating(status: dict[str, Any], expected: set[str]) -> bool:
    """Every enabled node of the config is listed (the supervisor answers before it has started
    them) and has sent a heartbeat."""
    nodes = {n["name"]: n for n in status["nodes"]}
    return expected <= nodes.keys() and all(
        nodes[name]["state"] == "running" and nodes[name]["heartbeat_age_s"] is not None
        for name in expected
    )


@dataclass
class JointStates:
    """Arrival times and publisher sequence numbers of joint_states on the laptop."""

    arrivals: list[float] = field(default_factory=list)
    seqs: list[int] = field(default_factory=list)
    counting: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_message(self, _key: str, seq: int, _ns: int, _payload: bytes) -> None:
        if not self.counting:
            return
        with self.lock:
            self.arrivals.append(time.monotonic())
            self.seqs.append(seq)

    def reset(self) -> None:
        with self.lock:
            self.arrivals.clear()
            self.seqs.clear()

    def summary(self, t0: float, seconds: float) -> dict[str, Any]:
        with self.lock:
            arr, seqs = list(self.arrivals), list(self.seqs)
        if len(arr) < 2:
            return {"n": len(arr), "error": "fewer than two samples on the laptop"}
        per_s = [0] * int(seconds)
        for t in arr:
            i = int(t - t0)
            if 0 <= i < len(per_s):
                per_s[i] += 1
        gaps = [b - a for a, b in itertools.pairwise(arr)]
        missed = sum(max(0, b - a - 1) for a, b in itertools.pairwise(seqs))
        return {
            "n": len(arr),
            "rate_hz": round((len(arr) - 1) / (arr[-1] - arr[0]), 2),
            "per_second_min": min(per_s),
            "per_second_max": max(per_s),
            "max_gap_ms": round(max(gaps) * 1000, 1),
            "gaps_over_50ms": sum(g > 0.05 for g in gaps),
            "seq_missed": missed,
        }


class Laptop:
    """The host side: one Zenoh client session for queries and the subscriber, the CLI for the
    operator's commands (arm, pattern), exactly as a lab laptop drives the board."""

    def __init__(self, at: str, zenoh_config: str | None, device: str) -> None:
        self.at, self.zenoh_config, self.device = at, zenoh_config, device
        # A saturated guest answers Zenoh's handshake late: with the CLI's 3 s the bench laptop
        # never connected to the proxy (600 s of retries, last stop).
        self.session = messaging.open_client_session(at, zenoh_config, handshake_s=HANDSHAKE_S)
        self.joint_states = JointStates()
        self._sub: messaging.MessageSubscription | None = None
        self.holder: subprocess.Popen[str] | None = None

    def call(self, *path: str, body: dict[str, Any] | None = None, timeout: float = 10) -> Any:
        key = messaging.mgmt_key(self.device, *path)
        user = messaging.client_login(self.zenoh_config)
        return messaging.request(self.session, key, body or {}, timeout, user)

    def cli(self, *args: str, tries: int = 5) -> subprocess.CompletedProcess[str]:
        """One CLI command; retried while the board does not answer (exit 4: a busy guest can
        take longer than the CLI's timeout to accept a new session)."""
        for _ in range(tries):
            r = subprocess.run(self._cli(*args), capture_output=True, text=True, timeout=120)
            if r.returncode != 4:
                break
            time.sleep(2)
        return r

    def _cli(self, *args: str) -> list[str]:
        opts = ["--at", self.at, "--device", self.device, "--timeout", "20"]
        if self.zenoh_config:
            opts += ["--zenoh-config", self.zenoh_config]
        return [sys.executable, "-m", "exolink.cli.main", *args, *opts]

    def wait_beating(
        self, timeout: float, expected: set[str]
    ) -> tuple[dict[str, Any] | None, bool]:
        """The first status in which every enabled node has sent a heartbeat, or the last one
        seen when ``timeout`` ran out (with False)."""
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            with contextlib.suppress(messaging.Unreachable):
                st = self.call("status", timeout=10)
                if st.get("ok"):
                    last = dict(st)
                    if beating(st, expected):
                        self._subscribe()
                        return last, True
            time.sleep(2)
        return last, False

    def _subscribe(self) -> None:
        """joint_states, once the h2 reader runs: whether it is bundled is asked of its tokens
        (a laptop client takes a bundled topic as bundles, unless ONE_BY_ONE)."""
        if self._sub is None:
            key = messaging.topic_selector(0, "h2", "joint_states")
            on = self.joint_states.on_message
            self._sub = messaging.MessageSubscription(
                self.session, self.device, key, on, bundles=not ONE_BY_ONE
            )

    @property
    def joint_states_shape(self) -> str:
        """How the laptop takes joint_states: as bundles or one message per sample."""
        if self._sub is None:
            return "not subscribed"
        return "bundles" if self._sub.bundled else "one by one"

    def arm_and_start_pattern(self, timeout: float = 120) -> dict[str, Any]:
        """``exolink arm`` (retried while refused), select, speed 10, ``pattern start`` held."""
        out: dict[str, Any] = {}
        deadline = time.monotonic() + timeout
        while True:
            r = self.cli("arm")
            out["arm"] = (r.stdout + r.stderr).strip()
            if r.returncode == 0 or time.monotonic() > deadline:
                break
            time.sleep(3)
        out["armed"] = r.returncode == 0
        for args in (("pattern", "select", *PATTERN_JOINTS), ("pattern", "speed", "10")):
            r = self.cli(*args)
            out[" ".join(args[:2])] = (r.stdout + r.stderr).strip()
        self.holder = subprocess.Popen(
            self._cli("pattern", "start"),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        if PID_JOINT:  # a feedback controller beside the gait: the manager's 100 Hz cycle loop
            time.sleep(5)  # the pattern's holder first (the PID needs a holder too)
            params = json.dumps({"joints": [PID_JOINT], "kp": 0.5})
            r = self.cli("controllers", "load", "benchpid", "pid", "--params", params, "--activate")
            out["pid"] = (r.stdout + r.stderr).strip()
        return out

    def fetch(self, name: str, dest: Path) -> subprocess.Popen[str]:
        """``exolink record fetch NAME`` in the background, as an operator's laptop runs it."""
        dest.mkdir(parents=True, exist_ok=True)
        (dest / name).unlink(missing_ok=True)
        return subprocess.Popen(
            self._cli("record", "fetch", name, "-o", str(dest)),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )

    def stop_pattern(self) -> str:
        if self.holder is None:
            return ""
        if self.holder.poll() is None:
            os.killpg(self.holder.pid, 2)  # Ctrl-C: the CLI stops the pattern itself
        try:
            out, _ = self.holder.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.holder.kill()
            out, _ = self.holder.communicate()
        return out.replace("\r", "\n")[-2000:]

    def close(self) -> None:
        if self._sub is not None:
            with contextlib.suppress(Exception):
                self._sub.close()
        self.session.close()


def counters(laptop: Laptop) -> dict[str, Any]:
    """What the appliance itself reports, read before and after the window."""
    out: dict[str, Any] = {}
    for name, path, body in (
        ("status", ("status",), {}),
        ("h2_reader", ("nodes", "h2_reader", "stats"), {}),
        ("pattern", ("pattern",), {"action": "status"}),
        ("recorder", ("record",), {"action": "status"}),
        ("controllers", ("controllers",), {"action": "list"}),
    ):
        try:
            out[name] = laptop.call(*path, body=body, timeout=15)
        except messaging.Unreachable as exc:
            out[name] = {"error": str(exc)}
    return out


def timing_query(laptop: Laptop, seconds: float, query: dict[str, Any]) -> dict[str, Any]:
    """The timing monitor's period deviation of ``query``'s frames over the ``seconds`` before
    now (``past``: asked after the window, so two questions do not queue behind each other's
    wait, as they did in J66), with the span it covers."""
    body = {**query, "seconds": round(seconds, 1), "past": True}
    try:
        return laptop.call("timing", body=body, timeout=60) | {"span_s": body["seconds"]}
    except messaging.Unreachable as exc:
        return {"error": str(exc)}


def measure(laptop: Laptop | None, probe: subprocess.Popen[str], seconds: float) -> dict[str, Any]:
    """The window: started by the probe's PROBE_T0 line (its first /proc snapshot). Without a
    laptop (it could not connect) only the probe's figures."""
    assert probe.stdout is not None
    before = counters(laptop) if laptop is not None else {}
    t_before = time.monotonic()
    line = ""
    for line in probe.stdout:
        if line.startswith("PROBE_T0"):
            break
    else:
        return {"error": f"probe ended before its first snapshot: {line!r}"}
    t0 = time.monotonic()
    if laptop is not None:
        laptop.joint_states.counting = True
    result = ""
    for line in probe.stdout:
        if line.startswith("PROBE_RESULT "):
            result = line.split(" ", 1)[1]
    probe.wait()
    out: dict[str, Any] = {"probe": json.loads(result) if result else {"error": "no probe result"}}
    if laptop is None:
        return out
    laptop.joint_states.counting = False
    span = time.monotonic() - t0  # the window and the probe's end: the gait still runs
    timing = timing_query(laptop, span, TIMING_QUERY)
    angles = timing_query(laptop, span, ANGLES_QUERY)
    after = counters(laptop)
    return out | {
        "joint_states": laptop.joint_states.summary(t0, seconds)
        | {"taken_as": laptop.joint_states_shape},
        "timing": timing,
        "angles": angles,
        "before": before,
        "after": after,
        # the two readings are further apart than the window (the timing queries end after it)
        "counters_span_s": round(time.monotonic() - t_before, 1),
    }


def derived(m: dict[str, Any]) -> dict[str, Any]:
    """The headline figures out of the raw before/after counters."""
    b, a = m.get("before", {}), m.get("after", {})
    out: dict[str, Any] = {}
    wd0, wd1 = b.get("status", {}).get("watchdog", {}), a.get("status", {}).get("watchdog", {})
    out["watchdog_state_end"] = wd1.get("state")
    out["watchdog_reason_end"] = wd1.get("reason")
    if "trips" in wd0 and "trips" in wd1:
        out["watchdog_trips_in_window"] = wd1["trips"] - wd0["trips"]
    out["read_lag_max_ms"] = wd1.get("read_lag_max_ms")
    if "frames_read" in wd0 and "frames_read" in wd1:
        out["watchdog_frames_read"] = wd1["frames_read"] - wd0["frames_read"]
    r0, r1 = b.get("h2_reader", {}), a.get("h2_reader", {})
    if isinstance(r0.get("missing"), dict) and isinstance(r1.get("missing"), dict):
        out["h2_reader_missing"] = {
            k: r1["missing"][k] - r0["missing"].get(k, 0) for k in r1["missing"]
        }
        out["h2_reader_frames"] = {
            k: r1["frames"][k] - r0["frames"].get(k, 0) for k in r1.get("frames", {})
        }
        out["h2_reader_malformed"] = r1.get("malformed", 0) - r0.get("malformed", 0)
    p0, p1 = b.get("pattern", {}), a.get("pattern", {})
    if "sent" in p0 and "sent" in p1:
        out["pattern_state_end"] = p1.get("state")
        out["pattern_sent"] = p1["sent"] - p0["sent"]
    c0, c1 = b.get("controllers", {}), a.get("controllers", {})
    if "written" in c0 and "written" in c1:  # the manager writes the pattern: its cycle
        t0, t1 = c0.get("timer", {}), c1.get("timer", {})  # loop's frames and its timer's
        timer = t1["sent"] - t0["sent"] if "sent" in t0 and "sent" in t1 else 0
        out["pattern_sent"] = c1["written"] - c0["written"] + timer
    for name, x0, x1 in (("h2_reader", r0, r1), ("controller_manager", c0, c1)):
        if "loop_cpu" in x0 and "loop_cpu" in x1:  # where each loop's CPU went (phaseclock)
            out[f"{name}_loop_cpu"] = phaseclock.window(x0["loop_cpu"], x1["loop_cpu"])
            if "wall_max_ms" in x1["loop_cpu"]:  # since the reading before the window
                out[f"{name}_loop_wall_max_ms"] = x1["loop_cpu"]["wall_max_ms"]
    if "cycles" in c0 and "cycles" in c1:
        out["manager_cycles"] = c1["cycles"] - c0["cycles"]
        if m.get("counters_span_s"):
            out["manager_cycles_per_s"] = round(out["manager_cycles"] / m["counters_span_s"], 1)
    rec0, rec1 = b.get("recorder", {}), a.get("recorder", {})
    for k in ("received", "written", "dropped"):
        if k in rec0 and k in rec1:
            out[f"recorder_{k}"] = rec1[k] - rec0[k]
    out["recorder_state_end"] = rec1.get("state")
    nodes0 = {n["name"]: n for n in b.get("status", {}).get("nodes", [])}
    out["node_restarts_in_window"] = {
        n["name"]: n["restarts"] - nodes0.get(n["name"], {}).get("restarts", 0)
        for n in a.get("status", {}).get("nodes", [])
    }
    return out


def write_text(path: Path, text: str, mode: int = 0o644) -> Path:
    path.write_text(text)
    path.chmod(mode)
    return path
