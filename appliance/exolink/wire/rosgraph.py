"""The ROS 2 graph as rmw_zenoh declares it: liveliness tokens, GIDs, QoS strings, distros.

A ROS 2 tool (``ros2 node list``, ``ros2 topic list -t``, rqt_graph, ``ros2 topic echo`` without a
type) learns the graph from liveliness tokens under ``@ros2_lv``, not from data keys. rmw_zenoh
(rmw_zenoh_cpp/src/detail/liveliness_utils.cpp) writes one token per node (``NN``) and one per
publisher (``MP``), subscription (``MS``), service server (``SS``) and client (``SC``)::

    @ros2_lv/<domain>/<zid>/<nid>/<eid>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>
        [/<topic>/<type>/<type hash>/<qos>]

with every ``/`` inside a name replaced by ``%`` (so ``/`` -> ``%``, ``/h2`` -> ``%h2``), the
Zenoh session id as Zenoh prints it, node and entity ids from one counter per session, and a
QoS string that leaves out each value equal to rmw_zenoh's default (qos.cpp). An entity's GID,
which every message's attachment carries, is XXH3-128 of its token's key expression (low 64 bits
then high 64 bits, little-endian): a subscriber can tell which publisher sent a sample from the
graph alone. A token vanishes when its entity is closed or its session ends (a killed process
included), which is how a node "goes away" in ROS 2.

Distros: Jazzy, Kilted and Rolling put RIHS01 type hashes into keys and tokens and a 16-byte GID
into the 33-byte attachment; Humble's rmw_zenoh has no type hashes (``TypeHashNotSupported``) and
a 24-byte GID storage (rmw's RMW_GID_STORAGE_SIZE before Iron): the 16 hash bytes, 8 zeros.

Kept light on purpose: every node imports it (xxhash is a small C extension, no rosbags).
"""

from __future__ import annotations

import itertools
import struct
import threading
from dataclasses import dataclass
from typing import Any, Literal

import xxhash

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
Distro = Literal["jazzy", "kilted", "rolling", "humble"]
DISTROS: tuple[str, ...] = ("jazzy", "kilted", "rolling", "humble")
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
GID_SIZE = {"humble": 24}  # every other supported distro: 16

# rmw_qos_*_policy_e values (rmw/types.h) and rmw_zenoh's defaults (qos.cpp): a QoS string
# leaves a field empty where the value is the default.
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC = 1
_DEFAULT = {"reliability": RELIABLE, "durability": VOLATILE, "history": KEEP_LAST, "depth": 42}


@dataclass(frozen=True, slots=True)
class Qos:
    """The parts of a ROS 2 QoS profile exolink sets; deadline, lifespan and liveliness stay
    at their defaults (infinite, automatic), as rmw_zenoh writes them: empty."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10  # rclcpp's default for a publisher or subscription

    def keyexpr(self) -> str:
        """``<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liv>,<s>,<ns>``."""

        def part(name: str) -> str:
            value = getattr(self, name)
            return "" if value == _DEFAULT[name] else str(value)

        return (
            f"{part('reliability')}:{part('durability')}:{part('history')},{part('depth')}:,:,:,,"
        )


DEFAULT_QOS = Qos()
SERVICE_QOS = Qos()  # rclcpp's services default: reliable, volatile, keep last 10


def parse_qos(text: str) -> Qos:
    """A token's QoS string back to the values (empty fields: rmw_zenoh's defaults)."""
    parts = text.split(":")
    if len(parts) < 6:
        raise ValueError(f"not an rmw_zenoh QoS string: {text!r}")
    history, _, depth = parts[2].partition(",")

    def num(s: str, name: str) -> int:
        return int(s) if s else _DEFAULT[name]

    return Qos(
        num(parts[0], "reliability"),
        num(parts[1], "durability"),
        num(history, "history"),
        num(depth, "depth"),
    )


def mangle(name: str) -> str:
    """rmw_zenoh's mangle_name: every ``/`` of a ROS name becomes ``%``."""
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def fq_name(namespace: str, name: str) -> str:
    """A fully qualified ROS name: ``("h2", "joint_states")`` -> ``/h2/joint_states``."""
    parts = [p for p in (namespace.strip("/"), name.strip("/")) if p]
    return "/" + "/".join(parts)


def dds_type(typename: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_``; a service
    type keeps its own kind (``std_srvs::srv::dds_::Trigger_``), as rmw_zenoh's tokens do."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def gid_of(token: str, distro: str = "jazzy") -> bytes:
    """The entity's GID: XXH3-128 of its liveliness key expression, low 64 bits first (both
    little-endian, as rmw_zenoh memcpys them on a little-endian host), zero-padded to the
    distro's GID size."""
    digest = xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")
    return digest + bytes(GID_SIZE.get(distro, 16) - 16)


# --- attachments -----------------------------------------------------------------------------

_HEAD = struct.Struct("<qqB")


def encode_attachment(seq: int, source_ns: int, gid: bytes) -> bytes:
    """int64 sequence number, int64 source timestamp, the GID as Zenoh's serializer writes a
    byte array (LEB128 length, a single byte below 128, then the bytes): 33 bytes with a
    16-byte GID (Jazzy and later), 41 with Humble's 24."""
    return _HEAD.pack(seq, source_ns, len(gid)) + gid


def decode_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp, GID) from what any supported distro sends: a
    16-byte GID (33 bytes in all) or Humble's 24-byte one (41). ValueError otherwise."""
    if len(raw) < _HEAD.size:
        raise ValueError(f"attachment of {len(raw)} bytes is too short")
    seq, ts, n = _HEAD.unpack_from(raw)
    if n not in (16, 24) or len(raw) != _HEAD.size + n:
        raise ValueError(f"attachment of {len(raw)} bytes with a GID of {n}: not rmw_zenoh's")
    return seq, ts, bytes(raw[_HEAD.size :])


# --- tokens ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Entity:
    """One parsed graph token (what a ROS 2 tool reads from the network)."""

    key: str
    domain_id: int
    zid: str
    nid: str
    eid: str
    kind: str
    enclave: str
    namespace: str
    node: str
    topic: str = ""
    type: str = ""
    type_hash: str = ""
    qos: Qos | None = None

    @property
    def typename(self) -> str:
        """``sensor_msgs::msg::dds_::JointState_`` -> ``sensor_msgs/msg/JointState``."""
        pkg, kind, _, name = self.type.split("::")
        return f"{pkg}/{kind}/{name.removesuffix('_')}"

    @property
    def gid(self) -> bytes:
        return gid_of(self.key)


def parse_token(key: str) -> Entity:
    """A ``@ros2_lv`` key expression -> Entity; ValueError for anything else."""
    p = key.split("/")
    if len(p) < 9 or p[0] != ADMIN_SPACE or any(not x for x in p):
        raise ValueError(f"not an rmw_zenoh graph token: {key}")
    kind = p[5]
    if kind not in (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT):
        raise ValueError(f"unknown entity kind {kind!r} in {key}")
    base: dict[str, Any] = {
        "key": key,
        "domain_id": int(p[1]),
        "zid": p[2],
        "nid": p[3],
        "eid": p[4],
        "kind": kind,
        "enclave": demangle(p[6]),
        "namespace": demangle(p[7]),
        "node": demangle(p[8]),
    }
    if kind == NODE:
        return Entity(**base)
    if len(p) != 13:
        raise ValueError(f"{kind} token without topic, type, hash and QoS: {key}")
    return Entity(**base, topic=demangle(p[9]), type=p[10], type_hash=p[11], qos=parse_qos(p[12]))


_counters: dict[str, itertools.count[int]] = {}
_counters_lock = threading.Lock()


def _next_id(zid: str) -> int:
    """rmw_zenoh numbers nodes and entities from one counter per context (session)."""
    with _counters_lock:
        return next(_counters.setdefault(zid, itertools.count()))


class Token:
    """A declared entity: its key expression, GID and liveliness token (undeclared by close)."""

    def __init__(self, session: Any, key: str, distro: str) -> None:
        self.key = key
        self.gid = gid_of(key, distro)
        self._token = session.liveliness().declare_token(key)

    def close(self) -> None:
        if self._token is not None:
            self._token.undeclare()
            self._token = None


class RosNode:
    """One ROS 2 node on a Zenoh session: its NN token at once, an entity token per
    publisher, subscription, service or client declared through it."""

    def __init__(
        self,
        session: Any,
        domain_id: int,
        namespace: str,
        name: str,
        distro: str = "jazzy",
        enclave: str = "/",
    ) -> None:
        if distro not in DISTROS:
            raise ValueError(f"unknown ROS 2 distro {distro!r} ({', '.join(DISTROS)})")
        self.session = session
        self.domain_id = domain_id
        self.namespace = fq_name(namespace, "")
        self.name = name
        self.distro = distro
        self.zid = str(session.zid())
        self.nid = str(_next_id(self.zid))
        self._prefix = f"{ADMIN_SPACE}/{domain_id}/{self.zid}/{self.nid}"
        self._names = f"{mangle(enclave)}/{mangle(self.namespace)}/{mangle(name)}"
        self._lock = threading.Lock()
        self._tokens: list[Token] = []
        self.node_token = self._declare(f"{self._prefix}/{self.nid}/{NODE}/{self._names}")

    def type_hash(self, hash_rihs01: str) -> str:
        """What goes into keys and tokens for a type: its RIHS01 hash, or Humble's stand-in."""
        return HUMBLE_TYPE_HASH if self.distro == "humble" else hash_rihs01

    def entity_key(
        self, kind: str, topic: str, typename: str, type_hash: str, qos: Qos = DEFAULT_QOS
    ) -> str:
        """The token key of a new entity (``topic``: fully qualified, ``type_hash`` as in the
        data key) with the next entity id of this session."""
        eid = _next_id(self.zid)
        return (
            f"{self._prefix}/{eid}/{kind}/{self._names}/{mangle(topic)}/{dds_type(typename)}/"
            f"{type_hash}/{qos.keyexpr()}"
        )

    def declare(
        self, kind: str, topic: str, typename: str, type_hash: str, qos: Qos = DEFAULT_QOS
    ) -> Token:
        return self._declare(self.entity_key(kind, topic, typename, type_hash, qos))

    def _declare(self, key: str) -> Token:
        token = Token(self.session, key, self.distro)
        with self._lock:
            self._tokens.append(token)
        return token

    def release(self, token: Token) -> None:
        with self._lock:
            if token in self._tokens:
                self._tokens.remove(token)
        token.close()

    def close(self) -> None:
        """Every entity's token, then the node's: the node leaves the ROS graph."""
        with self._lock:
            tokens, self._tokens = self._tokens, []
        for t in reversed(tokens):
            t.close()
