"""CDR for fixed-layout messages from a prepared template: one ``struct.pack`` per message.

rosbags' generic serializer builds a message object and walks its fields (~12 us per JointState
on an x86 core, plus numpy arrays to hold the values); the reader publishes 200 messages a second
on a Cortex-A8. A message whose strings and sequence lengths never change (six joint names, an
empty frame_id) has a fixed byte layout: everything but the numbers is computed once. rosbags
stays the reference: tests/test_cdr.py checks every template byte for byte against its
serializer over generated values (checking at start-up would load rosbags and numpy into the
very processes this module keeps them out of).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any, NamedTuple, Protocol

CDR_LE = b"\x00\x01\x00\x00"  # encapsulation: plain CDR, little endian


class _Layout:
    """Lays out a message as constant bytes and typed slots, aligned as CDR aligns them
    (each primitive on its own size, counted from the end of the encapsulation header)."""

    def __init__(self) -> None:
        self.fmt = "<"
        self.consts: list[bytes] = []
        self._pending = b""
        self.pos = 0

    def _flush(self) -> None:
        if self._pending:
            self.fmt += f"{len(self._pending)}s"
            self.consts.append(self._pending)
            self._pending = b""

    def align(self, n: int) -> None:
        self.const(b"\x00" * ((-self.pos) % n))

    def const(self, data: bytes) -> None:
        self._pending += data
        self.pos += len(data)

    def u32(self, value: int) -> None:
        self.align(4)
        self.const(struct.pack("<I", value))

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.u32(len(data))
        self.const(data)

    def slots(self, code: str, count: int = 1) -> None:
        size = struct.calcsize("<" + code)
        self.align(size)
        self._flush()
        self.fmt += f"{count}{code}" if count > 1 else code
        self.pos += size * count

    def done(self) -> tuple[struct.Struct, list[bytes]]:
        self._flush()
        return struct.Struct(self.fmt), self.consts


def _header(lay: _Layout) -> None:
    lay.slots("i")  # stamp.sec
    lay.slots("I")  # stamp.nanosec
    lay.string("")  # frame_id


class JointStateCdr:
    """sensor_msgs/JointState with fixed names: positions, and efforts or none, no velocities."""

    TYPE = "sensor_msgs/msg/JointState"

    def __init__(self, names: Sequence[str]) -> None:
        self.names = list(names)
        n = len(self.names)
        self._with, self._with_consts = self._layout(n, n)
        self._without, self._without_consts = self._layout(n, 0)
        self.n = n

    def _layout(self, n: int, efforts: int) -> tuple[struct.Struct, list[bytes]]:
        lay = _Layout()
        _header(lay)
        lay.u32(n)
        for name in self.names:
            lay.string(name)
        lay.u32(n)
        lay.slots("d", n)  # position
        lay.u32(0)  # velocity: empty
        lay.u32(efforts)
        if efforts:
            lay.slots("d", efforts)
        return lay.done()

    def encode(self, ns: int, positions: Sequence[float], efforts: Sequence[float] | None) -> bytes:
        """positions (and efforts, if any) in SI units, one per name; ``ns`` is the stamp."""
        sec, nsec = divmod(ns, 1_000_000_000)
        if efforts is None:
            a, b = self._without_consts
            return CDR_LE + self._without.pack(sec, nsec, a, *positions, b)
        a, b = self._with_consts
        return CDR_LE + self._with.pack(sec, nsec, a, *positions, b, *efforts)


class FootSwitchesCdr:
    """exolink_msgs/FootSwitches (header, four bools, uint8 battery_raw, float32 battery_volts)."""

    TYPE = "exolink_msgs/msg/FootSwitches"

    def __init__(self) -> None:
        lay = _Layout()
        _header(lay)
        lay.slots("?", 4)
        lay.slots("B")
        lay.slots("f")
        self._s, (self._a, self._b) = lay.done()  # frame_id; float32's alignment

    def encode(self, ns: int, switches: Sequence[bool], battery_raw: int, volts: float) -> bytes:
        sec, nsec = divmod(ns, 1_000_000_000)
        return CDR_LE + self._s.pack(sec, nsec, self._a, *switches, battery_raw, self._b, volts)


class MaccepaStateCdr:
    """exolink_msgs/MaccepaState: header, uint8 board, uint8 stale, eleven int16 values."""

    TYPE = "exolink_msgs/msg/MaccepaState"
    N_VALUES = 11

    def __init__(self) -> None:
        lay = _Layout()
        _header(lay)
        lay.slots("B", 2)
        lay.slots("h", self.N_VALUES)
        self._s, (self._frame_id, self._pad) = lay.done()  # the int16s start on an even byte

    def encode(self, ns: int, board: int, stale: int, values: Sequence[int]) -> bytes:
        sec, nsec = divmod(ns, 1_000_000_000)
        return CDR_LE + self._s.pack(sec, nsec, self._frame_id, board, stale, self._pad, *values)


class HeartbeatCdr:
    """exolink_msgs/Heartbeat of one node and process: only the stamp and count change."""

    TYPE = "exolink_msgs/msg/Heartbeat"

    def __init__(self, node: str, pid: int, state: str = "running") -> None:
        lay = _Layout()
        lay.slots("i")
        lay.slots("I")
        lay.string(node)
        lay.slots("Q")  # count
        lay.slots("i")  # pid
        lay.string(state)
        self._s, consts = lay.done()
        self._a, self._b = consts
        self.pid = pid

    def encode(self, ns: int, count: int) -> bytes:
        sec, nsec = divmod(ns, 1_000_000_000)
        return CDR_LE + self._s.pack(sec, nsec, self._a, count, self.pid, self._b)


class _Writer:
    """CDR written field by field, for messages whose strings change with every message."""

    def __init__(self) -> None:
        self.buf = bytearray(CDR_LE)

    def put(self, code: str, *values: Any) -> None:
        size = struct.calcsize("<" + code[-1])
        self.buf += b"\x00" * ((-(len(self.buf) - 4)) % size)
        self.buf += struct.pack("<" + code, *values)

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.put("I", len(data))
        self.buf += data

    def stamp(self, ns: int) -> None:
        self.put("iI", *divmod(ns, 1_000_000_000))


def diagnostics(
    ns: int, name: str, level: int, message: str, hardware_id: str, values: dict[str, Any]
) -> bytes:
    """A one-status diagnostic_msgs/DiagnosticArray (once a second: written field by field)."""
    w = _Writer()
    w.stamp(ns)
    w.string("")  # frame_id
    w.put("I", 1)
    w.put("B", level)
    for text in (name, message, hardware_id):
        w.string(text)
    w.put("I", len(values))
    for k, v in values.items():
        w.string(str(k))
        w.string(str(v))
    return bytes(w.buf)


def string_msg(text: str) -> bytes:
    """A std_msgs/String (the command log's JSON lines)."""
    w = _Writer()
    w.string(text)
    return bytes(w.buf)


def joint_command(
    ns: int, joint: str, mode: int, setpoint: int, stiffness: int, source: str
) -> bytes:
    """exolink_msgs/JointCommand: a joint-control frame someone put on the bus."""
    w = _Writer()
    w.stamp(ns)
    w.string("")  # frame_id
    w.string(joint)
    w.put("B", mode)
    w.put("h", setpoint)
    w.put("B", stiffness)
    w.string(source)
    return bytes(w.buf)


class PatternFields(Protocol):
    """What a PatternState says (the pattern player's status, exolink.control.replies)."""

    state: str
    reason: str
    index: int
    length: int
    speed: int
    period_ms: float
    file: str
    operator: str
    timing: str


def pattern_state(ns: int, s: PatternFields, selected: Sequence[bool]) -> bytes:
    """exolink_msgs/PatternState from the player's status."""
    w = _Writer()
    w.stamp(ns)
    w.string(s.state)
    w.string(s.reason)
    w.put("II", s.index, s.length)
    w.put("B", s.speed)
    w.put("f", s.period_ms)
    w.put("6?", *selected)
    for text in (s.file, s.operator, s.timing):
        w.string(text)
    return bytes(w.buf)


def controller_activity(ns: int, version: int, controllers: Sequence[Sequence[str]]) -> bytes:
    """exolink_msgs/ControllerActivity from (name, type, state, error) per controller."""
    w = _Writer()
    w.stamp(ns)
    w.put("I", version)
    for i in range(4):
        w.put("I", len(controllers))
        for c in controllers:
            w.string(c[i])
    return bytes(w.buf)


def watchdog_event_msg(ns: int, state: str, reason: str, detail: str, frames_sent: int) -> bytes:
    """exolink_msgs/WatchdogEvent (the supervisor's, on change and once a second)."""
    w = _Writer()
    w.stamp(ns)
    for text in (state, reason, detail):
        w.string(text)
    w.put("I", frames_sent)
    return bytes(w.buf)


def trigger_event(ns: int, edge: str, chip: str, line: int, count: int, source: str) -> bytes:
    """exolink_msgs/TriggerEvent: one edge of the experiment trigger line."""
    w = _Writer()
    w.stamp(ns)
    w.string(edge)
    w.string(chip)
    w.put("I", line)
    w.put("Q", count)
    w.string(source)
    return bytes(w.buf)


class _Reader:
    """CDR read field by field, for messages from the network: any inconsistency is a
    ValueError naming the type, never an IndexError deep inside."""

    def __init__(self, payload: bytes, typename: str) -> None:
        if payload[:4] != CDR_LE:
            raise ValueError(f"{typename}: not little-endian CDR")
        self.data, self.pos, self.typename = payload, 4, typename

    def get(self, code: str) -> tuple[Any, ...]:
        """Values of one type (``code`` repeats one letter: the alignment is that type's)."""
        size = struct.calcsize("<" + code[-1])
        self.pos += (-(self.pos - 4)) % size
        try:
            values = struct.unpack_from("<" + code, self.data, self.pos)
        except struct.error as exc:
            raise ValueError(f"truncated {self.typename}: {exc}") from None
        self.pos += struct.calcsize("<" + code)
        return values

    def string(self) -> str:
        (n,) = self.get("I")
        raw = self.data[self.pos : self.pos + n]
        if n == 0 or len(raw) != n or raw[-1] != 0:
            raise ValueError(f"garbled {self.typename}: bad string at byte {self.pos}")
        self.pos += n
        try:
            return raw[:-1].decode()
        except UnicodeDecodeError as exc:
            raise ValueError(f"garbled {self.typename}: {exc}") from None

    def count(self, at_least: int) -> int:
        """A sequence's length, refused when the rest of the payload cannot hold it."""
        (n,) = self.get("I")
        if n * at_least > len(self.data) - self.pos:
            raise ValueError(
                f"garbled {self.typename}: a sequence of {n} in {len(self.data)} bytes"
            )
        return int(n)


def string_of(payload: bytes) -> str:
    """The text of a std_msgs/String; ValueError when the payload is not one."""
    return _Reader(payload, "String").string()


def watchdog_event(payload: bytes) -> tuple[str, str, str, int]:
    """(state, reason, detail, frames_sent) of an exolink_msgs/WatchdogEvent; ValueError when
    the payload is not one (it comes over the network: checked, never trusted)."""
    r = _Reader(payload, "WatchdogEvent")
    r.get("iI")  # stamp
    state, reason, detail = r.string(), r.string(), r.string()
    return state, reason, detail, r.get("I")[0]


def pattern_state_of(payload: bytes) -> tuple[str, str]:
    """(state, operator) of an exolink_msgs/PatternState: what the supervisor's operator-lost
    check needs; ValueError when the payload is not one."""
    r = _Reader(payload, "PatternState")
    r.get("iI")  # stamp
    state = r.string()
    r.string()  # reason
    for code in ("II", "B", "f", "6?"):  # index, length, speed, period_ms, selected: each aligned
        r.get(code)
    r.string()  # file
    operator = r.string()
    r.string()  # timing_mode: read so that a message cut short is refused whole
    return state, operator


class KeyValue(NamedTuple):
    key: str
    value: str


class Status(NamedTuple):
    """One diagnostic_msgs/DiagnosticStatus."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: list[KeyValue]


def diagnostic_statuses(payload: bytes) -> list[Status]:
    """The statuses of a diagnostic_msgs/DiagnosticArray (a node's, once a second, read by the
    supervisor without a typestore); ValueError when the payload is not one."""
    r = _Reader(payload, "DiagnosticArray")
    r.get("iI")  # stamp
    r.string()  # frame_id
    out = []
    for _ in range(r.count(4 * 5)):
        (level,) = r.get("B")
        name, message, hardware_id = r.string(), r.string(), r.string()
        values = [KeyValue(r.string(), r.string()) for _ in range(r.count(2 * 5))]
        out.append(Status(level, name, message, hardware_id, values))
    return out
