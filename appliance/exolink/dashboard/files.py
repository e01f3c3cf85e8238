"""The dashboard's files: a recording the recorder names, fetched here for a page to download
or plot (its joint angles and trigger edges), and a bundled gait pattern's set-points for the
pattern page's plot. Names come from the network: a recording is asked of the recorder by its
plain name, a pattern is looked up by file name among the bundled ones only."""

from __future__ import annotations

import csv
import math
import os
import threading
from pathlib import Path
from typing import Any

from exolink import messaging
from exolink import nodes as node_plugins
from exolink.client import Remote
from exolink.protocol import h2
from exolink.recordings import fetching
from exolink.recordings import requests as reqs
from exolink.recordings import store as recstore
from exolink.recordings.readback import decode, info, iter_messages
from exolink.recordings.replies import FileStat, read
from exolink.wire.requests import body as request_body


def _cache_dir() -> Path:
    """Where a laptop's dashboard keeps the recordings it fetched for download and plots."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "exolink" / "recordings"


def _patterns_dir() -> Path:
    """The bundled patterns: the pattern page plots a pattern the player names by a file here."""
    return Path(node_plugins.__file__).resolve().parent / "patterns"


class Files:
    """Recordings fetched for pages, one at a time, on the dashboard's login."""

    def __init__(self, remote: Remote) -> None:
        self.remote = remote
        self._fetching = threading.Lock()

    def recording(self, board_path: str) -> Path:
        """A recording the recorder names, as a file here to serve or plot: asked for through
        the recorder's ``recordings`` (this dashboard's login must be allowed to fetch, and the
        file must be closed: roles.RECORDINGS, exolink.recordings.store), then the file itself when it
        is on this machine (the board's own dashboard; the sim), else fetched into a cache
        (chunked, resumed, checked as `exolink record fetch`). Refused and StoreError say
        why not."""
        name = recstore.plain_name(Path(board_path).name)
        ask = fetching.Patient(self._recordings_request)
        st = read(ask(request_body(reqs.Stat(name))), FileStat)
        local = Path(board_path)
        if local.is_file() and local.stat().st_size == st.size:
            return local
        with self._fetching:  # two pages asking for one file must not share its .part
            cache = _cache_dir() / self.remote.device
            cache.mkdir(parents=True, exist_ok=True)
            return fetching.fetch(ask, name, cache).path

    def _recordings_request(self, body: dict[str, Any]) -> dict[str, Any]:
        key = messaging.mgmt_key(self.remote.device, "recordings")
        return messaging.request(self.remote.session, key, body, 5.0, self.remote.user)


def pattern_points(name: str) -> list[list[int]] | None:
    """The set-points of a pattern the player names, when it is one of the bundled files
    (looked up by file name only: a name from the network never opens another file)."""
    base = _patterns_dir()
    path = base / Path(name).name
    if not name or path.suffix != ".csv" or not path.is_file():
        return None
    rows = list(csv.reader(path.read_text(encoding="utf-8-sig").splitlines()))
    header = [c.strip() for c in rows[0]]
    if sorted(header) != sorted(h2.JOINTS):
        return None
    order = [header.index(j) for j in h2.JOINTS]
    return [[int(r[i]) for i in order] for r in rows[1:] if len(r) == 6]


def recording_plot(path: str, max_points: int = 2000) -> dict[str, Any]:
    """A finished recording's joint angles (deg, every n-th message up to max_points) and its
    trigger edges, seconds from the first message: the Recording page's plot."""
    i = info(path)
    topics = [t for t in i.topics if t.endswith("/joint_states") and "/replay/" not in t]
    if not topics:
        return {"t": [], "pos_deg": [], "triggers_s": [], "joints": []}
    step = max(1, i.topics[topics[0]]["count"] // max_points)
    t: list[float] = []
    pos: list[list[float]] = []
    names: list[str] = []
    for n, (schema, _channel, m) in enumerate(iter_messages(path, topics=topics[:1])):
        if n % step:
            continue
        msg = decode(schema, m.data)
        t.append(messaging.stamp_ns(msg.header.stamp) / 1e9)
        pos.append([round(math.degrees(v), 2) for v in msg.position.tolist()])
        names = names or list(msg.name)
    t0 = t[0] if t else 0.0
    return {
        "t": [round(x - t0, 3) for x in t],
        "joints": names,
        "pos_deg": [list(col) for col in zip(*pos, strict=True)] if pos else [],
        "triggers_s": [round(x / 1e9 - t0, 3) for x in i.triggers],
    }
