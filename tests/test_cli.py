"""The CLI's own edges (issue 19): option placement, one-line errors, negative lists, units,
playback namespaces, the status table. Parsing is checked in-process; behaviour against a
simulated appliance through real `exolink` processes."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from exolink.nodes.recorder import McapFile, RecorderParams

from benchmarks.harness import EXOLINK, Appliance
from exolink import messaging
from exolink.cli.main import parse
from exolink.client import DEFAULT_AT
from exolink.wire import replies

JS = "sensor_msgs/msg/JointState"
WD = "exolink_msgs/msg/WatchdogEvent"
RECORDED_S = 1_700_000_000

SIM_NODES = [
    {"name": "simulator", "plugin": "simulator"},
    {"name": "h2_reader", "plugin": "h2_reader"},
]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*EXOLINK, *args], capture_output=True, text=True, timeout=30)


# --- appliance options before or after the command --------------------------------------------


def test_appliance_options_before_the_command(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("EXOLINK_AT", raising=False)
    a = parse(["--at", "tcp/1.2.3.4:7447", "--timeout", "7", "--device", "exo-02", "status"])
    assert (a.at, a.timeout, a.device, a.command) == ("tcp/1.2.3.4:7447", 7.0, "exo-02", "status")
    a = parse(["--zenoh-config", "login.json5", "send", "stream", "on"])  # nested subcommand
    assert a.zenoh_config == "login.json5" and a.at == DEFAULT_AT and a.timeout == 3.0
    # after the command, as before; after wins over before
    a = parse(["status", "--at", "tcp/5.6.7.8:7447"])
    assert a.at == "tcp/5.6.7.8:7447"
    a = parse(["--at", "tcp/1.2.3.4:7447", "--ns", "x", "echo", "t", "--at", "tcp/5.6.7.8:7447"])
    assert (a.at, a.ns) == ("tcp/5.6.7.8:7447", "x")
    # neither: the environment, then the default
    monkeypatch.setenv("EXOLINK_AT", "tcp/9.9.9.9:7447")
    assert parse(["status"]).at == "tcp/9.9.9.9:7447"
    assert parse(["--at", "tcp/1.2.3.4:7447", "status"]).at == "tcp/1.2.3.4:7447"


def test_appliance_options_refused_by_board_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        parse(["--at", "tcp/1.2.3.4:7447", "config", "x.yaml"])
    assert e.value.code == 2
    assert "--at: `exolink config` does not talk to an appliance" in capsys.readouterr().err


def test_options_before_the_command_reach_the_appliance(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    app = Appliance(write_config(nodes=SIM_NODES), spawn)
    r = run("--at", app.at, "--timeout", "3", "status")
    assert r.returncode == 0, r.stderr
    assert "h2_reader" in r.stdout
    # The status reply is its schema, whole: read as exolink.wire.replies.Status and written
    # back, it is what the supervisor sent (no field the schema leaves out or renames).
    raw = app.call("status")
    assert replies.plain(replies.read(raw, replies.Status)) == {
        k: v for k, v in raw.items() if k != "ok"
    }
    # a value after the command wins: an unreachable endpoint before it does not matter
    r = run("--at", "tcp/127.0.0.1:9", "nodes", "--at", app.at)
    assert r.returncode == 0, r.stderr


# --- one-line errors ---------------------------------------------------------------------------


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    """A small MCAP file as the recorder writes them: joint states and the appliance's own state
    (watchdog, a node's diagnostics), stamped in 2023 (RECORDED_S): nothing live is."""
    path = tmp_path / "trial.mcap"
    f = McapFile(path, RecorderParams(), {})
    for i in range(20):
        ns = RECORDED_S * 1_000_000_000 + i * 10_000_000
        for topic, typename, msg in (
            (
                "h2/joint_states",
                JS,
                messaging.msg_class(JS)(
                    header=messaging.header(ns),
                    name=["r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"],
                    position=np.radians([10.0, 20, 0, 10, 20, 0]),
                    velocity=np.empty(0),
                    effort=np.array([1.0, 2, 0, 1, 2, 0]),
                ),
            ),
            (
                "h2/watchdog",
                WD,
                messaging.msg_class(WD)(
                    stamp=messaging.stamp(ns), state="armed", reason="", detail="", frames_sent=0
                ),
            ),
        ):
            cid = f.channel(topic, typename)
            f.w.add_message(
                cid,
                log_time=ns,
                data=messaging.serialize(msg, typename),
                publish_time=ns,
                sequence=i,
            )
        diag = messaging.diagnostics(ns, "h2_reader/h2_stream", "error", "replayed fault", "h2", {})
        cid = f.channel("h2/nodes/h2_reader/diagnostics", messaging.DIAGNOSTICS_TYPE)
        f.w.add_message(
            cid,
            log_time=ns,
            data=messaging.serialize(diag, messaging.DIAGNOSTICS_TYPE),
            publish_time=ns,
            sequence=i,
        )
    f.close({})
    return path


def one_line_error(r: subprocess.CompletedProcess[str], *expected: str) -> None:
    assert r.returncode != 0, r.stdout
    assert "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr
    for text in expected:
        assert text in r.stderr, r.stderr


def test_bad_label_and_paths_are_one_line(recording: Path, tmp_path: Path) -> None:
    r = run("record", "start", "--label", "noequals", "--at", "tcp/127.0.0.1:9", "--timeout", "1")
    one_line_error(r, "label 'noequals' must be KEY=VALUE")
    assert r.returncode == 2  # refused before any network
    one_line_error(run("export", str(recording), "--csv", "/proc/x"), "/proc/x")
    one_line_error(run("export", str(recording), "--csv", f"{recording}/out"), f"{recording}/out")
    assert not (tmp_path / "never").exists()
    one_line_error(run("export", str(tmp_path / "none.mcap"), "--csv", str(tmp_path / "never")))
    assert not (tmp_path / "never").exists()  # no output for an input that is not there
    one_line_error(run("info", str(tmp_path)), str(tmp_path))  # a directory
    one_line_error(run("play", str(tmp_path), "--at", "tcp/127.0.0.1:9"), str(tmp_path))
    one_line_error(run("recover", str(recording), "-o", str(recording)), f"{recording} exists")
    one_line_error(run("recover", str(recording), "-o", "/proc/x.mcap"), "/proc/x.mcap")
    r = run("export", str(recording), "--csv", str(tmp_path / "csv"))
    assert r.returncode == 0 and "/h2/joint_states" in r.stdout, r.stderr


# --- negative lists ----------------------------------------------------------------------------


def test_negative_lists_parse_without_equals_sign() -> None:
    a = parse(["send", "limits", "--min", "-10,0,-20,-20,0,-20", "--max", "-5,80,-1.5,90,80,15"])
    assert a.min == [-10, 0, -20, -20, 0, -20] and a.max == [-5, 80, -1.5, 90, 80, 15]
    assert parse(["send", "limits", "--min=-10,0,-20,-20,0,-20"]).min[0] == -10  # as before
    assert parse(["maccepa", "0", "setpoint", "-30"]).value == -30
    assert parse(["echo", "t", "-n", "2"]).count == 2  # options are still options


# --- units in echo -----------------------------------------------------------------------------


def test_echo_text_shows_units_from_the_table() -> None:
    from exolink.cli.data import _pretty

    js = {
        "header": {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": ""},
        "name": ["r_hip", "r_knee"],
        "position": [float(np.radians(10)), float(np.radians(-20))],
        "velocity": [],
        "effort": [1.5, -2.0],
    }
    text = _pretty(js, typename=JS).splitlines()
    assert "position: [0.174533, -0.349066] rad  ([10, -20] deg)" in text
    assert "effort: [1.5, -2] N·m" in text and "velocity: []" in text
    assert "    sec: 1" in text  # nested fields: no unit
    jc = "exolink_msgs/msg/JointCommand"
    cmd = {"joint": "r_knee", "mode": 3, "setpoint": 12, "stiffness": 0, "source": "cli"}
    assert "setpoint: 12 counts" in _pretty(cmd, typename=jc)
    assert "setpoint: 30 deg" in _pretty({**cmd, "mode": 1, "setpoint": 30}, typename=jc)
    assert "setpoint: 0\n" in _pretty({**cmd, "mode": 4, "setpoint": 0}, typename=jc)
    assert _pretty({"x": 1.0}, typename="unknown/msg/Type") == "x: 1"


# --- play: a separate namespace unless --live, never the appliance's own state -------------------


def test_what_play_never_republishes_live() -> None:
    from exolink.recordings.playback import replay_topic

    assert replay_topic("/h2/joint_states", live=False) == "replay/h2/joint_states"
    assert replay_topic("/h2/joint_states", live=True) == "h2/joint_states"
    assert replay_topic("/h2/maccepa/b0/state", live=True) == "h2/maccepa/b0/state"
    for own in (
        "/h2/watchdog",
        "/other/ns/pattern_state",
        "/h2/trigger",
        "/h2/supervisor/diagnostics",
        "/h2/nodes/recorder/diagnostics",
        "/h2/nodes/h2_reader/heartbeat",
        "/watchdog",
    ):
        assert replay_topic(own, live=True) is None, own
        assert replay_topic(own, live=False) == "replay/" + own.strip("/")


def test_play_lands_on_live_keys_only_with_live(write_config, spawn, recording) -> None:  # type: ignore[no-untyped-def]
    app = Appliance(write_config(nodes=SIM_NODES), spawn)
    s = messaging.open_client_session(app.at)
    replayed: list[str] = []  # data topics of samples carrying the recording's stamps

    def on(sample) -> None:  # type: ignore[no-untyped-def]
        topic, typename = messaging.parse_key(str(sample.key_expr))
        msg = messaging.deserialize(sample.payload.to_bytes(), typename)
        stamp = msg.header.stamp if hasattr(msg, "header") else getattr(msg, "stamp", None)
        if stamp is not None and RECORDED_S <= stamp.sec < RECORDED_S + 10:
            replayed.append(topic)

    sub = s.declare_subscriber("0/**", on)
    try:
        r = run("play", str(recording), "--rate", "5", "--at", app.at)
        assert r.returncode == 0, r.stderr
        time.sleep(0.5)
        assert sorted(set(replayed)) == [
            "replay/h2/joint_states",
            "replay/h2/nodes/h2_reader/diagnostics",
            "replay/h2/watchdog",
        ]
        assert "played 60 messages onto /replay/..." in r.stdout
        replayed.clear()
        r = run("play", str(recording), "--rate", "5", "--live", "--at", app.at)
        assert r.returncode == 0, r.stderr
        time.sleep(0.5)
        assert sorted(set(replayed)) == ["h2/joint_states"] and len(replayed) == 20
        assert "played 20 messages onto the live keys" in r.stdout
        assert "/h2/watchdog" in r.stderr and "/h2/nodes/h2_reader/diagnostics" in r.stderr
        assert "replayed fault" not in app.node("h2_reader")["health"]
    finally:
        sub.undeclare()
        s.close()


# --- the status table ----------------------------------------------------------------------------


def node(name: str, state: str = "running", **kw: object) -> dict:
    running = state == "running"
    return {
        "name": name,
        "critical": True,
        "enabled": True,
        "state": state,
        "pid": 4321 if running else None,
        "uptime_s": 12.5 if running else 0.0,
        "restarts": 0,
        "last_exit": "",
        "health": "",
        "heartbeat_age_s": 0.2 if running else None,
        **({"cpu_s": 1.25, "rss_mb": 31.5} if running else {}),
        **kw,
    }


def test_status_table_aligned_and_health_never_blank() -> None:
    from exolink.cli.status import _node_table
    from exolink.wire.replies import NodeInfo, read

    nodes = [
        node("simulator", critical=False),
        node("maccepa_bridge_left_leg_board_3", health="error: joint angle outside its range"),
        node("h2_reader", health="ok", starved=2),  # late twice while it waited for the CPU
        node("pattern_player", heartbeat_age_s=None),  # spawned, no heartbeat yet
        node("recorder", "stopped", critical=False, last_exit="stopped by operator"),
        node("timing_monitor", "stopped", enabled=False, critical=False),
        node("h2_sender", "backoff", restarts=3, last_exit="exit 1"),
        node("x", "failed", restarts=10, last_exit="exit 1: restart limit (5 in 60 s)"),
        node("y", "killed", last_exit="killed: no heartbeat for 510 ms"),
    ]
    head, *rows, footer = _node_table([read(n, NodeInfo) for n in nodes]).splitlines()
    assert footer == "(* critical)" and len(rows) == len(nodes)
    health = head.index("health")
    left = {t: head.index(t) for t in ("node", "state", "last exit", "health")}
    right = {t: head.index(t) + len(t) for t in ("pid", "uptime", "restarts", "cpu_s", "rss_mb")}
    for n, row in zip(nodes, rows, strict=True):
        assert row.startswith(n["name"] + ("*" if n["critical"] else "")), row
        state = n["state"] if n["enabled"] else "disabled"
        assert row[left["state"] :].startswith(state + " "), (row, head)
        for title, end in right.items():  # right-aligned numbers end under their title
            assert row[end - 1] != " " and row[end] == " ", (title, row, head)
        assert row[left["last exit"] - 1] == " " and row[left["last exit"]] != " ", (row, head)
        assert row[health - 1] == " " and row[health:].strip(), (row, head)
    said = [row[health:] for row in rows]
    assert said == [
        "ok",
        "error: joint angle outside its range",
        "ok (starved 2x)",
        "starting",
        "stopped",
        "disabled",
        "restarting",
        "failed",
        "killed",
    ]
    assert "stopped by operator" in rows[4] and "restart limit" in rows[7]
