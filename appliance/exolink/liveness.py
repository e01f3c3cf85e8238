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

Leased: a motion node whose set-points go out on a lease the kernel ends by itself (the controller
manager's broadcast-manager op, renewed before each beat) says so, and is then held to its
``leased_deadline_ms`` (config): a hang then stops the motion at the lease's end, not at the
watchdog's word, so the watchdog need not judge it as tightly as a loop that writes every cycle.
The node checks at start that its lease ends within that deadline (+ hung detection's budget).

The deadline itself is a kernel timer: with each beat the node also sets a timerfd, shared with
the supervisor at spawn, to expire at that beat's time plus its deadline (``EXOLINK_LIVENESS_TIMER_FD``,
deadlines in ``EXOLINK_LIVENESS_DEADLINES``). The supervisor waits on the timers and wakes only
when one expires, then judges the node by the beats in its pipe as before. Polling each node's
deadline wakes it many times a second (the controller manager's 50 ms), each wake a cost on
the one core (measured: docs/performance.md); a re-arm costs the node one system call and wakes
nobody.
"""

from __future__ import annotations

import contextlib
import enum
import os
import select
import struct
import sys
import time
from collections.abc import Iterable
from typing import NamedTuple

ENV = "EXOLINK_LIVENESS_FD"
TIMER_ENV = "EXOLINK_LIVENESS_TIMER_FD"
DEADLINES_ENV = "EXOLINK_LIVENESS_DEADLINES"  # "<own s>,<idle s>,<leased s>"
_RECORD = struct.Struct("=dB")
MIN_INTERVAL_S = 0.01  # a loop beating faster than this writes once per interval
REARM_AHEAD = 0.6  # of a deadline: a timer set at least this far ahead is not re-set (Beater.beat)


class _Timers:
    """timerfd on CLOCK_MONOTONIC, non-blocking: ``os.timerfd_*`` (Python 3.13, the board's), else
    libc's through ctypes (3.11 and 3.12)."""

    def __init__(self) -> None:
        if sys.version_info < (3, 13):  # (a version check, which a type checker follows)
            import ctypes
            import ctypes.util

            class TimeSpec(ctypes.Structure):
                _fields_ = (("sec", ctypes.c_long), ("nsec", ctypes.c_long))

            class ITimerSpec(ctypes.Structure):
                _fields_ = (("interval", TimeSpec), ("value", TimeSpec))

            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            self._spec = ITimerSpec
            self._create, self._set, self._get = (
                libc.timerfd_create,
                libc.timerfd_settime,
                libc.timerfd_gettime,
            )
            self._ctypes = ctypes

    def _check(self, rc: int) -> int:
        """libc's return code, or the OSError its errno names."""
        if rc < 0:
            err = self._ctypes.get_errno()
            raise OSError(err, os.strerror(err))
        return int(rc)

    def create(self) -> int:
        flags = os.O_NONBLOCK | os.O_CLOEXEC  # TFD_NONBLOCK, TFD_CLOEXEC
        if sys.version_info >= (3, 13):
            return os.timerfd_create(time.CLOCK_MONOTONIC, flags=flags)
        return self._check(self._create(time.CLOCK_MONOTONIC, flags))

    def arm_at(self, fd: int, t: float) -> None:
        """Expire once at monotonic time ``t`` (> 0)."""
        if sys.version_info >= (3, 13):
            os.timerfd_settime(fd, flags=_TFD_TIMER_ABSTIME, initial=t)
            return
        spec = self._spec()
        spec.value.sec, spec.value.nsec = int(t), int((t % 1) * 1e9)
        self._check(self._set(fd, _TFD_TIMER_ABSTIME, self._ctypes.byref(spec), None))

    def remaining(self, fd: int) -> float:
        """Seconds until it expires (0: not set, or run out)."""
        if sys.version_info >= (3, 13):
            return float(os.timerfd_gettime(fd)[0])
        spec = self._spec()
        self._check(self._get(fd, self._ctypes.byref(spec)))
        return spec.value.sec + spec.value.nsec / 1e9


_TFD_TIMER_ABSTIME = 1
TIMER_SLACK_S = 0.001  # the node adds its deadline to its beat's time in floating point
TIMERS = _Timers()


class Pace(enum.IntEnum):
    """How a beat asks to be judged: by the node's own deadline, as idle (the appliance's
    default), or as leased (``leased_deadline_ms``). The byte after the beat's time."""

    OWN = 0
    IDLE = 1
    LEASED = 2

    @classmethod
    def of(cls, raw: int) -> Pace:
        """A byte from the pipe; one no version wrote is judged by the node's own deadline
        (the strictest), never a longer one."""
        try:
            return cls(raw)
        except ValueError:
            return cls.OWN


class Beat(NamedTuple):
    t: float  # the node's CLOCK_MONOTONIC time of the beat
    pace: Pace  # the deadline it is judged by (``Pace``)


class Channel:
    """The supervisor's end for one spawn of one node: the pipe's read end and the deadline
    timer (the child gets the pipe's write end, ``child_fd``, and the same timer)."""

    def __init__(self) -> None:
        self._r, self.child_fd = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._tail = b""
        try:
            self.timer = TIMERS.create()
        except OSError:
            self.close()
            raise

    def fileno(self) -> int:
        return self._r

    def spawned(self) -> None:
        """After the child has its copy: the parent must not hold the write end open."""
        os.close(self.child_fd)
        self.child_fd = -1

    def expired(self) -> bool:
        """The timer ran out since the last look (the node missed the deadline of its last
        beat, or was preempted between that beat and setting its timer)."""
        try:
            return len(os.read(self.timer, 8)) == 8
        except (BlockingIOError, OSError):
            return False

    def armed(self, longest_s: float) -> bool:
        """The node set its timer, no further ahead than ``longest_s`` (its longest deadline),
        and it has not run out; else the supervisor polls. The timer is set by the node's own
        process, like its beats, whose times are never taken from the future either: one set
        too far (a bug) must not put off the node's judgment to the next sweep."""
        try:
            return 0 < TIMERS.remaining(self.timer) <= longest_s + TIMER_SLACK_S
        except OSError:
            return False

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
        t, pace = _RECORD.unpack_from(data, whole - _RECORD.size)
        return Beat(min(t, now), Pace.of(pace))

    def close(self) -> None:
        for fd in (self._r, self.child_fd, getattr(self, "timer", -1)):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._r = self.child_fd = self.timer = -1


def with_beats(channels: Iterable[Channel]) -> set[Channel]:
    """The channels holding unread beats: one select per supervisor tick, not a read per node.

    A node is started or stopped by a management command on another thread, which closes its
    old channel: one closed between the list and the select made select fail with EBADF, and
    that crashes the supervisor. The select is then retried on the channels still open."""
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
    """The node's end. Without a supervisor (a node run by hand, a test) it does nothing.
    ``timer_fd``: the deadline timer, and ``deadlines`` (s) its beats set it by, by ``Pace``
    (own, idle, leased; leased missing: own)."""

    def __init__(
        self, fd: int | None, timer_fd: int | None = None, deadlines: tuple[float, ...] = ()
    ) -> None:
        self.fd = fd
        self.timer_fd = timer_fd if deadlines else None
        self.deadlines = deadlines + deadlines[:1] * (len(Pace) - len(deadlines))
        self._last = 0.0
        self._armed_until = 0.0  # when the deadline timer runs out, as last set
        self.pace = Pace.OWN  # what the loop's last beat said (the heartbeat thread repeats it)

    @classmethod
    def from_env(cls) -> Beater:
        raw = os.environ.pop(ENV, None)  # not inherited further (a child of the node)
        raw_timer = os.environ.pop(TIMER_ENV, None)
        raw_deadlines = os.environ.pop(DEADLINES_ENV, None)
        if raw is None:
            return cls(None)
        fd = int(raw)
        os.set_blocking(fd, False)
        os.set_inheritable(fd, False)
        if raw_timer is None or raw_deadlines is None:
            return cls(fd)
        timer_fd = int(raw_timer)
        os.set_inheritable(timer_fd, False)
        return cls(fd, timer_fd, tuple(float(x) for x in raw_deadlines.split(",")))

    def beat(self, now: float | None = None, pace: Pace | None = None) -> None:
        """``pace`` None: as the last beat said. A change is written at once (the end of idle,
        or of a lease, must reach the supervisor before the node drives anything by its own
        deadline)."""
        changed = pace is not None and pace != self.pace
        if pace is not None:
            self.pace = pace
        if self.fd is None:
            return
        t = time.monotonic() if now is None else now
        if t - self._last < MIN_INTERVAL_S and not changed:
            return
        self._last = t
        # A full pipe (supervisor stalled) or a gone one (supervisor dead): nothing to do here.
        with contextlib.suppress(BlockingIOError, BrokenPipeError, OSError):
            os.write(self.fd, _RECORD.pack(t, self.pace))
        if self.timer_fd is not None:  # after the record: when it runs out, the pipe says why
            fd, deadline = self.timer_fd, self.deadlines[self.pace]
            expiry = t + deadline
            # A timer still set at least REARM_AHEAD of a deadline ahead, and not later than
            # this beat's, is left as it is: it can only run out early, never late, and the
            # supervisor, finding this later beat in the pipe then, judges it by its own
            # deadline (exolink.supervisor.judging.NodeJudge._due). One system call in two saved on a loop
            # that beats more than twice per deadline (the controller manager's 20 ms).
            if expiry < self._armed_until or self._armed_until - t < REARM_AHEAD * deadline:
                with contextlib.suppress(OSError):  # the supervisor polls a timer not set
                    TIMERS.arm_at(fd, expiry)
                    self._armed_until = expiry
