"""Recordings over the network, the board's side (``Store``: list, checksum, chunks, delete, the
card's space); the laptop's is exolink.recordings.fetching.

The recorder serves a ``Store`` (``exolink/<device>/recordings``) because it alone knows which
file it is writing: that file is listed as ``recording`` and refused for fetch and delete. Every
request comes over Zenoh from a login and is untrusted: a name is only ever one the board lists
(a plain regular file directly in the recordings directory, never a symlink, never ``..`` nor a
path), and a chunk is at most ``MAX_CHUNK`` bytes (base64 in JSON: ~1.4 MB, well under the
router's ``messaging.MAX_MESSAGE_BYTES``). Which role may do what is decided where every request
is decided (``roles.RECORDINGS`` through ``messaging.serve``), not here.

A closed file's sha256 is computed once, on a thread of its own (hashlib releases the GIL), and
kept while its size and mtime stay the same: a fetch asks for it (``stat``) before the chunks
and again after them, so the hashing overlaps the transfer and no chunk request pays for it.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import os
import shutil
import stat
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import structlog

from exolink.recordings.replies import Card, Chunk, Deleted, FileEntry, FileStat

SUFFIX = ".mcap"
PART = ".part"
MAX_CHUNK = 1 << 20  # bytes per chunk at most (the reply: base64 in JSON, ~1.4 MB)
# A reply to a laptop must fit the router's transmit queue toward it: Zenoh drops a reply that
# waits there longer than wait_before_drop (messaging.ROUTER_QOS: 50 ms for the rest of a
# fragmented one), and a 1 MiB chunk (1.4 MB of JSON) behind a slow link always did; 64 KiB
# replies pass (docs/performance.md, "Measurements behind the code").
DEFAULT_CHUNK = 1 << 16
MAX_NAME = 255
HASH_BLOCK = 1 << 20
HASH_PACE = 4  # the board hashes this many times faster than it serves a fetch
RECORDING, CLOSED = "recording", "closed"
_log = structlog.get_logger("exolink.recordings.store")


class StoreError(Exception):
    """A request the store refuses; the text reaches the caller verbatim."""


def plain_name(name: object) -> str:
    """``name`` if it can only mean a file directly in one directory; StoreError otherwise.
    Checked on both sides: the board's names are untrusted text on the laptop too."""
    if not isinstance(name, str) or not name:
        raise StoreError("a recording is named by its file name (exolink record list)")
    bad = (
        len(name) > MAX_NAME
        or name in (".", "..")
        or name.startswith(".")
        or any(c in name for c in "/\\\x00")
        or not name.endswith(SUFFIX)
        or not name.isprintable()
    )
    if bad:
        raise StoreError(f"{name[:80]!r} is not a recording's name (exolink record list)")
    return name


class Store:
    """The recordings directory as the network sees it. ``writing()`` names the file the
    recorder has open (or is opening), which is listed but never read nor deleted."""

    def __init__(
        self,
        directory: Path,
        writing: Callable[[], Path | None],
        reserve_bytes: int = 0,
        bytes_per_s: float = 0.0,
    ) -> None:
        self.dir = directory
        self.writing = writing
        self._lock = threading.Lock()
        self._sums: dict[str, tuple[int, int, int, str]] = {}  # name -> (ino, size, mtime, sum)
        self._hashing: dict[str, int] = {}  # name -> bytes hashed so far
        self._one_hash = threading.Lock()  # one file hashed at a time: the card is shared
        # Hashing is paced too (HASH_PACE times the fetches' pace): a 1 GB file at full speed
        # took the board's core for most of a minute, and under the service's CPU quota that
        # throttles every node, motion included.
        self.pace, self.hash_pace = Pace(0.0), Pace(0.0)
        self.set_limits(reserve_bytes, bytes_per_s)

    def set_limits(self, reserve_bytes: int, bytes_per_s: float) -> None:
        """The reserve and the fetches' pace, at the start and at run time (``exolink params``:
        the card is shared, and a lab raises the pace at the end of the day, nothing moving)."""
        self.reserve_bytes = reserve_bytes
        self.pace.bytes_per_s = bytes_per_s
        self.hash_pace.bytes_per_s = bytes_per_s * HASH_PACE

    # --- what is there ---------------------------------------------------------------------

    def _files(self) -> Iterator[tuple[str, os.stat_result]]:
        """Regular files named like recordings, directly in the directory (lstat: a symlink
        is not a file here, whatever it points to)."""
        with os.scandir(self.dir) as it:
            for e in it:
                try:
                    plain_name(e.name)
                    st = e.stat(follow_symlinks=False)
                except (StoreError, OSError):
                    continue
                if stat.S_ISREG(st.st_mode):
                    yield e.name, st

    def _state(self, name: str) -> str:
        w = self.writing()
        return RECORDING if w is not None and w.name == name and w.parent == self.dir else CLOSED

    def _cached(self, name: str, st: os.stat_result) -> str | None:
        with self._lock:
            c = self._sums.get(name)
        return c[3] if c is not None and c[:3] == (st.st_ino, st.st_size, st.st_mtime_ns) else None

    def entries(self) -> list[FileEntry]:
        """Every recording, oldest first; a closed one's sha256 if it was computed."""
        out = []
        for name, st in sorted(self._files(), key=lambda f: (f[1].st_mtime_ns, f[0])):
            state = self._state(name)
            digest = self._cached(name, st) if state == CLOSED else None
            out.append(FileEntry(name, st.st_size, st.st_mtime_ns / 1e9, state, digest))
        return out

    def _closed(self, name: object, what: str) -> tuple[Path, os.stat_result]:
        """The path of a closed recording the board lists, or StoreError saying why not."""
        name = plain_name(name)
        path = self.dir / name
        try:
            st = path.lstat()
        except FileNotFoundError:
            raise StoreError(f"no recording {name!r} on the board (exolink record list)") from None
        if not stat.S_ISREG(st.st_mode):
            raise StoreError(f"{name!r} is not a recording on the board (exolink record list)")
        if self._state(name) == RECORDING:
            raise StoreError(
                f"{name} is still being recorded: {what} it once the recording stops or "
                "moves on to its next file (exolink record stop)"
            )
        return path, st

    # --- requests --------------------------------------------------------------------------

    def stat(self, name: object) -> FileStat:
        """A closed file's size and sha256 (None while it is computed: ask again)."""
        path, st = self._closed(name, "fetch")
        digest = self._cached(path.name, st)
        if digest is None:
            self._hash_later(path.name)
        with self._lock:
            hashed = st.st_size if digest is not None else self._hashing.get(path.name, 0)
        return FileStat(path.name, st.st_size, st.st_mtime_ns / 1e9, CLOSED, digest, hashed)

    def chunk(self, name: object, offset: object, length: object) -> Chunk:
        """Up to ``length`` bytes at ``offset`` of a closed file (base64)."""
        path, st = self._closed(name, "fetch")
        if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0:
            raise StoreError("offset must be a whole number of bytes >= 0")
        if not isinstance(length, int) or isinstance(length, bool) or not 0 < length <= MAX_CHUNK:
            raise StoreError(f"length must be 1..{MAX_CHUNK} bytes")
        if offset > st.st_size:
            raise StoreError(f"offset {offset} is past the end of {path.name} ({st.st_size} bytes)")
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        try:
            data = os.pread(fd, length, offset)
            # The card is shared with the recorder: what a fetch read is not worth caching.
            with contextlib.suppress(AttributeError, OSError):
                os.posix_fadvise(fd, offset, len(data), os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)
        self.pace.wait(len(data))
        return Chunk(path.name, offset, st.st_size, base64.b64encode(data).decode("ascii"))

    def delete(self, name: object) -> Deleted:
        path, st = self._closed(name, "delete")
        path.unlink()
        with self._lock:
            self._sums.pop(path.name, None)
        _log.info("recording_deleted", name=path.name, size=st.st_size)
        return Deleted(path.name, st.st_size)

    # --- checksums -------------------------------------------------------------------------

    def _hash_later(self, name: str) -> None:
        """One thread per file being hashed, at most one per file."""
        with self._lock:
            if name in self._hashing:
                return
            self._hashing[name] = 0
        threading.Thread(target=self._hash, args=(name,), daemon=True, name="rec-sha256").start()

    def _hash(self, name: str) -> None:
        path = self.dir / name
        try:
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
            with os.fdopen(fd, "rb") as f, self._one_hash:
                before = os.fstat(f.fileno())
                digest = file_sha256(f, lambda n: self._hashed(name, n))
                after = os.fstat(f.fileno())
            key = (before.st_ino, before.st_size, before.st_mtime_ns)
            if key == (after.st_ino, after.st_size, after.st_mtime_ns):
                with self._lock:
                    self._sums[name] = (*key, digest)
        except OSError as exc:
            _log.warning("recording_hash_failed", name=name, error=str(exc))
        finally:
            with self._lock:
                self._hashing.pop(name, None)

    def _hashed(self, name: str, n: int) -> None:
        """``n`` more bytes of ``name`` hashed: its progress for ``stat``, and the pace."""
        with self._lock:
            self._hashing[name] = self._hashing.get(name, 0) + n
        self.hash_pace.wait(n)

    # --- the card --------------------------------------------------------------------------

    def card(self) -> Card:
        """The card's size and what a non-root writer may still use, in bytes."""
        u = shutil.disk_usage(self.dir)
        return Card(u.total, u.free, self.reserve_bytes)


class Pace:
    """At most ``bytes_per_s`` handed out on average (0: no limit): a fetch at the link's full
    speed would take the board's one core from the nodes that record and move (reading,
    base64 and JSON of each chunk in the recorder, its transmission in the router). Chunks are
    served one at a time (messaging.Served: one worker per key), so a sleep before a reply
    paces them all; the sleep holds no lock and no GIL, and other keys are answered meanwhile."""

    def __init__(self, bytes_per_s: float) -> None:
        self.bytes_per_s = bytes_per_s
        self._free_at = 0.0

    def wait(self, n: int) -> None:
        if self.bytes_per_s <= 0:
            return
        now = time.monotonic()
        start = max(now, self._free_at)
        self._free_at = start + n / self.bytes_per_s
        if start > now:
            time.sleep(start - now)


def file_sha256(f: Any, progress: Callable[[int], None] | None = None) -> str:
    h = hashlib.sha256()
    while block := f.read(HASH_BLOCK):
        h.update(block)
        if progress is not None:
            progress(len(block))
    return h.hexdigest()


class Rate:
    """Bytes per second the recorder writes, over the last ``window_s``: what ``hours left``
    divides by. Fed the total written so far (closed files and the open one)."""

    def __init__(self, window_s: float = 30.0) -> None:
        self.window_s = window_s
        self._points: list[tuple[float, int]] = []
        self.last = 0.0  # the last rate measured while recording (bytes/s)

    def note(self, written: int, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        pts = self._points
        pts.append((now, written))
        while len(pts) > 2 and now - pts[0][0] > self.window_s:
            pts.pop(0)
        (t0, b0), (t1, b1) = pts[0], pts[-1]
        if t1 - t0 >= 1.0 and b1 >= b0:
            self.last = (b1 - b0) / (t1 - t0)
        return self.last

    def reset(self) -> None:
        self._points.clear()


def hours_left(free: int, reserve: int, rate_bps: float) -> float | None:
    """Hours until the recorder stops for the reserve at ``rate_bps``; None without a rate."""
    if rate_bps <= 0:
        return None
    return max(0, free - reserve) / rate_bps / 3600
