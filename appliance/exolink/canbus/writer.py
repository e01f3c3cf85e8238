"""The send hot path: ``FrameWriter`` sends a batch of frames (a controller cycle's set-points)
in one ``sendmmsg`` on SocketCAN, through python-can one by one elsewhere. A bus that only sends
(the controller manager's while no reader is open) needs no reader for it; a reader's ``writer``
is one too."""

from __future__ import annotations

import ctypes
import errno
import os
import socket
from collections.abc import Sequence
from typing import TYPE_CHECKING

from exolink.canbus.frames import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_FRAME, CAN_RTR_FLAG
from exolink.canbus.mmsg import BATCH, MMsgHdr, mmsg_buffers, sendmmsg
from exolink.canbus.sockets import bus_socket
from exolink.config import CanConfig

if TYPE_CHECKING:
    import can


class FrameWriter:
    """Sends a batch of frames (a controller cycle's set-points) in one system call.

    python-can's SocketCAN ``send`` costs, per frame, a ``select`` for room and the ``send``
    (two system calls), two logger look-ups and a frame build; the controller manager sends up
    to eight frames per H2 cycle, and on a slow core (qemu TCG) the kernel's side of a call is
    where the time goes, as for ``BatchReceiver``. On SocketCAN a batch goes to the kernel
    in one ``sendmmsg`` (libc's, through ctypes), never blocking; frames the kernel refuses (a
    full transmit queue) raise ``can.CanOperationError`` naming how many of the batch went out,
    after one more try for the rest. Order on the bus is the batch's. Other interfaces (the
    simulated bus, the virtual one) and CAN FD frames go through python-can, one by one."""

    def __init__(self, bus: can.BusABC, cfg: CanConfig) -> None:
        self.bus = bus
        sock = bus_socket(bus)
        self.fd = sock.fileno() if sock is not None and sock.family == socket.AF_CAN else None
        self._data, _, self._iov, self._msgs = mmsg_buffers(CAN_FRAME.size, 0)
        self._addr = ctypes.addressof(self._msgs)
        self._view = memoryview(self._data).cast("B")

    def send(self, msgs: Sequence[can.Message]) -> None:
        if self.fd is None or any(m.is_fd for m in msgs):
            self._send_each(msgs)
            return
        for at in range(0, len(msgs), BATCH):
            self._send_batch(msgs[at : at + BATCH])

    def _send_each(self, msgs: Sequence[can.Message]) -> None:
        """Through python-can; a refused frame does not hold back the ones after it."""
        import can  # lazy: python-can only on the fallback path

        failed: list[str] = []
        for m in msgs:
            try:
                self.bus.send(m)
            except can.CanError as exc:
                failed.append(str(exc))
        if failed:
            raise can.CanOperationError(
                f"sent {len(msgs) - len(failed)} of {len(msgs)} frames: {failed[0]}"
            )

    def _send_batch(self, msgs: Sequence[can.Message]) -> None:
        view, size = self._view, CAN_FRAME.size
        for i, m in enumerate(msgs):
            can_id = m.arbitration_id
            if m.is_extended_id:
                can_id |= CAN_EFF_FLAG
            if m.is_remote_frame:
                can_id |= CAN_RTR_FLAG
            if m.is_error_frame:
                can_id |= CAN_ERR_FLAG
            CAN_FRAME.pack_into(view, i * size, can_id, m.dlc, bytes(m.data))
        total, done, tries = len(msgs), 0, 0
        while done < total:
            n = sendmmsg(
                self.fd,
                self._addr + done * ctypes.sizeof(MMsgHdr),
                total - done,
                socket.MSG_DONTWAIT,
            )
            if n > 0:
                done += n
                continue
            tries += 1
            err = ctypes.get_errno() if n < 0 else errno.ENOBUFS
            if err == errno.EINTR and tries < 3:
                continue
            if tries < 2 and err in (errno.ENOBUFS, errno.EAGAIN):
                continue
            import can  # lazy: python-can only to raise its error

            raise can.CanOperationError(
                f"sent {done} of {total} frames: {os.strerror(err)} (transmit queue full?)"
            )
