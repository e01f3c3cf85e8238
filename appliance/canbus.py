"""The one place that opens a python-can bus from configuration.

SocketCAN gets kernel receive filters so a node only wakes for its own ids; the other interfaces
(virtual in-process, udp_multicast across processes) apply the same filters in python-can. The
simulated bus (python-can's udp_multicast) is kept on the loopback interface: ``SimBus``.
"""

from __future__ import annotations

import contextlib
import ipaddress
import select
import socket
import struct
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, NamedTuple

from exolink.config import CanConfig

if TYPE_CHECKING:
    import can

STD_MASK = 0x7FF
_I32 = struct.Struct("@i")


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

    try:
        if cfg.interface == "udp_multicast":
            bus = sim_bus_class()(
                cfg.channel, can_filters=filters, receive_own_messages=receive_own_messages
            )
            if filters is not None:
                _udp_kernel_filter(bus, filters)
            return bus
        kwargs: dict[str, object] = {
            "interface": cfg.interface,
            "channel": cfg.channel,
            "receive_own_messages": receive_own_messages,
        }
        if filters is not None:
            kwargs["can_filters"] = filters
        return can.Bus(**kwargs)
    except (OSError, can.CanError, ValueError) as exc:
        raise CanOpenError(_explain(cfg, exc)) from exc


# --- the simulated bus: python-can's udp_multicast, kept on this machine ------------------------
#
# python-can joins its group on whatever interface the route to the group names and sends that
# way: with a default route the sim bus went out on eth0, and a route change mid-run left the
# members joined on the old interface while frames left by the new one (silence, no error).
# Here every socket is bound to the loopback interface: joined on lo, sending through lo with TTL 0
# (the kernel never lets a TTL-0 multicast leave the host). No route is needed at all.

SIM_PORT = 43113  # python-can's default udp_multicast port
LOOPBACK = "lo"
IP_MULTICAST_ALL = 49  # linux/in.h; Python's socket module does not export it
SO_TIMESTAMPNS = 35


def _loopback_socket(group: str, port: int) -> socket.socket:
    """A UDP socket on ``group`` through the loopback interface only, for sending and receiving."""
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
        sock.setsockopt(ip, socket.IP_ADD_MEMBERSHIP, grp + loopback + _I32.pack(lo))
    except OSError:
        sock.close()
        raise
    return sock


def _check_loopback(group: str, port: int, lo: int) -> None:
    """What a send needs, asked of the kernel without sending: the loopback interface up, and
    the loopback network (127.0.0.0/8) on it."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(("127.0.0.1", 0))
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


_SIM_BUS: type | None = None


def sim_bus_class() -> type[can.BusABC]:
    """``SimBus``, defined on first use: python-can is imported only by processes that open a
    bus, and this module's import stays light."""
    global _SIM_BUS
    if _SIM_BUS is None:
        _SIM_BUS = _define_sim_bus()
    return _SIM_BUS


def _define_sim_bus() -> type[can.BusABC]:
    import can
    from can.interfaces.udp_multicast.bus import GeneralPurposeUdpMulticastBus, UdpMulticastBus
    from can.interfaces.udp_multicast.utils import is_msgpack_installed

    class LoopbackGroup(GeneralPurposeUdpMulticastBus):  # type: ignore[misc]
        """python-can's multicast socket holder with our socket (``_create_socket`` is its
        hook); python-can's send and receive as they are."""

        def _create_socket(self, address_family: socket.AddressFamily) -> socket.socket:
            try:
                sock = _loopback_socket(self.group, self.port)
            except OSError as exc:  # python-can turns OSError here into a vaguer message
                raise can.CanInitializationError(str(exc)) from exc
            self.timestamp_nanosecond = True
            return sock

    class SimBus(UdpMulticastBus):  # type: ignore[misc]
        """python-can's udp_multicast bus (its datagrams, its API) on the loopback interface."""

        def __init__(
            self,
            channel: str,
            port: int = SIM_PORT,
            receive_own_messages: bool = False,
            fd: bool = True,
            can_filters: list[dict[str, int | bool]] | None = None,
            **kwargs: object,
        ) -> None:
            is_msgpack_installed()
            if receive_own_messages:
                raise can.CanInterfaceNotImplementedError(
                    "receiving own messages is not yet implemented"
                )
            # The socket first: if it fails, no half-made bus is left to warn when collected.
            self._multicast = LoopbackGroup(channel, port, hop_limit=0)
            can.BusABC.__init__(self, channel, can_filters=can_filters, **kwargs)
            self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20

    return SimBus


# python-can's udp_multicast datagram is msgpack of a dict in pack_message's fixed key order:
# fixmap(11), "timestamp" (fixstr 9) + float64, "arbitration_id" (fixstr 14) + the id as a
# fixint, uint8 or uint16. Offsets below are from the UDP header, where a socket filter starts.
_UDP_HDR = 8
_MAP11, _STR14 = 0x8B, 0xAE
_AT_KEY, _AT_ID = _UDP_HDR + 20, _UDP_HDR + 35
_BPF_LDB, _BPF_LDH, _BPF_JA, _BPF_JEQ, _BPF_JGE, _BPF_RET = 0x30, 0x28, 0x05, 0x15, 0x35, 0x06
SO_ATTACH_FILTER = 26


def _udp_kernel_filter(bus: can.BusABC, filters: list[dict[str, int | bool]]) -> None:
    """The kernel filter SocketCAN has, for the simulated bus: a classic BPF socket filter that
    reads the id out of python-can's datagram and drops other ids before they wake the process.
    On the sim bus every process would otherwise wake for, and decode, every frame of every node.
    A datagram not laid out as expected passes (python-can's own filter still applies)."""
    import ctypes

    ids = [int(f["can_id"]) for f in filters]
    if any(f.get("extended") or int(f.get("can_mask", 0)) != STD_MASK for f in filters):
        return  # only exact standard ids are compiled; python-can filters the rest
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)  # python-can internals
    if not isinstance(sock, socket.socket):
        return
    program = _bpf_ids(ids)
    buf = ctypes.create_string_buffer(program)
    fprog = struct.pack("HL", len(program) // 8, ctypes.addressof(buf))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)


def _bpf_ids(ids: list[int]) -> bytes:
    """accept (the whole datagram) if its id is in ``ids`` or its layout is not the expected
    one, else drop. Jump offsets are counted from the next instruction."""
    n = len(ids)
    # index: 0 ldb[0]  1 jeq map11  2 ldb[key]  3 jeq str14  4 ldb[id]  5 jge 0x80  6 ja CHK
    #        7 jeq 0xcc  8 ldb[id+1]  9 ja CHK  10 jeq 0xcd  11 ldh[id+1]  12.. CHK  then drop, accept
    chk, drop = 12, 12 + n
    acc = drop + 1

    def j(at: int, target: int) -> int:
        return target - at - 1

    ins = [
        (_BPF_LDB, 0, 0, _UDP_HDR),
        (_BPF_JEQ, 0, j(1, acc), _MAP11),
        (_BPF_LDB, 0, 0, _AT_KEY),
        (_BPF_JEQ, 0, j(3, acc), _STR14),
        (_BPF_LDB, 0, 0, _AT_ID),
        (_BPF_JGE, j(5, 7), 0, 0x80),
        (_BPF_JA, 0, 0, j(6, chk)),
        (_BPF_JEQ, 0, j(7, 10), 0xCC),
        (_BPF_LDB, 0, 0, _AT_ID + 1),
        (_BPF_JA, 0, 0, j(9, chk)),
        (_BPF_JEQ, 0, j(10, acc), 0xCD),
        (_BPF_LDH, 0, 0, _AT_ID + 1),
    ]
    ins += [(_BPF_JEQ, j(chk + i, acc), 0, fid) for i, fid in enumerate(ids)]
    ins += [(_BPF_RET, 0, 0, 0), (_BPF_RET, 0, 0, 0xFFFFFFFF)]
    return b"".join(struct.pack("=HBBI", *i) for i in ins)


def _explain(cfg: CanConfig, exc: Exception) -> str:
    base = f"cannot open CAN bus {cfg.interface}:{cfg.channel}: {exc}"
    if cfg.interface == "socketcan":
        return (
            f"{base}. Is the interface present and up? On the board: check the DCAN1 overlay "
            f"and `ip link set {cfg.channel} up type can bitrate {cfg.bitrate}`; for tests: "
            f"`ip link add dev {cfg.channel} type vcan && ip link set {cfg.channel} up`."
        )
    if cfg.interface == "udp_multicast":
        return f"cannot open the simulated CAN bus (udp_multicast {cfg.channel} on loopback): {exc}"
    return base


# --- the receive hot path ----------------------------------------------------------------------

SO_RXQ_OVFL = 40  # asm-generic/socket.h; Python's socket module does not export it
_CAN_FRAME = struct.Struct("=IB3x8s")  # linux/can.h struct can_frame
_CAN_EFF_FLAG, _CAN_RTR_FLAG, _CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
_TIMESPEC = struct.Struct("@ll")
_U32 = struct.Struct("=I")
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size) + socket.CMSG_SPACE(_U32.size)
_BATCH = 64
SO_RCVBUFFORCE = 33
RCVBUF_BYTES = 1 << 20


class Frame(NamedTuple):
    """One received CAN frame: the attributes the protocol decoders read from a can.Message."""

    timestamp: float  # kernel receive time, seconds since the epoch
    arbitration_id: int
    data: bytes
    is_extended_id: bool = False
    is_remote_frame: bool = False
    is_error_frame: bool = False


class FrameReader:
    """Reads the socket under a python-can bus directly, in batches.

    python-can opens, configures and filters the bus (kernel filters on SocketCAN) and still
    sends; only receiving bypasses it: its ``recv`` builds a checked ``can.Message`` per frame
    behind a ``select`` per frame (~35 us per frame on an x86 core, the reader's largest cost).
    Here one ``select`` is followed by every frame already queued, each a ``recvmsg`` and one
    ``struct`` unpack. ``dropped`` is the kernel's count of frames this socket lost to a full
    receive buffer (SO_RXQ_OVFL), which python-can does not report.
    """

    def __init__(self, bus: can.BusABC, cfg: CanConfig, ids: Iterable[int] | None) -> None:
        self.bus = bus
        self.ids = frozenset(ids) if ids is not None else None
        # None where the kernel cannot tell: on the sim bus, datagrams our socket filter rejects
        # are counted in the same sk_drops as an overflowing queue.
        self.dropped: int | None = 0
        self.malformed = 0
        if cfg.interface == "socketcan":
            self._sock: socket.socket = bus.socket  # type: ignore[attr-defined]
            self._parse = self._parse_socketcan
        elif cfg.interface == "udp_multicast":
            self._sock = bus._multicast._socket  # type: ignore[attr-defined]  # python-can internals
            self._parse = self._parse_udp
            if ids is not None:
                self.dropped = None
            import msgpack

            self._unpackb = msgpack.unpackb
        else:  # the in-process virtual bus has no socket: python-can's own receive path
            self._sock = None  # type: ignore[assignment]
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
            _size_receive_buffer(self._sock)

    def read(self, timeout: float) -> list[Frame]:
        """Every frame queued now, waiting up to ``timeout`` for the first one."""
        if self._sock is None:
            msg = self.bus.recv(timeout)
            if msg is None:
                return []
            return [
                Frame(
                    msg.timestamp,
                    msg.arbitration_id,
                    bytes(msg.data),
                    msg.is_extended_id,
                    msg.is_remote_frame,
                    msg.is_error_frame,
                )
            ]
        sock = self._sock
        if not select.select((sock,), (), (), timeout)[0]:
            return []
        out: list[Frame] = []
        parse = self._parse
        for _ in range(_BATCH):
            try:
                raw, anc, _flags, _addr = sock.recvmsg(256, _ANCILLARY, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                break
            ts = 0.0
            for level, kind, cdata in anc:
                if level == socket.SOL_SOCKET:
                    if kind == SO_RXQ_OVFL and len(cdata) >= 4:
                        if self.dropped is not None:
                            self.dropped = _U32.unpack_from(cdata)[0]
                    elif len(cdata) >= _TIMESPEC.size:  # SO_TIMESTAMPNS, set by python-can
                        sec, ns = _TIMESPEC.unpack_from(cdata)
                        ts = sec + ns * 1e-9
            frame = parse(raw, ts or time.time())
            if frame is not None:
                out.append(frame)
        return out

    def _parse_socketcan(self, raw: bytes, ts: float) -> Frame | None:
        if len(raw) != _CAN_FRAME.size:  # a CAN FD frame on a classic reader
            self.malformed += 1
            return None
        can_id, dlc, data = _CAN_FRAME.unpack(raw)
        if dlc > 8:
            self.malformed += 1
            return None
        ext = bool(can_id & _CAN_EFF_FLAG)
        fid = can_id & (0x1FFFFFFF if ext else 0x7FF)
        return Frame(
            ts, fid, data[:dlc], ext, bool(can_id & _CAN_RTR_FLAG), bool(can_id & _CAN_ERR_FLAG)
        )

    def _parse_udp(self, raw: bytes, ts: float) -> Frame | None:
        try:
            d = self._unpackb(raw)
            fid = d["arbitration_id"]
            frame = Frame(
                ts,
                fid,
                bytes(d["data"]),
                bool(d.get("is_extended_id")),
                bool(d.get("is_remote_frame")),
                bool(d.get("is_error_frame")),
            )
        except Exception:  # anything on the group that is not python-can's msgpack layout
            self.malformed += 1
            return None
        if self.ids is not None and (frame.is_extended_id or fid not in self.ids):
            return None  # the kernel filter SocketCAN would have applied
        return frame


def _size_receive_buffer(sock: socket.socket) -> None:
    """Room for a 100 ms stall at a full 1 Mbit/s bus (~800 frames, ~1 KB of kernel memory each):
    SO_RCVBUFFORCE where permitted (CAP_NET_ADMIN), else as much as net.core.rmem_max allows."""
    for opt in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, RCVBUF_BYTES)
            return
        except OSError:
            continue


def open_reader(cfg: CanConfig, ids: Iterable[int] | None = None) -> FrameReader:
    """A bus for receiving ``ids`` (all if None), read in batches; ``.bus`` sends and closes."""
    bus = open_bus(cfg, filters=id_filters(ids) if ids is not None else None)
    return FrameReader(bus, cfg, ids)
