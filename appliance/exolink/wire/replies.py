"""The supervisor's replies, one schema each: what its handlers build (exolink.supervisor.api)
and what a client reads back (``read``; exolink.client's ``Remote.nodes``).

On the wire a reply stays a plain JSON object with ``ok`` beside these fields (a laptop without
exolink reads it as before). A client decodes it leniently: fields it does not know (a newer
supervisor's) are ignored, so an older laptop still reads a newer board. A field that is there
only when there is something to say (a running node's CPU) is ``UNSET`` otherwise, and left out.
"""

from __future__ import annotations

from typing import Any, TypeVar

import msgspec
from msgspec import UNSET, UnsetType

__all__ = ["UNSET", "UnsetType"]
R = TypeVar("R", bound=msgspec.Struct)


class Reply(msgspec.Struct):
    """The base of every reply: each field always there unless it may be ``UNSET``."""


class NodeInfo(Reply):
    """One node as the supervisor sees it (``exolink nodes``, the status's node table)."""

    name: str
    state: str  # starting | running | stopped | backoff | failed | killed
    pid: int | None
    heartbeat_age_s: float | None  # None: spawned, no heartbeat yet
    plugin: str = ""
    critical: bool = False
    enabled: bool = True
    uptime_s: float = 0.0
    restarts: int = 0
    last_exit: str = ""  # how its last spawn ended ("exit 1", "SIGKILL", ...)
    health: str = ""  # its own diagnostics' word, if it publishes any
    idle: bool = False  # held to the appliance's default deadline (exolink.liveness)
    leased: bool = False  # held to its lease's deadline while only the kernel sends
    start_s: float | None = None  # spawn to first heartbeat
    receive: dict[str, Any] | UnsetType = UNSET  # a bus reader's losses (FrameReader.counters)
    card: dict[str, Any] | UnsetType = UNSET  # the recorder's card: free space, hours left
    cpu_s: float | UnsetType = UNSET  # from /proc, while it runs
    rss_mb: float | UnsetType = UNSET
    api_refused: dict[str, int] | UnsetType = UNSET  # requests its API refused, by reason


class Nodes(Reply):
    nodes: list[NodeInfo]


class NodeReply(Reply):
    """A node started, stopped or restarted, as it is now."""

    node: NodeInfo


class LogLines(Reply):
    lines: list[str]


class Watchdog(Reply):
    """The watchdog route's answer to any action: where the latch is now."""

    state: str  # disarmed | armed | tripped
    reason: str
    detail: str


class WatchdogStatus(Watchdog):
    """The watchdog in the status: the latch and what it has seen and sent."""

    since_ns: int
    trips: int
    frames_sent: int
    violations: int
    socket_dropped: int | None  # kernel drops from a full receive buffer (None: not known)
    read_lag_max_ms: float = 0.0  # frame arrival -> read by the watchdog: its margin
    malformed: dict[str, int] = {}  # "110 bad length" -> count


class Bus(Reply):
    """The CAN link (exolink.supervisor.canlink) and the device's pulse on it."""

    interface: str
    channel: str
    pulse_silent_s: float | None  # None: never heard
    pulse: str = "pulse"  # what the device calls it (the H2: "h2 data")
    state: str = "n/a"  # error-active ... bus-off, up / down without CAN state, n/a off SocketCAN
    txerr: int | UnsetType = UNSET  # these four: SocketCAN only
    rxerr: int | UnsetType = UNSET
    bus_errors: int | UnsetType = UNSET
    restarts: int | UnsetType = UNSET


class TriggerStatus(Reply):
    count: int
    last_ns: int | None
    source: str | UnsetType = UNSET  # only in the status: the configured input


class Fired(Reply):
    fired_ns: int | None


class Memory(Reply):
    rss_mb: float
    trims: int


class Status(Reply):
    """``exolink status``: the watchdog, the bus, the trigger, the clock, the software and
    every node, in one answer."""

    device: str
    pid: int
    zygote_pid: int | None
    watchdog: WatchdogStatus
    bus: Bus
    trigger: TriggerStatus
    nodes: list[NodeInfo]
    memory: Memory
    clock: dict[str, Any] = {}  # exolink.board.clock's status
    software: dict[str, Any] = {}  # exolink.board.update's status
    api: dict[str, int] = {}  # the API's handled and refused counts (messaging.Admission)
    bad_samples: dict[str, int] = {}


def read(reply: dict[str, Any], cls: type[R]) -> R:
    """A reply as ``cls``: ValueError naming the field that does not fit."""
    try:
        return msgspec.convert(reply, cls, strict=False)
    except msgspec.ValidationError as exc:
        raise ValueError(f"a {cls.__name__} reply that does not fit: {exc}") from None


def plain(reply: Any) -> dict[str, Any]:
    """A reply as the JSON object it goes out as (a handler's dict passes through, uncopied)."""
    out: dict[str, Any] = (
        msgspec.to_builtins(reply) if isinstance(reply, msgspec.Struct) else reply or {}
    )
    return out
