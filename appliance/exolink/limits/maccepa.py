"""The limits every MACCEPA output of the controller manager passes, per configured board.

The H2's joints have ``exolink.limits.joints``; a MACCEPA board has no angle contract of its own
(its set-point is whatever its selected on-board controller reads: lever degrees or a
velocity), so the lab states what it allows here, once per board, in the controller manager's
params. A controller refuses a command outside these (``exolink.control.controller.Controller.boards``
gives it them), and the manager saturates whatever a controller returns to them anyway, so a
buggy plugin still cannot send a set-point the lab did not allow.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import msgspec

BoardId = Annotated[int, msgspec.Meta(ge=0, le=9)]
KINDS = ("setpoint", "duty", "gains")  # command interfaces of one board
GAINS = ("kp", "ki", "kd")


def target(board: int) -> str:
    """``maccepa0``: how a board is named in interfaces (``maccepa0/setpoint``) and commands."""
    return f"maccepa{board}"


def board_of(name: str) -> int | None:
    """The board id of ``maccepa<N>`` (an interface's first part), None for anything else."""
    if name.startswith("maccepa") and len(name) == 8 and name[7].isdigit():
        return int(name[7])
    return None


class BoardLimits(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """One board as the controller manager drives it (``params.maccepa[i]``)."""

    board: BoardId
    # The on-board controller every set-point and gain frame selects (the protocol carries it in
    # each frame): one per board under the manager, so two writers never toggle it.
    controller: Literal["position", "velocity"] = "position"
    # Set-points accepted (units of the selected controller: lever deg, or its velocity).
    setpoint_min: float = -90.0
    setpoint_max: float = 90.0
    # Largest set-point change from one H2 cycle (10 ms) to the next; the first one continues
    # from the lever's position (position controller) or from 0 (velocity).
    max_step: Annotated[float, msgspec.Meta(gt=0)] = 3.0
    duty_max: Annotated[int, msgspec.Meta(ge=0, le=100)] = 100
    # Each of kp, ki, kd in 0..gain_max.
    gain_max: Annotated[float, msgspec.Meta(ge=0)] = 100.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.setpoint_min) and math.isfinite(self.setpoint_max)):
            raise ValueError(f"board {self.board}: setpoint_min/max must be finite")
        if self.setpoint_min > self.setpoint_max:
            raise ValueError(
                f"board {self.board}: setpoint_min {self.setpoint_min:g} > "
                f"setpoint_max {self.setpoint_max:g}"
            )
        if not math.isfinite(self.gain_max) or not math.isfinite(self.max_step):
            raise ValueError(f"board {self.board}: gain_max and max_step must be finite")

    def violation(self, kind: str, value: float) -> str | None:
        """Why a set-point, a duty or one gain is outside what this board allows, or None."""
        name = target(self.board)
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            return f"{name} {kind} {value!r} is not a finite number"
        if kind == "setpoint" and not self.setpoint_min <= value <= self.setpoint_max:
            return (
                f"{name} set-point {value:g} is outside the board's range "
                f"{self.setpoint_min:g}..{self.setpoint_max:g}"
            )
        if kind == "duty" and (not 0 <= value <= self.duty_max or value != int(value)):
            return f"{name} duty {value:g} must be a whole percentage 0..{self.duty_max}"
        if kind in GAINS and not 0 <= value <= self.gain_max:
            return f"{name} {kind} {value:g} is outside 0..{self.gain_max:g}"
        return None

    def saturate_setpoint(self, value: float, last: float | None) -> float:
        """Inside the range and within ``max_step`` of the last written set-point."""
        v = min(self.setpoint_max, max(self.setpoint_min, value))
        if last is not None:
            v = min(last + self.max_step, max(last - self.max_step, v))
        return v

    def saturate_duty(self, value: float) -> int:
        return int(min(self.duty_max, max(0, round(value))))

    def saturate_gain(self, value: float) -> float:
        return min(self.gain_max, max(0.0, value))
