"""The simulated CAN bus: a python-can interface (``exolink_sim``) kept on this machine.

Registered under python-can's ``can.interface`` entry point, so ``can.Bus(interface="exolink_sim",
channel=group)`` opens it in any process, python-can's own tools included (``python -m can.viewer
-i exolink_sim -c 239.74.163.2``). Its datagrams are python-can's udp_multicast ones (msgpack,
port 43113): a plain udp_multicast bus on loopback hears it, and it hears that bus.

python-can's udp_multicast joins its group on whatever interface the route to the group names and
sends that way: with a default route frames went out on eth0, and a route change mid-run left the
members joined on the old interface while frames left by the new one (silence, no error). Here the
socket is bound to the loopback interface: joined on lo, sending through lo with TTL 0 (the kernel
never lets a TTL-0 multicast leave the host). No route is needed at all.

The kernel filter SocketCAN has, without losing count: every frame is sent from a source address
that encodes its id (127.111.0.0 + id for standard ids), and a reader of exact standard ids joins
the group for those sources only (source-specific membership). Datagrams from other sources are
never queued to its socket and never counted there, so the socket's drop counter (sk_drops) is
exactly the frames of its ids it lost; a socket filter (classic BPF) counted every datagram it
rejected in the same counter.

``socket`` and ``fileno()`` are public, as on python-can's SocketCAN bus: the appliance's batched
reader (exolink.canbus.FrameReader) reads the socket directly.
"""

from __future__ import annotations

import contextlib
import ipaddress
import select
import socket
import struct
from typing import Any

import can
import structlog
from can.interfaces.udp_multicast.utils import is_msgpack_installed, pack_message, unpack_message
from can.typechecking import AutoDetectedConfig, CanFilters

INTERFACE = "exolink_sim"  # the name python-can knows it by (pyproject.toml's entry point)
DEFAULT_GROUP = "239.74.163.2"  # python-can's default IPv4 group (exolink.config's sim group)
SIM_PORT = 43113  # python-can's default udp_multicast port
LOOPBACK = "lo"
STD_MASK = 0x7FF
_SOURCE_BASE = 0x7F6F0000  # 127.111.0.0: standard id i is sent from 127.111.(i >> 8).(i & 0xFF)
_SOURCE_OTHER = _SOURCE_BASE | 0xFFFE  # extended ids: never joined by a filtered reader
IP_PKTINFO, IP_ADD_SOURCE_MEMBERSHIP, IP_MULTICAST_ALL = 8, 39, 49  # linux/in.h
SO_TIMESTAMPNS = 35
_U32BE = struct.Struct("!I")
_I32 = struct.Struct("@i")
_PKTINFO = struct.Struct("@i4s4s")  # struct in_pktinfo
_TIMESPEC = struct.Struct("@ll")
_MAX_DATAGRAM = 4096  # python-can's receive size for this format
_CTL_SIZE = socket.CMSG_SPACE(_TIMESPEC.size)
Socket = socket.socket  # for annotations in SimBus, whose ``socket`` is the property


def sim_source(arbitration_id: int, extended: bool = False) -> str:
    """The loopback source address a frame with this id is sent from on the simulated bus."""
    addr = _SOURCE_OTHER if extended or arbitration_id > STD_MASK else _SOURCE_BASE | arbitration_id
    return socket.inet_ntoa(_U32BE.pack(addr))


def exact_ids(filters: CanFilters | None) -> list[int] | None:
    """The ids of filters that are all exact standard-id matches (what a kernel filter takes)."""
    if filters is None or any(
        f.get("extended") or int(f.get("can_mask", 0)) != STD_MASK for f in filters
    ):
        return None
    return sorted({int(f["can_id"]) for f in filters})


def loopback_socket(group: str, port: int, ids: list[int] | None) -> socket.socket:
    """A UDP socket on ``group`` through the loopback interface only, for sending and receiving.

    ``ids``: join for the sources of these standard ids only (None: every source, []: none,
    for a bus that only sends). More ids than the kernel takes per membership
    (net.ipv4.igmp_max_msf, 10 by default) join for every source instead; python-can's and the
    reader's own filters still apply."""
    try:
        if not ipaddress.IPv4Address(group).is_multicast:
            raise ValueError
    except ValueError:
        raise OSError(f"the simulated bus needs an IPv4 multicast group, not {group!r}") from None
    try:
        lo = socket.if_nametoindex(LOOPBACK)
    except OSError:
        raise OSError(f"no loopback interface {LOOPBACK!r}") from None
    _check_loopback(group, port, lo)
    loopback = socket.inet_aton("127.0.0.1")
    grp = socket.inet_aton(group)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        ip = socket.IPPROTO_IP
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        # Only the groups this socket joined (Linux otherwise delivers every group joined
        # anywhere on the host to a socket bound to the port: another sim bus would leak in).
        sock.setsockopt(ip, IP_MULTICAST_ALL, 0)
        sock.bind((group, port))  # unicast datagrams to the port are not frames
        sock.setsockopt(ip, socket.IP_MULTICAST_IF, bytes(4) + loopback + _I32.pack(lo))
        sock.setsockopt(ip, socket.IP_MULTICAST_TTL, 0)
        sock.setsockopt(ip, socket.IP_MULTICAST_LOOP, 1)
        if ids is None or (ids and not _join_sources(sock, grp, loopback, ids)):
            sock.setsockopt(ip, socket.IP_ADD_MEMBERSHIP, grp + loopback + _I32.pack(lo))
        # ids == []: a bus that only sends joins nothing and is sent nothing
    except OSError:
        sock.close()
        raise
    return sock


def _join_sources(sock: socket.socket, grp: bytes, loopback: bytes, ids: list[int]) -> bool:
    """Source-specific membership for these ids' sources; False (nothing joined) if refused."""
    try:
        for i in ids:
            src = socket.inet_aton(sim_source(i))
            sock.setsockopt(socket.IPPROTO_IP, IP_ADD_SOURCE_MEMBERSHIP, grp + loopback + src)
    except OSError as exc:  # ENOBUFS past net.ipv4.igmp_max_msf
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, grp + loopback)
        structlog.get_logger().bind(node="canbus").info(
            "sim_filter_in_python",
            ids=len(ids),
            reason=f"{exc.strerror}: more sources than net.ipv4.igmp_max_msf",
        )
        return False
    return True


def _check_loopback(group: str, port: int, lo: int) -> None:
    """What a send needs, asked of the kernel without sending: the loopback interface up, and
    the loopback network (127.0.0.0/8, where the frame sources live) on it."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((sim_source(0), 0))
        except OSError as exc:
            raise OSError(
                f"loopback has no 127.0.0.0/8 address ({exc.strerror}): "
                f"`ip addr add 127.0.0.1/8 dev {LOOPBACK}`"
            ) from None
        probe.setsockopt(
            socket.IPPROTO_IP, socket.IP_MULTICAST_IF, bytes(4) + bytes(4) + _I32.pack(lo)
        )
        try:
            probe.connect((group, port))
        except OSError as exc:
            raise OSError(
                f"no way to {group} through the loopback interface ({exc.strerror}): "
                f"is {LOOPBACK} up? `ip link set {LOOPBACK} up`"
            ) from None


class SimBus(can.BusABC):
    """python-can's udp_multicast datagrams on the loopback interface, as a python-can bus.

    Filters of exact standard ids given at open are applied in the kernel (source-specific
    membership), as SocketCAN applies them; python-can's filter applies as well, and filters
    set later apply in python-can only (the kernel keeps the sources joined at open)."""

    def __init__(
        self,
        channel: str = DEFAULT_GROUP,
        port: int = SIM_PORT,
        receive_own_messages: bool = False,
        fd: bool = True,
        can_filters: CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        is_msgpack_installed()
        if receive_own_messages:
            raise can.CanInterfaceNotImplementedError(
                "receiving own messages is not implemented on the simulated bus"
            )
        # The socket first: if it fails, no half-made bus is left to warn when collected.
        try:
            self._sim_sock = loopback_socket(channel, port, exact_ids(can_filters))
        except OSError as exc:
            raise can.CanInitializationError(str(exc)) from exc
        self._sim_dest = (channel, port)
        self._sim_fd = fd
        self._sim_timeout: float | None = None  # the socket's blocking timeout for sends
        self.channel_info = f"exolink simulated bus {channel}:{port} on {LOOPBACK}"
        super().__init__(channel, can_filters=can_filters, **kwargs)

    @property
    def socket(self) -> Socket:
        """The bus's UDP socket (bound to the group, joined on loopback), for direct reading."""
        return self._sim_sock

    @property
    def protocol(self) -> can.CanProtocol:
        return can.CanProtocol.CAN_FD if self._sim_fd else can.CanProtocol.CAN_20

    def fileno(self) -> int:
        return self._sim_sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send from the source address of the frame's id (what a filtered reader joins)."""
        if not self._sim_fd and msg.is_fd:
            raise can.CanOperationError("cannot send FD message over bus with CAN FD disabled")
        data = pack_message(msg)
        sock = self._sim_sock
        if timeout != self._sim_timeout:
            self._sim_timeout = timeout
            sock.settimeout(timeout)
        src = socket.inet_aton(sim_source(msg.arbitration_id, msg.is_extended_id))
        info = _PKTINFO.pack(0, src, bytes(4))
        try:
            sent = sock.sendmsg([data], [(socket.IPPROTO_IP, IP_PKTINFO, info)], 0, self._sim_dest)
        except TimeoutError:
            raise can.CanTimeoutError() from None
        except OSError as exc:
            raise can.CanOperationError(f"failed to send via socket: {exc}") from exc
        if sent < len(data):
            raise can.CanTimeoutError()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """One datagram as python-can's udp_multicast bus reads it, with the kernel's time."""
        sock = self._sim_sock
        try:
            ready = select.select([sock], [], [], timeout)[0]
        except OSError as exc:
            raise can.CanOperationError(f"failed to wait for the sim bus socket: {exc}") from exc
        if not ready:
            return None, False
        data, ancdata, _flags, _addr = sock.recvmsg(_MAX_DATAGRAM, _CTL_SIZE)
        stamp = None
        for level, kind, raw in ancdata:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                sec, nsec = _TIMESPEC.unpack(raw[: _TIMESPEC.size])
                stamp = sec + nsec * 1e-9
        if stamp is None:
            raise can.CanOperationError("the kernel gave no receive time (SO_TIMESTAMPNS)")
        try:
            msg = unpack_message(data, replace={"timestamp": stamp}, check=True)
        except Exception as exc:  # not python-can's msgpack layout
            raise can.CanOperationError("could not unpack received message") from exc
        if not self._sim_fd and msg.is_fd:
            return None, False
        return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        self._sim_sock.close()

    @staticmethod
    def _detect_available_configs() -> list[AutoDetectedConfig]:
        return [{"interface": INTERFACE, "channel": DEFAULT_GROUP}]
