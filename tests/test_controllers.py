"""Controller manager: the pure logic fed H2 states (no transport), then the node on the simulator
with the watchdog, every claim checked by an independent listener on the bus."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from exolink.controller import State
from exolink.jointlimits import Limits, default_max, default_min
from exolink.nodes.controller_manager.builtin import JointTrajectory, Pid, PidParams
from exolink.nodes.controller_manager.manager import Manager, ManagerRefused, Switch
from exolink.protocol import h2

SITTING = State((40, 60, 0, 40, 60, 0), (0,) * 6)


def manager(max_step: int = 60, budget_ms: float = 50.0, **caps: list[int]) -> Manager:
    limits = Limits.of(
        caps.get("min", default_min()),
        caps.get("max", default_max()),
        caps.get("torque", [127] * 6),
        caps.get("stiffness", [100] * 6),
        "test",
    )
    return Manager(limits, max_step, budget_ms)


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


def test_overrun_deactivates() -> None:
    import time

    m = manager(budget_ms=1.0)
    fwd(m, "a", ["r_knee"])
    switch(m, ["a"])
    real = m.slots["a"].ctrl.update

    def slow(*args: Any) -> Any:
        t = time.thread_time()
        while time.thread_time() - t < 0.005:  # CPU, not wall time: the budget counts CPU
            pass
        return real(*args)

    m.slots["a"].ctrl.update = slow  # type: ignore[method-assign]
    out = m.cycle(SITTING, 0.0, 0.01, None)
    assert out.safe == {1} and out.writes == [] and m.active() == []
    assert "overran its budget" in m.slots["a"].error and m.slots["a"].overruns == 1


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


def msgspec_convert(data: dict[str, Any], cls: type) -> Any:
    import msgspec

    return msgspec.convert(data, cls)
