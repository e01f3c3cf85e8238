"""The one place that opens a python-can bus from configuration, and a reader on it.

A node only wakes for its own ids: SocketCAN gets kernel receive filters, and so does the
simulated bus (python-can's interface ``exolink_sim``: exolink.canbus.simbus); the in-process virtual
bus filters in python-can. ``open_reader`` puts a ``FrameReader`` (canbus.reader) on one bus or
two (a waking one and a quiet one); ``Cadence`` is how a node reading a periodic stream sets the
reader's ``every_s`` and its read timeouts.
"""

from __future__ import annotations

import socket
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

from exolink.canbus import filters as canfilter
from exolink.canbus.frames import id_filters
from exolink.canbus.mmsg import BATCH
from exolink.canbus.reader import FrameReader
from exolink.canbus.sockets import bus_socket
from exolink.config import CanConfig

if TYPE_CHECKING:
    import can
    from can.typechecking import CanFilter


class CanOpenError(RuntimeError):
    pass


def open_bus(
    cfg: CanConfig,
    filters: list[CanFilter] | None = None,
    receive_own_messages: bool = False,
) -> can.BusABC:
    """Open the configured bus through python-can (the simulated bus is its interface
    ``exolink_sim``, exolink.canbus.simbus); failures name the interface and the likely fix.
    ``filters`` None: every frame; ``[]``: none (a bus that only sends)."""
    import can  # lazy: python-can (its interfaces) only where a bus is opened

    kwargs: dict[str, Any] = {"receive_own_messages": receive_own_messages}
    if filters is not None:
        kwargs["can_filters"] = filters
    try:
        bus = can.Bus(interface=cfg.bus_interface, channel=cfg.channel, **kwargs)
    except (OSError, can.CanError, ValueError) as exc:
        raise CanOpenError(_explain(cfg, exc)) from exc
    sock = bus_socket(bus)
    if filters == [] and sock is not None and sock.family == socket.AF_CAN:
        # python-can takes [] as "no filter" and receives every frame; a bus that only
        # sends must receive none (the kernel queued the whole bus for each such socket,
        # unread). No filter at all is the kernel's "receive nothing".
        try:
            sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, b"")
        except OSError as exc:
            bus.shutdown()
            raise CanOpenError(_explain(cfg, exc)) from exc
    return bus


def _explain(cfg: CanConfig, exc: Exception) -> str:
    base = f"cannot open CAN bus {cfg.interface}:{cfg.channel}: {exc}"
    if cfg.interface == "socketcan":
        return (
            f"{base}. Is the interface present and up? On the board: check the DCAN1 overlay "
            f"and `ip link set {cfg.channel} up type can bitrate {cfg.bitrate}`; for tests: "
            f"`ip link add dev {cfg.channel} type vcan && ip link set {cfg.channel} up`."
        )
    if cfg.simulated:
        return (
            f"cannot open the simulated CAN bus ({cfg.interface} {cfg.channel} on loopback): {exc}"
        )
    return base


class Cadence(NamedTuple):
    """How a reader of a periodic stream (the H2's or a MACCEPA board's 10 ms cycle) waits:
    woken once per ``cycles`` cycles, it publishes each cycle's samples back to back.

    On the board a wake-up and each Zenoh hop cost more than the samples they carry. Board
    proxy (qemu TCG, one core): a Python loop that only wakes at 100 Hz took 8.7 % of the CPU;
    one topic at 100 samples/s through the router to one subscriber took 88 % (publisher,
    router and subscriber), the same 100 samples as 25 bursts of four 32 %: Zenoh sends a burst
    as one batch, so every hop wakes once for it. Subscribers still get every sample with its
    CAN timestamp, up to ``cycles - 1`` periods later; the control path (the watchdog and the
    controller manager) reads the bus itself and never waits for this. 1: a wake per cycle."""

    period_s: float
    cycles: int = 1
    idle_s: float = 0.05  # nothing streams: look this often (stream restarts, shutdown)

    @property
    def every_s(self) -> float:
        """FrameReader's ``every_s``: a quarter period past the last cycle of the group, so its
        waking frame is already queued when the wait ends (one wake-up, not a sleep and a
        select)."""
        return (self.cycles + 0.25) * self.period_s if self.cycles > 1 else 0.0

    def batch(self, frames_per_cycle: int) -> int:
        """FrameReader's ``batch`` for a stream of ``frames_per_cycle`` frames a period: twice
        a wake's cycles and two more (a late wake on a busy core still reads all in one go), at
        least the default (canbus.mmsg.BATCH)."""
        return max(BATCH, (2 * self.cycles + 2) * frames_per_cycle)

    def timeout(self, found: bool) -> float:
        """The next read's timeout: while frames flow, a cycle whose waking frame was lost is
        read one and a half periods late at most; a quiet bus is looked at every ``idle_s``."""
        return self.every_s + 1.5 * self.period_s if found else self.idle_s


def open_reader(
    cfg: CanConfig,
    ids: Iterable[int] | None = None,
    rcvbuf: int | None = None,
    every_s: float = 0.0,
    wake_on: Iterable[int] | None = None,
    stale_s: float = 0.0,
    drop: Sequence[canfilter.Drop] = (),
    batch: int = BATCH,
) -> FrameReader:
    """A bus for receiving ``ids`` (all if None), read in batches; ``.bus`` sends, ``close()``
    closes. ``rcvbuf``: the receive queue to ask for, in bytes (default: ``RCVBUF_BYTES``);
    ``every_s``: wake at most that often while frames flow; ``wake_on``: only these of ``ids``
    wake the reader, the others are read with them (FrameReader's ``quiet``; a bus without
    sockets, the in-process virtual one, wakes for every id); ``stale_s``: skip (and count)
    frames read later than that after arrival (0: never); ``drop``: frames of these ids never
    delivered (canfilter: the kernel's socket filter on SocketCAN); ``batch``: frames read per
    socket and read at most (``Cadence.batch``)."""
    drop = canfilter.check(drop)
    kw: dict[str, Any] = {
        "rcvbuf": rcvbuf,
        "every_s": every_s,
        "stale_s": stale_s,
        "drop": drop,
        "batch": batch,
    }
    if ids is None or wake_on is None:
        return _one_bus_reader(cfg, ids, **kw)
    waking = sorted(set(wake_on) & set(ids))
    rest = sorted(set(ids) - set(waking))
    bus = open_bus(cfg, filters=id_filters(waking if waking and rest else ids))
    if bus_socket(bus) is None:  # nothing to wake on (the virtual bus): one reader of all ids
        bus.set_filters(id_filters(ids))
        return _reader_or_shutdown(bus, cfg, ids, **kw)
    if not waking or not rest:
        bus.shutdown()
        raise ValueError(
            f"wake_on {sorted(set(wake_on))} must name some, not all, of {sorted(set(ids))}"
        )
    try:
        quiet = open_bus(cfg, filters=id_filters(rest))
    except BaseException:
        bus.shutdown()
        raise
    try:
        return FrameReader(bus, cfg, ids, quiet=quiet, wake_ids=waking, **kw)
    except BaseException:
        quiet.shutdown()
        bus.shutdown()
        raise


def _one_bus_reader(cfg: CanConfig, ids: Iterable[int] | None, **kw: Any) -> FrameReader:
    bus = open_bus(cfg, filters=id_filters(ids) if ids is not None else None)
    return _reader_or_shutdown(bus, cfg, ids, **kw)


def _reader_or_shutdown(
    bus: can.BusABC, cfg: CanConfig, ids: Iterable[int] | None, **kw: Any
) -> FrameReader:
    """A FrameReader of ``bus``; the bus shut down if the reader cannot be made."""
    try:
        return FrameReader(bus, cfg, ids, **kw)
    except BaseException:
        bus.shutdown()
        raise
