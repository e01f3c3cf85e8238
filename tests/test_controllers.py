"""Controller manager: the pure logic fed H2 states (no transport), then the node on the simulator
with the watchdog, every claim checked by an independent listener on the bus."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import pytest
from conftest import bus_sockets
from exolink.nodes.controller_manager.builtin import JointTrajectory, Pid, PidParams
from exolink.nodes.controller_manager.manager import Manager
from exolink.nodes.controller_manager.params import LEASE_PAST_TRIP_MS, ManagerParams
from exolink.nodes.controller_manager.slots import ManagerRefused, Switch

from benchmarks.harness import Appliance, collect, connect, motion_nodes, wait_for
from exolink import messaging, roles
from exolink.config import ConfigError, load
from exolink.control.controller import State
from exolink.control.patterns import load_pattern
from exolink.limits.joints import Limits, default_max, default_min
from exolink.protocol import h2

SITTING = State((40, 60, 0, 40, 60, 0), (0,) * 6)


def manager(max_step: int = 60, budget_ms: float = 50.0, **caps: list[int]) -> Manager:
    limits = Limits.of(
        caps.get("min", default_min()),
        caps.get("max", default_max()),
        caps.get("torque", [127] * 6),
        caps.get("stiffness", [100] * 6),
        "test",
        caps.get("torque_step"),
        max_step,
    )
    return Manager(limits, budget_ms)


# Any whole degree the protocol's int8 could carry: for reading a pattern file as it is.
ANY_ANGLE = Limits((-90,) * 6, (120,) * 6, (127,) * 6, (100,) * 6)


def switch(m: Manager, activate: list[str] = (), deactivate: list[str] = ()) -> Switch:  # type: ignore[assignment]
    """Queue a switch and run the cycle boundary that applies it."""
    sw = Switch(list(activate), list(deactivate))
    m.request(sw)
    m.cycle(SITTING, 0.0, 0.01, None)
    assert sw.done.is_set()
    return sw


def fwd(m: Manager, name: str, joints: list[str], **kw: Any) -> None:
    m.load(name, "forward_command", {"joints": joints, **kw})


# --- pure logic ---------------------------------------------------------------------------------


def test_bad_params_refuse_the_load_with_the_reason() -> None:
    m = manager()
    with pytest.raises(ManagerRefused, match=r"pid1 \(pid\) params: .*kp"):
        m.load("pid1", "pid", {"joints": ["r_knee"], "kp": -1})
    with pytest.raises(ManagerRefused, match=r"unknown controller type 'nosuch'.*forward_command"):
        m.load("x", "nosuch", {})
    with pytest.raises(ManagerRefused, match=r"points\[1\].time_s must increase"):
        m.load(
            "t",
            "joint_trajectory",
            {"joints": ["r_knee"], "points": [{"time_s": 1, "positions": [1]}] * 2},
        )
    assert m.status()["controllers"] == []


def test_a_controller_type_found_is_kept_and_a_missing_one_is_looked_up_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The lookup reads every installed package's metadata (a burst at each gait start on the
    board): a type found once is not looked up again; one not found is, at every load, so a
    lab's type installed while the manager runs is seen at its first load."""
    import exolink.entrypoints
    from exolink import plugins

    looked: list[str] = []
    real = exolink.entrypoints.entry_points

    def counted(**kw: Any) -> Any:
        looked.append(kw.get("group", ""))
        return real(**kw)

    monkeypatch.setattr(exolink.entrypoints, "entry_points", counted)
    plugins.find_controller_class.cache_clear()
    first = plugins.find_controller_class("gait_pattern")
    n = len(looked)
    assert n >= 1 and plugins.find_controller_class("gait_pattern") is first
    assert len(looked) == n  # kept
    for _ in range(2):
        with pytest.raises(plugins.PluginError, match="unknown controller type 'nosuch'"):
            plugins.find_controller_class("nosuch")
    assert len(looked) > n + 1  # looked up at each


def test_a_replacement_is_checked_before_the_one_it_replaces_is_touched() -> None:
    """``load --replace``: bad params refuse the new one and leave the loaded one as it was; an
    active one is replaced only once it is deactivated (the node does that at a cycle)."""
    m = manager()
    fwd(m, "a", ["r_knee"])
    switch(m, ["a"])
    with pytest.raises(ManagerRefused, match=r"a \(forward_command\) params"):
        m.prepare("a", "forward_command", {"joints": 5}, replacing=True)
    with pytest.raises(ManagerRefused, match="already loaded"):
        m.prepare("a", "forward_command", {"joints": ["l_knee"]})
    new = m.prepare("a", "forward_command", {"joints": ["l_knee"]}, replacing=True)
    with pytest.raises(ManagerRefused, match="a is active: deactivate it first"):
        m.add(new, replace=True)
    assert m.status()["controllers"][0].claims == ["r_knee/position"]
    switch(m, deactivate=["a"])
    old = m.add(new, replace=True)
    assert old is not None and old.claims == ("r_knee/position",)
    assert [c.claims for c in m.status()["controllers"]] == [["l_knee/position"]]
    m.put_back(new, old)  # its activation refused: the one it replaced is back
    assert [c.claims for c in m.status()["controllers"]] == [["r_knee/position"]]


class ManagerStandIn:
    """The controller manager's transport for the pattern player's logic alone: records what the
    player asks and never answers a load (a reply lost on a real session cannot be made to
    happen on demand)."""

    def __init__(self) -> None:
        self.asked: list[tuple[str, Any, float]] = []

    def command(self, *_path: str, body: dict[str, Any], timeout_s: float, tolerate=()):  # type: ignore[no-untyped-def]
        from exolink.messaging import Refused

        self.asked.append((body["action"], body.get("within_s"), timeout_s))
        if body["action"] == "load":
            raise Refused("nothing answers at controllers: no answer within 5 s")
        return {"ok": True}


def player_on(manager: ManagerStandIn) -> Any:
    """A pattern player (timing: manager) without a transport: its logic on the stand-in."""
    import threading
    from types import SimpleNamespace

    import structlog
    from exolink.nodes import pattern_player as pp

    player = pp.PatternPlayer.__new__(pp.PatternPlayer)
    player.ctx = SimpleNamespace(messaging=manager)  # type: ignore[assignment]
    player.log = structlog.get_logger()
    player.lock = threading.RLock()
    player.pattern = load_pattern(str(pp.DEFAULT_PATTERN), manager_limits())
    player.selected, player.speed, player.index = [True] * 6, 10, 0
    player.state, player.reason, player._engaged, player._starts = "stopped", "", 0, 0
    player.sent, player.operator, player.arming = 0, "", None
    player._t0, player._i0 = 0.0, 0
    player._activity, player._disengage_due = threading.Event(), False
    player.pub = SimpleNamespace(put=lambda *_a: None)
    return player


def manager_limits() -> Limits:
    return Limits.of(default_min(), default_max(), [127] * 6, [100] * 6, "test")


def test_a_gait_start_the_manager_did_not_answer_is_followed_by_its_deactivation() -> None:
    """It may be the answer that was lost: the player asks for the gait's deactivation (the
    manager handles requests in order) and refuses the start."""
    from exolink.nodes import pattern_player as pp

    from exolink.messaging import Refused

    manager = ManagerStandIn()
    with pytest.raises(Refused, match="nothing answers"):
        player_on(manager)._engage()
    within = pp.ENGAGE_WAIT_S - pp.ENGAGE_MARGIN_S
    assert manager.asked == [
        ("load", within, pp.ENGAGE_WAIT_S),
        ("deactivate", None, pp.MANAGER_WAIT_S),
    ]


def test_a_pattern_the_player_stops_for_a_stale_watchdog_word_is_stopped_in_the_manager() -> None:
    """ "No word from the watchdog" is the player's own view (seen on the board proxy while the
    watchdog stayed armed): unlike a trip, it has not stopped the manager, so the player's
    follower thread tells it, off the loop that must keep beating."""
    import threading

    manager = ManagerStandIn()
    player = player_on(manager)
    player.arming = type("Stale", (), {"check": lambda _s: "no word from the watchdog for 3.0 s"})()
    player._publish = lambda: None
    player.state = "running"
    player._guard()
    assert player.state == "stopped" and manager.asked == []  # not on the loop's thread
    stop = threading.Event()
    follower = threading.Thread(target=player._follow_manager, args=(stop,))
    follower.start()
    try:
        assert wait_for(lambda: manager.asked, timeout=5)
    finally:
        stop.set()
        player._activity.set()
        follower.join(5)
    assert manager.asked[0][0] == "deactivate"


def test_conflicting_claim_refused_naming_the_owner() -> None:
    m = manager()
    fwd(m, "a", ["r_knee", "r_hip"])
    fwd(m, "b", ["r_knee"])
    m.load("p", "pid", {"joints": ["r_hip"]})
    assert switch(m, ["a"]).error is None
    with pytest.raises(ManagerRefused, match="cannot activate b: r_knee/position is owned by a"):
        m.request(Switch(["b"], []))
    # torque and position on one joint from two controllers: refused, both named
    with pytest.raises(ManagerRefused, match=r"r_hip/torque \(p\) and r_hip/position \(a\)"):
        m.request(Switch(["p"], []))
    assert m.active() == ["a"]


def test_switch_applies_whole_at_one_boundary() -> None:
    m = manager()
    fwd(m, "a", ["r_knee"])
    fwd(m, "b", ["r_knee"])
    switch(m, ["a"])
    m.command("a", {"values": {"r_knee": 61}})
    sw = Switch(["b"], ["a"])
    m.request(sw)
    assert m.active() == ["a"]  # nothing changes until the cycle boundary
    out = m.cycle(SITTING, 0.0, 0.01, None)
    assert m.active() == ["b"] and sw.error is None
    # b holds where the joint is (60); exactly one write for r_knee in that cycle
    assert [(w.motor, w.setpoint) for w in out.writes] == [(2, 60)]


def test_raising_controller_deactivated_its_joints_safe_others_keep_writing(
    tmp_path: Path,
) -> None:
    m = manager()
    fwd(m, "a", ["r_knee"])
    fwd(m, "b", ["l_knee"])
    switch(m, ["a", "b"])
    m.slots["a"].ctrl.update = lambda *_: 1 / 0  # type: ignore[method-assign]
    out = m.cycle(SITTING, 0.0, 0.01, None)
    assert out.safe == {1}  # r_knee
    assert [w.motor for w in out.writes] == [5]  # l_knee still written
    assert m.active() == ["b"]
    assert "update raised ZeroDivisionError" in m.slots["a"].error


def _spending(m: Manager, name: str, cpu_s: list[float]) -> None:
    """Its updates spend these CPU seconds, one per cycle (then none extra)."""
    import time

    real = m.slots[name].ctrl.update
    left = list(cpu_s)

    def slow(*args: Any) -> Any:
        t, spend = time.thread_time(), left.pop(0) if left else 0.0
        while time.thread_time() - t < spend:  # CPU, not wall time: the budget counts CPU
            pass
        return real(*args)

    m.slots[name].ctrl.update = slow  # type: ignore[method-assign]


def test_overrun_twice_in_a_row_deactivates() -> None:
    m = manager(budget_ms=1.0)  # an update every 10 ms
    fwd(m, "a", ["r_knee"])
    switch(m, ["a"])
    _spending(m, "a", [0.005, 0.005])
    m.command("a", {"values": {"r_knee": 61}})
    out = m.cycle(SITTING, 0.0, 0.01, None)  # one overrun: counted, still driving
    assert m.active() == ["a"] and m.slots["a"].overruns == 1 and out.writes
    out = m.cycle(SITTING, 0.01, 0.01, None)
    assert out.safe == {1} and out.writes == [] and m.active() == []
    assert "overran its budget twice in a row" in m.slots["a"].error
    assert m.slots["a"].overruns == 2


def test_one_overrun_alone_is_counted_and_one_past_the_update_period_deactivates() -> None:
    """A thread's CPU clock also takes the interrupts served while it ran: one update over its
    budget now and then is counted, not fatal; one longer than the update period (the cycle
    itself late) is."""
    m = manager(budget_ms=1.0)
    fwd(m, "a", ["r_knee"])
    switch(m, ["a"])
    _spending(m, "a", [0.005, 0.0, 0.005, 0.0, 0.012])
    m.command("a", {"values": {"r_knee": 61}})
    for i in range(4):
        assert m.cycle(SITTING, i * 0.01, 0.01, None).writes
    assert m.active() == ["a"] and m.slots["a"].overruns == 2
    out = m.cycle(SITTING, 0.04, 0.01, None)
    assert out.safe == {1} and m.active() == []
    assert "longer than the update period (10 ms)" in m.slots["a"].error


def test_a_cpu_clock_in_ticks_stops_no_controller_for_a_tick_it_touched(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """User-Mode Linux accounts a thread's CPU in 10 ms ticks: an update that straddles one
    reads 10 ms, "longer than the update period", and a gait was stopped for it (the kernel
    test, stop 54). The budget is judged on what was surely used: the reading less the clock's
    step. Here each read of the clock is one tick on, so every update straddles exactly one
    and takes no CPU otherwise."""
    import gc

    from exolink.nodes.controller_manager import manager as mgr

    ticks = iter(range(10**6))
    m = manager(budget_ms=1.0)
    fwd(m, "a", ["r_knee"])
    switch(m, ["a"])
    m.command("a", {"values": {"r_knee": 61}})
    tick = 0.0100001  # a tick as a reading shows it: the kernel test read "10.000 ms > 10 ms"
    monkeypatch.setattr(mgr.time, "thread_time", lambda: next(ticks) * tick)
    gc.disable()  # the collector's callback reads the clock too
    try:
        monkeypatch.setattr(mgr, "CPU_STEP_S", tick)  # what cpu_clock_step finds on such a clock
        for i in range(5):
            assert m.cycle(SITTING, i * 0.01, 0.01, None).writes
        assert m.active() == ["a"] and m.slots["a"].overruns == 0
        monkeypatch.setattr(mgr, "CPU_STEP_S", 0.0)  # judged on the readings alone, as before
        out = m.cycle(SITTING, 0.05, 0.01, None)
    finally:
        gc.enable()
    assert out.safe == {1} and m.active() == []
    assert "longer than the update period (10 ms)" in m.slots["a"].error


def test_the_cpu_clocks_step_here_is_fine() -> None:
    from exolink.nodes.controller_manager.budget import cpu_clock_step

    assert 0 < cpu_clock_step() < 0.001  # a clock in ns on this kernel, as on the board's


def test_a_garbage_collection_is_not_the_controllers_overrun() -> None:
    """The collector runs in whichever update allocates past its threshold: its time is not
    the controller's (a full collection of 300k objects takes far more than 1 ms here)."""
    import gc

    heap = [[i] for i in range(300_000)]
    m = manager(budget_ms=1.0)
    fwd(m, "a", ["r_knee"])
    switch(m, ["a"])
    real = m.slots["a"].ctrl.update

    def collects(*args: Any) -> Any:
        gc.collect()
        return real(*args)

    m.slots["a"].ctrl.update = collects  # type: ignore[method-assign]
    m.command("a", {"values": {"r_knee": 61}})
    out = m.cycle(SITTING, 0.0, 0.01, None)
    assert m.active() == ["a"] and m.slots["a"].overruns == 0, m.slots["a"].error
    assert [w.motor for w in out.writes] == [2]
    assert m.slots["a"].cpu_s_max < 0.001
    del heap


def test_outputs_saturate_to_limits_step_and_caps() -> None:
    m = manager(max_step=3, max=[100, 70, 20, 100, 100, 20], torque=[10] * 6)
    fwd(m, "a", ["r_knee"])
    m.load("t", "forward_command", {"joints": ["l_knee"], "interface": "torque"})
    switch(m, ["a", "t"])
    m.command("a", {"values": {"r_knee": 99}})
    m.command("t", {"values": {"l_knee": -50}})
    seen = []
    for _ in range(6):
        out = m.cycle(SITTING, 0.0, 0.01, None)
        seen.append({w.motor: (w.mode, w.setpoint) for w in out.writes})
    assert [s[2] for s in seen] == [(1, 63), (1, 66), (1, 69), (1, 70), (1, 70), (1, 70)]
    assert all(s[5] == (3, -10) for s in seen)
    assert m.slots["a"].limited == 6 and m.slots["t"].limited == 6
    # a non-finite output is a fault, not something to saturate
    m.slots["a"].ctrl.values = {"r_knee/position": float("nan")}  # type: ignore[attr-defined]
    out = m.cycle(SITTING, 0.0, 0.01, None)
    assert out.safe == {1} and "not a finite number" in m.slots["a"].error


def test_not_armed_stops_everything_and_activation_refused() -> None:
    m = manager()
    fwd(m, "a", ["r_knee"])
    switch(m, ["a"])
    out = m.cycle(SITTING, 0.0, 0.01, "motors not armed: watchdog is tripped")
    assert out.writes == [] and m.active() == []
    sw = Switch(["a"], [])
    m.request(sw)
    m.cycle(SITTING, 0.0, 0.01, "motors not armed: watchdog is tripped")
    assert sw.error == "motors not armed: watchdog is tripped"
    assert m.active() == [] and m.cycle(SITTING, 0.0, 0.01, None).writes == []
    assert switch(m, ["a"]).error is None and m.active() == ["a"]  # armed again + activate


def test_forward_command_timeout_hold_or_disable() -> None:
    import time

    m = manager()
    fwd(m, "h", ["r_knee"], timeout_s=0.001)
    fwd(m, "d", ["l_knee"], timeout_s=0.001, on_timeout="disable")
    switch(m, ["h", "d"])
    time.sleep(0.01)
    out = m.cycle(SITTING, 0.0, 0.01, None)
    assert out.safe == {4} and [(w.motor, w.setpoint) for w in out.writes] == [(2, 60)]
    assert m.slots["h"].ctrl.status()["timed_out"] and "no command" in m.slots["d"].error


def test_pid_anti_windup_and_cap() -> None:
    pid = Pid("p", PidParams(joints=["r_knee"], kp=1.0, ki=10.0, output_cap=5.0, i_clamp=3.0))
    pid.configure()
    pid.activate(State((0, 0, 0, 0, 0, 0), (0,) * 6))
    pid.command({"values": {"r_knee": 50}})
    for _ in range(100):  # far from the set-point: saturated, the integral must not wind up
        u = pid.update(State((0, 0, 0, 0, 0, 0), (0,) * 6), 0.0, 0.01)["r_knee/torque"]
        assert u == 5.0
    assert pid.integral["r_knee"] == 0.0
    # at the set-point the output is just the (bounded) integral
    u = pid.update(State((0, 50, 0, 0, 0, 0), (0,) * 6), 0.0, 0.01)["r_knee/torque"]
    assert abs(u) <= 3.0


def test_pid_brings_a_simulated_joint_in_torque_mode_to_its_setpoint() -> None:
    from exolink.nodes.simulator.boards import H2Board

    board = H2Board()
    pid = Pid("p", PidParams(joints=["r_knee"], kp=0.5, ki=0.2, output_cap=10, i_clamp=2))
    pid.configure()

    def state() -> State:
        return State(tuple(round(j.pos) for j in board.joints), (0,) * 6)

    pid.activate(state())
    pid.command({"values": {"r_knee": 45}})
    for _ in range(300):  # 3 s of 10 ms cycles through the codec and the board's dynamics
        u = pid.update(state(), 0.0, 0.01)["r_knee/torque"]
        board.handle(h2.encode_joint_control("r_knee", "torque", round(u)))
        board.step(0.01)
    assert abs(board.joints[1].pos - 45) <= 2


def test_trajectory_interpolates_from_where_the_joints_are() -> None:
    from exolink.nodes.controller_manager.builtin import TrajectoryParams

    p = msgspec_convert(
        {"joints": ["r_knee"], "points": [{"time_s": 1, "positions": [80]}]}, TrajectoryParams
    )
    t = JointTrajectory("t", p)
    t.configure()
    t.activate(SITTING)
    assert t.update(SITTING, 100.0, 0.01) == {"r_knee/position": 60}
    assert t.update(SITTING, 100.5, 0.01) == {"r_knee/position": 70}
    assert t.update(SITTING, 102.0, 0.01) == {"r_knee/position": 80}


def test_gait_pattern_moves_between_rows_and_the_default_pattern_fits_the_shipped_step() -> None:
    """The gait controller writes where the pattern is between rows, so the default pattern at
    speed 10 moves its knees 4 deg per 10 ms cycle, inside the shipped configs' step limit
    (8 deg per 20 ms row at once would not be); interpolate: false holds each row."""
    from exolink.nodes.controller_manager.gait_pattern import GaitParams, GaitPattern
    from exolink.nodes.pattern_player import DEFAULT_PATTERN

    from exolink.config import bundled, load
    from exolink.control.patterns import load_pattern

    rows = [[10, 20, 0, 0, 0, 0], [20, 28, 0, 0, 0, 0]]
    for interpolate, mid in ((True, {"r_hip/position": 15, "r_knee/position": 24}), (False, None)):
        g = GaitPattern("g", msgspec_convert({"rows": rows, "joints": ["r_hip", "r_knee"], "speed": 10, "interpolate": interpolate}, GaitParams))  # fmt: skip
        g.configure()
        g.activate(SITTING)
        assert g.update(SITTING, 50.0, 0.01) == {"r_hip/position": 10, "r_knee/position": 20}
        half = g.update(SITTING, 50.01, 0.01)  # half a 20 ms row later
        assert half == pytest.approx(mid or {"r_hip/position": 10, "r_knee/position": 20})
        assert g.update(SITTING, 50.02, 0.01) == pytest.approx(
            {"r_hip/position": 20, "r_knee/position": 28}
        )
    points = load_pattern(str(DEFAULT_PATTERN), ANY_ANGLE).points
    g = GaitPattern("g", msgspec_convert({"rows": points, "joints": list(h2.JOINTS), "speed": 10}, GaitParams))  # fmt: skip
    g.configure()
    g.activate(SITTING)
    out = [g.update(SITTING, 7.0 + 0.01 * k, 0.01) for k in range(3 * len(points))]
    step = max(abs(round(b[k]) - round(a[k])) for a, b in itertools.pairwise(out) for k in a)
    for name in ("sim", "board"):
        assert step <= load(bundled(name)).joint_limits().max_step_deg, name


def msgspec_convert(data: dict[str, Any], cls: type) -> Any:
    import msgspec

    return msgspec.convert(data, cls)


# --- on the simulator, with the watchdog ------------------------------------------------------

# A lab's own controller package, installed the way pip would (a dist-info with entry points on
# the path): how the tests get a controller that fails on demand, through the real plugin story.
LAB_PLUGIN = '''
from exolink.control.controller import Controller, NoParams


class Raiser(Controller):
    """Holds r_knee where it is until told to fail, then raises in update."""

    def configure(self):
        self.boom = False

    def claims(self):
        return ["r_knee/position"]

    def activate(self, state):
        self.hold = state.of("r_knee")

    def command(self, request):
        self.boom = True
        return {}

    def update(self, state, time, period):
        if self.boom:
            raise RuntimeError("lab controller bug")
        return {"r_knee/position": self.hold}
'''

CTRL = [
    {"name": "a", "type": "forward_command", "params": {"joints": ["r_knee"]}},
    {
        "name": "b",
        "type": "forward_command",
        "params": {"joints": ["r_knee"], "initial": {"r_knee": 45}},
    },
    {"name": "left", "type": "forward_command", "params": {"joints": ["l_knee"]}},
]


def nodes(controllers: list[dict[str, Any]], deadline_ms: int = 50) -> list[dict[str, Any]]:
    """``deadline_ms``: the manager's heartbeat deadline (300 where a test is not about hung
    detection: above a loaded machine's stalls)."""
    # Silence limits above a loaded test machine's stalls: these tests are not about them.
    return motion_nodes(
        deadline_ms=deadline_ms, h2_timeout_ms=300, params={"controllers": controllers}
    )


@pytest.fixture
def lab_plugin(lab_package) -> None:  # type: ignore[no-untyped-def]
    lab_package(
        "lab_ctrl", "[exolink.controllers]\nraiser = lab_ctrl:Raiser\n", {"lab_ctrl.py": LAB_PLUGIN}
    )


@pytest.fixture
def app(write_config, spawn, lab_plugin):  # type: ignore[no-untyped-def]
    # deadline 300 ms: above a loaded CI machine's stalls (at 50 ms one tripped the watchdog
    # mid-test, whose disable frames then went out before the window the test looked in)
    cfg = write_config(
        nodes=nodes(CTRL, deadline_ms=300), watchdog={"pulse_silence_ms": 500}, limits=STEP_3
    )
    return Appliance(cfg, spawn)


STEP_3 = {"max_step_deg": 3}  # the limits: section's step (per 10 ms cycle) these tests count on


def ctl(app: Appliance, *args: str) -> Any:
    r = app.cli("controllers", *args)
    return r


def listing(app: Appliance) -> dict[str, dict[str, Any]]:
    r = app.cli("controllers", "list", "--json")
    assert r.returncode == 0, r.stderr
    return {c["name"]: c for c in json.loads(r.stdout)["controllers"]}


def read_ids(app: Appliance) -> list[int]:
    """The ids the manager's reader takes from the bus (``Controller.reads``)."""
    r = ctl(app, "list", "--json")
    assert r.returncode == 0, r.stderr
    return list(json.loads(r.stdout)["read_ids"])


def joint_frames(frames: list[Any], motor: int) -> list[h2.JointControl]:
    return [
        f
        for f in (h2.decode(m) for m in frames)
        if isinstance(f, h2.JointControl) and f.motor == motor
    ]


class SwitchWindow(NamedTuple):
    points: list[int]  # r_knee set-points on the bus in the half second after the switch
    angles: int  # angle frames in that half second
    gaps_before: int
    gaps_after: int
    void: str | None  # why this window says nothing about the switch (None: it counts)


def switch_window(app: Appliance, mbus: Any) -> SwitchWindow:
    """a holds r_knee at 30, then a -> b in one switch, watched by the bus listener.

    A window counts only if the listener lost no frame and the watchdog did not trip in it: a
    stalled test machine does both (seen in CI: the listener missed b's ramp and an H2 silence
    trip disabled the joint), and then the frames say nothing about the switch itself."""
    assert ctl(app, "command", "a", "r_knee=30").returncode == 0
    wait_for(lambda: [f.setpoint for f in joint_frames(collect(mbus, 0.1, {70}), 2)][-1:] == [30])
    mbus.q.queue.clear()
    dropped = mbus.dropped
    before = json.loads(ctl(app, "list", "--json").stdout)["gaps"]
    assert ctl(app, "switch", "--activate", "b", "--deactivate", "a").returncode == 0
    frames = collect(mbus, 0.5, {70, 110})
    knee = joint_frames(frames, 2)
    after = json.loads(ctl(app, "list", "--json").stdout)["gaps"]
    void = None
    if mbus.dropped != dropped:
        void = f"the bus listener lost {mbus.dropped - dropped} frames"
    elif any(f.mode == h2.MODES["disabled"] for f in knee):
        void = "the watchdog tripped in the window"
    points = [f.setpoint for f in knee]
    angles = sum(m.arbitration_id == 110 for m in frames)
    return SwitchWindow(points, angles, before, after, void)


def test_claims_switch_and_failure_on_the_bus(app, mbus) -> None:  # type: ignore[no-untyped-def]
    r = ctl(app, "activate", "a")
    assert r.returncode == 5 and "motors not armed" in r.stderr, r.stderr
    app.arm_and_hold()
    assert ctl(app, "activate", "a", "left").returncode == 0
    # one owner per interface: refused with the owner named
    r = ctl(app, "activate", "b")
    assert r.returncode == 5 and "cannot activate b: r_knee/position is owned by a" in r.stderr
    # the switch: b's ramp to 45 follows a's 30 with no cycle where both or neither wrote.
    # On the bus: no interleaving (a both-write cycle would put a 30 after b's first value) and
    # one r_knee frame per angle frame (frames in flight at the window's ends aside: a loaded
    # machine delays a command past the next angle frame, which shifts it, never drops it);
    # in the manager: no cycle in which a claimed joint went unwritten.
    for attempt in range(3):
        window = switch_window(app, mbus)
        if window.void is None:
            break
        warnings.warn(f"switch window {attempt} void: {window.void}; measured again", stacklevel=1)
        for name in ("a", "b", "left"):  # whatever the trip left active
            ctl(app, "deactivate", name)
        app.arm_and_hold()
        assert ctl(app, "activate", "a", "left").returncode == 0
    else:
        pytest.fail(f"no switch window with a seeing listener and no trip: {window.void}")
    points, angles = window.points, window.angles
    assert points == sorted(points) and points[0] == 30 and points[-1] == 45, points
    assert {p for p in points if p not in (30, 45)} <= {33, 36, 39, 42}  # step limit 3 deg
    assert abs(len(points) - angles) <= 2, (len(points), angles)
    assert window.gaps_after == window.gaps_before
    # a lab controller that raises: deactivated, its joint disabled, the other keeps writing
    assert (
        ctl(app, "switch", "--activate", "lab", "--deactivate", "b").returncode == 5
    )  # not loaded
    # the built-ins read positions only: no torque (120) or foot-switch (130) frames are read
    # for them; a lab controller that does not say what it reads gets both
    assert read_ids(app) == [h2.JOINT_CONTROL, h2.JOINT_ANGLES]
    r = ctl(app, "load", "lab", "raiser")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: h2.JOINT_TORQUES in read_ids(app))
    assert read_ids(app) == [70, 110, 120, 130]
    assert ctl(app, "switch", "--activate", "lab", "--deactivate", "b").returncode == 0
    assert ctl(app, "command", "lab", "r_knee=0").returncode == 0
    frames = collect(mbus, 0.5, {70})
    knee = joint_frames(frames, 2)
    assert h2.JointControl(2, 4, 0, 0) in knee
    assert all(f.mode == 4 for f in knee[knee.index(h2.JointControl(2, 4, 0, 0)) :])
    after = frames[[h2.decode(m) for m in frames].index(h2.JointControl(2, 4, 0, 0)) :]
    assert joint_frames(after, 5) and all(f.mode == 1 for f in joint_frames(after, 5))
    s = listing(app)
    assert (
        s["lab"]["state"] == "inactive" and "RuntimeError: lab controller bug" in s["lab"]["error"]
    )
    assert s["left"]["state"] == "active"
    # bad params refuse the load, naming the controller and the param
    r = ctl(app, "load", "p", "pid", "--params", '{"joints": ["r_hip"], "kp": "fast"}')
    assert r.returncode == 5 and "p (pid) params" in r.stderr and "kp" in r.stderr, r.stderr


def test_trip_deactivates_all_until_rearm_and_activate(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert ctl(app, "activate", "a", "left").returncode == 0
    assert joint_frames(collect(mbus, 0.3, {70}), 2)
    assert app.cli("estop").returncode == 0
    collect(mbus, 0.3)  # the trip's frames and anything in flight
    assert [f for f in (h2.decode(m) for m in collect(mbus, 0.5, {70})) if f.mode != 4] == []  # type: ignore[union-attr]
    s = listing(app)
    assert s["a"]["state"] == s["left"]["state"] == "inactive"
    r = ctl(app, "activate", "a")
    assert r.returncode == 5 and "motors not armed" in r.stderr
    app.arm()  # re-arming does not bring them back
    assert joint_frames(collect(mbus, 0.4, {70}), 2) == []
    assert ctl(app, "activate", "a").returncode == 0
    assert joint_frames(collect(mbus, 0.3, {70}), 2)
    # one request replaces a running controller (how the pattern player starts the gait)
    at50 = '{"joints": ["r_knee"], "initial": {"r_knee": 50}}'
    r = ctl(app, "load", "a", "forward_command", "--params", at50, "--replace", "--activate")
    assert r.returncode == 0, r.stderr
    assert wait_for(lambda: 50 in [f.setpoint for f in joint_frames(collect(mbus, 0.2, {70}), 2)])
    assert listing(app)["a"]["state"] == "active"
    # ... and the watchdog stops what it started, as any other activation
    assert app.cli("estop").returncode == 0
    collect(mbus, 0.3)  # the trip's frames and anything in flight
    assert [f for f in (h2.decode(m) for m in collect(mbus, 0.5, {70})) if f.mode != 4] == []  # type: ignore[union-attr]
    assert listing(app)["a"]["state"] == "inactive"
    app.arm_and_hold()
    assert ctl(app, "activate", "a").returncode == 0
    # within_s: an activation that cannot happen within the asker's wait is refused, not applied
    # after the asker gave up, and the controllers stay as they were
    s = connect(app.at)
    try:
        key = messaging.mgmt_key(app.cfg.device, "controllers")
        late = {"action": "load", "name": "a", "type": "forward_command", "replace": True}
        late |= {"params": {"joints": ["l_ankle"]}, "activate": True}
        r = messaging.request(s, key, {**late, "within_s": 1e-6}, 10)
        assert not r["ok"] and "within_s ran out" in r["error"], r
        r = messaging.request(s, key, {**late, "within_s": "soon"}, 10)
        assert not r["ok"] and "within_s must be a number" in r["error"], r
    finally:
        s.close()
    ctls = listing(app)
    assert ctls["a"]["claims"] == ["r_knee/position"] and ctls["a"]["state"] == "inactive"
    assert ctl(app, "activate", "a").returncode == 0
    # ... unarmed, it is refused before anything changes
    assert app.cli("estop").returncode == 0
    r = ctl(app, "load", "a", "forward_command", "--params", "{}", "--replace", "--activate")
    assert r.returncode == 5 and "motors not armed" in r.stderr, r.stderr
    assert listing(app)["a"]["claims"] == ["r_knee/position"]


@pytest.fixture
def every_other(write_config, spawn, lab_plugin):  # type: ignore[no-untyped-def]
    """The manager as on the board: one update per two H2 cycles (``cycles_per_update``)."""
    n = nodes(CTRL, deadline_ms=300)
    n[2]["params"]["cycles_per_update"] = 2
    cfg = write_config(nodes=n, watchdog={"pulse_silence_ms": 500}, limits=STEP_3)
    return Appliance(cfg, spawn)


def test_an_update_every_other_cycle_writes_half_as_often_and_the_watchdog_stops_it(
    every_other, mbus
) -> None:  # type: ignore[no-untyped-def]
    """cycles_per_update 2: at most one set-point per joint per two angle frames (the loop
    sleeps through the other), the step limit kept per 10 ms of motion (3 deg per cycle: 6 per
    update), and a trip disables the joints as at every cycle; nothing moves after it."""
    app = every_other
    app.arm_and_hold()
    assert ctl(app, "activate", "a", "left").returncode == 0
    assert ctl(app, "command", "a", "r_knee=30").returncode == 0
    wait_for(lambda: [f.setpoint for f in joint_frames(collect(mbus, 0.1, {70}), 2)][-1:] == [30])
    assert json.loads(ctl(app, "list", "--json").stdout)["cycles_per_update"] == 2
    assert ctl(app, "command", "a", "r_knee=60").returncode == 0
    frames = collect(mbus, 1.0, {70, 110})
    knee = [f.setpoint for f in joint_frames(frames, 2)]
    angles = sum(m.arbitration_id == 110 for m in frames)
    assert knee[-1] == 60 and knee == sorted(knee), knee
    assert {b - a for a, b in itertools.pairwise(knee)} <= {0, 6}, knee
    assert 0 < len(knee) <= angles // 2 + 2, (len(knee), angles)
    assert app.cli("estop").returncode == 0
    collect(mbus, 0.3)  # the trip's frames and anything in flight
    assert [f for f in (h2.decode(m) for m in collect(mbus, 0.5, {70})) if f.mode != 4] == []  # type: ignore[union-attr]
    assert listing(app)["a"]["state"] == "inactive"


def test_cycles_per_update_needs_an_h2_timeout_above_its_wait(write_config) -> None:  # type: ignore[no-untyped-def]
    """A silence limit the manager's own sleep could reach is a bad config: nothing starts,
    and the error names the param's place and both values."""
    n = nodes(CTRL)
    n[2]["params"] |= {"cycles_per_update": 3, "h2_timeout_ms": 40}
    with pytest.raises(ConfigError) as err:
        load(write_config(nodes=n))
    assert "nodes[2].params" in str(err.value), err.value
    assert "h2_timeout_ms 40 must exceed 40 ms with cycles_per_update 3" in str(err.value)


@pytest.mark.parametrize("sig", [signal.SIGSTOP, signal.SIGKILL])
def test_hung_or_killed_manager_disables_motors(app, mbus, sig) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert ctl(app, "activate", "a", "left").returncode == 0
    assert joint_frames(collect(mbus, 0.3, {70}), 2)
    pid = app.node("controller_manager")["pid"]
    os.kill(pid, sig)
    try:
        frames = [h2.decode(m) for m in collect(mbus, 1.0, {70})]
        assert {h2.JointControl(m, 4, 0, 0) for m in range(1, 7)} <= set(frames)
        assert app.status()["watchdog"]["state"] == "tripped"
    finally:
        if sig == signal.SIGSTOP:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)


def test_h2_silent_claimed_joints_get_the_safe_action(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert ctl(app, "activate", "a").returncode == 0
    assert joint_frames(collect(mbus, 0.3, {70}), 2)
    from exolink import messaging

    s = messaging.open_client_session(app.at)
    try:
        reply = messaging.request(s, "exolink/sim/sim/fault", {"fault": "silent", "duration_s": 2})
    finally:
        s.close()
    assert reply["ok"], reply
    safe = h2.JointControl(2, 4, 0, 0)
    # waited for, not looked for in a fixed window: a stalled CI host once let the window end
    # before the listener had read the frames (the trip and its frames had come)
    got = mbus.wait_for(lambda m: m.arbitration_id == 70 and h2.decode(m) == safe, timeout=10)
    assert got is not None, (mbus.dropped, app.status()["watchdog"])
    after = [h2.decode(m) for m in collect(mbus, 0.5, {70})]  # before it: frames in flight
    assert [f for f in after if f.mode == 1] == []  # type: ignore[union-attr]
    assert "no H2 joint angles" in listing(app)["a"]["error"]


@pytest.fixture
def routed(write_config, spawn):  # type: ignore[no-untyped-def]
    """`exolink send` motion becomes the manager's operator controllers."""
    gait = {"name": "gait", "type": "forward_command", "params": {"joints": ["r_knee"]}}
    cfg = write_config(
        nodes=nodes([gait], deadline_ms=300), watchdog={"pulse_silence_ms": 500}, limits=STEP_3
    )
    return Appliance(cfg, spawn)


def test_operator_motion_goes_through_the_manager(routed, mbus) -> None:  # type: ignore[no-untyped-def]
    app = routed
    app.arm_and_hold()
    r = app.cli("send", "position", "r_knee", "20")
    assert r.returncode == 0 and "held by controller operator.r_knee.position" in r.stdout, r
    # held every cycle by the manager (one writer), ramped by its step limit, until told else
    wait_for(lambda: [f.setpoint for f in joint_frames(collect(mbus, 0.1, {70}), 2)][-1:] == [20])
    assert {f.setpoint for f in joint_frames(collect(mbus, 0.3, {70}), 2)} == {20}
    # another mode on the same joint: one switch, no cycle with both
    assert app.cli("send", "torque", "r_knee", "5").returncode == 0
    wait_for(lambda: [f.mode for f in joint_frames(collect(mbus, 0.1, {70}), 2)][-1:] == [3])
    s = listing(app)
    assert s["operator.r_knee.torque"]["state"] == "active"
    assert s["operator.r_knee.position"]["state"] == "inactive"
    # an operator's disable releases the joint at once
    assert app.cli("send", "disable", "r_knee").returncode == 0
    collect(mbus, 0.3)
    assert joint_frames(collect(mbus, 0.3, {70}), 2) == []
    assert listing(app)["operator.r_knee.torque"]["state"] == "inactive"
    # a joint another controller drives: refused with that controller named, nothing sent
    assert ctl(app, "activate", "gait").returncode == 0
    assert ctl(app, "command", "gait", "r_knee=10").returncode == 0
    seen: list[Any] = []

    def knee_at_10() -> bool:
        seen[:] = collect(mbus, 0.1, {70})
        return [f.setpoint for f in joint_frames(seen, 2)][-1:] == [10]

    wait_for(  # if not: the watchdog, the controller and the last frames say why
        knee_at_10,
        explain=lambda: (
            app.status()["watchdog"],
            listing(app)["gait"],
            joint_frames(seen, 2)[-5:],
        ),
    )
    r = app.cli("send", "position", "r_knee", "30")
    assert r.returncode == 5 and "r_knee is driven by controller gait" in r.stderr, r.stderr
    assert {f.setpoint for f in joint_frames(collect(mbus, 0.3, {70}), 2)} == {10}
    # a laptop cannot hold a joint past the checks: there is no side door to operator
    # controllers (the old sender's `operator` action), only `exolink send`
    laptop = messaging.open_client_session(app.at)
    try:
        key = messaging.mgmt_key("sim", "controllers")
        body = {"action": "operator", "joint": "r_hip", "mode": "position", "setpoint": 5}
        r = messaging.request(laptop, key, body, 5.0, roles.ADMIN)
        assert not r["ok"] and "unknown controllers action 'operator'" in r["error"], r
    finally:
        laptop.close()
    assert "operator.r_hip.position" not in listing(app)
    # the codec's checks come first (refused, nothing made)
    r = app.cli("send", "position", "r_hip", "500")
    assert r.returncode != 0 and "r_hip" in r.stderr
    # the watchdog stops an operator-held joint: after e-stop no set-point follows the disable
    assert ctl(app, "deactivate", "gait").returncode == 0
    assert app.cli("send", "position", "r_hip", "5").returncode == 0
    wait_for(lambda: joint_frames(collect(mbus, 0.1, {70}), 1))
    assert app.cli("estop").returncode == 0
    collect(mbus, 0.3)  # the trip's frames and anything in flight
    assert [f for f in (h2.decode(m) for m in collect(mbus, 0.5, {70})) if f.mode != 4] == []  # type: ignore[union-attr]
    assert listing(app)["operator.r_hip.position"]["state"] == "inactive"


def dedup(values: list[int]) -> list[int]:
    return [v for i, v in enumerate(values) if i == 0 or v != values[i - 1]]


def mean_step(values: list[int]) -> float:
    """How far a joint's set-point moves from one frame to the next, on average: the gait's
    speed as the bus carries it (a frame each 20 ms slot on the timer)."""
    steps = [abs(b - a) for a, b in itertools.pairwise(values)]
    assert steps, values
    return sum(steps) / len(steps)


def test_a_late_manager_runs_the_newest_cycle_not_a_burst(routed, mbus) -> None:  # type: ignore[no-untyped-def]
    """Stopped for 150 ms (what a full core does to it), the manager finds ~15 cycles queued: it
    runs the newest and counts the others (late_cycles). Replaying them wrote their set-points
    back to back, a step limit apart each: a burst that could move a joint many steps at once."""
    app = routed
    app.arm_and_hold()
    assert ctl(app, "activate", "gait").returncode == 0
    assert ctl(app, "command", "gait", "r_knee=30").returncode == 0
    wait_for(lambda: joint_frames(collect(mbus, 0.1, {70}), 2))
    late0 = json.loads(ctl(app, "list", "--json").stdout)["late_cycles"]
    pid = app.node("controller_manager")["pid"]
    mbus.q.queue.clear()
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(0.15)
    finally:
        os.kill(pid, signal.SIGCONT)
    frames = [m for m in collect(mbus, 0.5, {70}) if joint_frames([m], 2)]
    stamps = [m.timestamp for m in frames]
    gaps = [round(b - a, 4) for a, b in itertools.pairwise(stamps)]
    bunched = sum(g < 0.002 for g in gaps)
    late = json.loads(ctl(app, "list", "--json").stdout)["late_cycles"] - late0
    assert bunched <= 2, (bunched, gaps)
    assert late >= 5, late
    assert listing(app)["gait"]["state"] == "active"


def test_the_timers_wake_and_lease_fit_the_deadline_they_are_judged_by() -> None:
    """While only the timer sends, the manager wakes at 40 % of the shorter of its lease and its
    leased deadline (stock 200 / 200: every 80 ms, renewing each time), never more often than
    its cycle's beat; a lease that would outlast the watchdog's disable by more than hung
    detection's budget is refused at start, naming both."""
    p = ManagerParams()
    assert (p.lease_for(200), p.slot_ms) == (200, 20)
    assert p.timed_wake_s(200, 0.02) == pytest.approx(0.08)
    # unset, the lease is the deadline it is judged by, at least 100 ms where that deadline
    # allows: a manager judged by its own 50 ms (no leased_deadline_ms) as before, 100 ms
    assert p.lease_for(50) == 100 and p.timed_wake_s(50, 0.02) == pytest.approx(0.02)
    assert p.lease_for(30) == 90
    short = ManagerParams(lease_ms=100)
    assert short.timed_wake_s(100, 0.02) == pytest.approx(0.04)
    assert short.timed_wake_s(50, 0.02) == pytest.approx(0.02)  # judged by 50 ms: as before
    assert short.timed_wake_s(40, 0.02) == pytest.approx(0.02)
    with pytest.raises(ValueError, match=r"lease_ms 200 exceeds the leased heartbeat deadline "):
        ManagerParams(lease_ms=200).timed_wake_s(100, 0.02)
    assert ManagerParams(lease_ms=160).timed_wake_s(100, 0.02) == pytest.approx(0.04)
    assert LEASE_PAST_TRIP_MS == 60


def pattern_slots(rows: list[int], f: float) -> list[int]:
    """Four cycles of the pattern sampled a fraction ``f`` of the way from each row to the next."""
    return dedup(
        [round(a + f * (b - a)) for a, b in zip(rows, rows[1:] + rows[:1], strict=True)] * 4
    )


def in_order(runs: list[int], slots: list[int]) -> bool:
    """``runs`` (values deduplicated) follow ``slots`` in order, skipping at most one in ten."""
    starts = [i for i in range(len(slots) // 4) if slots[i : i + 3] == runs[:3]]
    for at in starts:
        skipped = 0
        for v in runs[1:]:
            if v not in slots[at + 1 : at + 4]:
                break
            step = slots[at + 1 : at + 4].index(v) + 1
            skipped, at = skipped + step - 1, at + step
        else:
            if skipped <= len(runs) // 10:
                return True
    return False


@pytest.mark.parametrize("sig", [signal.SIGSTOP, signal.SIGKILL])
def test_a_hung_or_killed_manager_ends_the_gaits_timer(gait, mbus, sig) -> None:  # type: ignore[no-untyped-def]
    """The gait's set-points leave on a timer the manager leases (timed.py). Its owner stopped
    or killed: no set-point after the watchdog's disable frames, and none but the one in flight
    after the signal (on this bus the timer is a thread of the stopped process; the kernel's
    broadcast manager, which outlives a stopped owner by its lease, is tested in the UML guest:
    tests/kernel/test_socketcan.py)."""
    app = gait
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    wait_for(lambda: json.loads(ctl(app, "list", "--json").stdout)["timer"]["sending"])
    # only the timer sends: the supervisor judges the manager by its leased deadline
    wait_for(lambda: app.node("controller_manager")["leased"])
    # the gait's set-points are the timer's alone, its first one too: the cycle loop wrote none
    # (written there, it put the manager on its own 50 ms for the activation: node.py)
    assert json.loads(ctl(app, "list", "--json").stdout)["written"] == 0
    pid = app.node("controller_manager")["pid"]
    mbus.q.queue.clear()
    at = time.time()
    os.kill(pid, sig)
    try:
        frames = [(m.timestamp, h2.decode(m)) for m in collect(mbus, 1.0, {70})]
        disabled = [t for t, f in frames if isinstance(f, h2.JointControl) and f.mode == 4]
        moving = [t for t, f in frames if isinstance(f, h2.JointControl) and f.mode == 1]
        assert disabled, "the watchdog did not disable the joints"
        assert [t for t in moving if t > disabled[0]] == []
        assert len([t for t in moving if t > at + 0.002]) <= 1, moving  # one in flight
        assert app.status()["watchdog"]["state"] == "tripped"
    finally:
        if sig == signal.SIGSTOP:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)


def test_a_feedback_controller_beside_the_gait_runs_each_cycle_the_gait_stays_timed(
    gait, mbus
) -> None:  # type: ignore[no-untyped-def]
    """A PID on a joint the pattern does not drive is a feedback controller: the cycle loop
    runs it every H2 cycle while the gait's joints stay on the timer, one set-point a slot
    (before, any such controller sent the gait back to the cycle loop as well)."""
    app = gait
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    wait_for(lambda: json.loads(ctl(app, "list", "--json").stdout)["timer"]["sending"])
    params = json.dumps({"joints": ["l_ankle"], "kp": 0.5})
    r = ctl(app, "load", "ankle", "pid", "--params", params, "--activate")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: listing(app)["ankle"]["state"] == "active")
    # the activation was a switch: the gait left the timer for it, then went back on alone
    wait_for(lambda: json.loads(ctl(app, "list", "--json").stdout)["timer"]["sending"])
    mbus.q.queue.clear()
    frames = collect(mbus, 1.0, {70, 110})
    angles = sum(m.arbitration_id == 110 for m in frames)
    hips = joint_frames(frames, 1)  # the gait's r_hip
    ankle = joint_frames(frames, 6)  # the PID's l_ankle, in torque mode
    # on the timer (again, if its lease lapsed on a loaded host meanwhile: counted in lapses)
    timer = wait_for(
        lambda: (t := json.loads(ctl(app, "list", "--json").stdout)["timer"])["sending"] and t
    )
    assert timer["runs"] >= 2, timer  # type: ignore[index]
    assert angles / 4 <= len(hips) <= angles / 2 + 3, (len(hips), angles, timer)
    assert len(ankle) > angles * 3 / 4, (len(ankle), angles)  # about one a cycle
    assert {f.mode for f in ankle} == {h2.MODES["torque"]}, ankle[:3]
    assert listing(app)["pattern"]["state"] == "active"
    # The watchdog stops both. The e-stop reaches the supervisor, not the manager: a slot's
    # set-point already due on the gait's timer may still leave in the milliseconds before the
    # manager reads the disable (seen here on a loaded host: one, 2-7 ms after it). The watchdog
    # answers such a frame with the safe action at once (a motion frame while not armed), so
    # each joint's last word is a disable, and none comes later than the design's bound.
    mbus.q.queue.clear()
    assert app.cli("estop").returncode == 0
    after = [(m.timestamp, h2.decode(m)) for m in collect(mbus, 0.6, {70})]
    first = min((t for t, f in after if f.mode == h2.MODES["disabled"]), default=None)  # type: ignore[union-attr]
    assert first is not None, "no disable frame"
    late = [(round((t - first) * 1e3, 1), f) for t, f in after if t > first and f.mode != 4]  # type: ignore[union-attr]
    assert all(ms <= LEASE_PAST_TRIP_MS for ms, _f in late), late
    last = {f.motor: f.mode for _t, f in sorted(after, key=lambda x: x[0])}  # type: ignore[union-attr]
    assert set(last.values()) == {h2.MODES["disabled"]}, (last, late)


def test_with_the_timer_off_the_gait_runs_in_the_cycle_loop(write_config, spawn, mbus) -> None:  # type: ignore[no-untyped-def]
    """``timer: false`` (the board's for now): planned controllers are written by the cycle
    loop like the others, one set-point per H2 cycle, and no send op is made."""
    n = nodes([], deadline_ms=300)
    n[2]["params"] |= {"timer": False}
    player = {
        "name": "pattern_player",
        "plugin": "pattern_player",
        "critical": True,
        "params": {"speed": 10, "selected": ["r_hip", "r_knee"]},
    }
    app = Appliance(write_config(nodes=[*n, player], watchdog={"pulse_silence_ms": 500}), spawn)
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    wait_for(lambda: joint_frames(collect(mbus, 0.1, {70}), 1))
    frames = collect(mbus, 1.0, {70, 110})
    hips = joint_frames(frames, 1)
    angles = sum(m.arbitration_id == 110 for m in frames)
    assert len(hips) > angles * 3 / 4, (len(hips), angles)  # about one a cycle, not a slot
    timer = json.loads(ctl(app, "list", "--json").stdout)["timer"]
    assert not timer["sending"] and timer["runs"] == 0, timer


@pytest.fixture
def gait(write_config, spawn):  # type: ignore[no-untyped-def]
    """The pattern player: one writer, the manager."""
    extra = [
        {
            "name": "pattern_player",
            "plugin": "pattern_player",
            "critical": True,
            "params": {"speed": 10, "selected": ["r_hip", "r_knee"]},
        },
    ]
    # the sim config's step limit (5 deg per cycle): the default pattern at speed 10 needs 4
    cfg = write_config(
        nodes=[*nodes([], deadline_ms=300), *extra], watchdog={"pulse_silence_ms": 500}
    )
    return Appliance(cfg, spawn)


def test_pattern_through_the_manager_owns_its_joints(gait, mbus) -> None:  # type: ignore[no-untyped-def]
    from exolink.nodes.pattern_player import DEFAULT_PATTERN

    from exolink.control.patterns import load_pattern

    app = gait
    r = app.cli("pattern", "start", "--detach")
    assert r.returncode == 5 and "not armed" in r.stderr, r.stderr
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0, "start"
    mbus.q.queue.clear()
    frames = collect(mbus, 1.0, {70, 110})
    hips = [f.setpoint for f in joint_frames(frames, 1)]
    angles = sum(m.arbitration_id == 110 for m in frames)
    # planned ahead and on a timer (timed.py): one set-point per 20 ms slot, half the H2's
    # angle frames, where the pattern is then: at speed 10 (20 ms a row) a row each, in the
    # pattern's order (the step limit may shorten the first swing)
    points = load_pattern(str(DEFAULT_PATTERN), ANY_ANGLE).points
    rows = [p[0] for p in points]
    # never more than one a slot; fewer when the timer's lease lapsed (the manager's loop later
    # than the lease on a loaded host: the joints hold, then it starts again, counted)
    timer = json.loads(ctl(app, "list", "--json").stdout)["timer"]
    assert timer["sending"] and timer["runs"] >= 1, timer
    assert angles / 4 <= len(hips) <= angles / 2 + 3, (len(hips), angles, timer)
    # what the timer sent is counted (both joints, as of its last renewal): at least the hip's
    assert timer["sent"] >= len(hips), (timer, len(hips))

    # and counted as the pattern's own: its `written` (the pattern player's "sent") kept step
    # with the bus once the gait's cycle was replayed (it stood at the first cycle's slots)
    def written() -> int:
        listed = json.loads(ctl(app, "list", "--json").stdout)["controllers"]
        return int(next(c["written"] for c in listed if c["name"] == "pattern"))

    before = written()
    time.sleep(1.5)  # ~150 set-points of two joints, one each a 20 ms slot
    assert written() - before >= 50, (before, written())
    runs = dedup(hips[20:])  # values repeat: compare runs of equal values
    # in the pattern's order: a slot is where the pattern is at its time, the same fraction f of
    # the way from one row to the next each slot (the timer's phase against the pattern's);
    # each run the next slot's value, or one a slot or two further on (never replayed)
    assert any(in_order(runs, pattern_slots(rows, f / 10)) for f in range(10)), runs
    # the operator cannot write a joint the pattern drives; the owner is named, nothing sent
    r = app.cli("send", "position", "r_knee", "30")
    assert r.returncode == 5 and "driven by controller pattern" in r.stderr, r.stderr
    assert "operator.r_knee.position" not in listing(app)  # refused before anything was made
    s = listing(app)["pattern"]
    assert s["state"] == "active" and s["type"] == "gait_pattern"
    shown = app.cli("status").stdout  # each controller's state, claims, update times, overruns
    assert "pattern" in shown and "gait_pattern" in shown and "r_knee/position" in shown, shown
    # speed and pause through the same CLI; pause stops the manager writing. The new speed
    # is on the bus, not only in the status: with the gait's cycle replayed by the timer, a
    # speed once changed nothing there (the plan is made again: Manager.plan_key)
    fast = mean_step(hips[20:])
    assert app.cli("pattern", "speed", "2").returncode == 0
    assert listing(app)["pattern"]["own"]["speed"] == 2
    collect(mbus, 0.3)  # the timer's plan made again
    slow = mean_step([f.setpoint for f in joint_frames(collect(mbus, 1.0, {70}), 1)])
    assert slow < fast / 2, (slow, fast)  # a row every 180 ms instead of 20: ~1/9 a slot
    assert app.cli("pattern", "pause").returncode == 0
    collect(mbus, 0.2)
    assert joint_frames(collect(mbus, 0.3, {70}), 1) == []
    assert app.cli("pattern", "start", "--detach").returncode == 0
    wait_for(lambda: joint_frames(collect(mbus, 0.1, {70}), 1))
    # the watchdog stops it: after e-stop nothing but the safe action, pattern stopped
    assert app.cli("estop").returncode == 0
    collect(mbus, 0.3)
    assert [f for f in (h2.decode(m) for m in collect(mbus, 0.5, {70})) if f.mode != 4] == []  # type: ignore[union-attr]
    assert "stopped" in app.cli("pattern", "status").stdout
    assert listing(app)["pattern"]["state"] == "inactive"


def test_a_feedback_controller_failing_beside_the_gait_leaves_its_timer_running(gait, mbus) -> None:  # type: ignore[no-untyped-def]
    """A feedback controller stopped by itself beside the gait on the timer (a command
    controller's timeout asking for the safe action; a PID over its budget takes the same
    path): its joint gets the safe action, the gait's op goes on (not ended and planned again: on the board proxy that restart
    held the manager 108 ms and tripped the watchdog, A67), and the cycle loop stops running
    beside it."""
    app = gait
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0

    def timer() -> dict[str, Any]:
        return dict(json.loads(ctl(app, "list", "--json").stdout)["timer"])

    wait_for(lambda: timer()["sending"], timeout=10)
    before = timer()
    params = (
        '{"joints": ["l_ankle"], "interface": "torque", "timeout_s": 1, "on_timeout": "disable"}'
    )
    r = ctl(app, "load", "p", "forward_command", "--params", params, "--activate")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: listing(app)["p"]["state"] == "inactive", timeout=10)
    assert "no command for 1 s" in listing(app)["p"]["error"]
    wait_for(lambda: timer()["sending"], timeout=10)
    time.sleep(0.5)
    after = timer()
    # one restart: the PID's activation (a switch is applied by the cycle loop), not its
    # failure; a lapse not resumed in place would be one more
    handed_back = (after["lapses"] - after["resumes"]) - (before["lapses"] - before["resumes"])
    assert after["runs"] - before["runs"] == 1 + handed_back, (before, after)
    assert listing(app)["pattern"]["state"] == "active"
    hips = joint_frames(collect(mbus, 0.5, {70}), 1)
    assert len(hips) >= 10, len(hips)  # the gait goes on, a set-point each 20 ms slot
    assert app.cli("pattern", "stop").returncode == 0


def test_the_manager_reads_the_bus_only_while_a_controller_is_active(app, mbus) -> None:  # type: ignore[no-untyped-def]
    """Idle, it holds no socket frames reach (reading ~400 frames/s for nothing took >= 47 % of
    the board proxy's CPU 0); an activation opens its reader (two sockets: the angle frame wakes
    it, the cycle's other frames wait in the second) and starts from fresh frames, the last
    deactivation closes it, and activating again works. While it reads, one wake-up per H2 cycle,
    not one per frame."""
    pid = app.node("controller_manager")["pid"]
    idle = bus_sockets(pid)
    assert json.loads(ctl(app, "list", "--json").stdout)["reading"] is False
    app.arm_and_hold()
    for _round in range(2):
        assert ctl(app, "activate", "a").returncode == 0
        assert bus_sockets(pid) == idle + 2
        assert joint_frames(collect(mbus, 0.3, {70}), 2)
        listed = json.loads(ctl(app, "list", "--json").stdout)
        rx = listed["receive"]
        # 1 frame per cycle reaches it (110; not 120 or 130, which no loaded controller reads,
        # nor MACCEPA board 0's status on 70, which its content filter drops: on the sim bus
        # in Python, counted in filtered; on SocketCAN in the kernel, tests/kernel)
        assert listed["read_ids"] == [70, 110]
        assert rx["frames"] >= rx["batches"] > 0 and rx["filtered"] > 0, rx
        assert ctl(app, "deactivate", "a").returncode == 0
        wait_for(lambda: bus_sockets(pid) == idle, timeout=5)
        collect(mbus, 0.1)  # frames in flight
        assert joint_frames(collect(mbus, 0.3, {70}), 2) == []
    assert json.loads(ctl(app, "list", "--json").stdout)["reader_opens"] == 2


def test_pattern_through_the_manager_follows_the_managers_stops(gait, mbus) -> None:  # type: ignore[no-untyped-def]
    """With timing: manager the player reads no bus (id 70 then carries the manager's 100 Hz
    set-points): a disable on the bus stops the manager's pattern controller, the manager says
    so on controllers/activity (the whole list, read here by rosbags as a ROS 2 laptop would),
    and the player's state follows from the manager, with its reason."""
    from exolink import messaging
    from exolink.control.controller import ACTIVITY_TOPIC, ACTIVITY_TYPE

    app = gait
    pid = app.node("pattern_player")["pid"]
    before = bus_sockets(pid)
    laptop = messaging.open_client_session(app.at)
    told: list[Any] = []
    sub = laptop.declare_subscriber(
        messaging.topic_key(0, "h2", ACTIVITY_TOPIC, ACTIVITY_TYPE),
        lambda x: told.append(messaging.deserialize(x.payload.to_bytes(), ACTIVITY_TYPE)),
    )
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    wait_for(lambda: joint_frames(collect(mbus, 0.1, {70}), 2))
    assert bus_sockets(pid) == before  # only its send-only socket, as when idle

    def shown_active() -> bool:
        states = dict(zip(told[-1].names, told[-1].states, strict=True)) if told else {}
        return states.get("pattern") == "active"

    wait_for(shown_active)
    assert app.cli("send", "disable", "r_knee").returncode == 0
    wait_for(lambda: listing(app)["pattern"]["state"] != "active")
    wait_for(lambda: "stopped" in app.cli("pattern", "status").stdout, timeout=5)
    shown = app.cli("pattern", "status").stdout
    assert "r_knee disabled by admin" in shown, shown  # the manager's word, with who
    last = told[-1]
    i = list(last.names).index("pattern")
    assert last.states[i] == "inactive" and last.types[i] == "gait_pattern", last
    assert "r_knee disabled by admin" in last.errors[i], last
    assert [m.version for m in told] == sorted({m.version for m in told})  # each change once
    sub.undeclare()
    laptop.close()
    collect(mbus, 0.2)  # frames in flight
    assert [f for f in joint_frames(collect(mbus, 0.3, {70}), 2) if f.mode == 1] == []
    # a new start re-engages the manager (r_knee is switched back on by the pattern)
    assert app.cli("pattern", "start", "--detach").returncode == 0
    wait_for(lambda: [f for f in joint_frames(collect(mbus, 0.1, {70}), 2) if f.mode == 1])
    pattern = listing(app)["pattern"]
    assert pattern["state"] == "active", (pattern.get("error"), app.status()["watchdog"])
