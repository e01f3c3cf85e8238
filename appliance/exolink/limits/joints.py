"""The joint limits every H2 motion command and controller output passes, whoever asks.

One module, so the operator's one-off commands (refused when they break a limit), the gait and
every controller's outputs (saturated to the same limits, like ros2_control's joint limiters)
can never disagree about what a lab allowed. The lab's limits are the appliance config's
``limits:`` section (``LimitsConfig``, validated with the file); an operator may narrow the angles
at run time (``Limits.narrowed``), never widen them past the config. Limits are whole degrees
and raw torque counts in joint order, as the H2 protocol carries them.

Default caps, where the config names none: the H2's actuators give a continuous 35 N·m at the
joint (a 220 mN·m motor through a 160:1 Harmonic Drive, the thesis' chapter 2), and the
protocol's int8 torque goes to 127 counts (127 N·m at the default 1 N·m per count): 3.6 times
that. The default cap is 20 counts at the hips and knees (57 % of the continuous torque; the
thesis' MACCEPA actuators were sized for 25 N·m peak, "about 50 % assistance") and 10 at the
ankles, whose actuators move a smaller lever; a torque set-point may change by at most 2 counts
per 10 ms cycle (0 to the cap in 100 ms), so a controller's jump arrives as a ramp.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Annotated

import msgspec

from exolink.protocol import ProtocolError, h2

Angles = Annotated[list[int], msgspec.Meta(min_length=6, max_length=6)]
Caps = Annotated[
    list[Annotated[int, msgspec.Meta(ge=0, le=127)]], msgspec.Meta(min_length=6, max_length=6)
]
POSITION, STIFFNESS, TORQUE = h2.MODES["position"], h2.MODES["stiffness"], h2.MODES["torque"]
DEFAULT_TORQUE_CAP = {"hip": 20, "knee": 20, "ankle": 10}  # counts; see the module docstring
DEFAULT_TORQUE_STEP = 2  # counts per 10 ms cycle
DEFAULT_MAX_STEP_DEG = 3  # a position set-point's change per 10 ms cycle


def default_min() -> list[int]:
    return [h2.RANGES[j][0] for j in h2.JOINTS]


def default_max() -> list[int]:
    return [h2.RANGES[j][1] for j in h2.JOINTS]


def default_torque_cap() -> list[int]:
    return [DEFAULT_TORQUE_CAP[j.split("_", 1)[1]] for j in h2.JOINTS]


class JointLimit(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """One joint's limits in the config; what is left out is the default (the mechanical
    range, the default caps)."""

    min: int | None = None  # deg
    max: int | None = None
    torque: Annotated[int, msgspec.Meta(ge=0, le=127)] | None = None  # |counts|
    torque_step: Annotated[int, msgspec.Meta(ge=1, le=127)] = DEFAULT_TORQUE_STEP
    stiffness: Annotated[int, msgspec.Meta(ge=0, le=100)] = 100  # percent


# One field per joint (so a config error names ``limits.joints.r_knee.max`` and an unknown joint
# is an unknown key), made from the protocol's joint list.
JointsLimits = msgspec.defstruct(
    "JointsLimits",
    [(j, JointLimit, msgspec.field(default_factory=JointLimit)) for j in h2.JOINTS],
    forbid_unknown_fields=True,
    frozen=True,
    kw_only=True,
)


class LimitsConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The config's ``limits:`` section: the one place a lab states its joint limits."""

    max_step_deg: Annotated[int, msgspec.Meta(ge=1, le=60)] = DEFAULT_MAX_STEP_DEG
    joints: JointsLimits = msgspec.field(default_factory=JointsLimits)  # type: ignore[valid-type]


@dataclass(frozen=True)
class Limits:
    """A lab's accepted angles (deg), per-joint caps on |torque| (counts) and stiffness
    (percent), and rate limits: a position's and a torque's change per 10 ms cycle."""

    min_angles: tuple[int, ...]
    max_angles: tuple[int, ...]
    torque_cap: tuple[int, ...]
    stiffness_cap: tuple[int, ...]
    torque_step: tuple[int, ...] = (127,) * 6
    max_step_deg: int = DEFAULT_MAX_STEP_DEG

    @classmethod
    def of(
        cls,
        min_angles: list[int],
        max_angles: list[int],
        torque_cap: list[int],
        stiffness_cap: list[int],
        who: str,
        torque_step: list[int] | None = None,
        max_step_deg: int = DEFAULT_MAX_STEP_DEG,
    ) -> Limits:
        """Checked with the codec (inside the mechanical ranges, min <= max): a bad config
        starts nothing; ValueError names ``who`` and the joint."""
        try:
            h2.encode_accepted_angles("min", min_angles)
            h2.encode_accepted_angles("max", max_angles)
        except ProtocolError as exc:
            raise ValueError(f"{who}: {exc}") from None
        for j, lo, hi in zip(h2.JOINTS, min_angles, max_angles, strict=True):
            if lo >= hi:
                raise ValueError(f"{who}: {j} min {lo} must be below max {hi}")
        steps = tuple(torque_step) if torque_step is not None else (127,) * 6
        return cls(
            tuple(min_angles),
            tuple(max_angles),
            tuple(torque_cap),
            tuple(stiffness_cap),
            steps,
            max_step_deg,
        )

    @classmethod
    def configured(cls, cfg: LimitsConfig) -> Limits:
        """The config's ``limits:`` section; ValueError names the path in it
        (``limits.joints.r_knee.max``) and what is wrong."""
        lo, hi, caps, steps, stiff = [], [], [], [], []
        torque_caps = default_torque_cap()
        for i, name in enumerate(h2.JOINTS):
            j: JointLimit = getattr(cfg.joints, name)
            rlo, rhi = h2.RANGES[name]
            jlo = rlo if j.min is None else j.min
            jhi = rhi if j.max is None else j.max
            for key, v in (("min", jlo), ("max", jhi)):
                if not rlo <= v <= rhi:
                    raise ValueError(
                        f"limits.joints.{name}.{key}: {v} deg is outside {name}'s mechanical "
                        f"range {rlo}..{rhi}"
                    )
            if jlo >= jhi:
                raise ValueError(f"limits.joints.{name}: min {jlo} must be below max {jhi}")
            lo.append(jlo)
            hi.append(jhi)
            caps.append(torque_caps[i] if j.torque is None else j.torque)
            steps.append(j.torque_step)
            stiff.append(j.stiffness)
        return cls.of(lo, hi, caps, stiff, "limits", steps, cfg.max_step_deg)

    def narrowed(self, min_angles: list[int], max_angles: list[int]) -> Limits:
        """An operator's accepted angles, which may only narrow the configured ones (``self``):
        ValueError names the joint and what is wrong."""
        for j, lo, hi, clo, chi in zip(
            h2.JOINTS, min_angles, max_angles, self.min_angles, self.max_angles, strict=True
        ):
            if lo >= hi:
                raise ValueError(f"{j}: min {lo} must be below max {hi}")
            if lo < clo or hi > chi:
                raise ValueError(
                    f"{j}: limits {lo}..{hi} reach outside the configured {clo}..{chi} "
                    "(the config's limits: section; an operator may only narrow them)"
                )
        return replace(self, min_angles=tuple(min_angles), max_angles=tuple(max_angles))

    def describe(self) -> dict[str, dict[str, int]]:
        """Per joint, for status: what a reader of `exolink status` needs to see."""
        return {
            j: {
                "min": self.min_angles[i],
                "max": self.max_angles[i],
                "torque": self.torque_cap[i],
                "torque_step": self.torque_step[i],
                "stiffness": self.stiffness_cap[i],
            }
            for i, j in enumerate(h2.JOINTS)
        }

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
            return (
                f"{name} torque {setpoint} counts is above its cap {self.torque_cap[i]} "
                f"(limits.joints.{name}.torque)"
            )
        if mode == STIFFNESS and stiffness > self.stiffness_cap[i]:
            return (
                f"{name} stiffness {stiffness} % is above its cap {self.stiffness_cap[i]} "
                f"(limits.joints.{name}.stiffness)"
            )
        return None

    def saturate(
        self, i: int, mode: int, setpoint: int, stiffness: int, last: int | None, cycles: int = 1
    ) -> tuple[int, int]:
        """The nearest command inside every limit: a position within the angles and within
        ``cycles`` steps of ``last`` (the previous position written, or the measured one), a
        torque within its cap and ``cycles`` torque steps of ``last`` (the previous torque
        written; None: from 0, so a torque starts as a ramp), a stiffness within 0..cap. A loop
        cannot ask an operator: it saturates, like ros2_control's joint limiters, and the
        result still passes ``violation``."""
        if mode in (POSITION, STIFFNESS):
            if last is not None:
                step = self.max_step_deg * cycles
                setpoint = min(max(setpoint, last - step), last + step)
            setpoint = min(max(setpoint, self.min_angles[i]), self.max_angles[i])
        elif mode == TORQUE:
            step, base = self.torque_step[i] * cycles, 0 if last is None else last
            setpoint = min(max(setpoint, base - step), base + step)
            setpoint = min(max(setpoint, -self.torque_cap[i]), self.torque_cap[i])
        stiffness = min(max(stiffness, 0), self.stiffness_cap[i]) if mode == STIFFNESS else 0
        return setpoint, stiffness
