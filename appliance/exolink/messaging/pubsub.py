"""Typed publish/subscribe: attachments as rmw_zenoh writes them, publishers, the outbox,
a laptop's message subscriptions and each process's ``Messaging``."""

from __future__ import annotations

import os
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import zenoh

from exolink import roles
from exolink.config import ZenohConfig
from exolink.messaging.bundles import bundle_key, bundled_data_key, decode_bundle, encode_bundle
from exolink.messaging.keys import mgmt_key, topic_key
from exolink.messaging.rpc import (
    COMMANDS_TOPIC,
    COMMANDS_TYPE,
    Admission,
    CommandLog,
    Handler,
    Needs,
    Served,
    Urgent,
    request,
    serve,
)
from exolink.messaging.sessions import Unreachable
from exolink.messaging.types import prepare
from exolink.refusal import Refused
from exolink.wire import rosgraph

ATTACHMENT = struct.Struct("<qqB16s")  # Jazzy and later; rosgraph reads Humble's too


OnMessage = Callable[[str, int, int, bytes], None]  # data key, sequence number, source ns, CDR


class MessageSubscription:
    """A laptop's subscription to a topic's messages, each handed to ``on_message`` with its
    data key, sequence number, source time and CDR bytes.

    A bundled topic (one with a bundle token: joint_states and the MACCEPA states when the
    board reads in batches) is taken as its bundles, one sample per batch: the publisher then
    puts its messages one by one only for subscribers of the topic's own key (a ROS 2 tool,
    Foxglove): each such sample costs the one core in the publisher and in the router, 100
    a second for joint_states (docs/performance.md). The messages are the
    same (CDR, sequence numbers, stamps); they arrive in bursts, one per batch (up to 90 ms
    later at the board's cadence, as the one-by-one samples of that batch already do).
    Whether a topic is bundled is asked once, at subscription: a publisher that appears later
    is taken as it then is only by a new subscription. ``bundles=False``: one by one always.
    """

    def __init__(
        self,
        session: zenoh.Session,
        device: str,
        selector: str,
        on_message: OnMessage,
        bundles: bool = True,
        ask_s: float = 3.0,
    ) -> None:
        self._on, self._device = on_message, device
        self.malformed = 0  # bundles or attachments that did not decode (anything may arrive)
        where = bundle_key(device, selector)
        self.bundled = bundles and any(
            r.ok is not None for r in session.liveliness().get(where, timeout=ask_s)
        )
        if self.bundled:
            self._sub = session.declare_subscriber(where, self._bundle)
        else:
            self._sub = session.declare_subscriber(selector, self._single)

    def _single(self, sample: zenoh.Sample) -> None:
        try:
            seq, ns, _gid = source_of(sample)
        except ValueError:
            self.malformed += 1  # as a bundle that does not decode
            return
        self._on(str(sample.key_expr), seq, ns, sample.payload.to_bytes())

    def _bundle(self, sample: zenoh.Sample) -> None:
        try:
            key = bundled_data_key(self._device, str(sample.key_expr))
            _gid, items = decode_bundle(sample.payload.to_bytes())
        except ValueError:
            self.malformed += 1
            return
        for seq, ns, payload in items:
            self._on(key, seq, ns, payload)

    def close(self) -> None:
        self._sub.undeclare()


# --- typed pub/sub ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Meta:
    key: str
    seq: int
    source_ns: int
    gid: bytes


def encode_attachment(seq: int, source_ns: int, gid: bytes) -> bytes:
    return rosgraph.encode_attachment(seq, source_ns, gid)


def source_of(sample: zenoh.Sample) -> tuple[int, int, bytes]:
    """(sequence number, source ns, GID) from a sample's attachment; zeros without one,
    ValueError for one that does not decode (it came over the network)."""
    att = sample.attachment
    return (0, 0, b"") if att is None else decode_attachment(att.to_bytes())


def decode_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """Any supported distro's attachment (16-byte GID, or Humble's 24); ValueError else."""
    return rosgraph.decode_attachment(raw)


class Publisher:
    """A typed publisher: node code hands it message objects (or, from an ``exolink.wire.cdr``
    template, their CDR bytes), never keys or attachments."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        typename: str,
        raw: bool = False,
        token: rosgraph.Token | None = None,
        graph: rosgraph.RosNode | None = None,
        bundle: tuple[Any, Any] | None = None,
    ) -> None:
        self.key, self.typename = key, typename
        # (publisher, liveliness token) of its bundle key (Messaging.publisher, bundled=True)
        self._bundle: Any
        self._bundle_token: Any
        self._bundle, self._bundle_token = bundle or (None, None)
        self._pub = session.declare_publisher(key)
        # With a graph token (an appliance node's publisher) the GID is the token's, as
        # rmw_zenoh derives it; a publisher outside the ROS graph (a tool) keeps a random one.
        self._token, self._graph = token, graph
        self._gid = token.gid if token is not None else os.urandom(16)
        self._head = struct.Struct(f"<qqB{len(self._gid)}s")
        self._seq = 0
        self.sent = self.bundles = 0
        # A raw publisher never serializes: rosbags (and numpy) stay out of its process.
        self._ser = None if raw else prepare(typename).serialize_cdr
        self._lock = threading.Lock()

    def publish(self, msg: Any, source_ns: int | None = None) -> None:
        if self._ser is None:
            raise TypeError(f"{self.key}: raw publisher, use put() with CDR bytes")
        self.put(bytes(self._ser(msg, self.typename)), source_ns)

    def put(self, payload: bytes, source_ns: int | None = None) -> None:
        """CDR bytes (with their encapsulation header) of one message of this type."""
        with self._lock:
            self._seq += 1
            att = self._head.pack(self._seq, source_ns or time.time_ns(), len(self._gid), self._gid)
            self._pub.put(payload, attachment=att)
            self.sent += 1

    def put_many(self, items: list[tuple[bytes, int]]) -> None:
        """Several messages (CDR, source ns) at once, numbered in order. A bundled publisher
        puts them one by one only while a subscriber of the topic's own key (a laptop, a ROS 2
        tool) exists, and always as one bundle for the appliance's recorder."""
        if self._bundle is None:
            for payload, ns in items:
                self.put(payload, ns)
            return
        with self._lock:
            first = self._seq + 1
            self._seq += len(items)
            # one Rust call per batch, not per sample (zenoh 1.10's stub says bool: it is a
            # MatchingStatus)
            if self._pub.matching_status.matching:  # type: ignore[attr-defined]
                head, gid = self._head, self._gid
                for i, (payload, ns) in enumerate(items):
                    self._pub.put(payload, attachment=head.pack(first + i, ns, len(gid), gid))
                self.sent += len(items)
            body = [(first + i, ns, payload) for i, (payload, ns) in enumerate(items)]
            self._bundle.put(encode_bundle(self._gid, body))
            self.bundles += 1

    def counters(self) -> dict[str, int]:
        """Messages numbered, put one by one, and bundles put (a bundled publisher)."""
        return {"messages": self._seq, "sent": self.sent, "bundles": self.bundles}

    @property
    def gid(self) -> bytes:
        return self._gid

    def close(self) -> None:
        if self._bundle is not None:
            self._bundle.undeclare()
        if self._bundle_token is not None:
            self._bundle_token.undeclare()
        self._pub.undeclare()
        if self._token is not None and self._graph is not None:
            self._graph.release(self._token)


class Outbox:
    """The samples one read of the bus produced, put back to back once the read is handled.

    Zenoh joins samples queued together into one network message, and a router or subscriber
    then handles them for a fraction of the cost of each alone; but it does not wait for more:
    puts spread over a read's decoding cost the router and subscriber several times more CPU per
    sample than the same puts in a row (measured: docs/performance.md)."""

    def __init__(self) -> None:
        self._items: list[tuple[Publisher, bytes, int]] = []

    def add(self, pub: Publisher, payload: bytes, source_ns: int) -> None:
        self._items.append((pub, payload, source_ns))

    def flush(self) -> None:
        """Each publisher's messages in order (a bundled one's as one bundle)."""
        items, self._items = self._items, []
        batches: dict[Publisher, list[tuple[bytes, int]]] = {}
        for pub, payload, ns in items:
            batches.setdefault(pub, []).append((payload, ns))
        for pub, batch in batches.items():
            pub.put_many(batch)


class Scope(Protocol):
    """What Messaging reads of a config: an appliance's, or a laptop's options (cli)."""

    @property
    def device(self) -> str: ...
    @property
    def zenoh(self) -> ZenohConfig: ...


class Messaging:
    """Binds a session to the appliance's domain and namespace.

    With ``ros_node`` (every appliance process names one) the session is also that ROS 2 node
    in the graph rmw_zenoh laptops read: each publisher and subscription declared here gets its
    graph token and its GID from it (exolink.wire.rosgraph); ``close`` takes the node out.
    """

    def __init__(self, session: zenoh.Session, cfg: Scope, ros_node: str | None = None) -> None:
        self.session = session
        self.domain_id = cfg.zenoh.domain_id
        self.namespace = cfg.zenoh.namespace
        self.device = cfg.device
        self.distro = cfg.zenoh.ros_distro
        self._commands: CommandLog | None = None
        self.admission = Admission()  # what this process' queryables did with requests
        self.graph = (
            rosgraph.RosNode(session, self.domain_id, self.namespace, ros_node, self.distro)
            if ros_node
            else None
        )

    def close(self) -> None:
        """Leave the ROS graph (every token of this node); the session stays the caller's."""
        if self.graph is not None:
            self.graph.close()

    def key(self, topic: str, typename: str) -> str:
        return topic_key(self.domain_id, self.namespace, topic, typename, self.distro)

    def _token(
        self, kind: str, topic: str, typename: str, qos: rosgraph.Qos | None
    ) -> rosgraph.Token | None:
        if self.graph is None or "*" in topic:  # a wildcard subscription is no ROS entity
            return None
        key = self.key(topic, typename)
        return self.graph.declare(
            kind,
            rosgraph.fq_name(self.namespace, topic),
            typename,
            key.rsplit("/", 1)[-1],
            qos or rosgraph.DEFAULT_QOS,
        )

    def publisher(
        self,
        topic: str,
        typename: str,
        raw: bool = False,
        qos: rosgraph.Qos | None = None,
        bundled: bool = False,
    ) -> Publisher:
        """``bundled``: a high-rate topic whose batches (``Outbox``) also go out as one bundle
        sample each for the recorder (see ``bundle_key``)."""
        key = self.key(topic, typename)
        bundle = None
        if bundled:  # its token before the graph's: a recorder learns it is bundled first
            where = bundle_key(self.device, key)
            bundle = (
                self.session.declare_publisher(where),
                self.session.liveliness().declare_token(where),
            )
        token = self._token(rosgraph.PUBLISHER, topic, typename, qos)
        return Publisher(self.session, key, typename, raw, token, self.graph, bundle)

    def subscribe(
        self, topic: str, typename: str, callback: Callable[[Any, Meta], None]
    ) -> zenoh.Subscriber:
        self._token(rosgraph.SUBSCRIPTION, topic, typename, None)
        # The typestore at the first sample, not now: a subscription nobody publishes to (the
        # supervisor's ROS 2 joint_command topic) then never loads rosbags and numpy.
        store: list[Any] = []

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            seq, ts, gid = decode_attachment(att.to_bytes()) if att else (0, 0, b"")
            if not store:
                store.append(prepare(typename).deserialize_cdr)
            msg = store[0](sample.payload.to_bytes(), typename)
            callback(msg, Meta(str(sample.key_expr), seq, ts, gid))

        return self.session.declare_subscriber(self.key(topic, typename), on_sample)

    def subscribe_raw(
        self, topic: str, typename: str, callback: Callable[..., None], timed: bool = False
    ) -> zenoh.Subscriber:
        """CDR bytes to a decoder of the caller's (exolink.wire.cdr): no typestore in the process.
        ``timed``: also the time the publisher put it (ns since the epoch, from the sample's
        attachment; 0 without a readable one)."""
        self._token(rosgraph.SUBSCRIPTION, topic, typename, None)
        if not timed:
            return self.session.declare_subscriber(
                self.key(topic, typename), lambda sample: callback(sample.payload.to_bytes())
            )

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                sent = source_of(sample)[1]
            except ValueError:
                sent = 0  # the payload is still the caller's to judge; only its time is lost
            callback(sample.payload.to_bytes(), sent)

        return self.session.declare_subscriber(self.key(topic, typename), on_sample)

    def mgmt(self, *path: str) -> str:
        return mgmt_key(self.device, *path)

    def _command_log(self) -> CommandLog:
        return CommandLog(self.publisher(COMMANDS_TOPIC, COMMANDS_TYPE, raw=True))

    def log_command(
        self, user: str, key: str, request: dict[str, Any], reply: dict[str, Any]
    ) -> None:
        """A command that came another way than ``serve`` (a ROS 2 service or topic)."""
        if self._commands is None:
            self._commands = self._command_log()
        self._commands.write(user, key, request, reply)

    def serve(
        self,
        path: str | tuple[str, ...],
        handler: Handler,
        needs: Needs = roles.OBSERVER,
        urgent: Urgent | None = None,
    ) -> Served:
        """This appliance's management queryable at ``exolink/<device>/<path>`` (see serve);
        this process' queryables share one rate limit per login (``admission``)."""
        if self._commands is None:
            self._commands = self._command_log()
        parts = (path,) if isinstance(path, str) else path
        key = self.mgmt(*parts)
        return serve(self.session, key, handler, needs, self._commands, self.admission, urgent)

    def request(
        self, *path: str, body: dict[str, Any] | None = None, timeout_s: float = 0.5
    ) -> dict[str, Any]:
        """A query from inside the appliance, as its own login."""
        return request(self.session, self.mgmt(*path), body, timeout_s, roles.APPLIANCE_USER)

    def command(
        self,
        *path: str,
        body: dict[str, Any],
        timeout_s: float,
        tolerate: tuple[str, ...] = (),
    ) -> dict[str, Any]:
        """One node asking another to act: the answer, or Refused with the other's
        refusal verbatim (or that nothing answered), so the caller's own caller sees why.
        A refusal containing one of ``tolerate`` counts as done (e.g. "is not active")."""
        try:
            reply = self.request(*path, body=body, timeout_s=timeout_s)
        except Unreachable as exc:
            raise Refused(f"nothing answers at {'/'.join(path)}: {exc}") from None
        error = str(reply.get("error", f"refused by {'/'.join(path)}"))
        if not reply.get("ok") and not any(t in error for t in tolerate):
            raise Refused(error)
        return reply
