"""Supervisor parts that face the kernel or systemd, exercised as far as this kernel allows.

Real: a unix datagram socket standing in for systemd's notify socket, /proc for priorities.
Not exercised here (no CAN or GPIO in this kernel): netlink bring-up of a CAN link and libgpiod
edge events; `make test-kernel` runs those in a VM (tests/kernel/).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from benchmarks.harness import free_port
from exolink.config import NodeConfig, Priority, TriggerConfig
from exolink.supervisor import canlink, starving, trigger
from exolink.supervisor.osproc import apply_priority, proc_usage
from exolink.supervisor.systemd import Notifier


def test_overlay_check(tmp_path: Path) -> None:
    status = tmp_path / "status"
    status.write_bytes(b"okay\x00")
    canlink.check_overlay(status)
    status.write_bytes(b"disabled\x00")
    with pytest.raises(canlink.CanLinkError, match=r"DCAN1 is 'disabled'.*overlay is not applied"):
        canlink.check_overlay(status)
    with pytest.raises(canlink.CanLinkError, match="DCAN1 not found in the device tree"):
        canlink.check_overlay(tmp_path / "missing")


def test_missing_interface_names_the_fix() -> None:
    with pytest.raises(canlink.CanLinkError, match=r"no network interface 'can7'.*c_can_platform"):
        canlink.health("can7")


def test_link_monitor_follows_the_drivers_error_frames_and_names_the_fix() -> None:
    """The state machine on the driver's error frames (no CAN socket in this kernel: the
    frames are given to it here; tests/kernel/test_socketcan.py injects them on a vcan), the
    link's up/down from sysfs (loopback: no CAN state, "up")."""
    m = canlink.LinkMonitor("lo")
    assert m.health().state == "up"
    err, crtl, cnt = canlink.ERR_FLAG, canlink.ERR_CRTL, canlink.ERR_CNT
    m.on_error_frame(err | crtl | cnt, 8, bytes([0, 0x08, 0, 0, 0, 0, 97, 3]))  # tx warning
    assert m.health() == canlink.LinkHealth("error-warning", 97, 3)
    m.on_error_frame(err | crtl | cnt, 8, bytes([0, 0x20, 0, 0, 0, 0, 130, 5]))  # tx passive
    assert m.health().state == "error-passive" and m.health().bad
    m.on_error_frame(err | canlink.ERR_BUSOFF, 8, bytes(8))
    assert m.health().state == "bus-off"
    m.on_error_frame(err | canlink.ERR_RESTARTED, 8, bytes(8))
    h = m.health()
    assert (h.state, h.txerr, h.rxerr, h.restarts) == ("error-active", 0, 0, 1) and not h.bad
    m.on_error_frame(70, 6, bytes(8))  # not an error frame: ignored
    assert m.health().state == "error-active"
    with pytest.raises(canlink.CanLinkError, match=r"no network interface 'can7'"):
        canlink.LinkMonitor("can7").health()


def test_the_supervisor_never_loads_pyroute2(tmp_path: Path) -> None:
    """Bring-up runs pyroute2 in a child (``bring_up_apart``: a missing link refused there,
    named here); the supervisor's modules and its link monitor do not import it."""
    code = (
        "import sys\n"
        "from exolink.config import CanConfig\n"
        "from exolink.supervisor import canlink, core\n"
        "m = canlink.LinkMonitor('lo'); m.health(); m.wait(0.01); m.close()\n"
        "try:\n"
        "    canlink.bring_up_apart(CanConfig(channel='can7'))\n"
        "except canlink.CanLinkError as exc:\n"
        "    print('refused:', exc)\n"
        "print('pyroute2' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "refused: no network interface 'can7'" in r.stdout, r.stdout
    assert r.stdout.strip().endswith("False"), r.stdout


def test_link_health_bad_states() -> None:
    assert canlink.LinkHealth("bus-off").bad and canlink.LinkHealth("error-passive").bad
    assert not canlink.LinkHealth("error-active").bad and not canlink.LinkHealth("up").bad


def test_sd_notify_over_a_real_socket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = str(tmp_path / "notify")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    srv.settimeout(1)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    n = Notifier()
    assert n.enabled and n.ping_interval_s == 1.0
    n.ready()
    n.ping()
    assert srv.recv(64) == b"READY=1"
    assert srv.recv(64) == b"WATCHDOG=1"
    srv.close()


THREADED = "import threading, time\nfor _ in range(3): threading.Thread(target=time.sleep, args=(5,)).start()\nprint(flush=True)\ntime.sleep(5)"


def test_priority_and_usage_applied_to_a_real_process() -> None:
    """On every thread: a running node already has Zenoh's threads when its priority comes."""
    p = subprocess.Popen([sys.executable, "-c", THREADED], stdout=subprocess.PIPE)
    try:
        assert p.stdout is not None and p.stdout.readline() == b"\n"  # its threads are running
        apply_priority(
            NodeConfig(name="x", plugin="h2_reader", priority=Priority(nice=7, cpus=[0])), p.pid
        )
        tids = [int(t) for t in os.listdir(f"/proc/{p.pid}/task")]
        assert len(tids) == 4
        assert {os.getpriority(os.PRIO_PROCESS, t) for t in tids} == {7}
        assert {frozenset(os.sched_getaffinity(t)) for t in tids} == {frozenset({0})}
        usage = proc_usage(p.pid)
        assert usage["rss_mb"] > 1
    finally:
        p.kill()
        p.wait()


def test_simulated_trigger_fires_and_periods() -> None:
    edges: list[trigger.Edge] = []
    src = trigger.SimulatedTrigger(
        TriggerConfig(source="simulated", sim_period_s=0.05), edges.append
    )
    time.sleep(0.3)
    src.fire()
    src.close()
    assert len(edges) >= 4 and all(e.rising and e.source == "simulated" for e in edges)
    assert all(abs(e.stamp_ns - time.time_ns()) < 5e9 for e in edges)


def test_gpio_trigger_missing_chip_is_a_clear_error() -> None:
    with pytest.raises(trigger.TriggerError, match="no GPIO chip /dev/gpiochip42"):
        trigger.GpioTrigger(TriggerConfig(chip="/dev/gpiochip42"), lambda e: None)


SIGNAL_STORM = """
import os, signal, sys, threading
import structlog
from exolink.runtime import stop_on_signals

stop, got = threading.Event(), threading.Event()
stop_on_signals(stop, structlog.get_logger())

def pester() -> None:
    for _ in range(int(sys.argv[1])):
        os.kill(os.getpid(), signal.SIGTERM)
        if not got.wait(5):
            os._exit(3)  # the main thread never saw the stop: it is stuck
        got.clear()
    os._exit(0)

threading.Thread(target=pester, daemon=True).start()
while True:  # busy polling: most of the time inside wait(), holding its lock
    if stop.wait(0):
        stop.clear()
        got.set()
"""


def test_sigterm_while_waiting_on_the_stop_event_never_deadlocks() -> None:
    # Seen on a laptop: `exolink up` logged SIGTERM and then hung for good. The handler ran
    # Event.set() while the interrupted main thread held that Event's lock inside wait().
    r = subprocess.run(
        [sys.executable, "-c", SIGNAL_STORM, "400"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, f"exit {r.returncode}: the process stopped reacting to SIGTERM"
    assert r.stdout.count("signal=SIGTERM") == 400, r.stdout[-500:]


def test_simulated_buses_on_different_groups_do_not_hear_each_other(group: str) -> None:
    # Found when a leftover `exolink up --sim` on the default group made a test's bus see
    # foreign disable frames: Linux hands a 0.0.0.0-bound socket every group joined on the host.
    import can

    from exolink.canbus import open_bus
    from exolink.config import CanConfig

    other = "239.74.0.1" if group != "239.74.0.1" else "239.74.0.2"
    a, a2, b = (
        open_bus(CanConfig(interface="udp_multicast", channel=g)) for g in (group, group, other)
    )
    try:
        a.send(can.Message(arbitration_id=0x46, data=bytes(8), is_extended_id=False))
        got = a2.recv(2.0)
        assert got is not None and got.arbitration_id == 0x46
        assert b.recv(0.5) is None
    finally:
        for bus in (a, a2, b):
            bus.shutdown()


def test_the_loop_sleeps_until_the_nearest_deadline() -> None:
    """No 100 Hz tick: the supervisor wakes when a heartbeat would be late (the pattern player's
    50 ms deadline in board.yaml is the nearest), a restart is due, or the watchdog has work."""
    from exolink.config import bundled, parse
    from exolink.supervisor.core import Supervisor
    from exolink.supervisor.judging import MAX_SLEEP_S, STARTING_SLEEP_S
    from exolink.supervisor.processes import NodeProcess

    cfg = parse(bundled("board").read_text(), "board.yaml")
    sup = Supervisor(cfg)

    class Idle:  # a watchdog with nothing to do
        def next_due(self) -> float:
            return float("inf")

    sup.watchdog = Idle()  # type: ignore[assignment]
    now = 1000.0
    grace = cfg.watchdog.start_grace_ms / 1000

    def judged(node: NodeProcess) -> None:  # as _check_nodes leaves it (due_at)
        node.due_at = sup._due(node, now, grace)

    for ncfg in cfg.nodes:
        node = NodeProcess(ncfg, "", lambda _e: None, lambda _n, _l: None)
        node.state, node.heartbeat_at = "running", now
        judged(node)
        sup.nodes[ncfg.name] = node
    assert sup._next_due(now) == now + 0.05  # the motion nodes' heartbeat_deadline_ms
    for name in [n.name for n in cfg.nodes if n.heartbeat_deadline_ms == 50]:
        del sup.nodes[name]
    assert sup._next_due(now) == now + MAX_SLEEP_S  # 500 ms deadlines: the cap comes first
    sup.nodes["recorder"].state, sup.nodes["recorder"].next_start = "backoff", now + 0.03
    judged(sup.nodes["recorder"])
    assert sup._next_due(now) == now + 0.03
    sup.nodes["recorder"].state, sup.nodes["recorder"].heartbeat_at = "running", None
    sup.nodes["recorder"].started_at = now
    judged(sup.nodes["recorder"])  # starting: looked at often, for its first beat
    assert sup._next_due(now) == now + STARTING_SLEEP_S


def test_an_idle_motion_node_is_held_to_the_default_deadline_until_it_says_otherwise() -> None:
    """The controller manager with nothing active beats 5 times a second, not 50, and says it is
    idle (exolink.liveness): judged by the 500 ms default then, by its own 50 ms from its first
    beat that is not idle, which the supervisor reads within those 50 ms."""
    from exolink import liveness
    from exolink.config import bundled, parse
    from exolink.supervisor.core import Supervisor
    from exolink.supervisor.processes import NodeProcess

    cfg = parse(bundled("board").read_text(), "board.yaml")
    sup = Supervisor(cfg)
    trips: list[str] = []

    class Armed:  # a real watchdog needs a bus; only its trip matters here
        armed = True

        def trip(self, _reason: str, detail: str) -> None:
            trips.append(detail)

        def next_due(self) -> float:
            return float("inf")

    sup.watchdog = Armed()  # type: ignore[assignment]
    node = NodeProcess(cfg.node("controller_manager"), "", lambda _e: None, lambda _n, _l: None)
    node.channel = liveness.Channel()
    beater = liveness.Beater(node.channel.child_fd)
    sup.nodes = {node.name: node}

    def spawn() -> None:  # a process to kill when it is found hung, past its first beat
        node.proc = subprocess.Popen(["sleep", "60"])
        node.state, node.heartbeat_at = "running", 999.0

    spawn()
    try:
        beater.beat(1000.0, pace=liveness.Pace.IDLE)
        sup._check_nodes(1000.3)
        assert trips == [] and node.pace == liveness.Pace.IDLE
        assert sup._next_due(1000.3) == pytest.approx(1000.35)  # its own deadline from now
        beater.beat(1000.31, pace=liveness.Pace.OWN)  # activating: then hung
        sup._check_nodes(1000.35)
        assert trips == [] and node.pace == liveness.Pace.OWN
        sup._check_nodes(1000.37)
        assert trips == ["controller_manager: no heartbeat for 60 ms (deadline 50 ms)"]
        assert node.state == "killed"
        node.proc.wait()
        spawn()
        beater.beat(1001.0, pace=liveness.Pace.IDLE)  # idle, then silent past the default deadline
        sup._check_nodes(1001.4)
        assert len(trips) == 1
        sup._check_nodes(1001.6)
        assert trips[1] == "controller_manager: no heartbeat for 600 ms (deadline 500 ms)"
        assert node.state == "killed"
    finally:
        node.kill()
        node.channel.close()


def test_a_leased_motion_node_is_held_to_its_leased_deadline_until_the_lease_ends() -> None:
    """The controller manager while only the kernel's timer sends says so (Pace.LEASED): the
    board config's leased_deadline_ms (200) judges it, then its own 50 ms again from its first
    beat that is not leased. The lease (200 ms) has ended the motion by then (node.py)."""
    from exolink import liveness

    sup, trips = _supervisor_recording_trips()
    node, beater = _sleeping_node(sup, "controller_manager", timer=False)
    assert sup.cfg.deadline_s(node.cfg, liveness.Pace.LEASED) == 0.2
    try:
        beater.beat(1000.0, pace=liveness.Pace.LEASED)
        sup._check_nodes(1000.19)  # 190 ms: late by its own 50 ms, not by the lease's 200
        assert trips == [] and node.pace == liveness.Pace.LEASED
        assert sup._next_due(1000.19) == pytest.approx(1000.2)
        beater.beat(1000.195, pace=liveness.Pace.OWN)  # back to the cycle loop: then hung
        sup._check_nodes(1000.24)
        assert trips == [] and node.pace == liveness.Pace.OWN
        sup._check_nodes(1000.255)
        assert trips == ["controller_manager: no heartbeat for 60 ms (deadline 50 ms)"]
        node.proc.wait()
        node.proc = subprocess.Popen(["sleep", "60"])
        node.state = "running"
        beater.beat(1001.0, pace=liveness.Pace.LEASED)  # leased, then silent past 200 ms
        sup._check_nodes(1001.21)
        assert trips[1:] == ["controller_manager: no heartbeat for 210 ms (deadline 200 ms)"]
        assert node.state == "killed"
    finally:
        node.kill()
        node.channel.close()


def test_between_sweeps_the_loop_reads_only_the_nodes_whose_deadline_came() -> None:
    """The manager's 50 ms deadline wakes the loop ~20 times a second: those wakes read its
    pipe, not the others' (their beats wait for their own deadlines or the next sweep), and a
    hung node with a 500 ms deadline is still caught at that deadline, not at a sweep."""
    from exolink.supervisor.judging import SWEEP_S

    sup, trips = _supervisor_recording_trips()
    beaters = {}
    for name in ("controller_manager", "h2_reader"):
        node, beaters[name] = _sleeping_node(sup, name, timer=False)
        node.heartbeat_at = 999.0
    manager, reader = sup.nodes["controller_manager"], sup.nodes["h2_reader"]
    try:
        for name in beaters:
            beaters[name].beat(1000.0)
        sup._check_nodes(1000.0)  # the first look is a sweep: both read
        assert manager.heartbeat_at == reader.heartbeat_at == 1000.0
        t = 1000.0
        while t < 1000.0 + min(SWEEP_S, 0.5) - 0.06:  # the manager beats every 20 ms ...
            t = round(t + 0.02, 3)
            beaters["controller_manager"].beat(t)
            beaters["h2_reader"].beat(t)  # ... and so does the reader
            if t >= sup._next_due(t):
                sup._check_nodes(t)
        assert manager.heartbeat_at is not None and manager.heartbeat_at > 1000.3
        assert reader.heartbeat_at == 1000.0  # its beats wait in its pipe
        assert trips == []
        beaters["controller_manager"].beat(1000.5)
        sup._check_nodes(1000.5)  # the reader's deadline: its pipe read, on time
        assert reader.heartbeat_at == t and trips == []
        hung = reader.due_at + 0.001  # then it hangs: caught at its deadline
        beaters["controller_manager"].beat(hung)
        sup._check_nodes(hung)
        assert trips and trips[-1].startswith("h2_reader: no heartbeat for 501 ms")
        assert reader.state == "killed"
    finally:
        for node in sup.nodes.values():
            node.kill()
            assert node.channel is not None
            node.channel.close()


def test_a_trip_wakes_the_supervisor_for_its_repeats() -> None:
    import threading

    from exolink import hardware
    from exolink.canbus import open_reader
    from exolink.config import CanConfig, WatchdogConfig
    from exolink.supervisor.watchdog import REPEAT_AFTER_S, Watchdog

    reader = open_reader(CanConfig(interface="virtual", channel="wake-test"), [110, 70])
    wd = Watchdog(WatchdogConfig(), reader, lambda _s: None, hardware.load("h2"))
    woken = threading.Event()
    wd.wake = woken.set
    try:
        assert wd.next_due() == float("inf")
        before = time.monotonic()
        wd.trip("operator e-stop")
        assert woken.is_set()
        assert before + REPEAT_AFTER_S[0] <= wd.next_due() <= time.monotonic() + REPEAT_AFTER_S[0]
    finally:
        wd.close()
        reader.bus.shutdown()


def test_a_node_process_starts_on_its_configured_cpus(write_config) -> None:  # type: ignore[no-untyped-def]
    """Every thread, Zenoh's included, on the node's CPUs from the start: the supervisor's
    per-thread pass at the first heartbeat raced with the threads a session starts (on the
    board proxy the simulator, pinned to CPU 1, kept threads on CPU 0). Run here without a
    supervisor, so only the runtime itself can have pinned them."""
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs 2 CPUs")
    cpu = max(os.sched_getaffinity(0))
    node = {"name": "tm", "plugin": "timing_monitor", "priority": {"cpus": [cpu]}}
    path = write_config(nodes=[node])
    port = free_port()
    p = subprocess.Popen(
        [sys.executable, "-m", "exolink.runtime", "tm", "-c", str(path),
         "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert p.stdout is not None
        for line in p.stdout:
            if "node_running" in line:
                break
        else:
            raise AssertionError(f"the node did not start (rc {p.wait()})")
        tids = os.listdir(f"/proc/{p.pid}/task")
        assert len(tids) > 3  # Zenoh's threads and the heartbeat's
        assert {frozenset(os.sched_getaffinity(int(t))) for t in tids} == {frozenset({cpu})}
    finally:
        p.kill()
        p.wait()


def test_a_stop_whose_node_is_never_reaped_returns_and_says_why(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A stop waited without end after SIGKILL, and every later management request queued
    behind it (seen twice in native ladder runs: 206 s, 11 min). Stand-in for a process the
    kernel does not let go (D state, which cannot be made here): a process handle whose wait
    never returns, pointing at this test's own pid so the kernel's state can be read."""
    import structlog

    from exolink.supervisor import processes

    monkeypatch.setattr(processes, "REAP_WAIT_S", 0.1)

    class Unreaped:
        pid = os.getpid()
        signals: list[str] = []

        def poll(self) -> None:
            return None

        def terminate(self) -> None:
            self.signals.append("TERM")

        def kill(self) -> None:
            self.signals.append("KILL")

        def wait(self, timeout: float | None = None) -> int:
            raise subprocess.TimeoutExpired("unreaped", timeout or 0)

    node = processes.NodeProcess(
        NodeConfig(name="stuck", plugin="h2_reader"), "", lambda _e: None, lambda _n, _l: None
    )
    node.proc = Unreaped()  # type: ignore[assignment]
    with structlog.testing.capture_logs() as logs:
        node.stop(timeout=0.1)
    assert Unreaped.signals == ["TERM", "KILL"] and node.state == "stopped"
    (event,) = [e for e in logs if e["event"] == "node_not_reaped"]
    assert event["node_name"] == "stuck" and event["state"].split()[0] in {"R", "S"}


def test_junk_on_a_nodes_diagnostics_is_counted_not_believed_and_logged_once() -> None:
    """Anyone on the network may put on a node's diagnostics key: a payload that is no
    DiagnosticArray leaves the supervisor's view of the node (what `exolink status` shows) as
    it was, is counted, and is logged at its first and every 1000th occurrence, not at each."""
    from structlog.testing import capture_logs

    from exolink import messaging
    from exolink.config import bundled, parse
    from exolink.supervisor.core import Supervisor
    from exolink.supervisor.processes import NodeProcess
    from exolink.wire import cdr

    sup = Supervisor(parse(bundled("sim").read_text(), "sim.yaml"))
    cfg = sup.cfg.node("recorder")
    sup.nodes = {"recorder": NodeProcess(cfg, "", lambda _e: None, lambda _n, _l: None)}
    key = messaging.topic_key(0, "h2", "nodes/recorder/diagnostics", messaging.DIAGNOSTICS_TYPE)
    good = cdr.diagnostics(1, "recorder", 2, "disk full", "sim", {})
    with capture_logs() as logs:
        sup._node_diagnostics(key, good)
        for _ in range(1000):
            sup._node_diagnostics(key, good[:20])
    assert sup.nodes["recorder"].health == "error: disk full"
    assert sum(sup.bad_samples.values()) == 1000
    assert [e["count"] for e in logs if e["event"] == "bad_sample"] == [1, 1000]


def _supervisor_recording_trips() -> tuple[Any, list[str]]:
    """A supervisor (board config) whose watchdog only records trips, with no nodes yet."""
    from exolink.config import bundled, parse
    from exolink.supervisor.core import Supervisor

    sup = Supervisor(parse(bundled("board").read_text(), "board.yaml"))
    sup.nodes = {}
    trips: list[str] = []

    class Armed:
        armed = True

        def trip(self, _reason: str, detail: str) -> None:
            trips.append(detail)

        def next_due(self) -> float:
            return float("inf")

    sup.watchdog = Armed()
    return sup, trips


def _sleeping_node(sup: Any, name: str, timer: bool) -> tuple[Any, Any]:
    """Node ``name`` of the board config as a ``sleep`` process with a liveness pipe (and its
    deadline timer, set by the beater's beats: own deadline and idle), and the beater its loop
    would hold."""
    from exolink import liveness
    from exolink.supervisor.processes import NodeProcess

    cfg = sup.cfg
    node = NodeProcess(cfg.node(name), "", lambda _e: None, lambda _n, _l: None)
    node.channel = liveness.Channel()
    deadlines = cfg.deadlines_s(node.cfg) if timer else ()
    beater = liveness.Beater(node.channel.child_fd, node.channel.timer, deadlines)
    node.proc = subprocess.Popen(["sleep", "60"])
    # asleep before it is judged: a process not yet run (a loaded CI host) is runnable and
    # would be judged starved, not hung (exolink.supervisor.starving)
    end = time.monotonic() + 10
    while (st := starving.read(node.proc.pid, 0.0, states=True)) is not None and st.state != "S":
        assert time.monotonic() < end, st
        time.sleep(0.01)
    node.state, node.heartbeat_at = "running", time.monotonic()
    sup.nodes[name] = node
    return node, beater


def _manager_with_timer() -> tuple[Any, Any, Any, list[str]]:
    sup, trips = _supervisor_recording_trips()
    node, beater = _sleeping_node(sup, "controller_manager", timer=True)
    return sup, node, beater, trips


def _judged_hung_on_its_50_ms(sup: Any, node: Any, trips: list[str]) -> None:
    """The loop's next look trips the watchdog once, on the manager's own deadline, and kills
    the node."""
    sup._check_nodes(time.monotonic())
    assert len(trips) == 1 and trips[0].endswith("(deadline 50 ms)")
    assert node.state == "killed"


def test_a_nodes_deadline_timer_wakes_the_loop_only_when_it_runs_out() -> None:
    """Each beat sets the node's timerfd to the beat's time plus its deadline (exolink.liveness):
    the loop does not poll that deadline, the kernel wakes it when a node misses it, and the
    pipe then judges. A timer that ran out while the pipe holds a later beat (the node was
    preempted between the two) leaves the node to polling until its timer is set again."""
    import math

    from exolink import liveness
    from exolink.supervisor.judging import MAX_SLEEP_S

    sup, node, beater, trips = _manager_with_timer()
    try:
        beater.beat()
        now = time.monotonic()
        sup._check_nodes(now)
        assert node.due_at == math.inf and node.channel.armed(0.5)
        assert sup._next_due(now) == now + MAX_SLEEP_S  # no 50 ms polling
        # preempted between its record and its timer: the timer runs out, the pipe is newer
        time.sleep(0.03)
        liveness.Beater(node.channel.child_fd).beat()  # a record, no timer set
        woke, ready = sup.wake.wait_any(5.0, [node.channel.timer])
        assert ready == [node.channel.timer] and not woke
        sup._timer_ran_out(node, ready[0])
        sup._check_nodes(time.monotonic())
        assert trips == [] and node.due_at < math.inf  # polled until its next beat
        # then hung: the timer has run out, so the polled deadline catches it
        time.sleep(max(0.0, node.due_at - time.monotonic()) + 0.001)
        sup._check_nodes(time.monotonic())
        assert trips and trips[0].startswith("controller_manager: no heartbeat for")
        assert trips[0].endswith("(deadline 50 ms)") and node.state == "killed"
    finally:
        node.kill()
        node.channel.close()


def test_a_hung_node_is_judged_when_its_timer_runs_out() -> None:
    from exolink import liveness

    sup, node, beater, trips = _manager_with_timer()
    try:
        beater.beat(pace=liveness.Pace.IDLE)  # idle: the default deadline
        sup._check_nodes(time.monotonic())
        t0 = time.monotonic()
        beater.beat(pace=liveness.Pace.OWN)  # driving: its own 50 ms from this beat, then silent
        _, ready = sup.wake.wait_any(5.0, [node.channel.timer])
        assert ready == [node.channel.timer] and time.monotonic() - t0 >= 0.05
        sup._timer_ran_out(node, ready[0])
        _judged_hung_on_its_50_ms(sup, node, trips)
    finally:
        node.kill()
        node.channel.close()


def test_a_timer_set_past_the_nodes_longest_deadline_is_not_trusted() -> None:
    """The node's own process sets its timer, as it writes its beats: one set a minute ahead
    (a bug) does not leave a hung node to the next sweep; its deadline is polled."""
    import math

    from exolink import liveness

    sup, node, beater, trips = _manager_with_timer()
    try:
        beater.beat()
        liveness.TIMERS.arm_at(node.channel.timer, time.monotonic() + 60)
        sup._check_nodes(time.monotonic())
        assert node.due_at < math.inf
        time.sleep(max(0.0, node.due_at - time.monotonic()) + 0.001)
        _judged_hung_on_its_50_ms(sup, node, trips)
    finally:
        node.kill()
        node.channel.close()


def test_an_old_spawns_exit_after_a_restart_leaves_the_new_one_alone() -> None:
    """`exolink restart`: the stopped spawn's exit can be reported after the next one started
    (CI saw the restarted simulator shown as stopped): it neither trips nor changes the state."""
    from exolink.supervisor.processes import Exit

    sup, trips = _supervisor_recording_trips()
    node, _ = _sleeping_node(sup, "controller_manager", timer=False)
    try:
        sup._on_exit(Exit(node.name, None, "SIGTERM", True, pid=node.proc.pid + 100_000))
        assert node.state == "running" and trips == []
        sup._on_exit(Exit(node.name, None, "SIGKILL", False, pid=node.proc.pid))
        assert trips and node.state != "running"  # its own exit still counts
    finally:
        node.kill()
        node.channel.close()
