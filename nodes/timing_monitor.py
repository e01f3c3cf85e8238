"""CAN timing monitor [thesis: H2patternReceiver]: how far a periodic CAN id strays from its period.

The thesis judged its pattern sender with a second board; this node does the same from any board on
the bus, from the frames' kernel receive timestamps. Frames that share an id (all joint-control
frames are id 70) can be told apart by their first data byte (the motor id).
"""

from __future__ import annotations

import bisect
import collections
import itertools
import statistics
import threading
import time
from typing import Annotated, Any

import msgspec
from exolink.canbus import open_reader
from exolink.messaging import CommandRefused
from exolink.node import Node

HIST_EDGES_US = [0, 10, 20, 50, 100, 200, 500, 1000, 5000]
MAX_STAMPS = 200_000
READ_EVERY_S = 0.05


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


class TimingParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    ids: list[Annotated[int, msgspec.Meta(ge=0, le=0x7FF)]] = msgspec.field(
        default_factory=lambda: [70, 110]
    )


class TimingMonitor(Node):
    Params = TimingParams

    def configure(self) -> None:
        # Deviations come from kernel timestamps, so reading late costs nothing: one wake per
        # READ_EVERY_S instead of one per frame.
        self.reader = open_reader(self.ctx.config.can, self.params.ids, every_s=READ_EVERY_S)
        self.bus = self.reader.bus
        self.lock = threading.Lock()
        self.stamps: dict[tuple[int, int | None, int | None], collections.deque[float]] = {}
        self._q = self.ctx.messaging.serve("timing", self.on_query)

    def _key_stamps(self, fid: int, dlc: int | None, byte0: int | None) -> list[float]:
        with self.lock:
            return list(self.stamps.get((fid, dlc, byte0), ()))

    def on_query(self, req: dict[str, Any]) -> dict[str, Any]:
        fid, byte0, dlc = req.get("id"), req.get("byte0"), req.get("dlc")
        if fid not in self.params.ids:
            raise CommandRefused(f"id {fid!r} is not monitored (params.ids: {self.params.ids})")
        seconds = float(req.get("seconds", 0))
        if not 0 <= seconds <= 600:
            raise CommandRefused("seconds must be 0..600")
        since = time.time()
        if seconds:
            time.sleep(seconds)  # measure fresh frames only
        stamps = [t for t in self._key_stamps(fid, dlc, byte0) if not seconds or t >= since]
        exp = req.get("expected_ms")
        return deviation_stats(stamps, None if exp is None else float(exp) / 1000)

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self.beat()
            for msg in self.reader.read(0.05):
                fid, n = msg.arbitration_id, len(msg.data)
                b0 = msg.data[0] if msg.data else None
                with self.lock:
                    for key in ((fid, None, None), (fid, n, None), (fid, None, b0), (fid, n, b0)):
                        dq = self.stamps.get(key)
                        if dq is None:
                            dq = self.stamps[key] = collections.deque(maxlen=MAX_STAMPS)
                        dq.append(msg.timestamp)

    def shutdown(self) -> None:
        if hasattr(self, "_q"):
            self._q.undeclare()
        if hasattr(self, "bus"):
            self.bus.shutdown()
