"""CAN frames as the kernel and the readers see them: linux/can.h's ``can_frame`` layout and id
flags (the SocketCAN reader unpacks it, the writer packs it), the ``Frame`` a read returns, and
the exact-match id filters a bus is opened with. No I/O: the modules above share these."""

from __future__ import annotations

import struct
from collections.abc import Iterable
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    from can.typechecking import CanFilter

STD_MASK = 0x7FF

CAN_FRAME = struct.Struct(
    "=IB3x8s"
)  # linux/can.h struct can_frame: id, len, pad, res0, len8_dlc, data
CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000


def id_filters(ids: Iterable[int]) -> list[CanFilter]:
    """Exact-match filters on standard 11-bit ids."""
    return [{"can_id": i, "can_mask": STD_MASK, "extended": False} for i in sorted(set(ids))]


class Frame(NamedTuple):
    """One received CAN frame: the attributes the protocol decoders read from a can.Message."""

    timestamp: float  # kernel receive time, seconds since the epoch
    arbitration_id: int
    data: bytes
    is_extended_id: bool = False
    is_remote_frame: bool = False
    is_error_frame: bool = False
