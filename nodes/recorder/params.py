"""What the recorder is configured with (its node's ``params``) and what it counts in a
recording (``record status``, diagnostics, each file's ``exolink.stats``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

import msgspec


class RecorderParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    directory: str = "/var/lib/exolink/recordings"
    topics: list[str] = msgspec.field(default_factory=lambda: ["**"])  # relative to the namespace
    exclude: list[str] = msgspec.field(
        default_factory=lambda: ["*/nodes/*/heartbeat"]
    )  # fnmatch on topic
    autostart: bool = False  # field trials: record from boot
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size: Annotated[int, msgspec.Meta(ge=4096, le=64 * 2**20)] = 1 * 2**20
    fsync_interval_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 2.0
    split_size_mb: Annotated[float, msgspec.Meta(ge=0)] = 1024.0  # 0 = no split by size
    split_duration_s: Annotated[float, msgspec.Meta(ge=0)] = 3600.0  # 0 = no split by time
    labels: dict[str, str] = msgspec.field(default_factory=dict)
    # Samples each subscription's ring holds while the card pauses: ~90 s of the appliance's
    # data (~220 samples/s). A held sample keeps its share of Zenoh's receive buffer alive:
    # measured 1.5 KB per sample put in fours, 5.4 KB one by one (x86), so 20,000 is <= ~40 MB
    # in practice. What does not fit is counted as dropped.
    inbox: Annotated[int, msgspec.Meta(ge=16, le=1_000_000)] = 20_000
    # Free space the recorder leaves on the card: under it a recording stops (closed, indexed)
    # and none starts. The rest of the board (journal, logs, updates) writes to the same card.
    reserve_mb: Annotated[float, msgspec.Meta(ge=0)] = 256.0
    # What fetches of recordings may take (MB/s, all laptops together; 0 = no limit). Each MB
    # served cost ~8.5 ms of the recorder's CPU and ~1.8 ms of the supervisor's (its router) on
    # x86 (benchmarks/bench_fetch.py; 5 ms of it base64 and JSON): on the board's one core,
    # roughly ten times that, so 1 MB/s keeps a fetch to about a tenth of it while the
    # appliance runs (a 1 GB day syncs in ~17 min; raise it when nothing moves).
    fetch_mb_s: Annotated[float, msgspec.Meta(ge=0)] = 1.0


@dataclass
class Stats:
    received: int = 0
    written: int = 0
    dropped: int = 0
    duplicates: int = 0  # the same message by two ways (a topic's own key and its bundle)
    malformed: int = 0  # bundles that did not decode (skipped)
    refused_topics: int = 0  # graph tokens over a session's or all foreign sessions' budget
    refused_from: dict[str, int] = field(default_factory=dict)  # session zid -> tokens refused
    files: list[str] = field(default_factory=list)
