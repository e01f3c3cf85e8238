"""Foxglove live bridge: the appliance's live topics over the Foxglove WebSocket protocol.

Foxglove (or Lichtblick) connects to ``ws://<board>:8765`` and plots joint angles live, with no
ROS 2 on the laptop. Every data key under the appliance's namespace becomes a channel named
after its ROS 2 topic (``/h2/joint_states``) with its ``ros2msg`` schema (the definition text
rosbags generates, as the recorder writes into MCAP files) and the CDR payload exactly as it
travelled, stamped with the publisher's source timestamp from the attachment. Replays under
``<domain>/replay`` are not live and are left out.

The server is the maintained Foxglove SDK (``foxglove-sdk``: Rust underneath, armv7 wheels):
this node only forwards bytes, so its cost is one Zenoh callback and one ``Channel.log`` per
message. Off by default (board.yaml): it opens a port that anyone on the network can read.
"""

from __future__ import annotations

import threading
from typing import Any

import foxglove
import msgspec
import zenoh
from exolink import messaging, rosgraph
from exolink.node import Node


class BridgeParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    host: str = "0.0.0.0"
    port: int = 8765
    # Topics (relative to the namespace, e.g. "joint_states") to serve; empty: every live one.
    topics: list[str] = msgspec.field(default_factory=list)


class FoxgloveBridge(Node):
    Params = BridgeParams

    def configure(self) -> None:
        p, m = self.params, self.ctx.messaging
        messaging.typestore()  # rosbags loads now, at start, not on the first message
        self.context = foxglove.Context()
        self.server = foxglove.start_server(
            name=f"exolink {self.ctx.config.device}",
            host=p.host,
            port=p.port,
            context=self.context,
        )
        self.channels: dict[str, Any] = {}
        self.forwarded = 0
        self._lock = threading.Lock()
        wanted = p.topics or ["**"]
        self.subs = [
            self.ctx.session.declare_subscriber(
                messaging.topic_selector(m.domain_id, m.namespace, t)
                if t != "**"
                else f"{m.domain_id}/{m.namespace}/**",
                self._on_sample,
            )
            for t in wanted
        ]
        self.log.info("foxglove_bridge_listening", url=f"ws://{p.host}:{self.server.port}")

    def _channel(self, key: str) -> Any:
        """The channel of a data key, made on its first message (one rosbags call per type)."""
        ch = self.channels.get(key)
        if ch is not None:
            return ch
        with self._lock:
            if key in self.channels:
                return self.channels[key]
            topic, typename = messaging.parse_key(key)
            text, _ = messaging.typestore().generate_msgdef(typename, ros_version=2)
            ch = foxglove.Channel(
                "/" + topic,
                message_encoding="cdr",
                schema=foxglove.Schema(name=typename, encoding="ros2msg", data=text.encode()),
                context=self.context,
            )
            self.channels[key] = ch
            return ch

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            ch = self._channel(key)
        except (ValueError, KeyError):  # not a ROS 2 data key, or a type nobody defined
            return
        att = sample.attachment
        stamp = None
        if att is not None:
            try:
                stamp = rosgraph.decode_attachment(att.to_bytes())[1]
            except ValueError:
                stamp = None
        ch.log(sample.payload.to_bytes(), log_time=stamp)
        self.forwarded += 1

    def run(self, stop: threading.Event) -> None:
        while not stop.wait(0.1):
            self.beat()

    def shutdown(self) -> None:
        for s in getattr(self, "subs", []):
            s.undeclare()
        if hasattr(self, "server"):
            self.server.stop()
