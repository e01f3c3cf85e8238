"""Recordings over the network, the laptop's side: ``fetch`` (chunked, resumable, checked against
the board's sha256) and ``missing`` (what ``exolink record sync`` fetches), over any way of
asking the board's store (``Ask``: the CLI's session, the dashboard's, a benchmark's). The
board's side is exolink.recordings.store; what it answers, exolink.recordings.replies."""

from __future__ import annotations

import base64
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import msgspec

from exolink.recordings import requests as reqs
from exolink.recordings.replies import Chunk, FileEntry, FileStat, read
from exolink.recordings.store import (
    CLOSED,
    DEFAULT_CHUNK,
    MAX_CHUNK,
    PART,
    StoreError,
    file_sha256,
    plain_name,
)
from exolink.refusal import Refused
from exolink.wire.requests import body

R = TypeVar("R", bound=msgspec.Struct)
Ask = Callable[[dict[str, Any]], dict[str, Any]]  # one request to the board's store, its reply
# Tries of one request: the board's admission refuses a fast fetch now and then ("too many
# requests", "busy"), and the router drops a reply it cannot send at once rather than block
# (messaging.ROUTER_QOS): a large chunk's reply is sometimes lost and its query times out.
# Each chunk is asked for by offset, so asking again is all a retry is.
TRIES = 8
RETRY_S = 0.2


@dataclass
class Patient:
    """``send`` (one request, the reply as it came, ``messaging.Unreachable`` on a timeout)
    made patient: refusals for the board's load and lost replies are tried again, counted;
    any other refusal raises ``Refused``."""

    send: Callable[[dict[str, Any]], dict[str, Any]]
    tries: int = TRIES
    retried_rate: int = 0
    retried_lost: int = 0

    def __call__(self, body: dict[str, Any]) -> dict[str, Any]:
        from exolink.messaging import (
            Unreachable,  # heavy: Zenoh; a laptop's store needs it for fetches only
        )

        why = "no try"
        for _ in range(self.tries):
            try:
                reply = self.send(body)
            except Unreachable as exc:
                self.retried_lost += 1
                why = str(exc)
                continue
            if reply.get("ok"):
                return reply
            why = str(reply.get("error", "refused"))
            if not why.startswith(("too many requests", "busy")):
                raise Refused(why)
            self.retried_rate += 1
            time.sleep(RETRY_S)
        raise Refused(f"{self.tries} tries, the last: {why}")


@dataclass(frozen=True, slots=True)
class Fetched:
    name: str
    path: Path
    size: int
    sha256: str
    resumed_at: int  # bytes already in the .part file when this fetch began
    seconds: float
    skipped: bool = False  # already there, same size and checksum


def fetch(
    ask: Ask,
    name: str,
    dest: Path,
    chunk: int = DEFAULT_CHUNK,
    hash_wait_s: float = 60.0,
    progress: Callable[[int, int], None] | None = None,
) -> Fetched:
    """Copy one closed recording into ``dest``: chunks appended to ``<name>.part`` (resumed
    from its size), the whole checked against the board's sha256, renamed at the end. A
    mismatch removes the .part (it cannot be trusted for a resume either) and says so."""
    name = plain_name(name)
    chunk = max(1, min(chunk, MAX_CHUNK))
    t0 = time.monotonic()
    st = _stat(ask, name)
    size = st.size
    final, part = dest / name, dest / (name + PART)
    if final.is_file() and final.stat().st_size == size:
        digest = _wait_sum(ask, name, st, hash_wait_s)
        if _local_sha256(final) == digest:
            return Fetched(name, final, size, digest, size, 0.0, skipped=True)
    have = part.stat().st_size if part.is_file() else 0
    if have > size:  # not a prefix of this file
        have = 0
    resumed = have
    with part.open("r+b" if have else "wb") as out:
        out.truncate(have)
        out.seek(have)
        while have < size:
            r = _read(ask(body(reqs.Fetch(name, have, min(chunk, size - have)))), Chunk)
            if r.size != size or r.offset != have:
                raise StoreError(f"{name} changed on the board during the fetch; fetch it again")
            data = base64.b64decode(r.data, validate=True)
            if not data:
                raise StoreError(f"{name}: the board sent nothing at byte {have} of {size}")
            out.write(data)
            have += len(data)
            if progress is not None:
                progress(have, size)
        out.flush()
        os.fsync(out.fileno())
    digest = _wait_sum(ask, name, st, hash_wait_s)
    got = _local_sha256(part)
    if got != digest:
        part.unlink()
        raise StoreError(
            f"{name}: sha256 {got} here, {digest} on the board; the partial copy is removed, "
            "fetch it again"
        )
    os.replace(part, final)
    return Fetched(name, final, size, digest, resumed, time.monotonic() - t0)


def _read(reply: dict[str, Any], cls: type[R]) -> R:
    """A reply as ``cls``, or StoreError (the board said something that is not one)."""
    try:
        return read(reply, cls)
    except ValueError as exc:
        raise StoreError(str(exc)) from None


def _stat(ask: Ask, name: str) -> FileStat:
    return _read(ask(body(reqs.Stat(name))), FileStat)


def _wait_sum(ask: Ask, name: str, st: FileStat, wait_s: float) -> str:
    """The board's sha256 of the file (it computes it once, on first ``stat``, paced): waited
    for while its hashing moves on, given up after ``wait_s`` without progress."""
    deadline, hashed = time.monotonic() + wait_s, None  # the board's bytes hashed so far
    while st.sha256 is None:
        now = time.monotonic()
        if st.hashed != hashed:
            deadline, hashed = now + wait_s, st.hashed
        if now > deadline:
            raise StoreError(f"{name}: the board's sha256 made no progress in {wait_s:g} s")
        time.sleep(0.5)
        st = _stat(ask, name)
    digest = st.sha256
    if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
        raise StoreError(f"{name}: the board's sha256 {digest[:80]!r} is not one")
    return digest


def _local_sha256(path: Path) -> str:
    with path.open("rb") as f:
        return file_sha256(f)


def missing(listing: list[FileEntry], dest: Path) -> list[str]:
    """The board's closed recordings that ``dest`` lacks (no file of the same size): what
    ``exolink record sync`` fetches. Names the board sent that are not plain are skipped."""
    out = []
    for e in listing:
        try:
            name = plain_name(e.name)
        except StoreError:
            continue
        if e.state != CLOSED:
            continue
        local = dest / name
        if not (local.is_file() and local.stat().st_size == e.size):
            out.append(name)
    return out
