"""A ROS 2 laptop's view of the appliance, through an rmw_zenoh implementation that is not this
project's: zenoh-ros2-sdk (PyPI; pure Python on zenoh + rosbags, its own token parser, CDR,
attachments and RIHS01 hashing). Against a real appliance (supervisor, nodes, simulator)."""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import xxhash
import yaml

from benchmarks.harness import Appliance, wait_for
from exolink import messaging
from exolink.config import bundled

sdk = pytest.importorskip("zenoh_ros2_sdk")

TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
# A laptop with sensor_msgs installed has these definitions; the type comes from the graph.
DEFINITIONS = {
    "sensor_msgs/msg/JointState": (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
        "float64[] effort\n"
    ),
    "exolink_msgs/msg/JointCommand": (
        "std_msgs/Header header\nstring joint\nuint8 mode\nint16 setpoint\nuint8 stiffness\n"
        "string source\n"
    ),
}
TRIGGER_RESPONSE = "bool success\nstring message\n"


@pytest.fixture
def appliance(tmp_path: Path, write_config, spawn) -> Iterator[tuple[Appliance, int]]:  # type: ignore[no-untyped-def]
    nodes = yaml.safe_load(bundled("sim").read_text())["nodes"]
    for n in nodes:
        if n["name"] == "recorder":
            n["params"]["directory"] = str(tmp_path / "rec")
    app = Appliance(write_config(nodes=nodes), spawn)
    port = int(app.at.rsplit(":", 1)[1])
    yield app, port
    session = sdk.ZenohSession._instance  # the SDK keeps one session per process
    if session is not None:
        session.close()
        sdk.ZenohSession._instance = None


def _sdk_session(port: int) -> Any:
    s = sdk.ZenohSession.get_instance("127.0.0.1", port)
    for typename, text in (("builtin_interfaces/msg/Time", TIME), ("std_msgs/msg/Header", HEADER)):
        s.register_message_type(text, typename)
    return s


def _graph(port: int) -> list[str]:
    """Every @ros2_lv token key, read with plain Zenoh."""
    s = sdk.ZenohSession.get_instance("127.0.0.1", port).session
    return [str(r.ok.key_expr) for r in s.liveliness().get("@ros2_lv/0/**", timeout=2) if r.ok]


def test_a_ros2_laptop_sees_echoes_calls_and_publishes(appliance) -> None:  # type: ignore[no-untyped-def]
    app, port = appliance
    session = _sdk_session(port)

    # Nodes, topics with types, services: what ros2 node/topic/service list show.
    def topics() -> dict[str, list[str]]:
        return dict(sdk.get_topic_names_and_types(router_port=port, timeout=1.0))

    found = wait_for(lambda: "/h2/pattern_state" in (t := topics()) and t, timeout=30)
    assert found["/h2/joint_states"] == ["sensor_msgs/msg/JointState"]  # type: ignore[index]
    assert found["/h2/watchdog"] == ["exolink_msgs/msg/WatchdogEvent"]  # type: ignore[index]
    services = dict(sdk.get_service_names_and_types(router_port=port, timeout=1.0))
    assert services["/h2/arm"] == ["std_srvs/srv/Trigger"]
    assert services["/h2/estop"] == ["std_srvs/srv/Trigger"]
    assert services["/h2/record"] == ["std_srvs/srv/SetBool"]
    assert services["/h2/joint_command"] == ["exolink_msgs/srv/SendJointCommand"]
    info = sdk.get_topic_info("/h2/joint_states", router_port=port, verbose=True)
    assert [(p.node_name, p.node_namespace) for p in info.publishers] == [("h2_reader", "/h2")]
    node_tokens = [k for k in _graph(port) if k.split("/")[5] == "NN"]
    nodes = {k.split("/")[8] for k in node_tokens}
    assert {"supervisor", "h2_reader", "controller_manager", "pattern_player", "recorder"} <= nodes

    # joint_states echoed with the type (and its hash) learnt from the graph.
    js_type = found["/h2/joint_states"][0]  # type: ignore[index]
    js_hash = next(p.type_hash for p in info.publishers)
    got: list[Any] = []
    sub = sdk.ROS2Subscriber(
        "/h2/joint_states",
        js_type,
        got.append,
        msg_definition=DEFINITIONS[js_type],
        type_hash=js_hash,
        router_port=port,
    )
    wait_for(lambda: len(got) >= 5, timeout=20)
    assert list(got[-1].name) == ["r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"]
    sub.close()

    # The GID in each sample's attachment is the one derived from the publisher's token.
    mp = next(k for k in _graph(port) if "/MP/" in k and "%h2%joint_states/" in k)
    high, low = struct.unpack(">QQ", xxhash.xxh3_128(mp.encode()).digest())
    raw: list[bytes] = []
    z = session.session.declare_subscriber(
        f"0/h2/joint_states/*/{js_hash}", lambda s: raw.append(s.attachment.to_bytes())
    )
    wait_for(lambda: raw, timeout=10)
    z.undeclare()
    assert len(raw[0]) == 33 and raw[0][16] == 16
    assert raw[0][17:] == struct.pack("<QQ", low, high)

    # Services: e-stop, then arm, and the watchdog changes each time.
    def call(name: str, srv: str, request: str, **fields: Any) -> Any:
        client = sdk.ROS2ServiceClient(
            name,
            srv,
            request_definition=request,
            response_definition=TRIGGER_RESPONSE,
            router_port=port,
            timeout=10,
        )
        try:
            return client.call(**fields)
        finally:
            client.close()

    r = call("/h2/estop", "std_srvs/srv/Trigger", "# empty\n")
    assert r.success and r.message.startswith("tripped"), r
    assert app.status()["watchdog"]["state"] == "tripped"
    r = wait_for(lambda: (x := call("/h2/arm", "std_srvs/srv/Trigger", "# empty\n")).success and x)
    assert r.message.startswith("armed")  # type: ignore[union-attr]
    assert app.status()["watchdog"]["state"] == "armed"
    jc = "string joint\nstring mode\nint16 setpoint\nuint8 stiffness\n"
    r = call("/h2/joint_command", "exolink_msgs/srv/SendJointCommand", jc, joint="r_knee",
             mode="position", setpoint=300, stiffness=0)  # fmt: skip
    assert not r.success and "outside" in r.message  # the CLI's validation, verbatim
    r = call("/h2/joint_command", "exolink_msgs/srv/SendJointCommand", jc, joint="r_knee",
             mode="position", setpoint=30, stiffness=0)  # fmt: skip
    assert not r.success and "nobody holds motion" in r.message  # presence binds ROS 2 too
    app.hold()  # the operator's laptop holds motion (`exolink hold`)

    # A message a ROS 2 node publishes reaches the appliance: a joint command on /h2/cmd/joint,
    # validated and sent as the CLI's is, and logged with the publisher's GID.
    inbox: list[dict[str, Any]] = []
    log = session.session.declare_subscriber(
        messaging.topic_selector(0, "h2", "commands"),
        lambda s: inbox.append(json.loads(s.payload.to_bytes()[8:-1])),
    )
    cmd_in = sdk.get_topic_info("/h2/cmd/joint", router_port=port, verbose=True)
    cmd_hash = next(s.type_hash for s in cmd_in.subscribers)
    pub = sdk.ROS2Publisher(
        "/h2/cmd/joint",
        "exolink_msgs/msg/JointCommand",
        msg_definition=DEFINITIONS["exolink_msgs/msg/JointCommand"],
        type_hash=cmd_hash,
        router_port=port,
    )
    msgs = session.store.types
    stamp = msgs["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    header = msgs["std_msgs/msg/Header"](stamp=stamp, frame_id="")

    def sent() -> list[dict[str, Any]]:
        return [e for e in inbox if e["by"] == "ros2" and "cmd/joint" in e["key"]]

    def publish() -> bool:
        pub.publish(header=header, joint="l_knee", mode=1, setpoint=25, stiffness=0, source="t")
        return bool(sent())

    wait_for(publish, timeout=15, step=0.3)
    entry = sent()[0]
    assert entry["ok"], entry
    assert entry["request"]["publisher"] == pub.publisher_gid.hex()
    assert entry["request"]["setpoint"] == 25 and entry["request"]["mode"] == "position"
    pub.close()
    log.undeclare()


def test_the_graph_goes_away_with_a_node(appliance) -> None:  # type: ignore[no-untyped-def]
    app, port = appliance
    _sdk_session(port)

    def of(node: str) -> list[str]:
        return [k for k in _graph(port) if k.split("/")[8] == node]

    before = wait_for(lambda: of("timing_monitor"), timeout=30)
    r = app.cli("stop", "timing_monitor")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: of("timing_monitor") == [], timeout=20)
    r = app.cli("start", "timing_monitor")
    assert r.returncode == 0, r.stderr
    after = wait_for(lambda: of("timing_monitor"), timeout=30)
    # A new process, a new session: new zid, so new tokens and GIDs.
    assert {k.split("/")[2] for k in after} != {k.split("/")[2] for k in before}  # type: ignore[union-attr]


def test_humble_switch(tmp_path: Path, write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    """zenoh.ros_distro: humble: keys and tokens carry Humble's TypeHashNotSupported, GIDs
    Humble's 24 bytes; a client that sends 16-byte GIDs (Jazzy's form) is still answered."""
    nodes = [n for n in yaml.safe_load(bundled("sim").read_text())["nodes"]
             if n["name"] in ("simulator", "h2_reader", "controller_manager")]  # fmt: skip
    app = Appliance(write_config(nodes=nodes, zenoh={"ros_distro": "humble"}), spawn)
    port = int(app.at.rsplit(":", 1)[1])
    try:
        session = _sdk_session(port)
        info = wait_for(
            lambda: (
                (i := sdk.get_topic_info("/h2/joint_states", router_port=port, verbose=True))
                and i.publishers
                and i
            ),
            timeout=30,
        )
        assert [p.type_hash for p in info.publishers] == ["TypeHashNotSupported"]  # type: ignore[union-attr]
        raw: list[bytes] = []
        z = session.session.declare_subscriber(
            "0/h2/joint_states/sensor_msgs::msg::dds_::JointState_/TypeHashNotSupported",
            lambda s: raw.append(s.attachment.to_bytes()),
        )
        wait_for(lambda: raw, timeout=10)
        z.undeclare()
        assert len(raw[0]) == 41 and raw[0][16] == 24 and raw[0][33:] == bytes(8)
        client = sdk.ROS2ServiceClient(
            "/h2/estop", "std_srvs/srv/Trigger", request_definition="# empty\n",
            response_definition=TRIGGER_RESPONSE, router_port=port, timeout=10,
            type_hash="TypeHashNotSupported",
        )  # fmt: skip
        r = client.call()
        client.close()
        assert r is not None and r.success and r.message.startswith("tripped"), r
    finally:
        app.proc.stop()
        s = sdk.ZenohSession._instance
        if s is not None:
            s.close()
            sdk.ZenohSession._instance = None
