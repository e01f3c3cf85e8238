"""The MACCEPA actuator-board protocol, typed: the one place that encodes and decodes its frames.

Frame id = base + board id (0..9). Layouts come from maccepa.dbc (one message per board, generated);
decoding never raises, encoding validates first so an invalid command makes no frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Final, NamedTuple

import can

from exolink.protocol import h2
from exolink.protocol.dbc import FrameSpec, ProtocolError, Received, bundled, load

BOARDS = range(10)
GAIN_BASE = {"kp": 10, "ki": 20, "kd": 30}
SETPOINT_BASE, DUTY_BASE = 40, 80
SENSORS_BASE: Final = 50
POSITIONS_BASE: Final = 60
CONTROLLER_BASE: Final = 70
CONTROLLERS = {"position": 0, "velocity": 1}


class Sensors(NamedTuple):
    board: int
    current: int
    temperature: int
    velocity: int
    load: int


class Positions(NamedTuple):
    board: int
    link: int
    lever: int
    extra_position: int
    extra_sensor: int


class Controller(NamedTuple):
    board: int
    setpoint: int
    actuation: int
    process_variable: int


class Gain(NamedTuple):
    board: int
    which: str  # kp | ki | kd
    value: float
    controller: int


class Setpoint(NamedTuple):
    board: int
    value: float
    controller: int


class Duty(NamedTuple):
    board: int
    duty: int
    action: int  # 0 stop control, 1 set duty


class Unknown(NamedTuple):
    frame_id: int
    reason: str
    data: bytes


GAIN_NAMES = ("Kp", "Ki", "Kd")
MaccepaFrame = Sensors | Positions | Controller | Gain | Setpoint | Duty
_KIND = {
    "Sensors": Sensors,
    "Positions": Positions,
    "Controller": Controller,
    "Setpoint": Setpoint,
    "Duty": Duty,
}


def _table() -> dict[int, tuple[FrameSpec, str, int]]:
    layout = load(bundled("maccepa"))
    table = {}
    for spec in layout.by_id.values():
        kind, _, board = spec.name.rpartition("_B")
        table[spec.frame_id] = (spec, kind, int(board))
    return table


_TABLE = _table()
_BY_NAME = {spec.name: spec for spec, _, _ in _TABLE.values()}
BOARD_DATA_IDS = tuple(
    fid for fid, (_, kind, _) in _TABLE.items() if kind in ("Sensors", "Positions", "Controller")
)


def dlc_of(frame_id: int) -> int | None:
    """The length of the MACCEPA frame with this id (None: not a MACCEPA id)."""
    entry = _TABLE.get(frame_id)
    return entry[0].dlc if entry is not None else None


def h2_shaped(ids: Iterable[int]) -> list[tuple[int, int]]:
    """(id, length) of the H2 frames on these MACCEPA ids (the H2 uses 70, 75, 80 and 85, which
    are boards 0 and 5's status and board 0 and 5's duty ids): a frame of that length there is
    the H2's, not a board's (a reader of board frames need not receive it: exolink.canbus.filters)."""
    out = []
    for i in ids:
        theirs, ours = h2.dlc_of(i), dlc_of(i)
        if theirs is not None and theirs != ours:
            out.append((i, theirs))
    return out


def data_ids(boards: list[int] | range) -> list[int]:
    return [base + b for b in boards for base in (SENSORS_BASE, POSITIONS_BASE, CONTROLLER_BASE)]


def command_ids(boards: list[int] | range) -> list[int]:
    bases = (*GAIN_BASE.values(), SETPOINT_BASE, DUTY_BASE)
    return [base + b for b in boards for base in bases]


def decode(msg: Received) -> MaccepaFrame | Unknown:
    """Decode any MACCEPA frame; never raises."""
    entry = _TABLE.get(msg.arbitration_id)
    if entry is None or msg.is_extended_id or msg.is_remote_frame:
        return Unknown(msg.arbitration_id, "unknown id", bytes(msg.data))
    spec, kind, board = entry
    if len(msg.data) != spec.dlc:
        return Unknown(msg.arbitration_id, "bad length", bytes(msg.data))
    values = spec.decode(msg.data)
    if kind in GAIN_NAMES:
        return Gain(board, kind.lower(), values[0], values[1])
    return _KIND[kind](board, *values)


def _board(board: int) -> int:
    if isinstance(board, bool) or not isinstance(board, int) or board not in BOARDS:
        raise ProtocolError(f"MACCEPA board id {board!r} is outside 0..9")
    return board


def _controller(controller: int | str) -> int:
    if isinstance(controller, str):
        if controller not in CONTROLLERS:
            raise ProtocolError(f"unknown controller type {controller!r} (position or velocity)")
        return CONTROLLERS[controller]
    if controller not in (0, 1) or isinstance(controller, bool):
        raise ProtocolError(f"controller type {controller!r} is not 0 (position) or 1 (velocity)")
    return controller


def _finite(value: float, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ProtocolError(f"{what}: {value!r} is not a finite number")
    return float(value)


def _msg(name: str, values: tuple[float, ...], checked: bool = True) -> can.Message:
    spec = _BY_NAME[name]
    data = spec.encode(values) if checked else spec.pack(values)
    return can.Message(arbitration_id=spec.frame_id, data=data, is_extended_id=False)


def encode_gain(board: int, which: str, value: float, controller: int | str) -> can.Message:
    """Kp/Ki/Kd (ids 10/20/30 + board); writing a gain also selects the controller type."""
    b = _board(board)
    if which not in GAIN_BASE:
        raise ProtocolError(f"unknown gain {which!r} (kp, ki or kd)")
    v = _finite(value, which)
    return _msg(f"{which.capitalize()}_B{b}", (v, _controller(controller)))


def encode_setpoint(board: int, value: float, controller: int | str) -> can.Message:
    b = _board(board)
    return _msg(f"Setpoint_B{b}", (_finite(value, "setpoint"), _controller(controller)))


def encode_duty(board: int, duty: float) -> can.Message:
    b = _board(board)
    d = _finite(duty, "duty")
    if not 0 <= d <= 100 or d != int(d):
        raise ProtocolError(f"duty cycle {duty!r} must be a whole percentage 0..100")
    return _msg(f"Duty_B{b}", (int(d), 1))


def encode_stop(board: int) -> can.Message:
    return _msg(f"Duty_B{_board(board)}", (0, 0))


def model_message(frame: Sensors | Positions | Controller) -> can.Message:
    """A simulated board's status frame from its model's own bounded values (``FrameSpec.pack``:
    no check per value; ``encode`` is for everything else)."""
    return _msg(f"{type(frame).__name__}_B{frame.board}", tuple(frame)[1:], checked=False)


def encode(frame: MaccepaFrame) -> can.Message:
    """Any typed frame to a message, bounds-checked against the DBC."""
    if isinstance(frame, Gain):
        return encode_gain(frame.board, frame.which, frame.value, frame.controller)
    name = f"{type(frame).__name__}_B{_board(frame.board)}"
    return _msg(name, tuple(frame)[1:])
