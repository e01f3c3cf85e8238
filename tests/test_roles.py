"""Roles on the network, against a real appliance whose Zenoh router enforces the logins the
board's first boot writes (boardsetup renders them; Zenoh's own usrpwd and access control check
them). Every CLI call here is a real laptop process with a role's login file."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.reader import make_reader

from benchmarks.harness import Appliance, wait_for
from exolink import messaging, roles
from exolink.board import settings as boardsettings
from exolink.board import setup as boardsetup
from exolink.config import bundled

DEVICE = "sim"


def board_logins(tmp_path: Path) -> tuple[Path, dict[str, Path]]:
    """The board's Zenoh config (appliance login + dictionary) and one laptop file per role,
    as boardsetup renders them on a card whose settings ask for every role."""
    settings = boardsettings.BoardSettings(
        device=DEVICE, zenoh=boardsettings.ZenohAuth(logins=list(roles.ROLES))
    )
    plan = boardsetup.plan(settings, tmp_path / "root")
    users = tmp_path / "zenoh-users.txt"
    users.write_text(plan.files[boardsetup.ZENOH_USERS][0])
    board = json.loads(plan.files["etc/exolink/zenoh.json5"][0])
    board["transport"]["auth"]["usrpwd"]["dictionary_file"] = str(users)
    board_file = tmp_path / "zenoh.json5"
    board_file.write_text(json.dumps(board))
    logins = {}
    for role in roles.ROLES:
        name = boardsetup.laptop_file(role)
        logins[role] = tmp_path / name
        logins[role].write_text(plan.boot_files[name])
    return board_file, logins


def _guarded(tmp_path: Path, write_config, spawn, reader_cycles: int = 1):  # type: ignore[no-untyped-def]
    """The sim appliance with every login; ``reader_cycles``: the h2 reader's cycles_per_read
    (more than 1: joint_states is bundled, as on the board)."""
    board_file, logins = board_logins(tmp_path)
    nodes = yaml.safe_load(bundled("sim").read_text())["nodes"]
    for n in nodes:
        if n["name"] == "recorder":
            n["params"]["directory"] = str(tmp_path / "rec")
        if n["plugin"] == "h2_reader":
            n.setdefault("params", {})["cycles_per_read"] = reader_cycles
    cfg = write_config(nodes=nodes, zenoh={"config_file": str(board_file)})
    return Appliance(cfg, spawn, login=logins["admin"]), board_file, logins


@pytest.fixture
def guarded(tmp_path: Path, write_config, spawn) -> tuple[Appliance, Path, dict[str, Path]]:  # type: ignore[no-untyped-def]
    return _guarded(tmp_path, write_config, spawn)  # type: ignore[no-any-return]


class Inbox:
    """Samples one session receives on a key, for checks from the test thread."""

    def __init__(self, session: Any, key: str) -> None:
        self.items: list[Any] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: Any) -> None:
        with self._lock:
            self.items.append(sample)

    def payloads(self) -> list[bytes]:
        with self._lock:
            return [bytes(s.payload.to_bytes()) for s in self.items]


def commands(inbox: Inbox) -> list[dict[str, Any]]:
    """The command log's JSON entries (std_msgs/String CDR: 4-byte header, uint32 length)."""
    return [json.loads(p[8:-1].decode()) for p in inbox.payloads()]


def test_roles_decide_who_may_do_what(guarded) -> None:  # type: ignore[no-untyped-def]
    app, board_file, logins = guarded
    obs, op, admin = (logins[r] for r in roles.ROLES)
    inside = messaging.open_client_session(app.at, str(board_file))  # the appliance's own login
    try:
        log = Inbox(inside, messaging.topic_selector(0, "h2", "commands"))
        # Anyone without a login, or with a wrong password, is refused at the door.
        with pytest.raises(messaging.Unreachable):
            messaging.open_client_session(app.at)
        wrong = obs.parent / "wrong.json5"
        wrong.write_text(obs.read_text().replace('"observer"', '"operator"'))
        assert app.cli("status", login=wrong).returncode == 4

        # observer: reads and e-stops, nothing else.
        assert app.cli("status", login=obs).returncode == 0
        r = app.cli("echo", "joint_states", "-n", "1", "--json", login=obs)
        assert r.returncode == 0 and "position" in r.stdout, r.stderr
        for cmd in (("arm",), ("send", "position", "l_knee", "20"), ("stop", "recorder")):
            r = app.cli(*cmd, login=obs)
            assert r.returncode == 5, (cmd, r.stdout, r.stderr)
            assert "role; this login is observer" in r.stderr, (cmd, r.stderr)
        r = app.cli("record", "start", login=obs)
        assert r.returncode == 5 and "needs the operator role" in r.stderr
        r = app.cli("hold", login=obs)  # holding motion is the operator's
        assert r.returncode == 5 and "needs the operator role" in r.stderr, r.stderr
        assert app.cli("nodes", login=obs).returncode == 0
        assert app.node("recorder")["state"] == "running"

        # operator: arms, holds motion, commands, records; cannot stop nodes.
        app.arm_as(op)
        app.hold(login=op)
        r = app.cli("send", "position", "l_knee", "20", login=op)
        assert r.returncode == 0, r.stderr
        r = app.cli("stop", "recorder", login=op)
        assert r.returncode == 5 and "needs the admin role; this login is operator" in r.stderr
        r = app.cli("estop", login=obs)
        assert r.returncode == 0 and "watchdog tripped" in r.stdout  # (an earlier trip may win)

        # admin: node control.
        r = app.cli("restart", "timing_monitor", login=admin)
        assert r.returncode == 0, r.stderr

        # Every command above observer is in the command log with the login that sent it.
        def logged() -> list[tuple[str, str, str, bool]]:
            return [
                (e["by"], e["key"].rsplit("/", 1)[-1], e["request"].get("action", ""), e["ok"])
                for e in commands(log)
            ]

        wait_for(lambda: ("admin", "control", "restart", True) in logged(), timeout=10)
        got = logged()
        assert ("observer", "watchdog", "arm", False) in got
        assert ("operator", "watchdog", "arm", True) in got
        assert ("operator", "command", "", True) in got  # h2/command: the joint set-point
        assert ("operator", "control", "stop", False) in got
        assert ("observer", "watchdog", "estop", True) in got
    finally:
        inside.close()


def test_a_login_cannot_forge_data_or_serve_commands(guarded) -> None:  # type: ignore[no-untyped-def]
    """An operator's session publishing a watchdog state or answering management keys reaches
    nothing: Zenoh's access control drops it at the router."""
    app, board_file, logins = guarded
    inside = messaging.open_client_session(app.at, str(board_file))
    laptop = messaging.open_client_session(app.at, str(logins["operator"]))
    try:
        wd_key = messaging.topic_selector(0, "h2", "watchdog")
        seen = Inbox(inside, wd_key)
        wait_for(lambda: seen.payloads(), timeout=5)  # the supervisor's own state does arrive
        key = messaging.topic_key(0, "h2", "watchdog", "exolink_msgs/msg/WatchdogEvent")
        js_key = messaging.topic_key(0, "h2", "joint_states", "sensor_msgs/msg/JointState")
        before = len(seen.payloads())
        for _ in range(20):
            laptop.put(key, b"forged armed")
            laptop.put(js_key, b"x")
            time.sleep(0.01)
        time.sleep(0.5)
        assert b"forged armed" not in seen.payloads()[before:]
        # What a laptop may put: a replay, under replay/ (exolink play), seen by others.
        replay = Inbox(inside, "0/replay/**")
        wait_for(
            lambda: laptop.put("0/replay/h2/joint_states/x/y", b"replayed") or replay.payloads()
        )
        # A laptop serving a management key never gets the queries meant for the appliance.
        fake = laptop.declare_queryable(
            messaging.mgmt_key(DEVICE, "watchdog", "*"),
            lambda q: q.reply(q.key_expr, b'{"ok": true, "state": "armed"}'),
        )
        try:
            for _ in range(5):  # the real watchdog is disarmed: only the fake would say armed
                reply = messaging.request(inside, messaging.mgmt_key(DEVICE, "watchdog"))
                assert reply["ok"] and reply["state"] == "disarmed", reply
        finally:
            fake.undeclare()
    finally:
        laptop.close()
        inside.close()


def test_commands_are_written_into_the_recording(guarded) -> None:  # type: ignore[no-untyped-def]
    app, _board_file, logins = guarded
    op = logins["operator"]
    assert app.cli("record", "start", "--label", "subject=S01", login=op).returncode == 0

    app.hold(login=op)

    def armed_and_sent() -> bool:  # a loaded machine can trip the watchdog in between: again
        app.arm_as(op)
        return app.cli("send", "position", "l_knee", "15", login=op).returncode == 0

    wait_for(armed_and_sent, timeout=20)
    time.sleep(0.5)
    r = app.cli("record", "stop", login=op)
    assert r.returncode == 0, r.stderr
    files = wait_for(
        lambda: list((Path(app.cfg.node("recorder").params["directory"])).glob("*.mcap"))
    )
    with open(files[0], "rb") as f:  # type: ignore[index]
        entries = [
            json.loads(bytes(msg.data)[8:-1].decode())
            for _schema, channel, msg in make_reader(f).iter_messages()
            if channel.topic.endswith("/commands")
        ]
    assert {(e["by"], e["request"].get("action")) for e in entries} >= {
        ("operator", "arm"),
        ("operator", "start"),
    }


def test_ros2_services_and_topics_follow_the_roles(guarded, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A ROS 2 client (zenoh-ros2-sdk, not this project's code) with a role's login file: the
    router lets each login query exactly the ROS 2 services its role may call, and put only on
    the command topics its role may use; a refused call gets no answer at all."""
    sdk = pytest.importorskip("zenoh_ros2_sdk")
    app, board_file, logins = guarded
    port = int(app.at.rsplit(":", 1)[1])
    inside = messaging.open_client_session(app.at, str(board_file))
    log = Inbox(inside, messaging.topic_selector(0, "h2", "commands"))
    empty, reply = "# empty\n", "bool success\nstring message\n"

    def as_role(role: str) -> None:
        if sdk.ZenohSession._instance is not None:
            sdk.ZenohSession._instance.close()
            sdk.ZenohSession._instance = None
        monkeypatch.setenv("ZENOH_SESSION_CONFIG_URI", str(logins[role]))
        sdk.ZenohSession.get_instance("127.0.0.1", port)

    def call(name: str, srv: str, request: str, **fields: Any) -> Any:
        c = sdk.ROS2ServiceClient(
            name, srv, request_definition=request, response_definition=reply,
            router_port=port, timeout=3,
        )  # fmt: skip
        try:
            return c.call(**fields)
        finally:
            c.close()

    control = "string node\nstring action\n"
    try:
        as_role("observer")
        r = call("/h2/estop", "std_srvs/srv/Trigger", empty)
        assert r is not None and r.success, r
        assert call("/h2/arm", "std_srvs/srv/Trigger", empty) is None
        as_role("operator")
        r = wait_for(lambda: (x := call("/h2/arm", "std_srvs/srv/Trigger", empty)) and x.success)
        assert call("/h2/node_control", "exolink_msgs/srv/NodeControl", control,
                    node="timing_monitor", action="restart") is None  # fmt: skip
        as_role("admin")
        r = call("/h2/node_control", "exolink_msgs/srv/NodeControl", control,
                 node="timing_monitor", action="restart")  # fmt: skip
        assert r is not None and r.success, r
        want = {("ros2", "estop"), ("ros2", "arm"), ("ros2", "restart")}
        # the log entry is published after the reply: wait for it, do not race it
        wait_for(lambda: want <= {(e["by"], e["request"].get("action")) for e in commands(log)})
        got = [(e["by"], e["request"].get("action")) for e in commands(log)]
        assert got.count(("ros2", "arm")) == 1  # the observer's call never reached a handler

        # Topics: an observer's joint command is dropped at the router, an operator's arrives.
        header = (
            "builtin_interfaces/Time stamp\nstring frame_id\n",
            "int32 sec\nuint32 nanosec\n",
        )
        definition = (
            "std_msgs/Header header\nstring joint\nuint8 mode\nint16 setpoint\n"
            "uint8 stiffness\nstring source\n"
        )
        type_hash = messaging.type_hash("exolink_msgs/msg/JointCommand")

        def publish(role: str, setpoint: int) -> Any:
            as_role(role)
            s = sdk.ZenohSession._instance
            s.register_message_type(header[1], "builtin_interfaces/msg/Time")
            s.register_message_type(header[0], "std_msgs/msg/Header")
            pub = sdk.ROS2Publisher(
                "/h2/cmd/joint", "exolink_msgs/msg/JointCommand", msg_definition=definition,
                type_hash=type_hash, router_port=port,
            )  # fmt: skip
            t = s.store.types
            stamp = t["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
            h = t["std_msgs/msg/Header"](stamp=stamp, frame_id="")
            return lambda: pub.publish(
                header=h, joint="l_knee", mode=1, setpoint=setpoint, stiffness=0, source="t"
            )

        def setpoints() -> list[int]:
            return [e["request"].get("setpoint") for e in commands(log) if "cmd/joint" in e["key"]]

        send = publish("observer", 22)
        for _ in range(10):
            send()
            time.sleep(0.02)
        send = publish("operator", 21)
        wait_for(lambda: send() or 21 in setpoints(), timeout=15, step=0.3)
        time.sleep(0.5)
        assert 22 not in setpoints()
    finally:
        if sdk.ZenohSession._instance is not None:
            sdk.ZenohSession._instance.close()
            sdk.ZenohSession._instance = None
        inside.close()


def test_an_observer_reads_a_bundled_topic_as_bundles_and_cannot_forge_one(
    tmp_path: Path,
    write_config,  # type: ignore[no-untyped-def]
    spawn,  # type: ignore[no-untyped-def]
) -> None:
    """The board's joint_states (read 4 cycles at a time) through an observer's login: every
    message, in order, from the bundles, and the reader puts none one by one for it; a
    bundle the observer puts reaches nobody."""
    app, board_file, logins = _guarded(tmp_path, write_config, spawn, reader_cycles=4)
    laptop = messaging.open_client_session(app.at, str(logins["observer"]))
    inside = messaging.open_client_session(app.at, str(board_file))
    got: list[tuple[str, int, int, bytes]] = []
    try:
        wait_for(lambda: app.node("h2_reader")["state"] == "running", timeout=20)
        selector = messaging.topic_selector(0, "h2", "joint_states")
        sub = messaging.MessageSubscription(
            laptop, DEVICE, selector, lambda *m: got.append(m), ask_s=5
        )
        assert sub.bundled
        wait_for(lambda: len(got) >= 40, timeout=10)
        seqs = [m[1] for m in got]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # none missing, in order
        assert all(k.startswith("0/h2/joint_states/") for k, *_ in got)
        msg = messaging.deserialize(got[-1][3], "sensor_msgs/msg/JointState")
        assert len(msg.position) == 6
        stats = messaging.request(inside, messaging.mgmt_key(DEVICE, "nodes", "h2_reader", "stats"))
        assert stats["joint_states_out"]["sent"] == 0, stats["joint_states_out"]
        assert stats["joint_states_out"]["bundles"] > 0
        # `exolink echo` takes the bundles too: messages, and still nothing one by one.
        r = app.cli("echo", "joint_states", "-n", "5", "--json", login=logins["observer"])
        assert r.returncode == 0 and r.stdout.count('"position"') == 5, r.stderr
        stats = messaging.request(inside, messaging.mgmt_key(DEVICE, "nodes", "h2_reader", "stats"))
        assert stats["joint_states_out"]["sent"] == 0, stats["joint_states_out"]

        # Forged: an observer's bundle never reaches the appliance's recorder (or anyone).
        seen = Inbox(inside, messaging.bundle_selector(DEVICE))
        wait_for(lambda: seen.payloads(), timeout=5)  # the reader's own bundles do arrive
        forged = messaging.encode_bundle(bytes(16), [(1, 1, b"forged")])
        key = messaging.bundle_key(DEVICE, "0/h2/joint_states/x/y")
        for _ in range(20):
            laptop.put(key, forged)
            time.sleep(0.01)
        time.sleep(0.5)
        assert forged not in seen.payloads()
        sub.close()
    finally:
        laptop.close()
        inside.close()
