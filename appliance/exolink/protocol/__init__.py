"""CAN protocols as data: DBC files shipped here, typed codecs compiled from them."""

from exolink.protocol.dbc import ProtocolError

__all__ = ["ProtocolError"]
