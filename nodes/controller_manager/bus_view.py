"""What the controller manager knows of the bus between two cycles: each frame decoded (the
H2's contract first, then the MACCEPA boards': ids 70/75/80/85 are both, the length tells; a
frame neither reads is counted by id and reason, never fatal), the H2's latest torques and foot
switches, each configured board's latest state, and the stops anyone sent. The node's loop
decides what to do with them (``node``: cycles, ``on_timer``: the timer's echo)."""

from __future__ import annotations

from typing import Any

import structlog
from exolink.nodes.controller_manager.frames import SAFE_MODES

from exolink import logs
from exolink.control.controller import BoardState, State
from exolink.protocol import h2, maccepa


class BusView:
    """The latest readings (``forget`` drops them with the reader that brought them) and the
    malformed-frame counts (kept for the node's life)."""

    torque: tuple[int, ...]
    feet: tuple[int, int, int, int] | None

    def __init__(self, board_ids: set[int], log: Any = None) -> None:
        self.board_ids = board_ids
        self.log = log or structlog.get_logger()
        self.malformed: dict[str, int] = {}  # "<id> <reason>" -> count
        self.forget()

    def forget(self) -> None:
        self.boards: dict[int, BoardState] = {}  # the latest, replaced whole per frame
        self._view: dict[int, BoardState] = {}  # what cycles see: a copy taken when it changed
        self._changed = False
        self.torque = (0,) * 6
        self.feet = None

    def warm(self) -> bool:
        """Every configured board's positions seen (a fresh reader's first wait)."""
        return all((b := self.boards.get(i)) and b.positions for i in self.board_ids)

    def decode(self, f: Any) -> Any:
        """The frame as its contract reads it; an ``h2.Unknown`` (counted) when neither does."""
        d = h2.decode(f)
        if not isinstance(d, h2.Unknown):
            return d
        reason = d.reason
        # Also without configured boards: id 70 is MACCEPA board 0's too (8 bytes), which is
        # not a malformed H2 frame (there may be a hundred a second). Unconfigured
        # boards' frames are then skipped (``take``).
        m = maccepa.decode(f)
        if not isinstance(m, maccepa.Unknown):
            return m
        if self.board_ids and m.reason != "unknown id":  # a MACCEPA id: its contract's reason
            reason = m.reason
        key = f"{f.arbitration_id} {reason}"
        n = self.malformed[key] = self.malformed.get(key, 0) + 1
        if logs.rarely(n):
            self.log.warning("malformed_frame", id=f.arbitration_id, reason=reason, count=n)
        return d

    def stops(self, decoded: list[tuple[Any, Any]]) -> tuple[set[int], set[int]]:
        """The joints (indices) a disable or stop in the batch names, and the configured
        boards a "stop control" halts, whoever sent them."""
        joints = {
            d.motor - 1
            for _f, d in decoded
            if isinstance(d, h2.JointControl) and d.mode in SAFE_MODES and 1 <= d.motor <= 6
        }
        boards = {
            d.board
            for _f, d in decoded
            if isinstance(d, maccepa.Duty) and d.action == 0 and d.board in self.board_ids
        }
        return joints, boards

    def take(self, d: Any, stamp: float) -> None:
        """A reading that is not a cycle's start: torques, foot switches, a board's status
        (that board's state replaced whole: cycles hold immutable ones; configured boards
        only)."""
        if isinstance(d, h2.JointTorques):
            self.torque = tuple(d)
        elif isinstance(d, h2.FootSwitches):
            self.feet = (d.r_heel, d.r_toe, d.l_heel, d.l_toe)
        elif isinstance(d, maccepa.Sensors | maccepa.Positions | maccepa.Controller):
            b = d.board
            if b not in self.board_ids:
                return
            old = self.boards.get(b) or BoardState(b)
            pos, sens, ctl = old.positions, old.sensors, old.controller
            if isinstance(d, maccepa.Positions):
                pos = (d.link, d.lever, d.extra_position, d.extra_sensor)
            elif isinstance(d, maccepa.Sensors):
                sens = (d.current, d.temperature, d.velocity, d.load)
            else:
                ctl = (d.setpoint, d.actuation, d.process_variable)
            self.boards[b] = BoardState(b, pos, sens, ctl, stamp)
            self._changed = True

    def state(self, angles: h2.JointAngles) -> State:
        """A cycle's state: these angles with the latest of the rest."""
        if self._changed:
            self._view, self._changed = dict(self.boards), False
        return State(tuple(angles), self.torque, self.feet, self._view)
