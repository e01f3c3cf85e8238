"""The board's wall clock: is it right, and how it is made right at a site with no time server.

The BeagleBone has no battery-backed clock. With no time server in reach it boots on whatever
time systemd saved at the last shutdown, and recordings are stamped with it: a trial's files
cannot be lined up with the lab's motion capture or EMG. A laptop that connects has a good clock
(its own time server, or a phone's): it measures the board's offset by asking its time a few
times (the reply with the shortest round trip wins: its error is at most half that round trip)
and, when the board's clock is not synchronised by a time server, steps it.

- The kernel says whether a time server disciplines the clock (``adjtimex``, read only): a
  synchronised clock is never stepped from a laptop.
- A step is refused while the motors are armed (every controller paces by frame stamps and
  monotonic time, but a jump of the wall clock during a gait is not worth its risk), and on an
  appliance whose config says ``clock.from_laptop: false`` (the simulator: its clock is the
  host's).
- The last step is kept in ``state_dir/clock.json`` with the kernel's boot id, so a reboot
  (which loses the step) is told apart from it; the recorder writes what the clock was into each
  file (``exolink.board.clock`` metadata).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from exolink.refusal import Refused
from exolink.wire.replies import ClockStatus, ClockStep

CLOCK_FILE = "clock.json"
# `exolink status` warns when the board is further than this from the laptop (the bound:
# a gait lab's frame at 100-200 Hz is 5-10 ms; 50 ms is what a trigger-aligned trial tolerates).
WARN_OFFSET_S = 0.050
SAMPLES = 5  # time requests per offset measurement: the shortest round trip is kept
MAX_STEP_S = 100 * 365 * 86400.0  # a step further than this is a laptop's error, not a clock's
_TIME_ERROR = 5  # adjtimex's return: the clock is not synchronised (linux/timex.h)
_STA_UNSYNC = 0x0040


class _Timeval(ctypes.Structure):
    _fields_ = [("sec", ctypes.c_long), ("usec", ctypes.c_long)]


class _Timex(ctypes.Structure):
    """``struct timex`` (linux/timex.h): only ``status`` is read; the rest sizes the struct."""

    _fields_ = [
        ("modes", ctypes.c_uint),
        ("offset", ctypes.c_long),
        ("freq", ctypes.c_long),
        ("maxerror", ctypes.c_long),
        ("esterror", ctypes.c_long),
        ("status", ctypes.c_int),
        ("constant", ctypes.c_long),
        ("precision", ctypes.c_long),
        ("tolerance", ctypes.c_long),
        ("time", _Timeval),
        ("tick", ctypes.c_long),
        ("ppsfreq", ctypes.c_long),
        ("jitter", ctypes.c_long),
        ("shift", ctypes.c_int),
        ("stabil", ctypes.c_long),
        ("jitcnt", ctypes.c_long),
        ("calcnt", ctypes.c_long),
        ("errcnt", ctypes.c_long),
        ("stbcnt", ctypes.c_long),
        ("tai", ctypes.c_int),
        ("_pad", ctypes.c_int * 11),
    ]


class ClockRefused(Refused):
    """A step the board will not take; the text says why."""


@dataclass(frozen=True, slots=True)
class Kernel:
    """What the kernel says of its wall clock: ``synchronised`` by a time server (chrony,
    systemd-timesyncd), and its maximum error then (ms; None when unknown)."""

    synchronised: bool
    max_error_ms: float | None


@functools.cache
def _adjtimex() -> Callable[[Any], int]:
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").adjtimex


def kernel() -> Kernel:
    """``adjtimex`` with no mode set: a read, allowed to any process."""
    tx = _Timex()
    rc = _adjtimex()(ctypes.byref(tx))
    if rc < 0:
        return Kernel(False, None)
    synced = rc != _TIME_ERROR and not tx.status & _STA_UNSYNC
    return Kernel(synced, tx.maxerror / 1000 if synced else None)


def boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


@dataclass(frozen=True, slots=True)
class Offset:
    """The board's clock minus the laptop's (s), within +- ``error_s`` (half the round trip)."""

    offset_s: float
    error_s: float

    def off(self) -> bool:
        """Off by more than WARN_OFFSET_S for sure, whatever the round trip hid."""
        return abs(self.offset_s) - self.error_s > WARN_OFFSET_S


def measure(ask: Callable[[], float], samples: int = SAMPLES) -> Offset:
    """``ask`` returns the board's time (its reply); the shortest round trip of ``samples``
    sets the offset, as NTP's clock filter does for one server."""
    best: tuple[float, float] | None = None
    for _ in range(samples):
        t0 = time.time()
        board = ask()
        t1 = time.time()
        if not math.isfinite(board):
            raise ValueError(f"the board's time is not a number: {board!r}")
        rtt = t1 - t0
        if best is None or rtt < best[1]:
            best = (board - (t0 + t1) / 2, rtt)
    assert best is not None
    return Offset(best[0], best[1] / 2)


def source(k: Kernel, step: ClockStep | None) -> str:
    """What set the clock: a time server, a laptop's step in this boot, or nothing."""
    return "time server" if k.synchronised else ("laptop" if step else "unsynchronised")


def unset(status: ClockStatus) -> bool:
    """A board's clock (its ``status()``) that neither a time server nor a laptop has set."""
    return status.source == "unsynchronised"


class BoardClock:
    """The supervisor's side: reports the clock and takes a laptop's step when allowed."""

    def __init__(self, state_dir: Path | None, from_laptop: bool) -> None:
        self.path = state_dir / CLOCK_FILE if state_dir is not None else None
        self.from_laptop = from_laptop

    def last_step(self) -> ClockStep | None:
        """The last laptop step of this boot (a step before a reboot no longer holds; a file
        that is not one is no step)."""
        if self.path is None:
            return None
        try:
            step = msgspec.json.decode(self.path.read_bytes(), type=ClockStep)
        except (OSError, msgspec.DecodeError):
            return None
        return step if step.boot_id == boot_id() else None

    def status(self) -> ClockStatus:
        k, step = kernel(), self.last_step()
        return ClockStatus(
            now=time.time(),
            synchronised=k.synchronised,
            max_error_ms=k.max_error_ms,
            source=source(k, step),
            from_laptop=self.from_laptop,
            last_step=step,
        )

    def step(self, offset_s: Any, error_s: Any, login: str, armed: bool) -> ClockStep:
        """Step the wall clock by minus ``offset_s`` (the board's offset a laptop measured)."""
        for name, v in (("offset_s", offset_s), ("error_s", error_s)):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ClockRefused(f"clock step: {name} must be a finite number of seconds")
        if not abs(offset_s) <= MAX_STEP_S or not 0 <= error_s <= 10:
            raise ClockRefused(
                f"clock step: offset {offset_s:.6g} s +- {error_s:.3g} s is not a clock's error"
            )
        if not self.from_laptop:
            raise ClockRefused(
                "this appliance does not take its time from a laptop (clock.from_laptop: false)"
            )
        if kernel().synchronised:
            raise ClockRefused("the board's clock is synchronised by a time server: not stepped")
        if armed:
            raise ClockRefused("the motors are armed: disarm before the clock is stepped")
        before = time.time()
        time.clock_settime(time.CLOCK_REALTIME, time.time() - offset_s)
        step = ClockStep(
            by=login,
            at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            step_s=round(-offset_s, 6),
            error_ms=round(error_s * 1e3, 3),
            was=round(before, 3),
            boot_id=boot_id(),
        )
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            tmp.write_bytes(msgspec.json.encode(step))
            os.replace(tmp, self.path)
        return step


def recorded(state_dir: str | None) -> dict[str, str]:
    """What a recording says of its clock (MCAP metadata: strings only)."""
    k = kernel()
    step = BoardClock(Path(state_dir) if state_dir else None, False).last_step()
    info = {
        "synchronised": str(k.synchronised).lower(),
        "source": source(k, step),
    }
    if k.max_error_ms is not None:
        info["max_error_ms"] = f"{k.max_error_ms:g}"
    if step and not k.synchronised:
        info.update(
            stepped_by=step.by,
            stepped_at=step.at,
            step_s=str(step.step_s),
            error_ms=str(step.error_ms),
        )
    return info
