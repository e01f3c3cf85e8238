"""MACCEPA bridge [thesis: H2Rros, H2RrosSender]: board frames -> a per-board topic, validated
commands -> frames.

Topic ``maccepa/b<N>/state`` (exolink_msgs/MaccepaState): each board cycle's sensors,
positions and controller frames in one message, as JointState joins the H2's angle and torque
frames. One sample per cycle instead of three: on the board each Zenoh sample costs ~1 ms of the
one core (benchmarks/board/units.py), and the bridge's three topics were 300 of the appliance's
~500 samples a second.

The bridge only reads: commands to a board (``exolink maccepa ...``: gains, set-point, duty,
stop control) are the controller manager's, the one writer of motion, for the boards in its
``params.maccepa``.
"""

from __future__ import annotations

import threading
from typing import Annotated, Any, Literal

import can
import msgspec

from exolink import messaging
from exolink.canbus import Cadence, Frame, open_reader
from exolink.canbus.filters import Drop
from exolink.node import Node
from exolink.protocol import maccepa
from exolink.wire import cdr

BOARD_PERIOD_S = 0.01
STALE_S = 0.5
STATE = cdr.MaccepaStateCdr.TYPE

# The frames of a board cycle, in protocol order: the frame's int16 fields in MaccepaState's
# order, and the frame's bit in its ``stale`` field. The controller frame ends the cycle.
_PARTS: dict[type, tuple[int, tuple[str, ...]]] = {
    maccepa.Sensors: (1, ("current", "temperature", "velocity", "load")),
    maccepa.Positions: (2, ("link", "lever", "extra_position", "extra_sensor")),
    maccepa.Controller: (4, ("setpoint", "actuation", "process_variable")),
}
_ALL_PARTS = 7
_CYCLE_END = 4


class BoardCycle:
    """One board's frames of the cycle under way, and the last values of each kind of frame."""

    def __init__(self) -> None:
        self.values = {cls: [0] * len(fields) for cls, (_bit, fields) in _PARTS.items()}
        self.seen = 0  # bits of the frames this cycle brought
        self.first_ts = 0.0

    def add(self, frame: Any, ts: float) -> list[tuple[float, int, list[int]]]:
        """The cycles this frame ends: its own at the controller frame, the one before when a
        frame of a kind the cycle already has shows a new cycle began (a controller frame lost)."""
        bit, fields = _PARTS[type(frame)]
        done = [self._end()] if self.seen & bit else []
        if not self.seen:
            self.first_ts = ts
        self.seen |= bit
        self.values[type(frame)] = [getattr(frame, name) for name in fields]
        if bit == _CYCLE_END:
            done.append(self._end())
        return done

    def _end(self) -> tuple[float, int, list[int]]:
        """(first frame's time, stale bits, the eleven values) of the cycle; starts the next."""
        stale = _ALL_PARTS & ~self.seen
        out = [v for cls in _PARTS for v in self.values[cls]]
        self.seen = 0
        return self.first_ts, stale, out


class BridgeParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    boards: list[Annotated[int, msgspec.Meta(ge=0, le=9)]] = msgspec.field(
        default_factory=lambda: [0]
    )
    # The frame that ends each board's 10 ms cycle (sensors 50, positions 60, controller 70 +
    # board): only its arrival wakes the bridge, which takes the board's other frames with it,
    # one wake-up per board and cycle instead of three. 0: wake for every frame.
    wake_on_base: Literal[0, 50, 60, 70] = maccepa.CONTROLLER_BASE
    # Wake once per this many board cycles and publish their samples back to back (see the
    # h2 reader's param of the same name; canbus.Cadence).
    cycles_per_read: Annotated[int, msgspec.Meta(ge=1, le=10)] = 1


class MaccepaBridge(Node):
    Params = BridgeParams

    def configure(self) -> None:
        m = self.ctx.messaging
        base, boards = self.params.wake_on_base, self.params.boards
        self.cadence = Cadence(BOARD_PERIOD_S, self.params.cycles_per_read)
        ids = maccepa.data_ids(boards)
        self.reader = self.own(
            open_reader(
                self.ctx.config.can,
                ids,
                every_s=self.cadence.every_s,
                wake_on=[base + b for b in boards] if base else None,
                stale_s=STALE_S,  # a bridge that fell behind publishes news, not old frames
                # The H2's frames on board 0 and 5's controller ids (joint control on 70: the
                # manager's set-points, 400 a second with the gait) never reach the bridge.
                drop=[Drop(i, n) for i, n in maccepa.h2_shaped(ids)],
            )
        )
        self.bus = self.reader.bus
        bundled = self.params.cycles_per_read > 1  # a read's states: one bundle for the recorder
        self.pubs = {
            b: self.own(m.publisher(f"maccepa/b{b}/state", STATE, raw=True, bundled=bundled))
            for b in boards
        }
        self.cycles = {b: BoardCycle() for b in boards}
        self.template = cdr.MaccepaStateCdr()
        self.out = messaging.Outbox()  # a read's samples go out together, after its frames
        self.malformed = 0

    def handle(self, msg: Frame | can.Message) -> None:
        """One frame; the cycle goes out at its controller frame, or, if that never came, when
        the next cycle's first frame shows it ended. Never raises for bad input (counted)."""
        f = maccepa.decode(msg)
        board = getattr(f, "board", None)
        cycle = self.cycles.get(board) if type(f) in _PARTS else None
        if cycle is None or board is None:
            self.malformed += 1
            return
        for ts, stale, values in cycle.add(f, msg.timestamp):
            ns = int(ts * 1e9)
            self.out.add(self.pubs[board], self.template.encode(ns, board, stale, values), ns)

    def run(self, stop: threading.Event) -> None:
        timeout = self.cadence.idle_s
        while not stop.is_set():
            self.beat()
            frames = self.reader.read(timeout)
            for frame in frames:
                self.handle(frame)
            self.out.flush()
            timeout = self.cadence.timeout(bool(frames))
