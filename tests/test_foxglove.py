"""The Foxglove bridge node, checked with a plain WebSocket client speaking the public Foxglove
WebSocket protocol (foxglove.websocket.v1): advertise, subscribe, binary message data, decoded
with the schema the server advertised (rosbags parses the ros2msg text)."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Any

import yaml
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from websockets.sync.client import connect

from benchmarks.harness import Appliance, free_port, wait_for
from exolink import messaging
from exolink.config import bundled

# The SDK server speaks the protocol under its current name; older clients ask for
# foxglove.websocket.v1 (same messages).
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01
JOINT_STATE = "sensor_msgs/msg/JointState"


def test_foxglove_client_receives_joint_states_at_the_stream_rate(
    tmp_path: Path, write_config, spawn
) -> None:  # type: ignore[no-untyped-def]
    port = free_port()
    nodes = yaml.safe_load(bundled("sim").read_text())["nodes"]
    nodes = [n for n in nodes if n["name"] in ("simulator", "h2_reader", "controller_manager")]
    nodes.append({"name": "foxglove_bridge", "plugin": "foxglove_bridge",
                  "params": {"host": "127.0.0.1", "port": port}})  # fmt: skip
    app = Appliance(write_config(nodes=nodes), spawn)

    ws = wait_for(lambda: _connect(port), timeout=30)
    # Seen from outside as Zenoh's matching status of a publisher on joint_states's key (nothing
    # else in this appliance subscribes to it): the bridge takes data only for subscribed channels.
    zs = app_session(app)
    probe = zs.declare_publisher(messaging.topic_key(0, "h2", "joint_states", JOINT_STATE))
    try:
        channels: dict[int, dict[str, Any]] = {}

        def advertised() -> dict[str, Any] | None:
            msg = ws.recv(timeout=5)  # type: ignore[union-attr]
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["op"] == "advertise":
                    channels.update({c["id"]: c for c in m["channels"]})
            return next((c for c in channels.values() if c["topic"] == "/h2/joint_states"), None)

        js = wait_for(advertised, timeout=30)
        assert js["encoding"] == "cdr" and js["schemaEncoding"] == "ros2msg"  # type: ignore[index]
        assert js["schemaName"] == "sensor_msgs/msg/JointState"  # type: ignore[index]
        assert not probe.matching_status.matching  # advertised from the graph, not the data
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(js["schema"], js["schemaName"]))  # type: ignore[index]
        ws.send(json.dumps({"op": "subscribe",  # type: ignore[union-attr]
                            "subscriptions": [{"id": 7, "channelId": js["id"]}]}))  # type: ignore[index]  # fmt: skip

        wait_for(lambda: probe.matching_status.matching, timeout=10)
        # The same stream straight from Zenoh over the same window, for the ratio.
        direct: list[int] = []
        sub = zs.declare_subscriber("0/h2/joint_states/*/*", lambda s: direct.append(1))
        got: list[tuple[int, Any]] = []
        end = time.monotonic() + 5.0
        while time.monotonic() < end:
            msg = ws.recv(timeout=5)  # type: ignore[union-attr]
            if isinstance(msg, bytes) and msg[0] == MESSAGE_DATA:
                sid, stamp = struct.unpack_from("<IQ", msg, 1)
                assert sid == 7
                got.append((stamp, msg[13:]))
        sub.undeclare()
        ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [7]}))  # type: ignore[union-attr]
        wait_for(lambda: not probe.matching_status.matching, timeout=10)
        decoded = store.deserialize_cdr(got[-1][1], "sensor_msgs/msg/JointState")
        assert list(decoded.name) == ["r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"]
        stamps = [s for s, _ in got]
        rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)
        print(f"foxglove joint_states: {len(got)} messages, {rate:.1f} Hz by their stamps; "
              f"{len(direct)} straight from Zenoh")  # fmt: skip
        # ~100 Hz: the bridge forwards the stream it gets (no rate threshold: a loaded host
        # slows the simulator, not the bridge's share of it).
        assert len(got) >= 0.9 * len(direct) - 10 and len(got) > 50
    finally:
        ws.close()  # type: ignore[union-attr]
        zs.close()
        app.proc.stop()


def _connect(port: int) -> Any:
    try:
        return connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=2)  # type: ignore[list-item]
    except OSError:
        return None


def app_session(app: Appliance) -> Any:
    from exolink import messaging

    return messaging.open_client_session(app.at)
