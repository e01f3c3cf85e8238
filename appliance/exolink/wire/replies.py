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
    starved: int = 0  # silences past its deadline while it waited for the CPU (not hung)
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


class ClockStep(Reply):
    """A laptop's step of the board's clock (exolink.board.clock), kept for its boot."""

    by: str  # the login that stepped it
    at: str  # UTC, ISO 8601, after the step
    step_s: float
    error_ms: float  # the laptop's measurement's
    was: float  # the board's time before, s since the epoch
    boot_id: str = ""


class ClockStatus(Reply):
    """The board's clock: what set it, and its time when asked (a laptop's offset from it)."""

    now: float
    synchronised: bool  # by a time server
    max_error_ms: float | None
    source: str  # time server | laptop | unsynchronised
    from_laptop: bool  # the config lets a laptop step it
    last_step: ClockStep | None = None  # this boot's


class UploadProgress(Reply):
    received: int
    size: int


class Software(Reply):
    """The board's software (exolink.board.update): what runs, from which slot, and what
    became of the last update."""

    version: str  # exolink's, as installed
    slot: str | None  # A | B (None: not booted by RAUC)
    bundle_version: str | None
    result: str | None  # installing | installed | good | rolled back | refused | ...
    detail: str | None
    since: str | None
    installing: bool  # a bundle handed to the root agent: the board reboots when it is in
    upload: UploadProgress | UnsetType = UNSET  # a bundle on its way in


class UploadAt(Reply):
    """An upload begun or a chunk taken: the offset the next chunk starts at."""

    offset: int
    max_chunk: int | UnsetType = UNSET  # only when it begins


class Committed(Reply):
    accepted: bool
    upload_s: float


class NodeParams(Reply):
    """A node's params as it runs with them (``exolink params NODE``)."""

    params: dict[str, Any]  # the node type's own schema (its ``Params``)


class ParamSet(Reply):
    """A param changed at run time, as the node now holds it."""

    key: str
    value: Any


class TimingStats(Reply):
    """The timing monitor's answer (``exolink timing``): one id's period deviations from its
    kernel receive times."""

    n: int  # periods measured (0: too few frames, ``error`` says so)
    error: str = ""
    expected_ms: float = 0.0
    mean_period_ms: float = 0.0
    mean_dev_ms: float = 0.0
    p99_dev_ms: float = 0.0
    max_dev_ms: float = 0.0
    histogram: dict[str, int] = {}  # "0-50us" -> periods
    socket_dropped: int | None = None  # frames the kernel dropped from the monitor's queue


class FaultInjected(Reply):
    """The simulator took a fault (``exolink sim fault``): it plays it for its duration."""

    fault: str


class NodeStats(Reply):
    """What a node's ``stats`` says first, read by the recorder for each file: whose it is,
    and its bus reader's receive counters (FrameReader.counters). The rest is the node's own
    introspection (the h2 reader's frame counts), read by the benchmarks."""

    node: str
    receive: dict[str, Any] | None = None


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
    clock: ClockStatus | None = None  # None: an older supervisor's status
    software: Software | None = None  # None: an older supervisor's status
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
