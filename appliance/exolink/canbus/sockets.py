"""The kernel's side of a bus socket: the socket under a python-can bus, the socket options
Python does not name, the receive queue a reader asks for and the kernel's count of what the
socket dropped. Only socket state; what to do with it is the reader's."""

from __future__ import annotations

import socket
import struct
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import can

SO_RCVBUFFORCE, SO_MEMINFO, SO_TIMESTAMPNS = 33, 55, 35  # asm-generic/socket.h; not in Python
_MEMINFO = struct.Struct("=9I")  # linux/sock_diag.h SK_MEMINFO_*: [0] rmem_alloc .. [8] drops
# Receive queue asked for per socket: a 100 ms stall at full load loses nothing. The kernel
# charges each queued frame its whole buffer (x86-64: 768 B per SocketCAN frame, 832 B per sim
# datagram; an ARM32 sk_buff is smaller) and grants twice the request. SocketCAN at 1 Mbit/s:
# at most 21,277 frames/s (no data bytes, no stuffing), 2,128 in 100 ms = 1.6 MB of the 2 MiB
# granted. The sim bus has no bit rate: one sender floods it at ~50-70k frames/s on an x86
# core, 7,000 in 100 ms = 5.8 MB of the 6 MiB granted. Without CAP_NET_ADMIN, net.core.rmem_max
# caps the grant (often 212992: twice that holds ~510 frames), logged at open.
RCVBUF_BYTES = {socket.AF_CAN: 1 << 20, socket.AF_INET: 3 << 20}  # by the bus socket's family


def receive_none(sock: socket.socket) -> None:
    """A CAN_RAW socket that no frame reaches from now on (an empty id filter): a socket kept
    open while idle instead of closed (closing one with a BPF filter frees the program in a
    kernel worker: docs/performance.md, stop 69)."""
    sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, b"")


def bus_socket(bus: can.BusABC) -> socket.socket | None:
    """The socket under a bus that shows it (python-can's SocketCAN bus and the simulated bus
    both have a public ``socket``); None for a bus without one (the in-process virtual bus)."""
    sock = getattr(bus, "socket", None)
    return sock if isinstance(sock, socket.socket) else None


def socket_drops(sock: socket.socket) -> int | None:
    """The socket's kernel drop counter (sk_drops, SO_MEMINFO), None if the kernel won't say."""
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, _MEMINFO.size)
    except OSError:
        return None
    return _MEMINFO.unpack(raw)[8] if len(raw) == _MEMINFO.size else None


def size_receive_buffer(sock: socket.socket, want: int) -> int:
    """Ask for ``want`` bytes of receive queue: SO_RCVBUFFORCE where permitted (CAP_NET_ADMIN),
    else SO_RCVBUF, which net.core.rmem_max caps. Returns what the kernel granted (it doubles the
    request for its bookkeeping; each queued frame is charged its whole buffer, see README)."""
    for opt in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, want)
            break
        except OSError:
            continue
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
