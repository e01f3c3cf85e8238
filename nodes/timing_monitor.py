"""CAN timing monitor [thesis: H2patternReceiver]: how far a periodic CAN id strays from its period.

The thesis judged its pattern sender with a second board; this node does the same from any board on
the bus, from the frames' kernel receive timestamps. Frames that share an id (all joint-control
frames are id 70) can be told apart by their first data byte (the motor id).
"""

from __future__ import annotations

import bisect
import itertools
import statistics
import threading
import time
from array import array
from typing import Annotated, Any

import msgspec

from exolink.canbus import Frame, open_reader
from exolink.canbus.filters import Drop
from exolink.loops import Frames
from exolink.messaging import Refused
from exolink.node import Node
from exolink.wire import management
from exolink.wire.replies import TimingStats

HIST_EDGES_US = [0, 10, 20, 50, 100, 200, 500, 1000, 5000]
MAX_STAMPS = 200_000
# Deviations come from kernel timestamps, so reading late costs nothing but memory: a wake-up
# costs ~1 ms of the board's one core under TCG (benchmarks/board/units.py); the socket's
# queue holds far more than this many seconds of the monitored ids.
READ_EVERY_S = 0.25
# The socket's receive queue: an observer yields the CPU (board.yaml: nice 10) and reads late,
# so its queue must outlast a starved stretch. On a saturated core the 1 MiB default (~3000
# frames, ~6 s of ids 70 and 110 with the pattern running) overflows (docs/performance.md).
# 4 MiB asked (the kernel doubles it): ~25 s.
# Memory is taken only while frames wait.
RCVBUF_BYTES = 4 << 20
MAX_ONLY = 3  # ids with ``only``: up to 9 content-filter rules each (canfilter.MAX_RULES)


def deviation_stats(stamps: list[float], expected_s: float | None = None) -> dict[str, Any]:
    """Period deviations |dt - expected| (expected: the median period when not given). Plain
    Python (statistics, bisect): numpy would be this node's largest import for one query."""
    if len(stamps) < 3:
        return {"n": 0, "error": f"too few frames ({len(stamps)})"}
    dt = [b - a for a, b in itertools.pairwise(stamps)]
    exp = statistics.median(dt) if expected_s is None else expected_s
    dev = [abs(d - exp) * 1e3 for d in dt]
    counts = [0] * len(HIST_EDGES_US)
    for d in dev:
        counts[bisect.bisect_right(HIST_EDGES_US, d * 1e3) - 1] += 1
    labels = [f"{a}-{b}us" for a, b in itertools.pairwise(HIST_EDGES_US)] + [
        f">{HIST_EDGES_US[-1]}us"
    ]
    p99 = statistics.quantiles(dev, n=100, method="inclusive")[98]
    return {
        "n": len(dt),
        "expected_ms": round(exp * 1e3, 4),
        "mean_period_ms": round(statistics.fmean(dt) * 1e3, 4),
        "mean_dev_ms": round(statistics.fmean(dev), 4),
        "p99_dev_ms": round(p99, 4),
        "max_dev_ms": round(max(dev), 4),
        "histogram": dict(zip(labels, counts, strict=True)),
    }


class StampRing:
    """The last ``size`` frames of one id: kernel time and (length, first byte), in two flat
    arrays, 10 B a frame, grown as frames come. The four deques of floats per frame this
    replaced (one per way of asking, one more per first-byte value seen) cost ~130 B a frame:
    tens of MB within an hour of a trial."""

    def __init__(self, size: int = MAX_STAMPS) -> None:
        self.times = array("d")
        self.codes = array("H")  # dlc << 8 | first byte
        self.size, self.next = size, 0

    def add(self, t: float, data: bytes) -> None:
        code = len(data) << 8 | data[0] if data else 0
        i = self.next
        if len(self.times) < self.size:
            self.times.append(t)
            self.codes.append(code)
        else:
            self.times[i] = t
            self.codes[i] = code
        self.next = (i + 1) % self.size

    def copy(self) -> StampRing:
        """A snapshot (two memory copies) to select from without holding up the reader."""
        out = StampRing(self.size)
        out.times, out.codes, out.next = array("d", self.times), array("H", self.codes), self.next
        return out

    def select(self, dlc: int | None, byte0: int | None) -> list[float]:
        """Oldest first, the times of frames of that length (None: any) and first data byte
        (None: any; a frame without data has none)."""
        n = len(self.times)
        order = (
            range(n) if n < self.size else itertools.chain(range(self.next, n), range(self.next))
        )
        out = []
        for i in order:
            c = self.codes[i]
            if dlc is not None and c >> 8 != dlc:
                continue
            if byte0 is not None and (c >> 8 == 0 or c & 0xFF != byte0):
                continue
            out.append(self.times[i])
        return out


class Only(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    id: Annotated[int, msgspec.Meta(ge=0, le=0x7FF)]
    dlc: Annotated[int, msgspec.Meta(ge=1, le=8)]
    first_byte: list[Annotated[int, msgspec.Meta(ge=0, le=255)]] = []  # empty: any


class TimingParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    ids: list[Annotated[int, msgspec.Meta(ge=0, le=0x7FF)]] = msgspec.field(
        default_factory=lambda: [70, 110]
    )
    # Of these ids, only frames of this length (and first byte) are monitored; the others never
    # reach the monitor (exolink.canbus.filters: the kernel drops them on SocketCAN). E.g.
    # [{id: 70, dlc: 6, first_byte: [1]}]: motor 1's set-points only, not the other joints' nor
    # MACCEPA board 0's status on the same id (a third of the frames with the gait on 4 joints).
    only: list[Only] = []

    def __post_init__(self) -> None:
        named = [o.id for o in self.only]
        if stray := sorted(set(named) - set(self.ids)):
            raise ValueError(f"only names ids {stray} that are not in ids {self.ids}")
        if len(set(named)) != len(named):
            raise ValueError(f"only names an id twice ({named})")
        if len(named) > MAX_ONLY:
            raise ValueError(f"only: at most {MAX_ONLY} ids")

    def only_for(self, fid: int) -> Only | None:
        return next((o for o in self.only if o.id == fid), None)

    def drops(self) -> list[Drop]:
        """``only`` as content filters: every other length of each id, and (with
        ``first_byte``) that length's other first bytes."""
        rules = []
        for o in self.only:
            rules += [Drop(o.id, n) for n in range(9) if n != o.dlc]
            if o.first_byte:
                rules.append(Drop(o.id, o.dlc, 0, frozenset(o.first_byte)))
        return rules


class TimingMonitor(Node):
    Params = TimingParams
    stall_s = 1.0  # the loop beats every READ_EVERY_S

    def configure(self) -> None:
        # one wake per READ_EVERY_S, not one per frame (see READ_EVERY_S)
        self.reader = self.own(
            open_reader(
                self.ctx.config.can,
                self.params.ids,
                every_s=READ_EVERY_S,
                rcvbuf=RCVBUF_BYTES,
                drop=self.params.drops(),
            )
        )
        self.bus = self.reader.bus
        self.lock = threading.Lock()
        self.stamps = {fid: StampRing() for fid in self.params.ids}
        self.own(self.ctx.messaging.serve("timing", self.on_query))

    def _key_stamps(self, fid: int, dlc: int | None, byte0: int | None) -> list[float]:
        with self.lock:
            ring = self.stamps[fid].copy()
        return ring.select(dlc, byte0)

    def on_query(self, req: dict[str, Any]) -> TimingStats:
        ask = management.convert(req, management.Timing, "timing query")
        fid, byte0, dlc = ask.id, ask.byte0, ask.dlc
        if fid not in self.params.ids:
            raise Refused(f"id {fid!r} is not monitored (params.ids: {self.params.ids})")
        only = self.params.only_for(fid)
        if only is not None and (
            (dlc is not None and dlc != only.dlc)
            or (byte0 is not None and only.first_byte and byte0 not in only.first_byte)
        ):
            raise Refused(
                f"id {fid} is monitored only for dlc {only.dlc}"
                + (f" and first byte {only.first_byte}" if only.first_byte else "")
                + " (params.only)"
            )
        seconds = ask.seconds
        if not 0 <= seconds <= 600:
            raise Refused("seconds must be 0..600")
        since = time.time() - (seconds if ask.past else 0.0)
        until = since + seconds
        if seconds:  # the window's last frames read by the loop (its next wake) before selecting
            time.sleep(max(0.0, until - time.time()) + READ_EVERY_S + 0.05)
        stamps = [
            t for t in self._key_stamps(fid, dlc, byte0) if not seconds or since <= t <= until
        ]
        exp = ask.expected_ms
        out = deviation_stats(stamps, None if exp is None else exp / 1000)
        # Frames the kernel dropped from this monitor's full queue since it started: a record
        # with holes shows gaps that were never on the bus.
        return TimingStats(**out, socket_dropped=self.reader.dropped)

    def loop(self) -> Frames:
        return Frames(self.reader, self.keep, READ_EVERY_S)

    def keep(self, frames: list[Frame]) -> None:
        """A read's frames into their ids' rings, under the lock the queries take."""
        with self.lock:
            for msg in frames:
                ring = self.stamps.get(msg.arbitration_id)
                if ring is not None:  # the kernel filter lets only these through
                    ring.add(msg.timestamp, msg.data)
