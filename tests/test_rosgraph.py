"""The ROS graph tokens, GIDs, QoS strings and attachments as rmw_zenoh writes them
(rmw_zenoh_cpp/src/detail/liveliness_utils.cpp, qos.cpp, attachment_helpers.cpp)."""

from __future__ import annotations

import struct

import pytest
import xxhash
import zenoh

from benchmarks.harness import free_port, wait_for
from exolink import messaging
from exolink.config import ApplianceConfig, ZenohConfig
from exolink.wire import rosgraph


def test_qos_strings_leave_out_rmw_zenohs_defaults() -> None:
    # rclcpp's default profile (reliable, volatile, keep last 10): only the depth differs.
    assert rosgraph.Qos().keyexpr() == "::,10:,:,:,,"
    assert rosgraph.Qos(depth=42).keyexpr() == "::,:,:,:,,"  # all default: all empty
    best_effort = rosgraph.Qos(reliability=rosgraph.BEST_EFFORT, depth=5)
    assert best_effort.keyexpr() == "2::,5:,:,:,,"
    latched = rosgraph.Qos(durability=rosgraph.TRANSIENT_LOCAL, depth=1)
    assert latched.keyexpr() == ":1:,1:,:,:,,"
    for q in (rosgraph.Qos(), best_effort, latched, rosgraph.Qos(history=rosgraph.KEEP_ALL)):
        assert rosgraph.parse_qos(q.keyexpr()) == q
    # Humble-era tools write every value out; the reader takes that too.
    assert rosgraph.parse_qos("1:2:1,10:,:,:,,") == rosgraph.Qos()


def test_names_are_mangled_and_the_gid_is_xxh3_of_the_token() -> None:
    assert rosgraph.mangle("/h2/joint_states") == "%h2%joint_states"
    assert rosgraph.fq_name("h2", "nodes/x/heartbeat") == "/h2/nodes/x/heartbeat"
    assert rosgraph.fq_name("", "") == "/"
    key = "@ros2_lv/0/abc/0/1/MP/%/%h2/n/%h2%t/std_msgs::msg::dds_::String_/RIHS01_x/::,10:,:,:,,"
    h = xxhash.xxh3_128(key.encode()).digest()  # canonical big-endian: high64 then low64
    high, low = struct.unpack(">QQ", h)
    assert rosgraph.gid_of(key) == struct.pack("<QQ", low, high)
    assert rosgraph.gid_of(key, "humble") == struct.pack("<QQ", low, high) + bytes(8)
    e = rosgraph.parse_token(key)
    assert (e.kind, e.namespace, e.node, e.topic, e.typename) == (
        "MP",
        "/h2",
        "n",
        "/h2/t",
        "std_msgs/msg/String",
    )
    with pytest.raises(ValueError):
        rosgraph.parse_token("@ros2_lv/0/abc/0/1/MP/%/%h2/n")


def test_attachments_of_every_supported_distro() -> None:
    gid = bytes(range(16))
    jazzy = rosgraph.encode_attachment(7, 123, gid)
    assert len(jazzy) == 33 and jazzy[16] == 16
    assert rosgraph.decode_attachment(jazzy) == (7, 123, gid)
    humble = rosgraph.encode_attachment(7, 123, gid + bytes(8))
    assert len(humble) == 41 and rosgraph.decode_attachment(humble)[2] == gid + bytes(8)
    for bad in (jazzy[:-1], jazzy + b"\0", b"\0" * 10):
        with pytest.raises(ValueError):
            rosgraph.decode_attachment(bad)


def _router() -> tuple[zenoh.Session, str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = messaging.session_config(ZenohConfig(listen=[endpoint]), listen=[endpoint], mode="router")
    return zenoh.open(cfg), endpoint


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_a_nodes_tokens_and_publisher_gid_and_their_end(distro: str) -> None:
    hub, endpoint = _router()
    cfg = ApplianceConfig(device="t", zenoh=ZenohConfig(listen=[endpoint], ros_distro=distro))  # type: ignore[arg-type]
    node_session = messaging.open_node_session(cfg)
    seen: list[zenoh.Sample] = []
    msg = messaging.Messaging(node_session, cfg, ros_node="h2_reader")
    try:
        pub = msg.publisher("joint_states", "sensor_msgs/msg/JointState", raw=True)
        sub = hub.declare_subscriber("0/h2/joint_states/**", seen.append)

        def tokens() -> list[rosgraph.Entity]:
            got = hub.liveliness().get("@ros2_lv/0/**", timeout=1)
            return [rosgraph.parse_token(str(r.ok.key_expr)) for r in got if r.ok is not None]

        ents = wait_for(lambda: (t := tokens()) and len(t) == 2 and t)
        node = next(e for e in ents if e.kind == "NN")  # type: ignore[union-attr]
        mp = next(e for e in ents if e.kind == "MP")  # type: ignore[union-attr]
        assert node.zid == str(node_session.zid()) and node.nid == node.eid
        assert (node.namespace, node.node, node.enclave) == ("/h2", "h2_reader", "/")
        assert mp.nid == node.nid and mp.topic == "/h2/joint_states"
        assert mp.typename == "sensor_msgs/msg/JointState"
        want_hash = "TypeHashNotSupported" if distro == "humble" else "RIHS01_"
        assert mp.type_hash.startswith(want_hash) and pub.key.endswith(mp.type_hash)
        wait_for(lambda: (pub.put(b"\0\1\0\0"), seen)[1], timeout=10)
        _, _, gid = rosgraph.decode_attachment(seen[0].attachment.to_bytes())
        assert gid == rosgraph.gid_of(mp.key, distro)
        pub.close()
        wait_for(lambda: [e.kind for e in tokens()] == ["NN"])
        msg.close()
        wait_for(lambda: tokens() == [])
        sub.undeclare()
    finally:
        msg.close()
        node_session.close()
        hub.close()
