"""Foxglove live bridge: the appliance's live topics over the Foxglove WebSocket protocol.

Foxglove (or Lichtblick) connects to ``ws://<board>:8765`` and plots joint angles live, with no
ROS 2 on the laptop. Every topic published under the appliance's namespace becomes a channel named
after its ROS 2 topic (``/h2/joint_states``) with its ``ros2msg`` schema (the definition text
rosbags generates, as the recorder writes into MCAP files) and the CDR payload exactly as it
travelled, stamped with the publisher's source timestamp from the attachment. Replays under
``<domain>/replay`` are not live and are left out.

Channels come from the ROS 2 graph (the publishers' liveliness tokens, ``exolink.wire.rosgraph``), not
from data: the bridge subscribes to a topic's data only while a Foxglove client subscribes to its
channel. Without a client it receives nothing (an idle bridge subscribed to everything costs CPU
for nobody: docs/performance.md).

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

from exolink import messaging
from exolink.loops import Every
from exolink.node import Node
from exolink.wire import rosgraph


class BridgeParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    host: str = "0.0.0.0"
    port: int = 8765
    # Topics (relative to the namespace, e.g. "joint_states") to serve; empty: every live one.
    topics: list[str] = msgspec.field(default_factory=list)


class FoxgloveBridge(Node, foxglove.websocket.ServerListener):
    Params = BridgeParams

    def configure(self) -> None:
        p, m = self.params, self.ctx.messaging
        messaging.typestore()  # rosbags loads now, at start, not on the first client
        self.context = foxglove.Context()
        self._lock = threading.Lock()
        self.channels: dict[tuple[str, str], Any] = {}  # (topic, type) -> channel
        self.keys: dict[int, str] = {}  # channel id -> the data key it carries
        self.subs: dict[int, tuple[Any, set[int]]] = {}  # channel id -> (subscriber, clients)
        self.forwarded = 0
        ns = m.namespace.strip("/")
        self.prefix = f"/{ns}/" if ns else "/"  # live topics only (replays have their own)
        self.wanted = {self.prefix + t.strip("/") for t in p.topics}
        self.server = self.own(
            foxglove.start_server(
                name=f"exolink {self.ctx.config.device}",
                host=p.host,
                port=p.port,
                context=self.context,
                server_listener=self,
            )
        )
        self.own(
            self.ctx.session.liveliness().declare_subscriber(
                f"{rosgraph.ADMIN_SPACE}/{m.domain_id}/**", self._on_token, history=True
            )
        )
        self.log.info("foxglove_bridge_listening", url=f"ws://{p.host}:{self.server.port}")

    # --- channels from the graph ----------------------------------------------------------

    def _on_token(self, sample: zenoh.Sample) -> None:
        """A publisher's token: its topic becomes a channel (kept when the publisher goes, so a
        restarted node's topic keeps its channel and its clients)."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            e = rosgraph.parse_token(str(sample.key_expr))
        except ValueError:
            return
        if e.kind != rosgraph.PUBLISHER or not e.topic.startswith(self.prefix):
            return
        if self.wanted and e.topic not in self.wanted:
            return
        with self._lock:
            if (e.topic, e.typename) in self.channels:
                return
            try:
                text, _ = messaging.typestore().generate_msgdef(e.typename, ros_version=2)
            except (KeyError, ValueError):  # a type nobody defined here: not bridged
                self.log.warning("foxglove_unknown_type", topic=e.topic, type=e.typename)
                return
            distro = "humble" if e.type_hash == rosgraph.HUMBLE_TYPE_HASH else "jazzy"
            ch = foxglove.Channel(
                e.topic,
                message_encoding="cdr",
                schema=foxglove.Schema(name=e.typename, encoding="ros2msg", data=text.encode()),
                context=self.context,
            )
            self.channels[(e.topic, e.typename)] = ch
            self.keys[ch.id()] = messaging.topic_key(
                e.domain_id, "", e.topic, e.typename, distro=distro
            )

    # --- data while a client subscribes (foxglove's ServerListener) --------------------------

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            key = self.keys.get(channel.id)
            if key is None:
                return
            if channel.id not in self.subs:
                ch = next(c for c in self.channels.values() if c.id() == channel.id)
                sub = self.ctx.session.declare_subscriber(key, self._forwarder(ch))
                self.subs[channel.id] = (sub, set())
            self.subs[channel.id][1].add(client.id)
        self.log.info("foxglove_subscribed", topic=channel.topic, client=client.id)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        """Also called for every channel of a client that disconnects."""
        with self._lock:
            entry = self.subs.get(channel.id)
            if entry is None:
                return
            entry[1].discard(client.id)
            if not entry[1]:
                del self.subs[channel.id]
                entry[0].undeclare()

    def _forwarder(self, ch: Any) -> Any:
        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            stamp = None
            if att is not None:
                try:
                    stamp = rosgraph.decode_attachment(att.to_bytes())[1]
                except ValueError:
                    stamp = None
            ch.log(sample.payload.to_bytes(), log_time=stamp)
            self.forwarded += 1

        return on_sample

    def loop(self) -> Every:
        return Every(0.1)  # its work is the server's thread and the subscriptions' callbacks

    def shutdown(self) -> None:
        with self._lock:  # declared per client subscription, not owned
            for sub, _clients in self.subs.values():
                sub.undeclare()
            self.subs = {}
