"""The operator's intent at the system level: the limits in force, the caps and the presence of
whoever holds motion live in the controller manager, survive restarts, and bind every way in.

Real supervisor, nodes, CLI processes and Zenoh sessions; every frame claim is checked by an
independent listener on the simulated bus."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import time
from typing import Any

import pytest

from benchmarks.harness import EXOLINK, Appliance, collect, motion_nodes, wait_for
from exolink.protocol import h2

LOST_MS = 2000  # watchdog.operator_lost_ms, as shipped
NODES = [
    *motion_nodes(deadline_ms=300, h2_timeout_ms=300),
    {
        "name": "pattern_player",
        "plugin": "pattern_player",
        "critical": True,
        "params": {"speed": 10, "selected": ["r_hip", "r_knee"]},
    },
]


@pytest.fixture
def app(write_config, spawn, tmp_path):  # type: ignore[no-untyped-def]
    cfg = write_config(
        nodes=NODES, watchdog={"pulse_silence_ms": 500}, state_dir=str(tmp_path / "state")
    )
    return Appliance(cfg, spawn)


def knee(frames: list[Any], mode: int = 1) -> list[int]:
    return [
        f.setpoint
        for f in (h2.decode(m) for m in frames)
        if isinstance(f, h2.JointControl) and f.motor == 2 and f.mode == mode
    ]


def limits(app: Appliance) -> dict[str, Any]:
    r = app.cli("controllers", "list", "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)["limits"]


def restart_manager(app: Appliance) -> None:
    old = app.node("controller_manager")["pid"]
    assert app.cli("restart", "controller_manager").returncode == 0
    wait_for(
        lambda: (
            (n := app.node("controller_manager"))["pid"] not in (None, old)
            and n["heartbeat_age_s"] is not None
        ),
        timeout=20,
    )


def test_operator_limits_survive_a_restart_and_bind_every_way_in(app, mbus) -> None:  # type: ignore[no-untyped-def]
    """The tester's finding: after `send limits --max 100,60,...` a restart of the node that
    kept them re-sent the configured limits and `send position r_knee 80` moved the knee to
    80; a forward_command controller drove r_knee to 90 meanwhile. Now the manager keeps the
    operator's limits (on disk before they apply), re-sends them to the H2 when it restarts,
    refuses a command outside them and saturates every controller's output to them."""
    app.arm_and_hold()
    assert limits(app)["source"] == "config"
    r = app.cli("send", "limits", "--max", "100,60,20,100,100,20")
    assert r.returncode == 0, r.stderr
    restart_manager(app)  # a trip, and a fresh manager process
    # the fresh manager put the operator's limits back on the H2, not the configured ones
    sent = [h2.decode(m) for m in collect(mbus, 0.5, {h2.MAX_ANGLES})]
    lim = limits(app)
    assert lim["source"] == "operator" and lim["set_by"] == "admin", lim
    assert lim["joints"]["r_knee"]["max"] == 60
    app.arm()
    r = app.cli("send", "position", "r_knee", "80")
    assert r.returncode == 5 and "r_knee set-point 80 deg is outside the limits 0..60" in r.stderr
    assert "set by admin" in r.stderr, r.stderr
    shown = app.cli("status").stdout  # the limits in force and who set them
    assert "limits   set by admin" in shown and "r_knee      0..60" in shown, shown
    # a controller loaded by hand is held to them too: asked for 90, it gets 60
    body = '{"joints": ["r_knee"]}'
    assert app.cli("controllers", "load", "fc", "forward_command", "--params", body).returncode == 0
    assert app.cli("controllers", "activate", "fc").returncode == 0
    assert app.cli("controllers", "command", "fc", "r_knee=90").returncode == 0
    wait_for(lambda: knee(collect(mbus, 0.1, {70}))[-1:] == [60], timeout=10)
    assert max(knee(collect(mbus, 0.5, {70}))) == 60
    # the H2 saw them at the restart: the stricter max, not the configured 100
    assert any(isinstance(f, h2.MaxAngles) and f.r_knee == 60 for f in sent) or sent == [], sent
    # only narrower than the config's: a wider one is refused, nothing sent
    r = app.cli("send", "limits", "--max", "100,100,20,100,101,20")
    assert r.returncode == 5 and "outside 0..100" in r.stderr, r.stderr
    assert app.cli("send", "limits", "--reset").returncode == 0
    assert limits(app)["source"] == "config"


def test_the_operators_limits_are_kept_across_the_board_restarting(  # type: ignore[no-untyped-def]
    write_config, spawn, tmp_path, mbus
) -> None:
    """A reboot (a new supervisor) keeps them too: they are in the state directory."""
    state = str(tmp_path / "kept")
    cfg = write_config(nodes=NODES, state_dir=state)
    first = Appliance(cfg, spawn)
    assert first.cli("send", "limits", "--min", "0,10,-20,-20,0,-20").returncode == 0
    first.proc.stop()
    second = Appliance(cfg, spawn)
    lim = limits(second)
    assert lim["source"] == "operator" and lim["joints"]["r_knee"]["min"] == 10, lim
    mins = [h2.decode(m) for m in collect(mbus, 1.0, {h2.MIN_ANGLES})]
    assert any(f.r_knee == 10 for f in mins), mins  # and on the H2 again


def test_a_damaged_limits_file_refuses_motion_until_sent_again(  # type: ignore[no-untyped-def]
    write_config, spawn, tmp_path
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    (state / "operator-limits.json").write_text('{"min": [0, 0')  # a torn write
    app = Appliance(write_config(nodes=NODES, state_dir=str(state)), spawn)
    app.arm_and_hold()
    r = app.cli("send", "position", "r_knee", "30")
    assert r.returncode == 5 and "could not be read" in r.stderr, r.stderr
    assert app.cli("send", "limits", "--reset").returncode == 0
    assert app.cli("send", "position", "r_knee", "30").returncode == 0


def test_torque_has_a_real_cap_and_a_rate_limit(app, mbus) -> None:  # type: ignore[no-untyped-def]
    """The shipped defaults: 20 counts at the knee (127 is the int8's full scale), at most 2 per
    10 ms cycle: a forward_command torque of 1e9 arrives as a ramp to 20, never a jump."""
    app.arm_and_hold()
    r = app.cli("send", "torque", "r_knee", "127")
    assert r.returncode == 5 and "r_knee torque 127 counts is above its cap 20" in r.stderr
    # armed and held: requests any client may send, refused by their schema with the field
    # named (exolink.control.requests), and not one frame of them on the bus
    mbus.q.queue.clear()
    for body, err in [
        ({"kind": "joint", "joint": "r_knee", "mode": "torque", "setpoint": "5"}, "`$.setpoint`"),
        ({"kind": "joint", "joint": "r_knee", "mode": "position", "stifness": 5}, "`stifness`"),
        ({"kind": "joint", "mode": "position", "setpoint": 5}, "missing required field `joint`"),
        ({"kind": "stream", "on": "yes"}, "got `str` - at `$.on`"),
        (
            {"kind": "move", "joint": "r_knee"},
            "unknown command kind 'move' (joint, limits, stream)",
        ),
    ]:
        reply = app.call("h2/command", body)
        assert reply["ok"] is False and err in reply["error"], (body, reply)
    assert knee(collect(mbus, 0.3, {70}), 3) == []
    body = '{"joints": ["r_knee"], "interface": "torque"}'
    assert app.cli("controllers", "load", "t", "forward_command", "--params", body).returncode == 0
    assert app.cli("controllers", "activate", "t").returncode == 0
    mbus.q.queue.clear()
    assert app.cli("controllers", "command", "t", "r_knee=1000000000").returncode == 0
    torques = knee(collect(mbus, 1.0, {70}), 3)  # 0 -> 20 takes 10 cycles: 100 ms
    assert torques[-1] == 20 and max(torques) == 20, torques
    assert all(b - a <= 2 for a, b in itertools.pairwise([0, *torques])), torques


def test_nothing_moves_without_a_holder(app, mbus) -> None:  # type: ignore[no-untyped-def]
    """`pattern start --detach` and a gait loaded by hand ran with nobody watching: refused now,
    naming what to do; held, they run, and losing the holder stops them and trips."""
    app.arm()
    r = app.cli("pattern", "start", "--detach")
    assert r.returncode == 5 and "nobody holds motion" in r.stderr, r.stderr
    rows = json.dumps({"rows": [[0, 10, 0, 0, 0, 0], [0, 20, 0, 0, 0, 0]], "joints": ["r_knee"]})
    r = app.cli("controllers", "load", "g", "gait_pattern", "--params", rows, "--activate")
    assert r.returncode == 5 and "nobody holds motion" in r.stderr, r.stderr
    r = app.cli("send", "position", "r_knee", "30")
    assert r.returncode == 5 and "nobody holds motion" in r.stderr, r.stderr
    collect(mbus, 0.2)
    assert knee(collect(mbus, 0.3, {70})) == []
    holder = subprocess.Popen([*EXOLINK, "hold", "--at", app.at], stdout=subprocess.PIPE, text=True)
    assert holder.stdout is not None and "holding motion" in holder.stdout.readline()
    r = app.cli("controllers", "load", "g", "gait_pattern", "--params", rows, "--activate")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: knee(collect(mbus, 0.1, {70})), timeout=10)
    shown = app.cli("status").stdout
    assert "motion   held by admin (exolink hold on" in shown, shown
    holder.kill()  # the laptop vanishes
    holder.wait()
    wait_for(lambda: app.status()["watchdog"]["reason"] == "operator lost", timeout=10)
    collect(mbus, 0.3)  # frames in flight
    assert knee(collect(mbus, 0.5, {70})) == []


def attached_start(
    app: Appliance, mbus: Any, sigint_ignored: bool = False
) -> subprocess.Popen[str]:
    """An attached `pattern start` (its own session, as a laptop's terminal), once the knee
    moves; ``sigint_ignored``: as a process started in a script's background inherits it."""
    start = subprocess.Popen(
        [*EXOLINK, "pattern", "start", "--at", app.at],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
        if sigint_ignored
        else None,
    )
    try:
        wait_for(lambda: "running" in app.cli("pattern", "status").stdout, timeout=15)
        wait_for(lambda: knee(collect(mbus, 0.1, {70})), timeout=10)
    except BaseException:
        start.kill()
        start.wait()
        raise
    return start


def test_a_frozen_laptop_stops_the_gait_within_operator_lost_ms(app, mbus) -> None:  # type: ignore[no-untyped-def]
    """SIGSTOP of the attached `pattern start` (what a Wi-Fi drop looks like: no TCP close)
    kept the gait running ~12 s, Zenoh's session lease plus operator_lost_ms. The keep-alive is
    the application's own now: the first disable frame comes within operator_lost_ms + 1 s
    (asserted with room for a loaded machine; the bench measures it)."""
    app.arm()
    start = attached_start(app, mbus)
    try:
        mbus.q.queue.clear()
        t0 = time.time()
        os.kill(start.pid, signal.SIGSTOP)
        disabled = wait_for(
            lambda: [m for m in collect(mbus, 0.05, {70}) if h2.decode(m).mode == 4], timeout=10
        )
        took = disabled[0].timestamp - t0  # type: ignore[index]
        assert took < (LOST_MS + 2500) / 1000, took  # was ~12 s
        assert app.status()["watchdog"]["reason"] == "operator lost"
        collect(mbus, 0.3)
        assert knee(collect(mbus, 0.5, {70})) == []
    finally:
        os.kill(start.pid, signal.SIGKILL)
        start.wait()


@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGTERM])
def test_a_holder_told_to_stop_stops_the_gait_itself(app, mbus, how) -> None:  # type: ignore[no-untyped-def]
    """Ctrl-C or ``kill`` of the attached `pattern start` stops the pattern and lets go, even
    when it inherited SIGINT ignored (started in the background of a script, as the board
    bench's laptop did: its Ctrl-C was ignored, and 30 s later its kill tripped the watchdog
    on the lost presence). No trip: the operator stopped it."""
    app.arm()
    start = attached_start(app, mbus, sigint_ignored=True)
    try:
        start.send_signal(how)
        out, _ = start.communicate(timeout=10)
        assert start.returncode == 0, out
        assert "stopped" in app.cli("pattern", "status").stdout
        collect(mbus, 0.3)  # frames in flight
        assert knee(collect(mbus, 0.5, {70})) == []
        time.sleep(LOST_MS / 1000 + 0.5)  # past operator_lost_ms: the holder let go, no trip
        watchdog = app.status()["watchdog"]
        assert watchdog["state"] == "armed", watchdog
    finally:
        if start.poll() is None:
            start.kill()
            start.wait()


def test_a_second_holder_is_refused_or_takes_over_visibly(app) -> None:  # type: ignore[no-untyped-def]
    first = subprocess.Popen([*EXOLINK, "hold", "--at", app.at], stdout=subprocess.PIPE, text=True)
    try:
        assert first.stdout is not None and "holding motion" in first.stdout.readline()
        r = app.cli("hold")
        assert r.returncode == 5 and "motion is held by admin (exolink hold on" in r.stderr
        r = app.cli("pattern", "start")  # an attached start is a holder too
        assert r.returncode == 5 and "motion is held by admin" in r.stderr, r.stderr
        second = subprocess.Popen(
            [*EXOLINK, "hold", "--take-over", "--at", app.at], stdout=subprocess.PIPE, text=True
        )
        assert second.stdout is not None and "holding motion" in second.stdout.readline()
        assert first.wait(10) == 5  # the first is told, by whom, and gives up
        told = first.stdout.read()
        assert "no longer holding motion: motion was taken over by admin" in told, told
        second.send_signal(signal.SIGINT)
        second.wait(10)
    finally:
        for p in (first,):
            if p.poll() is None:
                p.kill()


def test_a_one_off_hold_gives_way_to_the_pattern(app, mbus) -> None:  # type: ignore[no-untyped-def]
    """`send position r_knee 30` leaves the joint held by operator.r_knee.position: starting
    the pattern takes the joint over (the operator means the pattern to drive) instead of
    refusing for an owner the operator may not know exists."""
    app.arm_and_hold()
    assert app.cli("send", "position", "r_knee", "30").returncode == 0
    r = app.cli("pattern", "start", "--detach")
    assert r.returncode == 0, r.stderr
    ctl = {
        c["name"]: c
        for c in json.loads(app.cli("controllers", "list", "--json").stdout)["controllers"]
    }
    assert ctl["pattern"]["state"] == "active"
    assert ctl["operator.r_knee.position"]["state"] == "inactive"
