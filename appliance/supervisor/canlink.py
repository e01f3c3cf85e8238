"""SocketCAN link bring-up and health through netlink (pyroute2), never through shell-outs.

Only meaningful for ``interface: socketcan``; the simulated buses have no link to manage. Every
failure names the fix a lab engineer can apply on the board.
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from exolink.config import CanConfig

# DCAN1 (0x481d0000) in Debian's am335x-boneblack.dtb (kernel 6.12); the overlay sets it "okay".
DCAN1_STATUS = Path(
    "/sys/firmware/devicetree/base/ocp/interconnect@48000000/segment@100000/target-module@d0000/can@0/status"
)
STATES = {
    0: "error-active",
    1: "error-warning",
    2: "error-passive",
    3: "bus-off",
    4: "stopped",
    5: "sleeping",
}


class CanLinkError(RuntimeError):
    pass


@dataclass(frozen=True)
class LinkHealth:
    state: str  # error-active ... bus-off, or "up"/"down" for links without CAN state (vcan)
    txerr: int = 0
    rxerr: int = 0
    bus_errors: int = 0
    restarts: int = 0

    @property
    def bad(self) -> bool:
        return self.state in ("error-passive", "bus-off", "stopped", "down")


def check_overlay(status_file: Path = DCAN1_STATUS) -> None:
    try:
        status = status_file.read_bytes().rstrip(b"\x00").decode()
    except FileNotFoundError:
        raise CanLinkError(
            f"DCAN1 not found in the device tree ({status_file}): boot the exolink image's dtb "
            "with the DCAN1 overlay merged, or set can.require_overlay: false"
        ) from None
    if status != "okay":
        raise CanLinkError(
            f"DCAN1 is {status!r} in the device tree, not 'okay': the overlay is not applied"
        )


def _index(ip: object, ifname: str) -> int:
    """By name through one ioctl (``if_nametoindex``), not pyroute2's lookup, which dumps and
    parses every link."""
    try:
        return socket.if_nametoindex(ifname)
    except OSError:
        raise CanLinkError(
            f"no network interface {ifname!r}: on the board check the DCAN1 overlay and that the "
            "c_can_platform module is loaded (`modprobe c_can_platform`); for tests create a vcan"
        ) from None


def bring_up(cfg: CanConfig) -> None:
    """Set bitrate and restart-ms, then bring the link up (it must be down to change timing)."""
    from pyroute2 import IPRoute
    from pyroute2.netlink.exceptions import NetlinkError

    try:
        with IPRoute() as ip:
            idx = _index(ip, cfg.channel)
            kind = _kind(ip, idx)
            if kind == "can":
                ip.link("set", index=idx, state="down")
                try:
                    ip.link(
                        "set",
                        index=idx,
                        kind="can",
                        can_bittiming={"bitrate": cfg.bitrate},
                        can_restart_ms=cfg.restart_ms,
                    )
                except NetlinkError as exc:
                    raise CanLinkError(
                        f"{cfg.channel}: the driver refused bitrate {cfg.bitrate} / restart-ms "
                        f"{cfg.restart_ms}: {exc}"
                    ) from None
            elif kind != "vcan":
                raise CanLinkError(
                    f"{cfg.channel} is a {kind or 'non-CAN'} link, not a CAN interface"
                )
            ip.link("set", index=idx, state="up")
    except NetlinkError as exc:
        if exc.code == errno.EPERM:
            raise CanLinkError(
                f"not permitted to configure {cfg.channel}: run the supervisor with CAP_NET_ADMIN "
                "(the systemd unit grants it) or set can.bring_up: false and configure it yourself"
            ) from None
        raise CanLinkError(f"netlink error configuring {cfg.channel}: {exc}") from None


def set_bitrate(channel: str, bitrate: int) -> None:
    """Request a bitrate on any link; a link that cannot take one (vcan) is a clear error."""
    from pyroute2 import IPRoute
    from pyroute2.netlink.exceptions import NetlinkError

    with IPRoute() as ip:
        idx = _index(ip, channel)
        try:
            ip.link("set", index=idx, kind="can", can_bittiming={"bitrate": bitrate})
        except NetlinkError as exc:
            raise CanLinkError(
                f"{channel} cannot take a bitrate ({_kind(ip, idx) or 'unknown kind'}): {exc}"
            ) from None


def _kind(ip: object, idx: int) -> str | None:
    link = ip.get_links(idx)[0]  # type: ignore[attr-defined]
    info = link.get_attr("IFLA_LINKINFO")
    return info.get_attr("IFLA_INFO_KIND") if info is not None else None


def set_state(channel: str, up: bool) -> None:
    from pyroute2 import IPRoute

    with IPRoute() as ip:
        ip.link("set", index=_index(ip, channel), state="up" if up else "down")


def health(channel: str) -> LinkHealth:
    """Bus state and error counters as the kernel reports them."""
    from pyroute2 import IPRoute

    with IPRoute() as ip:
        return _health(ip.get_links(_index(ip, channel))[0])


class LinkMonitor:
    """``health`` for the supervisor's periodic check: one netlink socket kept open and the
    link's index kept (a fresh socket plus a by-name lookup, which dumps every link, were two
    thirds of each check's cost: 3.2-3.8 ms -> 1.3-2.1 ms on a busy x86 host, five times a
    second, roughly 20x that on the emulated A8). Any error closes it; the next call starts
    afresh."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self._ip: object | None = None
        self._idx: int | None = None

    def health(self) -> LinkHealth:
        from pyroute2 import IPRoute
        from pyroute2.netlink.exceptions import NetlinkError

        try:
            if self._ip is None:
                self._ip = IPRoute()
            if self._idx is None:
                self._idx = _index(self._ip, self.channel)
            links = self._ip.get_links(self._idx)  # type: ignore[attr-defined]
        except (NetlinkError, OSError):  # gone (ENODEV) or renumbered: look it up again
            self.close()
            return health(self.channel)
        except CanLinkError:
            self.close()
            raise
        return _health(links[0])

    def close(self) -> None:
        if self._ip is not None:
            self._ip.close()  # type: ignore[attr-defined]
        self._ip = self._idx = None


def _health(link: Any) -> LinkHealth:  # a pyroute2 ifinfmsg
    up = "up" if link.get_attr("IFLA_OPERSTATE") in ("UP", "UNKNOWN") else "down"
    info = link.get_attr("IFLA_LINKINFO")
    data = info.get_attr("IFLA_INFO_DATA") if info is not None else None
    if data is None or not hasattr(data, "get_attr") or data.get_attr("IFLA_CAN_STATE") is None:
        return LinkHealth(up)
    berr = data.get_attr("IFLA_CAN_BERR_COUNTER") or {}
    xstats = (info.get_attr("IFLA_INFO_XSTATS") or {}) if info is not None else {}
    raw_state = data.get_attr("IFLA_CAN_STATE")
    state = (
        STATES.get(raw_state, str(raw_state))
        if isinstance(raw_state, int)
        else str(raw_state).lower()
    )
    return LinkHealth(
        state=state if up == "up" else "down",
        txerr=int(berr.get("txerr", 0)),
        rxerr=int(berr.get("rxerr", 0)),
        bus_errors=int(getattr(xstats, "get", lambda *_: 0)("bus_error", 0) or 0),
        restarts=int(getattr(xstats, "get", lambda *_: 0)("restarts", 0) or 0),
    )
