"""MACCEPA bridge [thesis: H2Rros, H2RrosSender]: board frames -> a per-board topic, validated
commands -> frames.

Topic ``maccepa/b<N>/state`` (exolink_msgs/MaccepaState): each board cycle's sensors,
positions and controller frames in one message, as JointState joins the H2's angle and torque
frames. One sample per cycle instead of three: on the board each Zenoh sample costs ~1 ms of the
one core (benchmarks/board/units.py), and the bridge's three topics were 300 of the appliance's
~500 samples a second. Commands arrive as Zenoh queries (``exolink maccepa ...``): gains with
controller type, set-point, duty cycle, stop control.
Set-point and duty move the actuator and need the watchdog armed; gains and stop do not.

With ``motion_via_manager`` (for boards the controller manager drives: its ``params.maccepa``)
set-point, duty and gains are checked here as always, then handed to the manager, which holds
them in that board's operator controller and writes them each H2 cycle inside the board's
limits (one writer per board; a board another controller drives refuses them, naming it). Stop
control stays here and goes straight to the bus: it can only make things safer, and the manager
releases the board when it sees it. Without it (the board config: no board listed in the
manager's ``params.maccepa``; the sim config sets it) the bridge writes every command itself.
"""

from __future__ import annotations

import threading
from typing import Annotated, Any, Literal

import can
import msgspec
from exolink import cdr, messaging, roles
from exolink.arming import ArmingState
from exolink.canbus import Cadence, open_reader
from exolink.canfilter import Drop
from exolink.messaging import CommandRefused
from exolink.node import Node
from exolink.protocol import ProtocolError, maccepa

MANAGED_KINDS = ("setpoint", "duty", "gains")  # what motion_via_manager hands the manager
MANAGER_WAIT_S = 2.0  # the manager's switch waits up to 1 s for an H2 cycle
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
    require_armed: bool = True
    # Set-point, duty and gains go to the controller manager (``exolink controllers``), which
    # writes them; stop stays here. For the boards in the manager's params.maccepa.
    motion_via_manager: bool = False
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
        self.arming = self.own(ArmingState(m)) if self.params.require_armed else None
        self.malformed = 0
        self.lock = threading.Lock()
        self.own(m.serve("maccepa", self.on_command, roles.OPERATOR))

    def build(self, req: dict[str, Any]) -> list[can.Message]:
        board, kind = req.get("board"), req.get("kind")
        if board not in self.params.boards:
            if isinstance(board, int) and not isinstance(board, bool) and 0 <= board <= 9:
                raise CommandRefused(
                    f"board {board} is not configured (params.boards: {self.params.boards})"
                )
            raise CommandRefused(f"MACCEPA board id {board!r} is outside 0..9")
        ctl = req.get("controller", "position")
        try:
            if kind == "gains":
                gains = [(g, req[g]) for g in ("kp", "ki", "kd") if req.get(g) is not None]
                if not gains:
                    raise CommandRefused("gains needs at least one of kp, ki, kd")
                return [maccepa.encode_gain(board, g, v, ctl) for g, v in gains]
            if kind == "stop":
                return [maccepa.encode_stop(board)]
            if kind in ("setpoint", "duty"):
                frame = (
                    maccepa.encode_setpoint(board, req.get("value"), ctl)
                    if kind == "setpoint"
                    else maccepa.encode_duty(board, req.get("value"))
                )
                if self.arming is not None and (why := self.arming.check()):
                    raise CommandRefused(why)
                return [frame]
        except ProtocolError as exc:
            raise CommandRefused(str(exc)) from None
        raise CommandRefused(f"unknown MACCEPA command {kind!r} (gains, setpoint, duty, stop)")

    def on_command(self, req: dict[str, Any]) -> dict[str, Any]:
        frames = self.build(req)
        if self.params.motion_via_manager and req.get("kind") in MANAGED_KINDS:
            return self._via_manager(req)
        with self.lock:
            for f in frames:
                self.bus.send(f)
        self.log.info("maccepa_command", request=req)
        return {"frames": [f"{f.arbitration_id:03X}#{f.data.hex().upper()}" for f in frames]}

    def _via_manager(self, req: dict[str, Any]) -> dict[str, Any]:
        """The checked command, for the controller manager to hold and write; its refusal
        (another controller drives the board, a set-point outside the board's limits, not
        armed) reaches the caller verbatim."""
        body: dict[str, Any] = {
            "action": "maccepa",
            "board": req["board"],
            "kind": req["kind"],
            "controller": req.get("controller", "position"),
        }
        if req["kind"] == "gains":
            body |= {g: req.get(g) for g in ("kp", "ki", "kd")}
        else:
            body["value"] = req.get("value")
            if req["kind"] == "duty":
                body.pop("controller")  # a duty frame carries no controller type
        reply = self.ctx.messaging.command("controllers", body=body, timeout_s=MANAGER_WAIT_S)
        self.log.info("maccepa_command_forwarded", request=body, controller=reply.get("controller"))
        return {"controller": reply.get("controller"), "frames": []}

    def handle(self, msg: can.Message) -> None:
        """One frame; the cycle goes out at its controller frame, or, if that never came, when
        the next cycle's first frame shows it ended. Never raises for bad input (counted)."""
        f = maccepa.decode(msg)
        board = getattr(f, "board", None)
        cycle = self.cycles.get(board) if type(f) in _PARTS else None
        if cycle is None:
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
