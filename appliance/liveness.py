"""Proof of life that only the node's own process can give: a pipe from each node to the
supervisor, created at spawn, never the network.

Anyone who reaches the Zenoh port can publish on a heartbeat key, so a Zenoh heartbeat proves
nothing (a forged one kept a SIGSTOPped node "running" and the watchdog armed). The write end of
this pipe exists only in the node process (inherited at spawn, its number in ``EXOLINK_LIVENESS_FD``).
Each beat is the node's CLOCK_MONOTONIC time and an idle flag (9 bytes): one write below
PIPE_BUF, atomic, so the supervisor reads whole records and knows when the node last beat, not
when it got round to reading. The supervisor drains every pipe on its periodic tick: a beat
costs the node one non-blocking write and wakes nobody.

Idle: a motion node with nothing to drive (the controller manager with no active controller)
says so, and is then held to the appliance's default deadline instead of its own short one, so
it need not wake 50 times a second to prove it could move nothing. Its first beat that is not
idle comes before it drives anything, and from then on its own deadline holds again.
"""

from __future__ import annotations

import contextlib
import os
import select
import struct
import time
from collections.abc import Iterable
from typing import NamedTuple

ENV = "EXOLINK_LIVENESS_FD"
_RECORD = struct.Struct("=d?")
MIN_INTERVAL_S = 0.01  # a loop beating faster than this writes once per interval


class Beat(NamedTuple):
    t: float  # the node's CLOCK_MONOTONIC time of the beat
    idle: bool  # nothing to drive: judged by the appliance's default deadline


class Channel:
    """The supervisor's end for one spawn of one node."""

    def __init__(self) -> None:
        self._r, self.child_fd = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._tail = b""

    def fileno(self) -> int:
        return self._r

    def spawned(self) -> None:
        """After the child has its copy: the parent must not hold the write end open."""
        os.close(self.child_fd)
        self.child_fd = -1

    def drain(self, now: float) -> Beat | None:
        """The newest beat since the last drain (None: no beat), its time never in the future."""
        data = self._tail
        with contextlib.suppress(BlockingIOError, OSError):
            while chunk := os.read(self._r, 65536):
                data += chunk
                if len(chunk) < 65536:
                    break
        whole = len(data) - len(data) % _RECORD.size
        self._tail = data[whole:]
        if not whole:
            return None
        t, idle = _RECORD.unpack_from(data, whole - _RECORD.size)
        return Beat(min(t, now), idle)

    def close(self) -> None:
        for fd in (self._r, self.child_fd):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._r = self.child_fd = -1


def with_beats(channels: Iterable[Channel]) -> set[Channel]:
    """The channels holding unread beats: one select per supervisor tick, not a read per node.

    A node is started or stopped by a management command on another thread, which closes its
    old channel: one closed between the list and the select made select fail with EBADF, and
    that crashed the supervisor (seen on the board proxy when a node stopped). The select is
    then retried on the channels still open."""
    channels = list(channels)
    for _ in range(3):
        live = {fd: c for c in channels if (fd := c.fileno()) >= 0}
        if not live:
            return set()
        try:
            ready = select.select(list(live), (), (), 0)[0]
        except (OSError, ValueError):  # closed meanwhile: look again
            continue
        return {live[fd] for fd in ready}
    return set()  # no beats this tick: the next one reads them


class Beater:
    """The node's end. Without a supervisor (a node run by hand, a test) it does nothing."""

    def __init__(self, fd: int | None) -> None:
        self.fd = fd
        self._last = 0.0
        self.idle = False  # what the loop's last beat said (the heartbeat thread repeats it)

    @classmethod
    def from_env(cls) -> Beater:
        raw = os.environ.pop(ENV, None)  # not inherited further (a child of the node)
        if raw is None:
            return cls(None)
        fd = int(raw)
        os.set_blocking(fd, False)
        os.set_inheritable(fd, False)
        return cls(fd)

    def beat(self, now: float | None = None, idle: bool | None = None) -> None:
        """``idle`` None: as the last beat said. A change is written at once (the end of idle
        must reach the supervisor before the node drives anything)."""
        changed = idle is not None and idle != self.idle
        if changed:
            self.idle = bool(idle)
        if self.fd is None:
            return
        t = time.monotonic() if now is None else now
        if t - self._last < MIN_INTERVAL_S and not changed:
            return
        self._last = t
        # A full pipe (supervisor stalled) or a gone one (supervisor dead): nothing to do here.
        with contextlib.suppress(BlockingIOError, BrokenPipeError, OSError):
            os.write(self.fd, _RECORD.pack(t, self.idle))
