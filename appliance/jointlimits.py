"""The joint limits every H2 motion command passes, whoever sends it.

One module so the operator's one-off commands (h2_sender, which refuses a command that breaks a
limit) and the controller manager's loop (which saturates a controller's output to the same
limits) can never disagree about what a lab allowed. Limits are whole degrees and raw torque
counts in joint order, as the H2 protocol carries them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import msgspec
from exolink.protocol import ProtocolError, h2

Angles = Annotated[list[int], msgspec.Meta(min_length=6, max_length=6)]
Caps = Annotated[
    list[Annotated[int, msgspec.Meta(ge=0, le=127)]], msgspec.Meta(min_length=6, max_length=6)
]
POSITION, STIFFNESS, TORQUE = h2.MODES["position"], h2.MODES["stiffness"], h2.MODES["torque"]


def default_min() -> list[int]:
    return [h2.RANGES[j][0] for j in h2.JOINTS]


def default_max() -> list[int]:
    return [h2.RANGES[j][1] for j in h2.JOINTS]


@dataclass(frozen=True)
class Limits:
    """A lab's accepted angles (deg) and per-joint caps on |torque| and stiffness (percent)."""

    min_angles: tuple[int, ...]
    max_angles: tuple[int, ...]
    torque_cap: tuple[int, ...]
    stiffness_cap: tuple[int, ...]

    @classmethod
    def of(
        cls,
        min_angles: list[int],
        max_angles: list[int],
        torque_cap: list[int],
        stiffness_cap: list[int],
        who: str,
    ) -> Limits:
        """Checked with the codec (inside the mechanical ranges, min <= max): a bad config
        starts nothing; ValueError names ``who`` and the joint."""
        try:
            h2.encode_accepted_angles("min", min_angles)
            h2.encode_accepted_angles("max", max_angles)
        except ProtocolError as exc:
            raise ValueError(f"{who} params: {exc}") from None
        for j, lo, hi in zip(h2.JOINTS, min_angles, max_angles, strict=True):
            if lo > hi:
                raise ValueError(f"{who} params: {j} min {lo} > max {hi}")
        return cls(tuple(min_angles), tuple(max_angles), tuple(torque_cap), tuple(stiffness_cap))

    def violation(
        self,
        i: int,
        mode: int,
        setpoint: int,
        stiffness: int,
        bounds: tuple[int, int] | None = None,
        where: str = "",
    ) -> str | None:
        """Why joint ``i``'s command breaks a limit, or None. ``bounds`` replaces the configured
        angles with stricter ones (the sender's: the last limits sent to the H2)."""
        name = h2.JOINTS[i]
        if mode in (POSITION, STIFFNESS):
            lo, hi = bounds or (self.min_angles[i], self.max_angles[i])
            if not lo <= setpoint <= hi:
                return f"{name} set-point {setpoint} deg is outside the limits {lo}..{hi}{where}"
        if mode == TORQUE and abs(setpoint) > self.torque_cap[i]:
            return f"{name} torque {setpoint} is above its cap {self.torque_cap[i]} (torque_cap)"
        if mode == STIFFNESS and stiffness > self.stiffness_cap[i]:
            return (
                f"{name} stiffness {stiffness} is above its cap {self.stiffness_cap[i]}"
                " (stiffness_cap)"
            )
        return None

    def saturate(
        self, i: int, mode: int, setpoint: int, stiffness: int, last: int | None, max_step: int
    ) -> tuple[int, int]:
        """The nearest command inside every limit: a position within the angles and within
        ``max_step`` of ``last`` (the previous position written, or the measured one), a torque
        within its cap, a stiffness within 0..cap. A loop cannot ask an operator: it saturates,
        like ros2_control's joint limiters, and the result still passes ``violation``."""
        if mode in (POSITION, STIFFNESS):
            if last is not None:
                setpoint = min(max(setpoint, last - max_step), last + max_step)
            setpoint = min(max(setpoint, self.min_angles[i]), self.max_angles[i])
        elif mode == TORQUE:
            cap = self.torque_cap[i]
            setpoint = min(max(setpoint, -cap), cap)
        stiffness = min(max(stiffness, 0), self.stiffness_cap[i]) if mode == STIFFNESS else 0
        return setpoint, stiffness
