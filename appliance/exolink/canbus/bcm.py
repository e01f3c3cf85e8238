"""The kernel's CAN broadcast manager (can-bcm) watching an id: silence judged by a kernel timer
and content compared in the kernel, not by a Python read of every frame.

The watchdog must know within ``pulse_silence_ms`` that the H2 stopped. Reading each angle frame
(100/s) in Python for that was most of the watchdog's CPU on the board (docs/performance.md,
"Measurements behind the code"). An ``RX_SETUP`` with a receive timeout does
the same in the kernel: every frame of the id restarts an hrtimer, and user space hears only
of changes:

- the first frame, and the first after each silence (``RX_ANNOUNCE_RESUME``): ``RX_CHANGED``
  with the frame and its kernel receive time;
- a frame whose length differs from the last one's (``RX_CHECK_DLC``; the content mask is all
  zero, so content never counts): ``RX_CHANGED``, so a malformed frame is seen even though the
  kernel's timer takes any length as life;
- no frame for the timeout: one ``RX_TIMEOUT``.

While the H2 streams well-formed frames nothing reaches this process at all. Without a timeout
(``timeout_s`` 0) an op only compares: the watchdog's op on id 70 has the mode byte in its mask,
so a joint-control frame reaches it when the mode (or the length) differs from the last frame's:
the first motion frame after a disable, never the MACCEPA board 0 traffic that shares the id.
SocketCAN only:
the simulated bus (exolink_sim) has no broadcast manager, and there the watchdog reads every
frame as before. ``struct bcm_msg_head`` per linux/can/bcm.h; its timevals are C longs (4 bytes
on the A8, 8 on x86-64), hence the native struct format, padded to the 8-byte alignment of the
CAN frame that follows.
"""

from __future__ import annotations

import os
import socket
import struct
import time
from typing import TYPE_CHECKING, NamedTuple

from exolink.canbus.frames import CAN_FRAME, Frame
from exolink.canbus.opening import CanOpenError
from exolink.canbus.sockets import SO_TIMESTAMPNS

if TYPE_CHECKING:
    pass

_HEAD_FMT = "@3I4l2I"
# struct bcm_msg_head, padded to the CAN frame that follows (both ops speak it)
HEAD = struct.Struct(_HEAD_FMT + "x" * (-struct.calcsize(_HEAD_FMT) % 8))
_TIMESPEC = struct.Struct("@ll")
_CAN_EFF_FLAG, _CAN_RTR_FLAG, _CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
_ANC = socket.CMSG_SPACE(_TIMESPEC.size)
_FULL = HEAD.size + CAN_FRAME.size
_TIMER = socket.CAN_BCM_SETTIMER | socket.CAN_BCM_STARTTIMER | socket.CAN_BCM_RX_ANNOUNCE_RESUME


class Event(NamedTuple):
    """A notification: a frame (the first, the first after a silence, or one whose length
    changed), or ``frame`` None: the timeout passed without a frame. ``at``: wall time (the
    frame's kernel receive time; for a timeout, when it was read)."""

    at: float
    frame: Frame | None


def open_bcm(channel: str) -> socket.socket:
    """A broadcast-manager socket connected to ``channel`` (CanOpenError if refused)."""
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_DGRAM, socket.CAN_BCM)
    except OSError as exc:
        raise CanOpenError(f"cannot open a CAN broadcast-manager socket: {exc}") from exc
    try:
        sock.connect((channel,))
    except OSError as exc:
        sock.close()
        raise CanOpenError(f"cannot reach {channel} for the broadcast manager: {exc}") from exc
    return sock


def tx_delete(sock: socket.socket, can_id: int) -> bool:
    """TX_DELETE of ``can_id``'s send op on ``sock``: whether there was one (never raises)."""
    try:
        sock.send(HEAD.pack(socket.CAN_BCM_TX_DELETE, 0, 0, 0, 0, 0, 0, can_id, 0))
    except OSError:  # EINVAL: no op on that id; EBADF: closed meanwhile
        return False
    return True


# the broadcast manager's entry per socket, named by the socket's inode (net/can/bcm.c)
PROC_DIR = "/proc/self/net/can-bcm"


class SentCounts:
    """The broadcast manager's own count of the frames each send op of a socket put on the bus:
    ``frames_abs``, in the socket's proc entry (a line ``tx_op: 046 can0 [36] t1=4887 # sent
    1234`` per op, unchanged since the broadcast manager's first kernels).

    It counts from the op's creation and no setup resets it, so unlike the op's ``count`` it
    loses nothing when the timer sends between a read and a setup. Only the kernel writes it:
    no frame on the bus, whoever sent it, moves it (the op's echoes read back on a raw socket
    could be forged by any sender of the id). A frame the link refused (a full transmit queue)
    is not counted, though the op's index moved on: the count is never ahead of the bus.
    One descriptor for the socket's life, read again from offset 0: one system call a read."""

    def __init__(self, sock: socket.socket) -> None:
        path = f"{PROC_DIR}/{os.fstat(sock.fileno()).st_ino}"
        try:
            self._fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        except OSError as exc:
            raise CanOpenError(
                f"cannot read the broadcast manager's frame counts at {path}: {exc}"
            ) from exc

    def sent(self, can_id: int) -> int | None:
        """Frames ``can_id``'s send op put on the bus since it was created; None: no such op
        (never set up, or deleted), or the entry unreadable."""
        try:
            text = os.pread(self._fd, 4096, 0)
        except OSError:
            return None
        at = text.find(b"tx_op: %03X " % can_id)
        if at < 0:
            return None
        end = text.find(b"\n", at)
        tail = text[at : end if end >= 0 else None].rpartition(b"# sent ")[2]
        return int(tail) if tail.isdigit() else None

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


class CyclicWatch:
    """One broadcast-manager receive op on ``channel``: ``can_id`` expected at least every
    ``timeout_s`` (0: no timer), frames reported when their length or the bits of ``mask``
    differ from the last reported one's. ``fileno`` is readable when a notification waits;
    ``poll`` takes them all."""

    def __init__(
        self, channel: str, can_id: int, timeout_s: float = 0.0, mask: bytes = bytes(8)
    ) -> None:
        if not 0 <= timeout_s < 60:
            raise ValueError(f"broadcast-manager timeout must be in [0, 60) s, got {timeout_s}")
        if len(mask) != 8:
            raise ValueError(f"broadcast-manager mask must be 8 bytes, got {len(mask)}")
        try:
            self._sock = socket.socket(socket.AF_CAN, socket.SOCK_DGRAM, socket.CAN_BCM)
        except OSError as exc:
            raise CanOpenError(f"cannot open a CAN broadcast-manager socket: {exc}") from exc
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self._sock.connect((channel,))
            self._sock.setblocking(False)
            sec, usec = int(timeout_s), round((timeout_s % 1) * 1e6)
            flags = socket.CAN_BCM_RX_CHECK_DLC | (_TIMER if timeout_s else 0)
            head = HEAD.pack(socket.CAN_BCM_RX_SETUP, flags, 0, sec, usec, 0, 0, can_id, 1)
            self._sock.send(head + CAN_FRAME.pack(can_id, 8, mask))
        except OSError as exc:
            self._sock.close()
            raise CanOpenError(
                f"cannot set up the CAN broadcast manager on {channel} for id {can_id}: {exc} "
                "(is the can-bcm module available? `modprobe can-bcm`)"
            ) from exc

    def fileno(self) -> int:
        return self._sock.fileno()

    def poll(self) -> list[Event]:
        """Every notification queued now, in order; never blocks."""
        out: list[Event] = []
        while True:
            try:
                data, anc, _flags, _addr = self._sock.recvmsg(_FULL, _ANC)
            except BlockingIOError:
                return out
            if len(data) < HEAD.size:
                continue
            head = HEAD.unpack_from(data)
            opcode, nframes = head[0], head[-1]
            if opcode == socket.CAN_BCM_RX_TIMEOUT:
                out.append(Event(time.time(), None))
            elif opcode == socket.CAN_BCM_RX_CHANGED and nframes and len(data) >= _FULL:
                out.append(self._changed(data, anc))

    def _changed(self, data: bytes, anc: list[tuple[int, int, bytes]]) -> Event:
        raw_id, length, payload = CAN_FRAME.unpack_from(data, HEAD.size)
        at = time.time()
        for level, kind, value in anc:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(value) >= 8:
                sec, ns = _TIMESPEC.unpack_from(value)
                if sec:  # 0: the kernel had no receive time for it
                    at = sec + ns * 1e-9
        frame = Frame(
            at,
            raw_id & 0x1FFFFFFF if raw_id & _CAN_EFF_FLAG else raw_id & 0x7FF,
            payload[: min(length, 8)],
            bool(raw_id & _CAN_EFF_FLAG),
            bool(raw_id & _CAN_RTR_FLAG),
            bool(raw_id & _CAN_ERR_FLAG),
        )
        return Event(at, frame)

    def close(self) -> None:
        """Closing the socket deletes its receive op in the kernel."""
        self._sock.close()

    def __enter__(self) -> CyclicWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
