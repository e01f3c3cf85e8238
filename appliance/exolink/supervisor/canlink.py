"""SocketCAN link bring-up through netlink (pyroute2), never through shell-outs; its health from
the driver's error frames and sysfs.

Only meaningful for ``interface: socketcan``; the simulated buses have no link to manage. Every
failure names the fix a lab engineer can apply on the board.

The supervisor never imports pyroute2: on x86 it is ~22 MB resident and 300 modules, seconds
of import on the A8, all for a bring-up at start and a poll every 2 s. The bring-up runs in a
child process (``bring_up_apart``: this module as a program), and ``LinkMonitor`` watches the
CAN state through an error-frame socket: the driver sends one at each state change (warning,
passive, bus-off, restarted) with the error counters, so a bus-off is known when it happens,
not at the next poll.
"""

from __future__ import annotations

import contextlib
import errno
import select
import socket
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from exolink.canbus import CAN_ERR_FLAG, CAN_FRAME
from exolink.config import CanConfig
from exolink.errors import CanLinkError

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
    from pyroute2 import IPRoute  # lazy: pyroute2 (~22 MB): never in the supervisor
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


def bring_up_apart(cfg: CanConfig, timeout_s: float = 120.0) -> None:
    """``bring_up`` in a child process (pyroute2 is loaded there and gone with it); its
    refusal is raised here as the same CanLinkError text."""
    cmd = [sys.executable, "-m", "exolink.supervisor.canlink", cfg.channel]
    cmd += [str(cfg.bitrate), str(cfg.restart_ms)]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise CanLinkError(f"bringing {cfg.channel} up took over {timeout_s:g} s") from None
    if r.returncode != 0:
        lines = r.stderr.strip().splitlines()
        raise CanLinkError(
            lines[-1] if lines else f"bringing {cfg.channel} up failed: rc {r.returncode}"
        )


def set_bitrate(channel: str, bitrate: int) -> None:
    """Request a bitrate on any link; a link that cannot take one (vcan) is a clear error."""
    from pyroute2 import IPRoute  # lazy: pyroute2 (~22 MB): never in the supervisor
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
    from pyroute2 import IPRoute  # lazy: pyroute2 (~22 MB): never in the supervisor

    with IPRoute() as ip:
        ip.link("set", index=_index(ip, channel), state="up" if up else "down")


def health(channel: str) -> LinkHealth:
    """Bus state and error counters as the kernel reports them."""
    from pyroute2 import IPRoute  # lazy: pyroute2 (~22 MB): never in the supervisor

    with IPRoute() as ip:
        return _health(ip.get_links(_index(ip, channel))[0])


# linux/can/error.h and linux/can/raw.h (Python exports neither)
CAN_RAW_ERR_FILTER = 2
ERR_FLAG = CAN_ERR_FLAG
ERR_CRTL, ERR_BUSOFF, ERR_RESTARTED, ERR_CNT = 0x4, 0x40, 0x100, 0x200
CRTL_WARNING, CRTL_PASSIVE, CRTL_ACTIVE = 0x04 | 0x08, 0x10 | 0x20, 0x40
# State changes only: bus-error and protocol classes can come thousands a second on a bad bus.
WATCHED = ERR_CRTL | ERR_BUSOFF | ERR_RESTARTED


class LinkMonitor:
    """The supervisor's view of the link: up or down from sysfs, the CAN state and error
    counters from the error frames the driver sends at each change (a kernel filter lets no
    data frame and no bus-error flood through). A CAN controller (a device behind the link)
    starts error-active, as ``bring_up`` leaves it; a link with no CAN state (vcan) is "up"
    until an error frame says more. ``wait`` ends at the first error frame."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        sysfs = Path("/sys/class/net") / channel
        self._operstate = sysfs / "operstate"
        self.state: str | None = "error-active" if (sysfs / "device").exists() else None
        self.txerr = self.rxerr = self.restarts = 0
        self._sock: socket.socket | None = None

    def _socket(self) -> socket.socket:
        if self._sock is None:
            _index(None, self.channel)  # a missing link named with its fix
            s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
            try:
                s.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, b"")  # no data frames
                s.setsockopt(socket.SOL_CAN_RAW, CAN_RAW_ERR_FILTER, struct.pack("=I", WATCHED))
                s.bind((self.channel,))
                s.setblocking(False)
            except OSError:
                s.close()
                raise
            self._sock = s
        return self._sock

    def wait(self, timeout: float) -> bool:
        """Up to ``timeout`` for an error frame; every one queued is taken (True: some came)."""
        try:
            sock = self._socket()
            if not select.select([sock], (), (), timeout)[0]:
                return False
            got = False
            while True:
                try:
                    raw = sock.recv(CAN_FRAME.size)
                except BlockingIOError:
                    return got
                if len(raw) == CAN_FRAME.size:
                    self.on_error_frame(*CAN_FRAME.unpack(raw))
                    got = True
        except (OSError, CanLinkError):  # the link is gone: health() says so, then reopen
            self.close()
            time.sleep(timeout)
            return False

    def on_error_frame(self, can_id: int, dlc: int, data: bytes) -> None:
        if not can_id & ERR_FLAG:
            return
        if can_id & ERR_CNT:
            self.txerr, self.rxerr = data[6], data[7]
        if can_id & ERR_BUSOFF:
            self.state = "bus-off"
        elif can_id & ERR_RESTARTED:
            self.state, self.txerr, self.rxerr = "error-active", 0, 0
            self.restarts += 1
        elif can_id & ERR_CRTL:
            if data[1] & CRTL_PASSIVE:
                self.state = "error-passive"
            elif data[1] & CRTL_WARNING:
                self.state = "error-warning"
            elif data[1] & CRTL_ACTIVE:
                self.state = "error-active"

    def health(self) -> LinkHealth:
        """A bus-off is reported as such even though the driver takes the carrier down with it."""
        try:
            oper = self._operstate.read_text().strip()
        except OSError as exc:
            _index(None, self.channel)  # a missing link: CanLinkError naming the fix
            raise CanLinkError(f"{self.channel}: its state cannot be read ({exc})") from None
        up = oper in ("up", "unknown")
        if self.state == "bus-off" or (up and self.state is not None):
            state = self.state
        else:
            state = "up" if up else "down"
        return LinkHealth(state, self.txerr, self.rxerr, 0, self.restarts)

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
        self._sock = None


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


def _main(argv: list[str]) -> int:
    """``bring_up_apart``'s child: CHANNEL BITRATE RESTART_MS; a refusal on stderr, exit 2."""
    channel, bitrate, restart_ms = argv
    cfg = CanConfig(channel=channel, bitrate=int(bitrate), restart_ms=int(restart_ms))
    try:
        bring_up(cfg)
    except CanLinkError as exc:
        sys.stderr.write(f"{exc}\n")
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
