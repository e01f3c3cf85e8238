"""MACCEPA boards' frames as their state: the sensors, positions and controller frames of one
10 ms board cycle become one ``exolink_msgs/MaccepaState`` (as JointState joins the H2's angle
and torque frames), with a stale bit for each kind of frame the cycle lacked.

One sample per board cycle instead of three: on the board each Zenoh sample costs ~1 ms of the
one core (benchmarks/board/units.py). Whichever node reads the boards off the bus publishes
these: the h2 reader with ``maccepa_boards`` (one process and one read for the whole bus), or
the MACCEPA bridge on a bus without the H2 reader.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from exolink.protocol import maccepa
from exolink.wire import cdr

STATE = cdr.MaccepaStateCdr.TYPE

# The frames of a board cycle, in protocol order, and each one's bit in MaccepaState's
# ``stale`` field; a frame's fields after ``board`` are MaccepaState's int16 values in order
# (the protocol's NamedTuples say so, and tests/test_maccepa_bridge.py checks it). The
# controller frame ends the cycle.
_PARTS: dict[type, int] = {maccepa.Sensors: 1, maccepa.Positions: 2, maccepa.Controller: 4}
_ALL_PARTS = 7
_CYCLE_END = 4


def topic(board: int) -> str:
    return f"maccepa/b{board}/state"


class BoardCycle:
    """One board's frames of the cycle under way, and the last values of each kind of frame."""

    def __init__(self) -> None:
        self.values: dict[type, tuple[int, ...]] = {
            cls: (0,) * (len(cls._fields) - 1)  # type: ignore[attr-defined]
            for cls in _PARTS
        }
        self.seen = 0  # bits of the frames this cycle brought
        self.first_ts = 0.0

    def add(self, frame: Any, ts: float) -> list[tuple[float, int, list[int]]]:
        """The cycles this frame ends: its own at the controller frame, the one before when a
        frame of a kind the cycle already has shows a new cycle began (a controller frame lost)."""
        kind = type(frame)
        bit = _PARTS[kind]
        done = [self._end()] if self.seen & bit else []
        if not self.seen:
            self.first_ts = ts
        self.seen |= bit
        self.values[kind] = frame[1:]  # its values, in MaccepaState's order
        if bit == _CYCLE_END:
            done.append(self._end())
        return done

    def _end(self) -> tuple[float, int, list[int]]:
        """(first frame's time, stale bits, the eleven values) of the cycle; starts the next."""
        stale = _ALL_PARTS & ~self.seen
        out = [v for cls in _PARTS for v in self.values[cls]]  # in _PARTS' (the protocol's) order
        self.seen = 0
        return self.first_ts, stale, out


class BoardStates:
    """The boards' frames in, each finished cycle out to ``emit(board, CDR payload, ns)``,
    stamped with its first frame's kernel time. A frame that is not one of these boards' status
    frames is counted (``malformed``) and skipped, never raised."""

    def __init__(self, boards: list[int], emit: Callable[[int, bytes, int], None]) -> None:
        self.boards = list(boards)
        self.ids = frozenset(maccepa.data_ids(self.boards))
        self.cycles = {b: BoardCycle() for b in self.boards}
        self.emit = emit
        self.template = cdr.MaccepaStateCdr()
        self.malformed = 0
        self.published = 0

    def drops(self) -> list[tuple[int, int]]:
        """(id, length) of the H2's frames on these boards' ids: not theirs, never needed
        (exolink.canbus.filters drops them in the kernel)."""
        return maccepa.h2_shaped(sorted(self.ids))

    def handle(self, msg: Any) -> None:
        f = maccepa.decode(msg)
        cycle = self.cycles.get(f[0]) if type(f) in _PARTS else None  # f[0]: its board
        if cycle is None:
            self.malformed += 1
            return
        board = f[0]
        for ts, stale, values in cycle.add(f, msg.timestamp):
            ns = int(ts * 1e9)
            self.emit(board, self.template.encode(ns, board, stale, values), ns)
            self.published += 1
