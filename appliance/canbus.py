"""The one place that opens a python-can bus from configuration.

SocketCAN gets kernel receive filters so a node only wakes for its own ids; the other interfaces
(virtual in-process, udp_multicast across processes) apply the same filters in python-can.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

from exolink.config import CanConfig

if TYPE_CHECKING:
    import can

STD_MASK = 0x7FF
IP_MULTICAST_ALL = 49  # linux/in.h; Python's socket module does not export it


class CanOpenError(RuntimeError):
    pass


def id_filters(ids: Iterable[int]) -> list[dict[str, int | bool]]:
    """Exact-match filters on standard 11-bit ids."""
    return [{"can_id": i, "can_mask": STD_MASK, "extended": False} for i in sorted(set(ids))]


def open_bus(
    cfg: CanConfig,
    filters: list[dict[str, int | bool]] | None = None,
    receive_own_messages: bool = False,
) -> can.BusABC:
    """Open the configured bus; failures name the interface and the likely fix."""
    import can

    kwargs: dict[str, object] = {
        "interface": cfg.interface,
        "channel": cfg.channel,
        "receive_own_messages": receive_own_messages,
    }
    if filters is not None:
        kwargs["can_filters"] = filters
    try:
        bus = can.Bus(**kwargs)
    except (OSError, can.CanError, ValueError) as exc:
        raise CanOpenError(_explain(cfg, exc)) from exc
    if cfg.interface == "udp_multicast":
        _own_group_only(bus)
    return bus


def _own_group_only(bus: can.BusABC) -> None:
    """python-can binds its multicast socket to 0.0.0.0:port, and Linux then delivers every group
    joined anywhere on the host: a second simulated appliance (or a test) on another group would
    see this bus's frames. IP_MULTICAST_ALL=0 keeps to the groups this socket joined."""
    import socket

    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)  # python-can internals
    if isinstance(sock, socket.socket) and sock.family == socket.AF_INET:
        sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)


def _explain(cfg: CanConfig, exc: Exception) -> str:
    base = f"cannot open CAN bus {cfg.interface}:{cfg.channel}: {exc}"
    if cfg.interface == "socketcan":
        return (
            f"{base}. Is the interface present and up? On the board: check the DCAN1 overlay "
            f"and `ip link set {cfg.channel} up type can bitrate {cfg.bitrate}`; for tests: "
            f"`ip link add dev {cfg.channel} type vcan && ip link set {cfg.channel} up`."
        )
    if cfg.interface == "udp_multicast":
        return (
            f"{base}. udp_multicast needs a multicast route: "
            "`ip route add 224.0.0.0/4 dev lo` (or a default route)."
        )
    return base
