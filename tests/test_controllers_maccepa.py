"""Controller manager with MACCEPA boards: the pure logic fed states, then the node on the
simulator (a simulated board 0) with the watchdog and the MACCEPA bridge, every claim checked by
an independent listener on the bus and in the simulated board's own status frames."""

from __future__ import annotations

import json
from typing import Any

import can
import pytest
from exolink.nodes.controller_manager.boards import MACCEPA_REFRESH_CYCLES
from exolink.nodes.controller_manager.manager import Manager
from exolink.nodes.controller_manager.slots import ManagerRefused, Switch

from benchmarks.harness import Appliance, collect, wait_for
from exolink.control.controller import BoardState, State
from exolink.limits.joints import Limits, default_max, default_min
from exolink.limits.maccepa import BoardLimits
from exolink.protocol import maccepa
from exolink.refusal import Refused

BOARD0 = BoardState(0, (10, 12, 0, 0), (0, 30, 0, 0), (0, 0, 12))
STATE = State((40, 60, 0, 40, 60, 0), (0,) * 6, None, {0: BOARD0})
NO_BOARD = State((40, 60, 0, 40, 60, 0), (0,) * 6)
LIMITS = {"board": 0, "setpoint_min": -60, "setpoint_max": 60, "max_step": 3, "gain_max": 10}


def manager(**board: Any) -> Manager:
    limits = Limits.of(default_min(), default_max(), [127] * 6, [100] * 6, "test", None, 60)
    return Manager(limits, 50.0, [BoardLimits(**{**LIMITS, **board})])


def switch(m: Manager, activate: list[str], state: State = STATE) -> Switch:
    sw = Switch(list(activate), [])
    m.request(sw)
    m.cycle(state, 0.0, 0.01, None)
    assert sw.done.is_set()
    return sw


def writes(m: Manager) -> list[tuple[str, float]]:
    return [(w.kind, w.value) for w in m.cycle(STATE, 0.0, 0.01, None).maccepa]


# --- pure logic ---------------------------------------------------------------------------------


def test_claims_one_owner_per_board_interface_and_configured_boards_only() -> None:
    m = manager()
    m.load("m0", "maccepa_setpoint", {"board": 0})
    m.load("m1", "maccepa_setpoint", {"board": 0, "gains": {"kp": 2}})
    m.load("d", "maccepa_operator", {"board": 0, "kind": "duty"})
    with pytest.raises(ManagerRefused, match=r"board 3 is not in the controller manager's"):
        m.load("m3", "maccepa_setpoint", {"board": 3})
    with pytest.raises(ManagerRefused, match=r"initial.*|set-point 99 is outside .*-60..60"):
        m.load("far", "maccepa_setpoint", {"board": 0, "initial": 99})
    # no status frame from the board yet: nothing to start from, so no activation
    assert "no position frame from MACCEPA board 0" in str(switch(m, ["m0"], NO_BOARD).error)
    assert switch(m, ["m0"]).error is None
    with pytest.raises(
        ManagerRefused, match="cannot activate m1: maccepa0/setpoint is owned by m0"
    ):
        m.request(Switch(["m1"], []))
    with pytest.raises(ManagerRefused, match=r"maccepa0/setpoint \(m0\) and maccepa0/duty \(d\)"):
        m.request(Switch(["d"], []))
    assert m.active() == ["m0"] and m.status()["owners"] == {"maccepa0/setpoint": "m0"}


def test_setpoint_held_from_the_lever_refused_out_of_range_saturated_by_step() -> None:
    m = manager()
    m.load("m0", "maccepa_setpoint", {"board": 0, "gains": {"kp": 2}})
    m.request(Switch(["m0"], []))
    # the activating cycle: the three gains once, the set-point holding the lever (12)
    first = [("kp", 2.0), ("ki", 0.0), ("kd", 0.0), ("setpoint", 12.0)]
    assert writes(m) == first
    assert m.status()["maccepa"]["maccepa0"].gains == [2.0, 0.0, 0.0]
    # a controller's refusal reaches the caller as it is (exolink.refusal: one type)
    with pytest.raises(Refused, match=r"set-point 500 is outside the board's range"):
        m.command("m0", {"values": {"maccepa0": 500}})
    with pytest.raises(Refused, match=r"kp 11 is outside 0..10"):
        m.command("m0", {"values": {"maccepa0/kp": 11}})
    assert writes(m) == []  # the refused ones changed nothing (and 12 holds)
    m.command("m0", {"values": {"maccepa0": 20, "maccepa0/kd": 0.5}})
    assert writes(m) == [("kd", 0.5), ("setpoint", 15.0)]  # only the changed gain
    assert [v for _, v in writes(m) + writes(m)] == [18.0, 20.0]
    # held: re-sent every MACCEPA_REFRESH_CYCLES cycles only (a lost frame repaired soon)
    held = [writes(m) for _ in range(MACCEPA_REFRESH_CYCLES)]
    assert held == [[]] * (MACCEPA_REFRESH_CYCLES - 1) + [[("setpoint", 20.0)]]
    # a plugin that ignores the range is saturated anyway
    m.slots["m0"].ctrl.values = {"maccepa0/setpoint": 1e6}  # type: ignore[attr-defined]
    assert writes(m) == [("setpoint", 23.0)] and m.slots["m0"].limited >= 1


def test_raising_maccepa_controller_stops_its_board_only() -> None:
    m = manager()
    m.load("m0", "maccepa_setpoint", {"board": 0})
    m.load("knee", "forward_command", {"joints": ["r_knee"]})
    switch(m, ["m0", "knee"])
    m.slots["m0"].ctrl.update = lambda *_: 1 / 0  # type: ignore[method-assign]
    out = m.cycle(STATE, 0.0, 0.01, None)
    assert out.safe_boards == {0} and out.safe == set() and out.maccepa == []
    assert [w.motor for w in out.writes] == [2] and m.active() == ["knee"]
    assert "update raised ZeroDivisionError" in m.slots["m0"].error


def test_timeout_stop_and_not_armed_stop_the_board() -> None:
    import time

    m = manager()
    # 50 ms: the switch's own cycle runs the first update, and with 1 ms a loaded CI host
    # once took longer than that between activation and update (the stop came a cycle early)
    m.load("m0", "maccepa_setpoint", {"board": 0, "timeout_s": 0.05, "on_timeout": "stop"})
    switch(m, ["m0"])
    time.sleep(0.1)
    out = m.cycle(STATE, 0.0, 0.01, None)
    assert out.safe_boards == {0} and "no command" in m.slots["m0"].error
    m.load("m1", "maccepa_setpoint", {"board": 0})
    switch(m, ["m1"])
    out = m.cycle(STATE, 0.0, 0.01, "motors not armed: watchdog is tripped")
    assert out.safe_boards == {0} and out.maccepa == [] and m.active() == []


# --- on the simulator, with the watchdog --------------------------------------------------------

LAB_PLUGIN = '''
from exolink.control.controller import Controller


class BoardRaiser(Controller):
    """Holds MACCEPA board 0's lever where it is until told to fail, then raises in update."""

    def configure(self):
        self.boom = False

    def claims(self):
        return ["maccepa0/setpoint"]

    def activate(self, state):
        self.hold = float(state.board(0).lever)

    def command(self, request):
        self.boom = True
        return {}

    def update(self, state, time, period):
        if self.boom:
            raise RuntimeError("lab maccepa controller bug")
        return {"maccepa0/setpoint": self.hold}
'''

CONTROLLERS = [
    {"name": "m0", "type": "maccepa_setpoint", "params": {"board": 0, "gains": {"kp": 2}}},
    {"name": "m0b", "type": "maccepa_setpoint", "params": {"board": 0}},
]


def nodes() -> list[dict[str, Any]]:
    return [
        {"name": "simulator", "plugin": "simulator", "params": {"maccepa_boards": [0]}},
        {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
        {
            "name": "controller_manager",
            "plugin": "controller_manager",
            "critical": True,
            "heartbeat_deadline_ms": 300,  # not about hung detection: above a loaded machine
            "params": {
                "controllers": CONTROLLERS,
                "maccepa": [{"board": 0, "setpoint_min": -60, "setpoint_max": 60}],
                "h2_timeout_ms": 300,
            },
        },
        {
            "name": "maccepa_bridge",
            "plugin": "maccepa_bridge",
            "critical": True,
            "params": {"boards": [0]},  # it reads; `exolink maccepa` is the manager's
        },
    ]


@pytest.fixture
def lab_board_plugin(lab_package) -> None:  # type: ignore[no-untyped-def]
    """A lab's controller package installed the way pip would (dist-info + entry point)."""
    entry = "[exolink.controllers]\nboard_raiser = lab_board:BoardRaiser\n"
    lab_package("lab_board", entry, {"lab_board.py": LAB_PLUGIN})


def appliance(write_config, spawn) -> Appliance:  # type: ignore[no-untyped-def]
    cfg = write_config(nodes=nodes(), watchdog={"pulse_silence_ms": 500, "maccepa_boards": [0]})
    return Appliance(cfg, spawn)


@pytest.fixture
def app(write_config, spawn, lab_board_plugin):  # type: ignore[no-untyped-def]
    return appliance(write_config, spawn)


@pytest.fixture
def routed(write_config, spawn):  # type: ignore[no-untyped-def]
    return appliance(write_config, spawn)


def ctl(app: Appliance, *args: str) -> Any:
    return app.cli("controllers", *args)


def listing(app: Appliance) -> dict[str, Any]:
    r = ctl(app, "list", "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)  # type: ignore[no-any-return]


def decoded(frames: list[can.Message], cls: type) -> list[Any]:
    return [f for f in (maccepa.decode(m) for m in frames) if isinstance(f, cls)]


def setpoints(frames: list[can.Message]) -> list[float]:
    return [f.value for f in decoded(frames, maccepa.Setpoint) if f.board == 0]


def lever(mbus: Any) -> list[int]:
    """The simulated board's lever, as it reports it (positions frames, id 60)."""
    return [f.lever for f in decoded(collect(mbus, 0.1, {60}), maccepa.Positions)]


def board_controller(mbus: Any) -> list[maccepa.Controller]:
    """The board's own controller frames (id 70, 8 bytes): set-point, actuation, process var."""
    return decoded(collect(mbus, 0.2, {70}), maccepa.Controller)


STOP = maccepa.Duty(0, 0, 0)


def test_setpoint_controller_drives_the_board_conflicts_and_range_refused(app, mbus) -> None:  # type: ignore[no-untyped-def]
    r = ctl(app, "types")
    assert r.returncode == 0 and "maccepa_setpoint" in r.stdout, r.stderr
    r = ctl(app, "activate", "m0")
    assert r.returncode == 5 and "motors not armed" in r.stderr, r.stderr
    app.arm_and_hold()
    assert ctl(app, "activate", "m0").returncode == 0
    r = ctl(app, "command", "m0", "maccepa0=40")
    assert r.returncode == 0, r.stderr
    # on the bus: the gains once, then a set-point every cycle ramping to 40 (step 3)
    wait_for(lambda: setpoints(collect(mbus, 0.1, {40}))[-1:] == [40.0])
    # the simulated board follows: its lever reaches the set-point under its own PID
    wait_for(lambda: any(abs(v - 40) <= 1 for v in lever(mbus)), timeout=10)
    assert {c.setpoint for c in board_controller(mbus)} == {40}
    # one owner per interface: refused with the owner named
    r = ctl(app, "activate", "m0b")
    assert r.returncode == 5 and "maccepa0/setpoint is owned by m0" in r.stderr, r.stderr
    # out of the board's range: refused, and no frame carries it (the held 40 continues)
    mbus.q.queue.clear()
    r = ctl(app, "command", "m0", "maccepa0=500")
    assert r.returncode == 5 and "outside the board's range -60..60" in r.stderr, r.stderr
    assert set(setpoints(collect(mbus, 0.5, {40}))) == {40.0}
    # malformed board frames on the bus: counted by the manager and skipped, control goes on
    for _ in range(3):
        mbus.send(can.Message(arbitration_id=60, data=b"\x01\x02\x03", is_extended_id=False))
    wait_for(lambda: listing(app)["malformed"].get("60 bad length") == 3)
    assert set(setpoints(collect(mbus, 0.3, {40}))) == {40.0}
    # claims and boards as the CLI shows them
    s = listing(app)
    m0 = next(c for c in s["controllers"] if c["name"] == "m0")
    assert m0["state"] == "active" and m0["claims"] == ["maccepa0/setpoint", "maccepa0/gains"]
    assert s["maccepa"]["maccepa0"] == {
        "controller": "position",
        "setpoint": 40.0,
        "gains": [2, 0, 0],
    }
    shown = app.cli("status").stdout
    assert "maccepa0/setpoint" in shown and "setpoint by m0" in shown, shown


def test_raising_controller_deactivated_and_its_board_stopped(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert ctl(app, "activate", "m0").returncode == 0  # gains kp=2, so the board moves
    assert ctl(app, "command", "m0", "maccepa0=30").returncode == 0
    wait_for(lambda: any(abs(v - 30) <= 1 for v in lever(mbus)), timeout=10)
    r = ctl(app, "load", "lab", "board_raiser")
    assert r.returncode == 0, r.stderr
    assert ctl(app, "switch", "--activate", "lab", "--deactivate", "m0").returncode == 0
    wait_for(lambda: listing(app)["owners"].get("maccepa0/setpoint") == "lab")
    mbus.q.queue.clear()
    assert ctl(app, "command", "lab", "maccepa0=0").returncode == 0
    frames = collect(mbus, 0.5, {40, 80})
    stops = [i for i, m in enumerate(frames) if maccepa.decode(m) == STOP]
    assert stops, [maccepa.decode(m) for m in frames]
    assert setpoints(frames[stops[0] :]) == []  # nothing drives the board after its stop
    s = {c["name"]: c for c in listing(app)["controllers"]}
    assert s["lab"]["state"] == "inactive"
    assert "RuntimeError: lab maccepa controller bug" in s["lab"]["error"]
    # the board itself: control stopped, zero actuation
    assert {c.actuation for c in board_controller(mbus)} == {0}


def test_estop_leaves_the_board_stopped_and_the_controller_inactive(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert ctl(app, "activate", "m0").returncode == 0
    assert ctl(app, "command", "m0", "maccepa0=-20").returncode == 0
    wait_for(lambda: setpoints(collect(mbus, 0.1, {40}))[-1:] == [-20.0])
    mbus.q.queue.clear()
    assert app.cli("estop").returncode == 0
    frames = collect(mbus, 0.3, {40, 80})  # the trip's frames and anything in flight
    assert STOP in [maccepa.decode(m) for m in frames]
    assert setpoints(collect(mbus, 0.5, {40})) == []
    assert {c.actuation for c in board_controller(mbus)} == {0}
    m0 = next(c for c in listing(app)["controllers"] if c["name"] == "m0")
    # stopped by whichever came first: the trip on Zenoh or the watchdog's stop frame on the bus
    assert m0["state"] == "inactive", m0
    assert "not armed" in m0["error"] or "maccepa0 stopped on the bus" in m0["error"], m0
    app.arm()  # re-arming does not bring it back
    assert setpoints(collect(mbus, 0.4, {40})) == []


def test_maccepa_commands_are_the_managers(routed, mbus) -> None:  # type: ignore[no-untyped-def]
    app = routed
    app.arm_and_hold()
    r = app.cli("maccepa", "0", "gains", "--kp", "2")
    assert r.returncode == 0 and "held by controller operator.maccepa0.gains" in r.stdout, r
    r = app.cli("maccepa", "0", "setpoint", "25")
    assert r.returncode == 0 and "held by controller operator.maccepa0.setpoint" in r.stdout, r
    wait_for(lambda: setpoints(collect(mbus, 0.1, {40}))[-1:] == [25.0])
    wait_for(lambda: any(abs(v - 25) <= 1 for v in lever(mbus)), timeout=10)
    # the board's limits apply to `exolink maccepa` too, refused verbatim
    r = app.cli("maccepa", "0", "setpoint", "70")
    assert r.returncode == 5 and "outside the board's range -60..60" in r.stderr, r.stderr
    # a controller activated on the board takes it over from the operator's one-off hold
    assert ctl(app, "activate", "m0b").returncode == 0
    held = listing(app)["owners"]
    assert held["maccepa0/setpoint"] == "m0b", held
    assert ctl(app, "deactivate", "m0b").returncode == 0
    r = app.cli("maccepa", "0", "setpoint", "25")
    assert r.returncode == 0 and "held by controller operator.maccepa0.setpoint" in r.stdout, r
    # stop goes straight to the bus and releases the operator's hold
    assert app.cli("maccepa", "0", "stop").returncode == 0
    wait_for(lambda: "operator.maccepa0.setpoint" not in listing(app)["owners"].values())
    collect(mbus, 0.2)
    assert setpoints(collect(mbus, 0.3, {40})) == []
    assert ctl(app, "activate", "m0b").returncode == 0
    r = app.cli("maccepa", "0", "setpoint", "10")
    assert r.returncode == 5 and "maccepa0 is driven by controller m0b" in r.stderr, r.stderr


def test_board_0_frames_on_id_70_are_not_malformed_for_a_manager_without_boards() -> None:
    """Id 70 is H2 joint control (6 bytes) and MACCEPA board 0's controller frame (8 bytes): a
    manager that drives no board skips board 0's frames instead of counting them malformed (the
    board proxy's manager counted 93 in its first second); a 7-byte id-70 frame still counts."""
    from exolink.nodes.controller_manager.bus_view import BusView

    from exolink.canbus import Frame
    from exolink.protocol import h2

    view = BusView(board_ids=set())  # the manager's decoding, without its transport
    board0 = Frame(0.0, h2.JOINT_CONTROL, bytes([10, 0, 20, 0, 9, 0, 0, 0]))  # what board 0 sends
    assert isinstance(view.decode(board0), maccepa.Controller)
    assert view.malformed == {}
    view.decode(Frame(0.0, 70, bytes(7)))
    assert view.malformed == {"70 bad length": 1}
