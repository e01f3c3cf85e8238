"""Pattern player, MACCEPA commands and timing monitor across real processes on simulated
hardware, the controller manager writing every motion frame; every frame claim is checked by an
independent listener on the bus."""

from __future__ import annotations

import itertools
import json
import os
import signal
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import bus_sockets
from exolink.nodes.pattern_player import DEFAULT_PATTERN

from benchmarks.harness import EXOLINK, Appliance, collect, wait_for
from exolink import messaging
from exolink.control import replies as ctl_replies
from exolink.control.gait import period_s
from exolink.control.patterns import load_pattern
from exolink.limits.joints import Limits, default_max, default_min
from exolink.protocol import ProtocolError, h2, maccepa
from exolink.wire import replies

NODES = [
    {"name": "simulator", "plugin": "simulator", "params": {"maccepa_boards": [0]}},
    {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
    {
        "name": "controller_manager",
        "plugin": "controller_manager",
        "critical": True,
        # set-points every 20 ms, the thesis' rate and the board's (one update per two cycles)
        "params": {"cycles_per_update": 2, "h2_timeout_ms": 300, "maccepa": [{"board": 0}]},
    },
    {
        "name": "pattern_player",
        "plugin": "pattern_player",
        "critical": True,
        "params": {"speed": 10, "selected": ["r_hip", "r_knee"]},
    },
    {
        "name": "maccepa_bridge",
        "plugin": "maccepa_bridge",
        "critical": True,
        "params": {"boards": [0], "cycles_per_read": 4},  # as on the board
    },
    {"name": "timing_monitor", "plugin": "timing_monitor", "params": {"ids": [70, 110]}},
]
LIMITS = Limits.of(default_min(), default_max(), [127] * 6, [100] * 6, "test")


@pytest.fixture
def app(write_config, spawn):  # type: ignore[no-untyped-def]
    cfg = write_config(nodes=NODES, watchdog={"maccepa_boards": [0], "pulse_silence_ms": 300})
    return Appliance(cfg, spawn)


def positions(frames) -> list[h2.JointControl]:  # type: ignore[no-untyped-def]
    return [
        f for f in (h2.decode(m) for m in frames) if isinstance(f, h2.JointControl) and f.mode == 1
    ]


# --- pattern files ------------------------------------------------------------------------------


def test_default_pattern_is_51_points_inside_ranges() -> None:
    p = load_pattern(str(DEFAULT_PATTERN), LIMITS)
    assert len(p.points) == 51
    for j, name in enumerate(h2.JOINTS):
        lo, hi = h2.RANGES[name]
        assert all(lo <= row[j] <= hi for row in p.points)
    assert max(r[1] for r in p.points) - min(r[1] for r in p.points) > 40  # a knee that swings


@pytest.mark.parametrize(
    ("text", "error"),
    [
        ("r_hip,r_knee\n1,2\n", "header must name the six joints"),
        (
            "r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle\n1,2,3,4,5,6\n",
            "needs 2..10000 set-points, got 1",
        ),
        (
            "r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle\n1,2,3,4,5,6\n1,2,30,4,5,6\n",
            ":3: r_ankle 30 deg is outside the limits -20..20",
        ),
        (
            "r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle\n1,2,3,4,5,6\n1,2.5,3,4,5,6\n",
            ":3: values must be whole degrees",
        ),
        (
            "r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle\n1,2,3,4,5,6\n1,2,3\n",
            ":3: expected 6 values, got 3",
        ),
    ],
)
def test_bad_pattern_files(tmp_path: Path, text: str, error: str) -> None:
    f = tmp_path / "p.csv"
    f.write_text(text)
    with pytest.raises(ProtocolError, match=error.replace(".", r"\.")):
        load_pattern(str(f), LIMITS)


def test_speed_mapping() -> None:
    assert period_s(10) == pytest.approx(0.020) and period_s(1) == pytest.approx(0.200)


# --- pattern on simulated hardware ----------------------------------------------------------


def test_pattern_reaches_joints_in_order_at_speed(app, mbus) -> None:  # type: ignore[no-untyped-def]
    r = app.cli("pattern", "start", "--detach")
    assert r.returncode == 5 and "watchdog is disarmed" in r.stderr
    app.arm()
    r = app.cli("pattern", "start", "--detach")  # armed, but nobody holds motion
    assert r.returncode == 5 and "nobody holds motion" in r.stderr, r.stderr
    assert positions(collect(mbus, 0.3, {70})) == []
    app.hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    frames = collect(mbus, 1.5, {70})
    sent = positions(frames)
    assert {f.motor for f in sent} == {1, 2}  # only the selected joints
    expected = load_pattern(str(DEFAULT_PATTERN), LIMITS).points
    hips = [f.setpoint for f in sent if f.motor == 1]
    lo, hi = min(r[0] for r in expected), max(r[0] for r in expected)
    assert all(lo <= v <= hi for v in hips) and max(hips) - min(hips) > 20  # the gait's swing
    t = [m.timestamp for m in frames if getattr(h2.decode(m), "motor", None) == 1]
    assert np.median(np.diff(t)) == pytest.approx(0.020, rel=0.1)  # one update per 2 H2 cycles
    # the simulated right knee follows the pattern
    angles = [h2.decode(m).r_knee for m in collect(mbus, 1.0, {110})]
    assert max(angles) - min(angles) > 20  # a 60 deg swing, low-passed by the joint dynamics
    assert (
        int(json.loads(app.cli("pattern", "status", "--json").stdout or "{}").get("sent", 1)) >= 0
    )


def test_the_replies_are_their_schemas_whole(app) -> None:  # type: ignore[no-untyped-def]
    """Each reply read as its schema and written back is what the node sent: no field that a
    schema leaves out, renames or retypes (the manager's while a pattern plays, the pattern
    player's, the supervisor's clock and software, a node's params)."""
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    asks = [
        ("controllers", {"action": "list"}, ctl_replies.ManagerStatus),
        ("controllers", {"action": "types"}, ctl_replies.Types),
        ("controllers", {"action": "state", "name": "pattern"}, ctl_replies.StateOf),
        ("pattern", {"action": "status"}, ctl_replies.PatternInfo),
        ("clock", {}, replies.ClockStatus),
        ("update", {}, replies.Software),
        ("nodes/h2_reader/params", {}, replies.NodeParams),
    ]
    for path, body, schema in asks:
        raw = app.call(path, body)
        assert raw.pop("ok"), (path, raw)
        assert replies.plain(replies.read(raw, schema)) == raw, (path, schema)
    gait = replies.read(app.call("controllers", {"action": "list"}), ctl_replies.ManagerStatus)
    pattern = next(c for c in gait.controllers if c.name == "pattern")
    assert pattern.state == "active" and pattern.own["speed"] == 10  # its type's own status


def test_speed_change_without_restart_and_pause(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    assert app.cli("pattern", "speed", "5").returncode == 0
    gait = json.loads(app.cli("controllers", "list", "--json").stdout)["controllers"]
    assert [c["own"]["speed"] for c in gait if c["name"] == "pattern"] == [5]
    r = app.cli("pattern", "speed", "11")
    assert r.returncode == 5 and "speed must be a whole level 1..10" in r.stderr
    r = app.cli("pattern", "select", "l_knee")
    assert r.returncode == 5 and "stop the pattern before changing the selection" in r.stderr
    assert app.cli("pattern", "pause").returncode == 0
    collect(mbus, 0.15)
    assert positions(collect(mbus, 0.4, {70})) == []
    assert "paused" in app.cli("pattern", "status").stdout


def test_disable_sends_type4_and_stops_driving_that_joint(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    collect(mbus, 0.3)
    assert app.cli("pattern", "disable", "r_knee").returncode == 0
    frames = positions_or_disable = [
        f
        for f in (h2.decode(m) for m in collect(mbus, 0.6, {70}))
        if isinstance(f, h2.JointControl)
    ]
    assert h2.JointControl(2, 4, 0, 0) in positions_or_disable
    after = frames[frames.index(h2.JointControl(2, 4, 0, 0)) + 1 :]
    assert after and all(f.motor == 1 for f in after)  # the pattern goes on with r_hip alone
    assert "running" in app.cli("pattern", "status").stdout


def test_watchdog_trip_stops_pattern_and_nothing_more_is_sent(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    collect(mbus, 0.3)
    assert app.cli("estop").returncode == 0
    collect(mbus, 0.3)  # the trip's own frames and anything in flight
    assert positions(collect(mbus, 1.0, {70})) == []
    wait_for(lambda: "stopped" in app.cli("pattern", "status").stdout, timeout=5)
    app.arm()  # re-arming does not resume the pattern by itself
    assert positions(collect(mbus, 0.5, {70})) == []


def test_a_disable_from_another_sender_stops_the_pattern(app, mbus) -> None:  # type: ignore[no-untyped-def]
    # The next set-point would switch the joint back on: the pattern must not undo a disable.
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    collect(mbus, 0.3)
    mbus.send(h2.encode_joint_control("l_ankle", "stopped"))  # a joint the pattern does not drive
    assert positions(collect(mbus, 0.3, {70}))
    mbus.send(h2.encode_joint_control("r_knee", "disabled"))  # e.g. a hand-held stop
    collect(mbus, 0.2)  # anything in flight
    assert positions(collect(mbus, 0.5, {70})) == []
    wait_for(lambda: "stopped (r_knee disabled or stopped on the bus)" in app.cli("pattern", "status").stdout, timeout=5)  # fmt: skip
    assert app.status()["watchdog"]["state"] == "armed"  # the watchdog was not involved


def test_the_player_holds_no_bus_socket(app) -> None:  # type: ignore[no-untyped-def]
    """The player writes nothing and reads no bus (the manager plays the gait): id 70 carries
    MACCEPA board 0's 100 Hz frames too, and reading them cost 14 % of the board proxy's CPU 0."""
    pid = app.node("pattern_player")["pid"]
    assert bus_sockets(pid) == 0
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    assert bus_sockets(pid) == 0


def test_kill9_of_pattern_player_disables_motors(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    collect(mbus, 0.3)
    os.kill(app.node("pattern_player")["pid"], signal.SIGKILL)
    frames = [h2.decode(m) for m in collect(mbus, 0.5, {70, 80 + 0})]
    assert sorted({f for f in frames if isinstance(f, h2.JointControl) and f.mode == 4}) == [
        h2.JointControl(m, 4, 0, 0) for m in range(1, 7)
    ]
    assert app.status()["watchdog"]["detail"] == "pattern_player: SIGKILL"


def test_operator_lost_trips(app, mbus) -> None:  # type: ignore[no-untyped-def]
    app.arm()
    holder = subprocess.Popen(
        [*EXOLINK, "pattern", "start", "--at", app.at], stdout=subprocess.PIPE, text=True
    )
    wait_for(lambda: "running" in app.cli("pattern", "status").stdout, timeout=10)
    time.sleep(0.5)
    assert app.status()["watchdog"]["state"] == "armed"  # the operator is present
    holder.kill()  # the laptop vanishes without a word
    holder.wait()
    wait_for(lambda: app.status()["watchdog"]["reason"] == "operator lost", timeout=10)
    collect(mbus, 0.3)  # frames queued before the trip
    assert positions(collect(mbus, 0.5, {70})) == []


# --- MACCEPA --------------------------------------------------------------------------------


def test_maccepa_gains_setpoint_followed_and_invalid_refused(app, mbus) -> None:  # type: ignore[no-untyped-def]
    r = app.cli("maccepa", "0", "setpoint", "40")
    assert r.returncode == 5 and "watchdog is disarmed" in r.stderr
    app.arm_and_hold()
    r = app.cli("maccepa", "0", "gains", "--kp", "2.5", "--controller", "position")
    assert r.returncode == 0
    assert maccepa.decode(collect(mbus, 0.3, {10})[0]) == maccepa.Gain(0, "kp", 2.5, 0)
    assert app.cli("maccepa", "0", "setpoint", "40").returncode == 0
    wait_for(
        lambda: any(abs(maccepa.decode(m).lever - 40) <= 1 for m in collect(mbus, 0.1, {60})),
        timeout=5,
    )
    # and the bridge publishes what the board reports
    s = messaging.open_client_session(app.at)
    got = []
    key = messaging.topic_key(0, "h2", "maccepa/b0/state", "exolink_msgs/msg/MaccepaState")
    sub = s.declare_subscriber(
        key,
        lambda x: got.append(
            messaging.deserialize(x.payload.to_bytes(), "exolink_msgs/msg/MaccepaState")
        ),
    )
    wait_for(lambda: got, timeout=5)
    time.sleep(1.0)
    sub.undeclare()
    # Woken every fourth board cycle, the bridge still publishes each cycle, in order: one
    # message per 10 ms cycle with all three of its frames (the first may start mid-cycle).
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in list(got)]
    assert len(stamps) >= 60 and stamps == sorted(stamps)
    assert 9e6 < statistics.median(b - a for a, b in itertools.pairwise(stamps)) < 11e6
    assert [m.stale for m in got[1:]] == [0] * (len(got) - 1)
    s.close()
    assert abs(got[-1].lever_deg - 40) <= 1
    collect(mbus, 0.2)
    for args, err in [
        (["maccepa", "3", "stop"], "MACCEPA board 3 is not driven by the controller manager"),
        (["maccepa", "12", "stop"], "MACCEPA board 12 is not driven by the controller manager"),
        (["maccepa", "0", "duty", "150"], "duty cycle 150 must be a whole percentage 0..100"),
        (["maccepa", "0", "gains"], "gains needs at least one of kp, ki, kd"),
    ]:
        r = app.cli(*args)
        assert r.returncode == 5 and err in r.stderr, (args, r.stderr)
    # requests as any client may send them, refused by the schema with the field named
    # (exolink.control.requests), before anything else looks at them
    for body, err in [
        ({"kind": "setpoint", "board": 0, "value": "41"}, "got `str` - at `$.value`"),
        ({"kind": "setpoint", "board": 0, "value": 41, "controler": "x"}, "field `controler`"),
        ({"kind": "spin", "board": 0}, "unknown MACCEPA command 'spin' (gains, setpoint, duty"),
    ]:
        reply = app.call("maccepa", body)
        assert reply["ok"] is False and err in reply["error"], (body, reply)
    # nothing of the refused commands: only the held set-point, re-sent every 100 ms
    held = {maccepa.decode(m) for m in collect(mbus, 0.4, set(maccepa.command_ids(range(10))))}
    assert {(type(d).__name__, d.board) for d in held} <= {("Setpoint", 0)}, held
    # a trip sends stop control to the configured board
    assert app.cli("estop").returncode == 0
    stops = [maccepa.decode(m) for m in collect(mbus, 0.5, {80})]
    assert maccepa.Duty(0, 0, 0) in stops


def test_maccepa_watch_plot_line() -> None:
    from exolink.cli.motion import strip

    line = strip(link=0, lever=60, width=25)
    assert line.index("L") == 12 and line.index("A") == 18
    assert "*" in strip(10, 10)


# --- timing monitor -------------------------------------------------------------------------


def test_timing_monitor_measures_the_pattern(app) -> None:  # type: ignore[no-untyped-def]
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    r = app.cli("timing", "70", "--motor", "1", "--dlc", "6", "--seconds", "2", "--json")
    assert r.returncode == 0, r.stderr
    import json

    s = json.loads(r.stdout)
    assert 80 <= s["n"] <= 101
    assert s["mean_period_ms"] == pytest.approx(20.0, abs=0.5)
    assert sum(s["histogram"].values()) == s["n"]
    assert s["socket_dropped"] == 0  # a record without holes
    # --past: the 2 s before the question, from what the monitor kept (the gait still runs)
    r = app.cli("timing", "70", "--motor", "1", "--dlc", "6", "--seconds", "2", "--past", "--json")
    assert r.returncode == 0, r.stderr
    past = json.loads(r.stdout)
    assert 80 <= past["n"] <= 101
    assert past["mean_period_ms"] == pytest.approx(20.0, abs=0.5)
    r = app.cli("timing", "99")
    assert r.returncode == 5 and "id 99 is not monitored" in r.stderr


def test_deviation_stats_on_known_stamps() -> None:
    from exolink.nodes.timing_monitor import deviation_stats

    stamps = [i * 0.020 for i in range(100)]
    stamps[50] += 0.001  # one frame 1 ms late: two periods off by 1 ms
    s = deviation_stats(stamps, 0.020)
    assert s["n"] == 99 and s["max_dev_ms"] == pytest.approx(1.0, abs=1e-6)
    assert s["histogram"]["1000-5000us"] == 2 or s["histogram"]["500-1000us"] == 2
    assert deviation_stats([0.0, 1.0])["n"] == 0


def test_pattern_load_reads_only_the_patterns_dir_and_never_echoes_content(app, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Issue 19 (4): `pattern load /etc/shadow` read the file and echoed its first line."""
    secret = tmp_path / "secret.csv"
    secret.write_text("root:$y$SECRETHASH:19000:0:99999:7:::\n")
    s = messaging.open_client_session(app.at)  # the request as anyone on the network sends it
    try:
        for target in ("/etc/shadow", "../../../../etc/passwd", "nosuch.csv"):
            body = {"action": "load", "file": target}
            r = messaging.request(s, messaging.mgmt_key("sim", "pattern"), body)
            assert not r["ok"] and "pattern" in r["error"], (target, r)
            assert "root" not in r["error"], r
    finally:
        s.close()
    r = app.cli("pattern", "load", str(secret))  # uploaded content that is not a pattern
    assert r.returncode == 5 and "secret.csv:1: header must name the six joints" in r.stderr
    assert "SECRET" not in r.stderr and "root" not in r.stderr
    good = tmp_path / "two.csv"
    good.write_text("r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle\n1,2,3,4,5,6\n2,3,4,5,6,7\n")
    r = app.cli("pattern", "load", str(good))
    assert r.returncode == 0, r.stderr
    r = app.cli("pattern", "load", "normal_walking.csv")  # the board's own, by name
    assert r.returncode == 0, r.stderr
