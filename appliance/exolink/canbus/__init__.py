"""The CAN bus: opening it from configuration, reading it in batches straight from its socket
(counting what the kernel dropped), sending a batch in one system call.

The package's modules, from the bottom up: ``frames`` (linux's can_frame, ``Frame``, id
filters), ``sockets`` (socket options, receive queue, drop counter), ``mmsg`` (recvmmsg and
sendmmsg through ctypes), ``writer`` (``FrameWriter``), ``reader`` (``FrameReader``),
``opening`` (``open_bus``, ``open_reader``, ``Cadence``). Everything is imported from here:
``from exolink.canbus import open_reader``.
"""

from __future__ import annotations

from exolink.canbus.frames import (
    CAN_EFF_FLAG,
    CAN_ERR_FLAG,
    CAN_FRAME,
    CAN_RTR_FLAG,
    STD_MASK,
    Frame,
    id_filters,
)
from exolink.canbus.mmsg import BatchReceiver
from exolink.canbus.opening import Cadence, CanOpenError, open_bus, open_reader
from exolink.canbus.reader import LATE_S, FrameReader
from exolink.canbus.sockets import (
    RCVBUF_BYTES,
    SO_MEMINFO,
    SO_RCVBUFFORCE,
    SO_TIMESTAMPNS,
    bus_socket,
    size_receive_buffer,
    socket_drops,
)
from exolink.canbus.writer import FrameWriter

__all__ = [
    "CAN_EFF_FLAG",
    "CAN_ERR_FLAG",
    "CAN_FRAME",
    "CAN_RTR_FLAG",
    "LATE_S",
    "RCVBUF_BYTES",
    "SO_MEMINFO",
    "SO_RCVBUFFORCE",
    "SO_TIMESTAMPNS",
    "STD_MASK",
    "BatchReceiver",
    "Cadence",
    "CanOpenError",
    "Frame",
    "FrameReader",
    "FrameWriter",
    "bus_socket",
    "id_filters",
    "open_bus",
    "open_reader",
    "size_receive_buffer",
    "socket_drops",
]
