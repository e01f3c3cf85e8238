"""A leased node's broadcast-manager socket, opened by the supervisor and held by both: so the
watchdog deletes the node's send ops itself, before its first disable frame, whatever the node
is doing (stopped, hung, starved by a CPU hog, between a read and a renewal).

A broadcast-manager op belongs to its socket, not to a process: any holder of the socket may
TX_DELETE it. The supervisor opens one socket per spawn of a node that runs a lease
(``leased_deadline_ms`` in its config: the controller manager), passes it to the node at its
spawn (``HELD_ENV`` names the descriptor) and keeps its own copy (``HeldOps``). Every safe
action of the watchdog first deletes the device's command op on every copy (``delete``), and a
node's exit deletes it and closes the copy (``release``): the op then ends with the process as
it did when the node's own socket closed. The lease itself stays the bound where no watchdog
can act (the supervisor gone too): its count ends the op by itself.

A renewal that races the deletion (the node read the count, then the op was deleted, then its
setup came) makes a new op that waits for a start; the node's resume could start it. The
watchdog's repeats of the safe action (50 and 250 ms after a trip) delete that one too, and the
node hears the disable frames and ends its timer at its next wake."""

from __future__ import annotations

import os
import socket
import threading
from functools import cache

from exolink.canbus.bcm import open_bcm, tx_delete
from exolink.canbus.opening import CanOpenError

HELD_ENV = "EXOLINK_LEASE_FD"


class HeldOps:
    """The supervisor's copies of its leased nodes' broadcast-manager sockets on ``channel``,
    and the ids whose ops a safe action deletes on them (the device's command id)."""

    def __init__(self, channel: str, can_ids: tuple[int, ...]) -> None:
        self.channel = channel
        self.can_ids = can_ids
        self._lock = threading.Lock()
        self._socks: set[socket.socket] = set()

    def open(self) -> socket.socket:
        """A new socket for one spawn, held until ``release``; CanOpenError if the kernel
        refuses it (no broadcast manager, no such link)."""
        sock = open_bcm(self.channel)
        with self._lock:
            self._socks.add(sock)
        return sock

    def delete(self) -> int:
        """Every held socket's ops on the ids deleted now: how many there were. Never raises
        (the watchdog's safe action must go on)."""
        with self._lock:
            socks = list(self._socks)
        return sum(tx_delete(s, i) for s in socks for i in self.can_ids)

    def release(self, sock: socket.socket) -> None:
        """A spawn's exit: its ops deleted, the copy closed."""
        with self._lock:
            self._socks.discard(sock)
        for i in self.can_ids:
            tx_delete(sock, i)
        sock.close()

    def close(self) -> None:
        """Every copy released (the supervisor's shutdown)."""
        with self._lock:
            socks = list(self._socks)
        for s in socks:
            self.release(s)


@cache
def held_socket() -> socket.socket | None:
    """In a node: the broadcast-manager socket the supervisor passed (``HELD_ENV``), for the
    node's life, or None (not passed: a node started by hand, a simulated bus). A descriptor
    that is not a CAN datagram socket is refused, not used."""
    raw = os.environ.get(HELD_ENV)
    if not raw:
        return None
    try:
        fd = int(raw)
        # family and protocol given: Python's own detection asks for the socket's name, which
        # a broadcast-manager socket does not have (EOPNOTSUPP)
        sock = socket.socket(socket.AF_CAN, socket.SOCK_DGRAM, socket.CAN_BCM, fileno=fd)
    except (OSError, ValueError) as exc:
        raise CanOpenError(f"{HELD_ENV}={raw!r}: not an open socket ({exc})") from None
    try:  # (SO_PROTOCOL is 0 on every CAN socket: the kernel does not keep it)
        kind = (
            sock.getsockopt(socket.SOL_SOCKET, socket.SO_DOMAIN),
            sock.getsockopt(socket.SOL_SOCKET, socket.SO_TYPE),
        )
    except OSError:
        kind = (-1, -1)
    if kind != (socket.AF_CAN, socket.SOCK_DGRAM):
        sock.detach()
        raise CanOpenError(f"{HELD_ENV}={raw!r}: not a CAN broadcast-manager socket")
    return sock
