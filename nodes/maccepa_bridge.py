"""MACCEPA bridge [thesis: H2Rros]: board frames -> a per-board topic, ``maccepa/b<N>/state``
(exolink_msgs/MaccepaState: each board cycle's sensors, positions and controller frames in one
message; exolink.hardware.maccepa).

For a bus without the H2 reader, or to give the boards a process of their own: where the H2
reader runs, its ``maccepa_boards`` publishes the same states from the same read, one process
fewer on the board's one core. The bridge only reads: commands to a board (``exolink maccepa
...``: gains, set-point, duty, stop control) are the controller manager's, the one writer of
motion, for the boards in its ``params.maccepa``.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from exolink import messaging
from exolink.canbus import Cadence, open_reader
from exolink.canbus.filters import Drop
from exolink.hardware.maccepa import STATE, BoardStates, topic
from exolink.loops import Frames, each
from exolink.node import Node
from exolink.protocol import maccepa

BOARD_PERIOD_S = 0.01
STALE_S = 0.5


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
    cycles_per_read: Annotated[int, msgspec.Meta(ge=1, le=25)] = 1


class MaccepaBridge(Node):
    Params = BridgeParams

    def configure(self) -> None:
        m = self.ctx.messaging
        base, boards = self.params.wake_on_base, self.params.boards
        self.cadence = Cadence(BOARD_PERIOD_S, self.params.cycles_per_read)
        bundled = self.params.cycles_per_read > 1  # a read's states: one bundle for the recorder
        self.pubs = {
            b: self.own(m.publisher(topic(b), STATE, raw=True, bundled=bundled)) for b in boards
        }
        self.out = messaging.Outbox()  # a read's samples go out together, after its frames
        self.states = BoardStates(
            boards, lambda b, payload, ns: self.out.add(self.pubs[b], payload, ns)
        )
        self.reader = self.own(
            open_reader(
                self.ctx.config.can,
                sorted(self.states.ids),
                every_s=self.cadence.every_s,
                wake_on=[base + b for b in boards] if base else None,
                stale_s=STALE_S,  # a bridge that fell behind publishes news, not old frames
                # The H2's frames on board 0 and 5's controller ids (joint control on 70: the
                # manager's set-points, 400 a second with the gait) never reach the bridge.
                drop=[Drop(i, n) for i, n in self.states.drops()],
            )
        )
        self.bus = self.reader.bus

    @property
    def malformed(self) -> int:
        return self.states.malformed

    def loop(self) -> Frames:
        return Frames(
            self.reader, each(self.states.handle), self.cadence, [("publish", self.out.flush)]
        )
