"""The H2 exoskeleton protocol, typed: the one place that encodes and decodes H2 frames.

Layouts come from h2.dbc; the classes below only give them names. Decoding never raises: an
unknown id or a wrong length comes back as ``Unknown`` so a reader counts it and moves on.
Encoding validates everything first and raises ProtocolError: an invalid command makes no frame.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from typing import Final, NamedTuple

import can

from exolink.protocol.dbc import FrameSpec, ProtocolError, Received, bundled, load

JOINTS: tuple[str, ...] = ("r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle")

JOINT_CONTROL, MIN_ANGLES, MAX_ANGLES, STREAM_CONTROL = 70, 75, 80, 85
JOINT_ANGLES: Final = 110
JOINT_TORQUES: Final = 120
FOOT_SWITCHES: Final = 130  # the last of a 10 ms cycle
DATA_IDS = (JOINT_ANGLES, JOINT_TORQUES, FOOT_SWITCHES)
COMMAND_IDS = (JOINT_CONTROL, MIN_ANGLES, MAX_ANGLES, STREAM_CONTROL)
PERIOD_S = 0.010

MODES = {"position": 1, "stiffness": 2, "torque": 3, "disabled": 4, "stopped": 5}
MODE_NAMES = {v: k for k, v in MODES.items()}


class JointAngles(NamedTuple):
    r_hip: int
    r_knee: int
    r_ankle: int
    l_hip: int
    l_knee: int
    l_ankle: int


class JointTorques(NamedTuple):
    r_hip: int
    r_knee: int
    r_ankle: int
    l_hip: int
    l_knee: int
    l_ankle: int


class FootSwitches(NamedTuple):
    r_heel: int
    r_toe: int
    l_heel: int
    l_toe: int
    battery: int


class JointControl(NamedTuple):
    motor: int
    mode: int
    setpoint: int
    stiffness: int


class MinAngles(NamedTuple):
    r_hip: int
    r_knee: int
    r_ankle: int
    l_hip: int
    l_knee: int
    l_ankle: int


class MaxAngles(NamedTuple):
    r_hip: int
    r_knee: int
    r_ankle: int
    l_hip: int
    l_knee: int
    l_ankle: int


class StreamControl(NamedTuple):
    start: int


class Unknown(NamedTuple):
    """A frame this protocol cannot read; ``reason`` is 'unknown id' or 'bad length'."""

    frame_id: int
    reason: str
    data: bytes


H2Frame = (
    JointAngles | JointTorques | FootSwitches | JointControl | MinAngles | MaxAngles | StreamControl
)
_CLASSES: dict[str, type] = {c.__name__: c for c in H2Frame.__args__}


class _Table:
    """Frame id -> (layout, class), checked once against the DBC so names cannot drift."""

    def __init__(self) -> None:
        layout = load(bundled("h2"))
        self.by_id: dict[int, tuple[FrameSpec, type]] = {}
        for name, cls in _CLASSES.items():
            spec = layout.frame(name)
            names = tuple(s.name for s in spec.signals)
            if names != cls._fields:  # type: ignore[attr-defined]
                raise ProtocolError(f"h2.dbc {name} signals {names} != codec fields {cls._fields}")  # type: ignore[attr-defined]
            self.by_id[spec.frame_id] = (spec, cls)
        self.spec = {cls: spec for spec, cls in self.by_id.values()}
        lo = layout.frame("MinAngles").signals
        # The mechanical range per joint is carried by the accepted-angle frames' DBC bounds.
        self.ranges = {s.name: (int(s.minimum), int(s.maximum)) for s in lo}


_TABLE = _Table()
RANGES: dict[str, tuple[int, int]] = _TABLE.ranges


def _signal_mask(cls: type, name: str) -> bytes:
    """Eight bytes with the DBC bytes of one signal set: a content mask (can-bcm's)."""
    sig = next(s for s in _TABLE.spec[cls].signals if s.name == name)
    size = struct.calcsize(sig.fmt)
    return bytes(8)[: sig.byte] + b"\xff" * size + bytes(8 - sig.byte - size)


MODE_MASK = _signal_mask(JointControl, "mode")  # joint control's mode byte, per h2.dbc
MODE_BYTE = MODE_MASK.index(0xFF)


def dlc_of(frame_id: int) -> int | None:
    """The length of the H2 frame with this id (None: not an H2 id): where another protocol
    shares an id (MACCEPA status on 70 and 75), the length tells the two apart."""
    entry = _TABLE.by_id.get(frame_id)
    return entry[0].dlc if entry is not None else None


def decode(msg: Received) -> H2Frame | Unknown:
    """Decode any H2 frame; never raises (hot path of the reader)."""
    entry = _TABLE.by_id.get(msg.arbitration_id)
    if entry is None or msg.is_extended_id or msg.is_remote_frame:
        return Unknown(msg.arbitration_id, "unknown id", bytes(msg.data))
    spec, cls = entry
    if len(msg.data) != spec.dlc:
        return Unknown(msg.arbitration_id, "bad length", bytes(msg.data))
    return cls._make(spec.decode(msg.data))  # type: ignore[attr-defined]


def _message(frame: H2Frame, checked: bool = True) -> can.Message:
    spec = _TABLE.spec[type(frame)]
    data = spec.encode(tuple(frame)) if checked else spec.pack(frame)
    return can.Message(arbitration_id=spec.frame_id, data=data, is_extended_id=False)


def model_message(frame: H2Frame) -> can.Message:
    """The simulator's frame from its model's own bounded values (``FrameSpec.pack``: no check
    per value; ``encode`` is for everything else)."""
    return _message(frame, checked=False)


def encode(frame: H2Frame) -> can.Message:
    """Any H2 frame to a CAN message, bounds-checked against the DBC."""
    return _message(frame)


def motor_id(joint: int | str) -> int:
    """Accept 1..6 or a joint name; the error lists what is valid."""
    if isinstance(joint, str):
        if joint in JOINTS:
            return JOINTS.index(joint) + 1
        if joint.isdigit():
            joint = int(joint)
        else:
            raise ProtocolError(f"unknown joint {joint!r} (valid: {', '.join(JOINTS)} or 1..6)")
    if isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= 6:
        raise ProtocolError(f"motor id {joint!r} is outside 1..6")
    return joint


def mode_id(mode: int | str) -> int:
    if isinstance(mode, str):
        if mode not in MODES:
            raise ProtocolError(f"unknown control mode {mode!r} (valid: {', '.join(MODES)})")
        return MODES[mode]
    if isinstance(mode, bool) or mode not in MODE_NAMES:
        raise ProtocolError(f"control mode {mode!r} is outside 1..5")
    return mode


def _whole(value: float, what: str, unit: str) -> int:
    """A field the frame carries in whole ``unit`` (degrees, torque counts, percent)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ProtocolError(f"{what}: {value!r} is not a finite number")
    if value != int(value):
        raise ProtocolError(
            f"{what}: {value} is not a whole number (the protocol carries whole {unit})"
        )
    return int(value)


def encode_joint_control(
    motor: int | str, mode: int | str, setpoint: float = 0, stiffness: float = 0
) -> can.Message:
    """Joint control (id 70). Position set-points must lie in the joint's mechanical range."""
    return _message(joint_control(motor, mode, setpoint, stiffness))


def joint_control_payload(motor: int, mode: int, setpoint: int, stiffness: int) -> bytes:
    """A joint-control frame's bytes for values the controller manager has already held to
    the limits in force (its planned slots): the DBC's bounds checked once more, cheaply, and
    no ``can.Message``. A whole set of checks per frame was most of a planned slot's CPU on
    the board (a new frame per joint per slot in a gait's first cycle)."""
    return _TABLE.spec[JointControl].pack_whole((motor, mode, setpoint, stiffness))


def joint_control(
    motor: int | str, mode: int | str, setpoint: float = 0, stiffness: float = 0
) -> JointControl:
    """A joint command checked as its frame would be (ProtocolError names what is wrong),
    without making the frame: a command checked here is encoded once, where it is sent."""
    m = motor_id(motor)
    md = mode_id(mode)
    sp = _whole(setpoint, "setpoint", "torque counts" if md == MODES["torque"] else "degrees")
    st = _whole(stiffness, "stiffness", "percent")
    joint = JOINTS[m - 1]
    if md in (MODES["position"], MODES["stiffness"]):
        lo, hi = RANGES[joint]
        if not lo <= sp <= hi:
            raise ProtocolError(f"{joint} position set-point {sp} deg is outside {lo}..{hi}")
    if md != MODES["stiffness"] and st != 0:
        raise ProtocolError(f"stiffness is only valid in stiffness mode, got {st}")
    if md in (MODES["disabled"], MODES["stopped"]) and sp != 0:
        raise ProtocolError(f"mode {MODE_NAMES[md]} takes no set-point, got {sp}")
    jc = JointControl(m, md, sp, st)
    _TABLE.spec[JointControl].check(tuple(jc))  # the DBC's bounds (stiffness 0..100, int8)
    return jc


def encode_accepted_angles(kind: str, angles: Mapping[str, float] | Sequence[float]) -> can.Message:
    """Min (id 75) or max (id 80) accepted position set-points, one per joint."""
    if isinstance(angles, Mapping):
        unknown = set(angles) - set(JOINTS)
        if unknown:
            raise ProtocolError(f"unknown joints {sorted(unknown)} (valid: {', '.join(JOINTS)})")
        missing = [j for j in JOINTS if j not in angles]
        if missing:
            raise ProtocolError(f"{kind} angles missing for {', '.join(missing)}")
        values = [angles[j] for j in JOINTS]
    else:
        values = list(angles)
    if len(values) != 6:
        raise ProtocolError(f"{kind} angles need 6 values (one per joint), got {len(values)}")
    ints = [_whole(v, f"{kind} angle {j}", "degrees") for v, j in zip(values, JOINTS, strict=True)]
    if kind == "min":
        return _message(MinAngles(*ints))
    if kind == "max":
        return _message(MaxAngles(*ints))
    raise ProtocolError(f"accepted-angle kind must be 'min' or 'max', got {kind!r}")


def encode_stream(start: bool) -> can.Message:
    """Start (True) or stop (False) the board's 100 Hz data stream (id 85)."""
    return _message(StreamControl(1 if start else 0))


def safe_action(action: str) -> list[can.Message]:
    """The watchdog's frames: every joint disabled (type 4) or stopped (type 5)."""
    md = {"disable": MODES["disabled"], "stop": MODES["stopped"]}.get(action)
    if md is None:
        raise ProtocolError(f"safe action must be 'disable' or 'stop', got {action!r}")
    return [_message(JointControl(m, md, 0, 0)) for m in range(1, 7)]
