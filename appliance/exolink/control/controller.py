"""The controller plugin interface: what the controller manager hands a controller and expects back.

Kept apart from the manager (and light: msgspec and the H2 joint names) because a lab's own
controller package imports only this, exactly as a node imports ``exolink.node``. A controller
never touches the bus, Zenoh or the watchdog: it gets the H2 state (and the configured MACCEPA
boards' last status frames) once per H2 cycle and returns values for the command interfaces it
claimed; the manager checks limits, encodes and writes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import msgspec

from exolink.limits.joints import Limits
from exolink.limits.maccepa import KINDS as MACCEPA_INTERFACES
from exolink.limits.maccepa import BoardLimits, target
from exolink.protocol.h2 import JOINTS
from exolink.refusal import Refused  # a controller refuses with it (a bad command, a bad joint)

# The controller manager publishes every change of a controller's state here (the whole list,
# exolink_msgs/ControllerActivity, as ros2_control's ~/activity); followers listen to it
ACTIVITY_TOPIC = "controllers/activity"
ACTIVITY_TYPE = "exolink_msgs/msg/ControllerActivity"

INTERFACES = ("position", "torque", "stiffness")


class NoParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    pass


class SafeStop(Exception):
    """Raised by ``update`` to ask for the safe action on this controller's joints (e.g. a
    forward-command timeout set to disable): it is deactivated like a failed one, logged as asked."""


@dataclass(frozen=True, slots=True)
class BoardState:
    """A MACCEPA board's last status frames, as its codec decoded them (None until the first of
    that kind): positions (link 2, lever arm, extra position, extra sensor), sensors (current mA,
    temperature degC, motor velocity rpm, load cell N) and its controller (set-point, actuation,
    process variable); ``stamp``: the newest of those frames' kernel receive time (s)."""

    board: int
    positions: tuple[int, int, int, int] | None = None
    sensors: tuple[int, int, int, int] | None = None
    controller: tuple[int, int, int] | None = None
    stamp: float = 0.0

    @property
    def lever(self) -> int | None:
        return self.positions[1] if self.positions is not None else None

    @property
    def link(self) -> int | None:
        return self.positions[0] if self.positions is not None else None


@dataclass(frozen=True, slots=True)
class State:
    """One H2 cycle: whole degrees and raw torque counts in joint order (``JOINTS``), foot
    switches (r_heel, r_toe, l_heel, l_toe; None until the first foot-switch frame), and the
    configured MACCEPA boards that have sent a status frame, by board id."""

    position: tuple[int, ...]
    torque: tuple[int, ...]
    feet: tuple[int, int, int, int] | None = None
    maccepa: dict[int, BoardState] = field(default_factory=dict)

    def of(self, joint: str) -> int:
        return self.position[JOINTS.index(joint)]

    def board(self, board: int) -> BoardState | None:
        return self.maccepa.get(board)


def interface(joint: str, kind: str) -> str:
    """``r_knee/position``: the one spelling of a command interface."""
    if joint not in JOINTS:
        raise Refused(f"unknown joint {joint!r} (valid: {', '.join(JOINTS)})")
    if kind not in INTERFACES:
        raise Refused(f"unknown interface {kind!r} (valid: {', '.join(INTERFACES)})")
    return f"{joint}/{kind}"


def maccepa_interface(board: int, kind: str) -> str:
    """``maccepa0/setpoint``: a MACCEPA board's command interface (kinds: setpoint, duty, gains).
    A ``gains`` value is the triple (kp, ki, kd); the others are numbers."""
    if isinstance(board, bool) or not isinstance(board, int) or not 0 <= board <= 9:
        raise Refused(f"MACCEPA board id {board!r} is outside 0..9")
    if kind not in MACCEPA_INTERFACES:
        raise Refused(
            f"unknown MACCEPA interface {kind!r} (valid: {', '.join(MACCEPA_INTERFACES)})"
        )
    return f"{target(board)}/{kind}"


class Controller:
    """Subclass, set ``Params`` to a msgspec Struct, implement ``claims`` and ``update``.

    Lifecycle: constructed with validated params (a bad param refuses the load) -> ``configure``
    (may raise to refuse the load) -> ``activate(state)`` at a cycle boundary (start from where
    the joints are, not from where they were last time) -> ``update`` once per H2 cycle ->
    ``deactivate``. ``update`` returns ``{interface: value}`` for interfaces it claimed; a
    claimed interface left out keeps its last value. Raising, or spending more CPU than the
    budget, deactivates the controller and puts its joints in the safe action.
    """

    Params: ClassVar[type[msgspec.Struct]] = NoParams
    # What of ``State`` beyond positions (and the boards it writes) ``update`` reads: "torque",
    # "feet". The manager reads those frames only while a loaded controller says so (two of
    # the four it decoded per cycle for the gait, which reads neither); a controller that does
    # not say gets both.
    reads: ClassVar[frozenset[str]] = frozenset({"torque", "feet"})
    # True: after ``activate``, ``update`` is a function of ``time`` alone (a gait pattern, a
    # trajectory), so the manager may call it ahead, once per set-point slot in increasing time,
    # and hand the results to the kernel's timer (nodes/controller_manager/timed.py). It reads
    # nothing of ``state`` there (it gets the activation's) and claims joint positions only.
    planned: ClassVar[bool] = False

    def __init__(self, name: str, params: Any) -> None:
        self.name = name
        self.params = params
        # The MACCEPA boards the manager drives and their limits (set by the manager before
        # ``configure``), so a controller can refuse a command the manager would saturate.
        self.boards: dict[int, BoardLimits] = {}
        # The joint limits in force when it was loaded (also set before ``configure``): a
        # controller that knows its outputs ahead (a pattern) refuses a plan outside them
        # whole instead of having it saturated point by point.
        self.limits: Limits | None = None

    def claims(self) -> list[str]:
        raise NotImplementedError

    def configure(self) -> None:
        pass

    def activate(self, state: State) -> None:
        pass

    def deactivate(self) -> None:
        pass

    def repeats_s(self) -> float | None:
        """A planned controller whose outputs repeat: their period (s; a gait's cycle at its
        speed), so the manager plans one cycle and replays it instead of computing every slot
        again. None: they do not repeat (the default)."""
        return None

    def update(self, state: State, time: float, period: float) -> dict[str, Any]:
        """``time``: the angle frame's kernel receive time (s since the epoch); ``period``: the
        measured time since the previous cycle's frame (s). Values are numbers, except a
        ``maccepa<N>/gains`` value: the triple (kp, ki, kd)."""
        raise NotImplementedError

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        """An operator's input (``exolink controllers command NAME ...``), from a Zenoh thread:
        hand the loop a new immutable value; never block it."""
        raise Refused(f"controller {self.name} takes no commands")

    def status(self) -> dict[str, Any]:
        return {}
