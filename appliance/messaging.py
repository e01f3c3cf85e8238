"""Zenoh messaging: the one module that knows key expressions, CDR, attachments and JSON queries.

Data topics are carried the way ROS 2's rmw_zenoh carries them, so a ROS 2 laptop can join later:
key ``<domain>/<namespace>/<topic>/<pkg>::msg::dds_::<Type>_/RIHS01_<hash>``, CDR payload with
its 4-byte encapsulation header, and a 33-byte attachment (int64 sequence number, int64 source
timestamp in ns since the epoch, uint8 16, 16-byte publisher GID). Types, CDR and hashes come
from rosbags' typestore; the project's own types are .msg files under msgs/.
Management uses JSON queries under ``exolink/<device>/...``; every reply says ok or an error.
"""

from __future__ import annotations

import json
import os
import struct
import threading
import time
from collections.abc import Callable, MutableMapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import structlog
import zenoh
from exolink import cdr, roles, rosgraph
from exolink.config import ApplianceConfig, ConfigError, ZenohConfig

MSG_DIR = Path(__file__).with_name("msgs")
# Every type's RIHS01 hash, written by `make msgs` and checked against rosbags by the tests: a
# key needs the hash, and rosbags' typestore costs ~140 ms of imports (seconds on the board).
TYPE_HASHES = MSG_DIR / "type_hashes.json"
ATTACHMENT = struct.Struct("<qqB16s")  # Jazzy and later; rosgraph reads Humble's too
DEFAULT_QUERY_TIMEOUT_S = 2.0
CLIENT_CONNECT_TIMEOUT_MS = 3000


# --- types -----------------------------------------------------------------------------------


@cache
def typestore() -> Any:
    """ROS 2 Jazzy's standard types plus every exolink_msgs .msg file."""
    from exolink import rosservices
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for path in sorted(MSG_DIR.glob("*/msg/*.msg")):
        name = f"{path.parent.parent.name}/msg/{path.stem}"
        types.update(get_types_from_msg(path.read_text(), name))
    for name, (request, response) in rosservices.srv_definitions(MSG_DIR).items():
        types.update(rosservices.service_fielddefs(name, request, response))
    store.register(types)
    return store


def msg_class(typename: str) -> Any:
    return typestore().types[typename]


def prepare(typename: str) -> Any:
    """The type's store, with its CDR code generated now. rosbags generates it on first use
    (88 ms for JointState on x86, seconds under emulation): done here, at declaration in a
    node's configure, the first message a node's loop sends or receives does not stall it."""
    store = typestore()
    store.get_msgdef(typename)
    return store


def dds_name(typename: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (rmw_zenoh)."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@cache
def _hash_table() -> dict[str, str]:
    try:
        table: dict[str, str] = json.loads(TYPE_HASHES.read_text())
    except FileNotFoundError:
        return {}
    return table


@cache
def type_hash(typename: str) -> str:
    """From the table when it has the type (no rosbags import), else computed by rosbags."""
    return _hash_table().get(typename) or str(typestore().hash_rihs01(typename))


def write_hash_table() -> int:
    """``make msgs``: the table for every type in the typestore (after editing a .msg file)."""
    from exolink import rosservices

    store = typestore()
    services = list(rosservices.srv_definitions(MSG_DIR))
    parts = {f"{s}_{p}" for s in services for p in ("Request", "Response", "Event")}
    table = {
        name: str(store.hash_rihs01(name))
        for name in sorted(store.types)
        if name not in parts and name not in services
    }
    table.update(rosservices.service_hashes(store, services))
    table = dict(sorted(table.items()))
    TYPE_HASHES.write_text(json.dumps(table, indent=0, sort_keys=True) + "\n")
    return len(table)


def topic_key(
    domain_id: int, namespace: str, topic: str, typename: str, distro: str = "jazzy"
) -> str:
    """The only place a data key expression is built (Humble's rmw_zenoh has no type hashes)."""
    path = "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)
    th = rosgraph.HUMBLE_TYPE_HASH if distro == "humble" else type_hash(typename)
    return f"{domain_id}/{path}/{dds_name(typename)}/{th}"


def topic_selector(domain_id: int, namespace: str, topic: str = "**") -> str:
    """Selector matching a topic of any type (for subscribers that discover types from keys)."""
    path = "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)
    return f"{domain_id}/{path}/*/*" if topic != "**" else f"{domain_id}/{path}"


def parse_key(key: str) -> tuple[str, str]:
    """A data key -> (topic path incl. namespace, typename); ValueError for other keys."""
    parts = key.split("/")
    hashed = parts[-1].startswith("RIHS01_") or parts[-1] == rosgraph.HUMBLE_TYPE_HASH
    if len(parts) < 4 or not hashed or "::dds_::" not in parts[-2]:
        raise ValueError(f"not a data key: {key}")
    pkg, kind, _, name = parts[-2].split("::")
    return "/".join(parts[1:-2]), f"{pkg}/{kind}/{name.rstrip('_')}"


def mgmt_key(device: str, *path: str) -> str:
    """The only place a management key expression is built."""
    return "/".join(("exolink", device, *path))


def data_key_of(entity: rosgraph.Entity) -> str:
    """The data key a graph publisher or subscription (its token) uses."""
    return f"{entity.domain_id}/{entity.topic.strip('/')}/{entity.type}/{entity.type_hash}"


# --- bundles ---------------------------------------------------------------------------------
# A high-rate topic (joint_states, a MACCEPA board's state: 100 Hz each) reaches the recorder as
# one sample per batch of messages instead of one per message. On the board proxy a Zenoh sample
# costs ~0.4 ms of the one core in the publisher, ~0.5 in the router and ~0.7 in each subscriber
# however small it is (benchmarks/board/units.py), and the recorder took every message of both
# topics through the router. The messages inside are the CDR bytes, sequence numbers and source
# times they have on the topic's own key, which a laptop still gets one by one.

BUNDLE_PATH = "bundle"
BUNDLE_MAGIC = b"EXB1"
_BUNDLE_HEAD = struct.Struct("<4sHB")  # magic, message count, GID length (then the GID)
_BUNDLE_ITEM = struct.Struct("<qqI")  # sequence number, source ns, CDR length (then the CDR)
MAX_BUNDLE = 4096


def bundle_key(device: str, data_key: str) -> str:
    """``exolink/<device>/bundle/<data key>``: outside the data key space on purpose, so a
    subscriber of data (a laptop's ``0/**``) never matches it, and no login but the
    appliance's may publish there (exolink.roles)."""
    return mgmt_key(device, BUNDLE_PATH, data_key)


def bundle_selector(device: str) -> str:
    return mgmt_key(device, BUNDLE_PATH, "**")


def bundled_data_key(device: str, key: str) -> str:
    """A bundle key -> the data key of its topic; ValueError for other keys."""
    prefix = mgmt_key(device, BUNDLE_PATH, "")
    if not key.startswith(prefix) or key == prefix:
        raise ValueError(f"not a bundle key of {device}: {key}")
    return key[len(prefix) :]


def encode_bundle(gid: bytes, items: list[tuple[int, int, bytes]]) -> bytes:
    """(sequence, source ns, CDR) messages of one publisher (its GID) as one payload."""
    if not 0 < len(items) <= MAX_BUNDLE:
        raise ValueError(f"a bundle holds 1 to {MAX_BUNDLE} messages, not {len(items)}")
    parts = [_BUNDLE_HEAD.pack(BUNDLE_MAGIC, len(items), len(gid)), gid]
    for seq, ns, payload in items:
        parts += (_BUNDLE_ITEM.pack(seq, ns, len(payload)), payload)
    return b"".join(parts)


def decode_bundle(raw: bytes) -> tuple[bytes, list[tuple[int, int, bytes]]]:
    """(GID, messages) of a bundle; ValueError naming what is wrong (anything may arrive)."""
    if len(raw) < _BUNDLE_HEAD.size:
        raise ValueError(f"bundle of {len(raw)} bytes is shorter than its header")
    magic, count, n = _BUNDLE_HEAD.unpack_from(raw)
    if magic != BUNDLE_MAGIC:
        raise ValueError(f"bundle magic {magic!r}, expected {BUNDLE_MAGIC!r}")
    if n not in (16, 24):
        raise ValueError(f"bundle GID of {n} bytes (16 or 24)")
    at = _BUNDLE_HEAD.size + n
    gid = bytes(raw[_BUNDLE_HEAD.size : at])
    items = []
    for i in range(count):
        if at + _BUNDLE_ITEM.size > len(raw):
            raise ValueError(f"bundle ends in message {i + 1} of {count}'s header")
        seq, ns, size = _BUNDLE_ITEM.unpack_from(raw, at)
        at += _BUNDLE_ITEM.size
        if at + size > len(raw):
            raise ValueError(f"bundle ends in message {i + 1} of {count} ({size} bytes)")
        items.append((seq, ns, bytes(raw[at : at + size])))
        at += size
    if at != len(raw) or not items:
        raise ValueError(f"bundle of {count} messages has {len(raw) - at} bytes left over")
    return gid, items


def serialize(msg: Any, typename: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, typename))


def deserialize(data: bytes, typename: str) -> Any:
    return typestore().deserialize_cdr(data, typename)


def stamp(ns: int) -> Any:
    """builtin_interfaces/Time from nanoseconds since the epoch."""
    return msg_class("builtin_interfaces/msg/Time")(
        sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
    )


def header(ns: int, frame_id: str = "") -> Any:
    return msg_class("std_msgs/msg/Header")(stamp=stamp(ns), frame_id=frame_id)


DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
LEVELS = {"ok": 0, "warn": 1, "error": 2}


def diagnostics(
    ns: int, name: str, level: str, message: str, hardware_id: str, values: dict[str, Any]
) -> Any:
    """A one-status diagnostic_msgs/DiagnosticArray (what ROS 2 tools show as diagnostics)."""
    types = typestore().types
    kv, status = (
        types["diagnostic_msgs/msg/KeyValue"],
        types["diagnostic_msgs/msg/DiagnosticStatus"],
    )
    return types[DIAGNOSTICS_TYPE](
        header=header(ns),
        status=[
            status(
                level=LEVELS[level],
                name=name,
                message=message,
                hardware_id=hardware_id,
                values=[kv(key=k, value=str(v)) for k, v in values.items()],
            )
        ],
    )


def stamp_ns(t: Any) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


# --- sessions --------------------------------------------------------------------------------


def session_config(
    zcfg: ZenohConfig,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    mode: str = "peer",
) -> zenoh.Config:
    """Multicast scouting off unless configured, no scouting delay (fast node restarts).

    The supervisor's hub session is a router (as rmw_zenoh's zenohd) and nodes and laptops are
    clients of it: measured with Zenoh 1.10, a router does not forward between two peers that
    cannot reach each other directly, and nodes should not open ports of their own.
    """
    try:
        cfg = zenoh.Config.from_file(zcfg.config_file) if zcfg.config_file else zenoh.Config()
    except zenoh.ZError as exc:
        raise ConfigError(f"{zcfg.config_file}: not a valid Zenoh config: {exc}") from None
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(zcfg.multicast_scouting))
    cfg.insert_json5("scouting/delay", "0")
    # Zenoh 1.x maps a 16 MiB shared-memory pool in each session and copies any message over
    # 3 KiB into it (status replies, logs): 8 MB of the supervisor's PSS on x86, touched for
    # nothing (every exolink sample is far smaller and goes over TCP). Off unless a config
    # file turns it on.
    if not (zcfg.config_file and "shared_memory" in Path(zcfg.config_file).read_text()):
        cfg.insert_json5("transport/shared_memory/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps(listen if listen is not None else []))
    cfg.insert_json5("connect/endpoints", json.dumps(connect if connect is not None else []))
    if mode == "client":
        cfg.insert_json5(
            "connect/timeout_ms",
            json.dumps({"router": -1, "peer": -1, "client": CLIENT_CONNECT_TIMEOUT_MS}),
        )
    if mode == "router" and roles.enforced(json.loads(cfg.get_json("transport/auth/usrpwd"))):
        acl = roles.access_control(zcfg.domain_id, zcfg.namespace)
        cfg.insert_json5("access_control", json.dumps(acl))
    return cfg


ZENOH_RUNTIME = "ZENOH_RUNTIME"  # read by Zenoh once, when a process first opens a session


def zenoh_runtime(zcfg: ZenohConfig, env: MutableMapping[str, str] = os.environ) -> str | None:
    """Set the process's Zenoh runtimes from ``zenoh.threads`` before any session exists;
    processes started afterwards (the zygote, nodes) inherit it. An operator's own
    ZENOH_RUNTIME is left as it is. Returns the setting in force.

    Why: Zenoh 1.x runs rx (2 threads), tx, accept, net and app runtimes; a sample crosses
    several of them in each process. On one core each hand-over is a thread wake-up, and on the
    board proxy a wake-up costs ~1 ms of CPU (benchmarks/board/units.py). Handlers that query
    another node from inside a queryable (the sender handing a position to the manager) still
    answer with one thread (tests/test_zenoh_runtime.py)."""
    if zcfg.threads is not None and ZENOH_RUNTIME not in env:
        names = ("rx", "tx", "acc", "net")
        handover = ", ".join(f"{n}: (handover: app)" for n in names)
        env[ZENOH_RUNTIME] = f"({handover}, app: (worker_threads: {zcfg.threads}))"
    return env.get(ZENOH_RUNTIME)


def login(cfg: zenoh.Config) -> str:
    """The login a session's management queries end with (see roles)."""
    return json.loads(cfg.get_json("transport/auth/usrpwd/user")) or roles.ANONYMOUS_USER


def open_session(cfg: zenoh.Config, what: str) -> zenoh.Session:
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as exc:
        raise Unreachable(f"{what}: {str(exc).split(' at ')[0]}") from None


def local_endpoint(zcfg: ZenohConfig) -> str:
    """Where a process on the board reaches the supervisor: its first listen port, on loopback."""
    if not zcfg.listen:
        raise ValueError("zenoh.listen is empty: nodes have no supervisor endpoint to reach")
    proto, _, addr = zcfg.listen[0].partition("/")
    port = addr.rsplit(":", 1)[-1]
    return f"{proto}/127.0.0.1:{port}"


def open_node_session(cfg: ApplianceConfig) -> zenoh.Session:
    """A node's client session, with the appliance's own login when the board has logins."""
    endpoint = local_endpoint(cfg.zenoh)
    zcfg = session_config(cfg.zenoh, connect=[endpoint], mode="client")
    return open_session(zcfg, f"supervisor's Zenoh router at {endpoint}")


def open_hub_session(cfg: ApplianceConfig) -> zenoh.Session:
    """The supervisor's (or a standalone run's) session: listens where laptops connect."""
    zcfg = session_config(
        cfg.zenoh, listen=cfg.zenoh.listen, connect=cfg.zenoh.connect, mode="router"
    )
    return open_session(zcfg, f"listening on {', '.join(cfg.zenoh.listen)}")


def open_client_session(
    endpoint: str, config_file: str | None = None, handshake_s: float | None = None
) -> zenoh.Session:
    """A laptop tool's session to one appliance (config_file: the login file the board wrote
    for a role; without one, an open appliance is assumed). Its queries end with client_login.
    ``handshake_s``: how long the connect and Zenoh's open handshake may take (default 3 s and
    Zenoh's 10 s); a board whose CPU is saturated answers the handshake later than that."""
    zcfg = _client_config(endpoint, config_file)
    if handshake_s is not None:
        ms = int(handshake_s * 1000)
        zcfg.insert_json5(
            "connect/timeout_ms", json.dumps({"router": -1, "peer": -1, "client": ms})
        )
        zcfg.insert_json5("transport/unicast/open_timeout", json.dumps(ms))
    hint = f" as {login(zcfg)} (is the login file this board's?)" if config_file else ""
    return open_session(zcfg, f"no appliance answers at {endpoint}{hint}")


def client_login(config_file: str | None) -> str:
    return login(_client_config("tcp/127.0.0.1:0", config_file))


def _client_config(endpoint: str, config_file: str | None) -> zenoh.Config:
    if config_file and not os.path.isfile(config_file):
        raise ConfigError(f"{config_file}: Zenoh config file not found")
    base = ZenohConfig(listen=[], config_file=config_file)
    return session_config(base, connect=[endpoint], mode="client")


# --- typed pub/sub ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Meta:
    key: str
    seq: int
    source_ns: int
    gid: bytes


def encode_attachment(seq: int, source_ns: int, gid: bytes) -> bytes:
    return rosgraph.encode_attachment(seq, source_ns, gid)


def decode_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """Any supported distro's attachment (16-byte GID, or Humble's 24); ValueError else."""
    return rosgraph.decode_attachment(raw)


class Publisher:
    """A typed publisher: node code hands it message objects (or, from an ``exolink.cdr``
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
            if self._pub.matching_status.matching:  # one Rust call per batch, not per sample
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
    measured (x86, pub -> router -> sub), 1.2 ms of work between puts, what decoding a cycle's
    frames takes on the board proxy, cost the router and subscriber 8x more CPU per sample than
    the same puts in a row. On the proxy the h2 reader's Zenoh thread and the router took ~11 %
    and ~30 % of CPU 0 for 100 samples/s published as each cycle was decoded."""

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


class Messaging:
    """Binds a session to the appliance's domain and namespace.

    With ``ros_node`` (every appliance process names one) the session is also that ROS 2 node
    in the graph rmw_zenoh laptops read: each publisher and subscription declared here gets its
    graph token and its GID from it (exolink.rosgraph); ``close`` takes the node out.
    """

    def __init__(
        self, session: zenoh.Session, cfg: ApplianceConfig, ros_node: str | None = None
    ) -> None:
        self.session = session
        self.domain_id = cfg.zenoh.domain_id
        self.namespace = cfg.zenoh.namespace
        self.device = cfg.device
        self.distro = cfg.zenoh.ros_distro
        self._commands: CommandLog | None = None
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
        self, topic: str, typename: str, callback: Callable[[bytes], None]
    ) -> zenoh.Subscriber:
        """CDR bytes to a decoder of the caller's (exolink.cdr): no typestore in the process."""
        self._token(rosgraph.SUBSCRIPTION, topic, typename, None)
        return self.session.declare_subscriber(
            self.key(topic, typename), lambda sample: callback(sample.payload.to_bytes())
        )

    def mgmt(self, *path: str) -> str:
        return mgmt_key(self.device, *path)

    def log_command(
        self, user: str, key: str, request: dict[str, Any], reply: dict[str, Any]
    ) -> None:
        """A command that came another way than ``serve`` (a ROS 2 service or topic)."""
        if self._commands is None:
            self._commands = CommandLog(self)
        self._commands.write(user, key, request, reply)

    def serve(
        self,
        path: str | tuple[str, ...],
        handler: Callable[[dict[str, Any]], dict[str, Any] | None],
        needs: Needs = roles.OBSERVER,
    ) -> zenoh.Queryable:
        """This appliance's management queryable at ``exolink/<device>/<path>`` (see serve)."""
        if self._commands is None:
            self._commands = CommandLog(self)
        parts = (path,) if isinstance(path, str) else path
        return serve(self.session, self.mgmt(*parts), handler, needs, self._commands)

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
        """One node asking another to act: the answer, or CommandRefused with the other's
        refusal verbatim (or that nothing answered), so the caller's own caller sees why.
        A refusal containing one of ``tolerate`` counts as done (e.g. "is not active")."""
        try:
            reply = self.request(*path, body=body, timeout_s=timeout_s)
        except Unreachable as exc:
            raise CommandRefused(f"nothing answers at {'/'.join(path)}: {exc}") from None
        error = str(reply.get("error", f"refused by {'/'.join(path)}"))
        if not reply.get("ok") and not any(t in error for t in tolerate):
            raise CommandRefused(error)
        return reply


# --- JSON queries (commands and management) --------------------------------------------------


class CommandRefused(Exception):
    """Raised by a handler to refuse a request; the text reaches the caller verbatim."""


# The role a request needs: one for the whole key, or chosen from the request (its action).
Needs = str | Callable[[dict[str, Any]], str]
COMMANDS_TOPIC = "commands"
COMMANDS_TYPE = "std_msgs/msg/String"
_LOGGED_VALUE_CHARS = 200
_log = structlog.get_logger("exolink.commands")


def _summary(request: dict[str, Any]) -> dict[str, Any]:
    """The request as the command log keeps it: uploaded content by size, long values cut."""
    out: dict[str, Any] = {}
    for k, v in request.items():
        if k == "content" and isinstance(v, str):
            out[k] = f"<{len(v)} chars>"
        else:
            text = json.dumps(v)
            out[k] = v if len(text) <= _LOGGED_VALUE_CHARS else text[:_LOGGED_VALUE_CHARS] + "..."
    return out


class CommandLog:
    """Every command a role above observer sent, with the login that sent it: in the process'
    log and on the ``commands`` topic (std_msgs/String, JSON), which the recorder records."""

    def __init__(self, msg: Messaging) -> None:
        self._msg = msg
        # Declared now, not at the first command: a recorder learns topics from the graph, and
        # a publisher born with its first message would lose that message to it.
        self._pub = msg.publisher(COMMANDS_TOPIC, COMMANDS_TYPE, raw=True)
        self._lock = threading.Lock()

    def write(self, user: str, key: str, request: dict[str, Any], reply: dict[str, Any]) -> None:
        entry = {"by": user, "key": key, "request": _summary(request), "ok": reply["ok"]}
        if not reply["ok"]:
            entry["error"] = reply.get("error", "")
        _log.info("command", **entry)
        with self._lock:
            self._pub.put(cdr.string_msg(json.dumps(entry)))


def serve(
    session: zenoh.Session,
    key: str,
    handler: Callable[[dict[str, Any]], dict[str, Any] | None],
    needs: Needs = roles.OBSERVER,
    log: CommandLog | None = None,
) -> zenoh.Queryable:
    """A JSON queryable at ``key/<login>``: the login (proven by Zenoh's access control on a
    board with logins) must hold the role the request needs; refusals and bugs become errors.
    Commands (more than observer needed, or an action such as e-stop) go into ``log`` with the
    login that sent them, accepted or not."""

    def on_query(query: zenoh.Query) -> None:
        qkey = str(query.key_expr)
        user = qkey.rsplit("/", 1)[-1]
        request: dict[str, Any] = {}
        needed = roles.OBSERVER
        try:
            raw = query.payload.to_bytes() if query.payload is not None else b"{}"
            request = json.loads(raw or b"{}")
            if not isinstance(request, dict):
                raise CommandRefused("request must be a JSON object")
            needed = needs(request) if callable(needs) else needs
            roles.check(user, needed, f"{key.split('/', 2)[-1]} {request.get('action', '')}")
            reply = {"ok": True, **(handler(request) or {})}
        except (CommandRefused, roles.Forbidden) as exc:
            reply = {"ok": False, "error": str(exc)}
        except json.JSONDecodeError as exc:
            reply = {"ok": False, "error": f"request is not valid JSON: {exc}"}
        except Exception as exc:  # never leave a caller waiting on a handler bug
            reply = {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}
        query.reply(query.key_expr, json.dumps(reply).encode())
        command = needed != roles.OBSERVER or request.get("action") not in (None, "status")
        if log is not None and command and user != roles.APPLIANCE_USER:
            log.write(user, key, request, reply)

    return session.declare_queryable(f"{key}/*", on_query)


class Unreachable(Exception):
    pass


def request(
    session: zenoh.Session,
    key: str,
    body: dict[str, Any] | None = None,
    timeout_s: float = DEFAULT_QUERY_TIMEOUT_S,
    user: str = roles.ANONYMOUS_USER,
) -> dict[str, Any]:
    """One JSON query as login ``user`` with a deadline; Unreachable when nothing answers."""
    payload = json.dumps(body or {}).encode()
    for reply in session.get(f"{key}/{user}", payload=payload, timeout=timeout_s):
        if reply.ok is not None:
            result: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return result
        raise Unreachable(
            f"{key}: error reply: {reply.err.payload.to_bytes().decode(errors='replace')}"
        )
    raise Unreachable(f"no answer from {key} within {timeout_s:g} s")
