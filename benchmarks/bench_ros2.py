"""What the ROS 2 face costs: graph tokens at node start, a ROS 2 service round trip, and the
Foxglove bridge's CPU while it forwards the 100 Hz joint_states to one subscribed client."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import threading
import time
from typing import Any

from benchmarks.harness import Appliance, cpu_s, free_port, pct
from exolink import messaging
from exolink.wire import rosgraph

COLD_TOKENS = """
import json, sys, time
import dataclasses, itertools, struct, threading  # what any node imports anyway
import structlog, zenoh
from exolink import config
t = time.perf_counter()
from exolink.wire import rosgraph  # what the graph adds: xxhash and the module
imported = (time.perf_counter() - t) * 1e3
from exolink import messaging
from exolink.config import ApplianceConfig, ZenohConfig
at = sys.argv[1]
cfg = ApplianceConfig(device="b", zenoh=ZenohConfig(listen=[at]))
s = messaging.open_node_session(cfg)
t = time.perf_counter()
m = messaging.Messaging(s, cfg, ros_node="bench_node")
node_ms = (time.perf_counter() - t) * 1e3
n = int(sys.argv[2])
import statistics
def each(make):  # per call, median: a loaded host's stalls land in a few calls, not all
    out, made = [], []
    for i in range(n):
        t = time.perf_counter()
        made.append(make(i))
        out.append(time.perf_counter() - t)
    return made, statistics.median(out) * 1e6
pubs, with_tokens = each(lambda i: m.publisher(f"t{i}", "sensor_msgs/msg/JointState", raw=True))
plain, without = each(lambda i: messaging.Publisher(
    s, m.key(f"u{i}", "sensor_msgs/msg/JointState"), "sensor_msgs/msg/JointState", raw=True))
tokens, token_only = each(lambda i: m.graph.declare(
    rosgraph.PUBLISHER, f"/h2/v{i}", "sensor_msgs/msg/JointState", "RIHS01_x"))
for p in pubs + plain:
    p.close()
m.close()
s.close()
print(json.dumps({"import_rosgraph_ms": imported, "node_token_ms": node_ms,
                  "publisher_with_token_us_p50": with_tokens,
                  "publisher_without_us_p50": without, "token_alone_us_p50": token_only}))
"""


def token_cost(quick: bool) -> dict[str, Any]:
    """A fresh interpreter (cold imports) declaring a node and publishers with and without
    their graph tokens, against a router of its own."""
    import zenoh

    from exolink.config import ZenohConfig

    at = f"tcp/127.0.0.1:{free_port()}"
    hub = zenoh.open(messaging.session_config(ZenohConfig(listen=[at]), listen=[at], mode="router"))
    try:
        n = 50 if quick else 300
        r = subprocess.run(
            [sys.executable, "-c", COLD_TOKENS, at, str(n)], capture_output=True, text=True
        )
        r.check_returncode()
        out = {k: round(v, 2) for k, v in json.loads(r.stdout).items()}
        out["publishers"] = n
        return out
    finally:
        hub.close()


def service_round_trip(app: Appliance, n: int) -> dict[str, Any]:
    """A ROS 2 client's call of /h2/estop, as rmw_zenoh sends it (query with CDR request and
    attachment), to the reply: through the router, the supervisor's worker thread, the
    watchdog handler."""
    key = messaging.topic_key(0, "h2", "estop", "std_srvs/srv/Trigger")
    gid = bytes(16)
    lat = []
    for i in range(n):
        att = rosgraph.encode_attachment(i + 1, time.time_ns(), gid)
        t = time.perf_counter()
        replies = list(app.session.get(key, payload=b"\0\1\0\0\0", attachment=att, timeout=3))
        lat.append(time.perf_counter() - t)
        assert replies and replies[0].ok is not None
    return pct(lat, 1e3)


def bridge_cpu(quick: bool) -> dict[str, Any]:
    from websockets.sync.client import connect

    port = free_port()
    nodes = [
        {"name": "simulator", "plugin": "simulator"},
        {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
        {
            "name": "foxglove_bridge",
            "plugin": "foxglove_bridge",
            "params": {"host": "127.0.0.1", "port": port},
        },
    ]
    app = Appliance.sim(nodes=nodes)
    try:
        pid = app.node("foxglove_bridge")["pid"]
        seconds = 5.0 if quick else 20.0
        c0, t0 = cpu_s(pid), time.monotonic()
        time.sleep(seconds)
        idle = (cpu_s(pid) - c0) / (time.monotonic() - t0)
        ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"])  # type: ignore[list-item]
        js = None
        while js is None:
            m = ws.recv(timeout=10)
            if isinstance(m, str) and json.loads(m)["op"] == "advertise":
                chans = json.loads(m)["channels"]
                js = next((c for c in chans if c["topic"] == "/h2/joint_states"), None)
        ws.send(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": js["id"]}]})
        )
        got: list[int] = []
        stop = threading.Event()

        def read() -> None:
            while not stop.is_set():
                try:
                    m = ws.recv(timeout=1)
                except TimeoutError:
                    continue
                except Exception:
                    return
                if isinstance(m, bytes) and m[0] == 1:
                    got.append(struct.unpack_from("<Q", m, 5)[0])

        t = threading.Thread(target=read, daemon=True)
        t.start()
        time.sleep(1.0)
        n0, c0, t0 = len(got), cpu_s(pid), time.monotonic()
        time.sleep(seconds)
        busy = (cpu_s(pid) - c0) / (time.monotonic() - t0)
        rate = (len(got) - n0) / (time.monotonic() - t0)
        stop.set()
        ws.close()
        t.join(2)
        rtt = service_round_trip(app, 50 if quick else 300)
        return {
            "seconds": seconds,
            "bridge_cpu_pct_no_client": round(idle * 100, 2),
            "bridge_cpu_pct_one_client_joint_states": round(busy * 100, 2),
            "joint_states_to_client_hz": round(rate, 1),
            "ros2_estop_call_ms": rtt,
        }
    finally:
        app.close()


def run(quick: bool) -> dict[str, Any]:
    return {"tokens_at_node_start": token_cost(quick), "bridge": bridge_cpu(quick)}
