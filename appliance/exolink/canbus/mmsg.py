"""recvmmsg and sendmmsg, libc's through ctypes (Python has neither): a batch of datagrams in one
system call, into message headers and buffers allocated once per socket. The headers' layout is
the platform's (armv7 and x86-64 differ), shared by both directions: ``BatchReceiver`` receives
(canbus.reader), ``mmsg_buffers`` and ``sendmmsg`` send (canbus.writer)."""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import functools
import os
import socket
import struct
from typing import Any

from exolink.canbus.sockets import SO_TIMESTAMPNS

_TIMESPEC = struct.Struct("@ll")
BATCH = 64  # frames read per socket and wake-up at most, unless a reader asks for more
MAX_BATCH = 1024


class _IoVec(ctypes.Structure):
    _fields_ = (("base", ctypes.c_void_p), ("len", ctypes.c_size_t))


class _MsgHdr(ctypes.Structure):
    _fields_ = (
        ("name", ctypes.c_void_p),
        ("namelen", ctypes.c_uint32),
        ("iov", ctypes.POINTER(_IoVec)),
        ("iovlen", ctypes.c_size_t),
        ("control", ctypes.c_void_p),
        ("controllen", ctypes.c_size_t),
        ("flags", ctypes.c_int),
    )


class MMsgHdr(ctypes.Structure):
    _fields_ = (("hdr", _MsgHdr), ("len", ctypes.c_uint))


_SIZE_T = struct.Struct("@N")
_CMSG_HDR = struct.Struct("@Nii")  # struct cmsghdr: len, level, type
MSG_SIZE, _CTL_SIZE = 256, socket.CMSG_SPACE(_TIMESPEC.size)


def _entry_formats() -> tuple[str, str]:
    """struct formats (standard sizes, explicit padding) of one mmsghdr as (controllen,
    flags, len) and of one SO_TIMESTAMPNS control message as (len, level, type, sec, nsec),
    for this platform's sizes (armv7: 4-byte size_t and long; x86-64: 8)."""
    st = {4: "I", 8: "Q"}[ctypes.sizeof(ctypes.c_size_t)]
    lg = {4: "i", 8: "q"}[ctypes.sizeof(ctypes.c_long)]
    ssz, lsz = ctypes.sizeof(ctypes.c_size_t), ctypes.sizeof(ctypes.c_long)
    hsize = ctypes.sizeof(MMsgHdr)
    co, fo, lo = _MsgHdr.controllen.offset, _MsgHdr.flags.offset, MMsgHdr.len.offset
    head = f"{co}x{st}{fo - co - ssz}xi{lo - fo - 4}xI{hsize - lo - 4}x"
    data_at = socket.CMSG_LEN(0)
    ctl = f"{st}ii{data_at - ssz - 8}x{lg}{lg}{_CTL_SIZE - data_at - 2 * lsz}x"
    return head, ctl


@functools.cache
def _batch_struct(n: int, entry: str) -> struct.Struct:
    """``n`` entries back to back, one unpack for a whole batch (made once per batch size)."""
    return struct.Struct("=" + entry * n)


def mmsg_buffers(size: int, ctl_size: int, n: int = BATCH) -> tuple[Any, Any, Any, Any]:
    """``n`` message headers for recvmmsg / sendmmsg, each with one ``size``-byte buffer
    (and a ``ctl_size``-byte control buffer, 0: none), allocated once: (data, control, iovecs,
    headers)."""
    data = ctypes.create_string_buffer(n * size)
    ctl = ctypes.create_string_buffer(max(1, n * ctl_size))
    iov, msgs = (_IoVec * n)(), (MMsgHdr * n)()
    for i in range(n):
        iov[i].base = ctypes.addressof(data) + i * size
        iov[i].len = size
        msgs[i].hdr.iov = ctypes.pointer(iov[i])
        msgs[i].hdr.iovlen = 1
        if ctl_size:
            msgs[i].hdr.control = ctypes.addressof(ctl) + i * ctl_size
            msgs[i].hdr.controllen = ctl_size
    return data, ctl, iov, msgs


_HEAD_ENTRY, _CTL_ENTRY = _entry_formats()
_MSG_TRUNC, _SOL_SOCKET = int(socket.MSG_TRUNC), int(socket.SOL_SOCKET)
_STAMP_LEN = _CMSG_HDR.size + _TIMESPEC.size  # a control message that holds a timespec


class BatchReceiver:
    """Every datagram queued on a socket, up to ``batch``, in one ``recvmmsg`` call.

    A ``recvmsg`` per frame costs a system call and a tuple of Python objects per frame; on
    a slow core (qemu TCG in `make bench-board`) the kernel's side of a call is where the time
    goes, so one call per wake-up instead of one per frame (12 frames at the h2 reader's board cadence). Python
    has no ``recvmmsg``: libc's, through ctypes, into buffers allocated once per socket.
    Returns (data, kernel receive time or None) pairs; raises OSError as ``recvmsg`` would."""

    def __init__(self, sock: socket.socket, msg_size: int = MSG_SIZE, batch: int = BATCH) -> None:
        if not 1 <= batch <= MAX_BATCH:
            raise ValueError(f"a receive batch is 1..{MAX_BATCH} datagrams, got {batch}")
        self.fd = sock.fileno()
        self.batch = n = batch
        self.msg_size = msg_size
        self._data, self._ctl, self._iov, self._msgs = mmsg_buffers(msg_size, _CTL_SIZE, n)
        self._addr = ctypes.addressof(self._msgs)
        self._view = memoryview(self._data).cast("B")
        self._ctl_view = memoryview(self._ctl).cast("B")
        size = ctypes.sizeof(MMsgHdr)
        self._hdrs = memoryview((ctypes.c_char * (n * size)).from_address(self._addr)).cast("B")
        self._ctl_len_at = [i * size + _MsgHdr.controllen.offset for i in range(n)]
        self._used = 0  # headers the kernel wrote last time: their controllen to reset

    def _call(self) -> int:
        """recvmmsg into the buffers: how many datagrams came (0: none queued)."""
        hdrs = self._hdrs
        for at in self._ctl_len_at[: self._used]:
            _SIZE_T.pack_into(hdrs, at, _CTL_SIZE)
        n = _recvmmsg(self.fd, self._addr, self.batch, socket.MSG_DONTWAIT, None)
        if n < 0:
            err = ctypes.get_errno()
            self._used = 0
            if err in (errno.EAGAIN, errno.EINTR):
                return 0
            raise OSError(err, os.strerror(err))
        self._used = n
        return int(n)

    def receive(self) -> list[tuple[bytes, float | None]]:
        n = self._call()
        if n == 0:
            return []
        lengths, _flags, stamps = self._headers(n)
        data, size_max = self._view, self.msg_size
        return [
            (bytes(data[i * size_max : i * size_max + min(length, size_max)]), stamps[i])
            for i, length in enumerate(lengths)
        ]

    def receive_fixed(self) -> tuple[int, memoryview, list[bool], list[float | None]]:
        """For datagrams of exactly ``msg_size`` bytes (SocketCAN's can_frame): how many came,
        their bytes back to back (one ``iter_unpack`` parses them all), whether each was whole
        (its length, not truncated), and its kernel time."""
        n = self._call()
        if n == 0:
            return 0, self._view[:0], [], []
        lengths, flags, stamps = self._headers(n)
        size, trunc = self.msg_size, _MSG_TRUNC
        whole = [ln == size and not fl & trunc for ln, fl in zip(lengths, flags, strict=True)]
        return n, self._view[: n * size], whole, stamps

    def discard(self) -> None:
        """Everything queued now, read and dropped (frames from before a reader's turn)."""
        while self._call():
            pass

    def _headers(self, n: int) -> tuple[tuple[int, ...], tuple[int, ...], list[float | None]]:
        """The last call's lengths, flags and kernel times (SO_TIMESTAMPNS, the only control
        message asked for; None where the kernel sent none), the whole batch's headers and
        control messages read by one ``struct`` call each, not four calls per datagram: on a slow
        core each call costs per frame of every reader (measured: docs/performance.md)."""
        heads = _batch_struct(n, _HEAD_ENTRY).unpack_from(self._hdrs)
        ctls = _batch_struct(n, _CTL_ENTRY).unpack_from(self._ctl_view)
        # plain ints: socket.MSG_TRUNC is an IntFlag, whose & costs ~1 us a frame
        need, sol, kind_ts = _STAMP_LEN, _SOL_SOCKET, SO_TIMESTAMPNS
        stamps: list[float | None] = [
            sec + ns * 1e-9 if cl >= need and lv == sol and kind == kind_ts else None
            for cl, lv, kind, sec, ns in zip(
                heads[0::3], ctls[1::5], ctls[2::5], ctls[3::5], ctls[4::5], strict=True
            )
        ]
        return heads[2::3], heads[1::3], stamps


def _libc(name: str, *argtypes: Any) -> Any:
    fn = getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True), name)
    fn.argtypes = argtypes
    fn.restype = ctypes.c_int
    return fn


_recvmmsg = _libc(
    "recvmmsg", ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
)
sendmmsg = _libc("sendmmsg", ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int)
