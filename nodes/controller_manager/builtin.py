"""The built-in controllers, registered under ``exolink.controllers`` like a lab's own would be.

- ``forward_command``: positions (or torques) an operator sends, held until the next one; a
  command timeout either holds the last value or asks for the safe action.
- ``pid``: position set-point -> torque set-point (torque mode), with anti-windup (the
  integral stops growing while the output is saturated, and is clamped) and an output cap.
- ``operator``: one joint held at what ``exolink send`` last asked (made by the manager).
- ``gait_pattern``: the pattern player's rows (gait_pattern.py).
- ``joint_trajectory``: time-stamped way-points, linearly interpolated from where the joints are
  at activation; the gait pattern becomes one of these later.
- the MACCEPA boards' controllers: maccepa.py.
"""

from __future__ import annotations

import math
import time
from typing import Annotated, Any, Literal

import msgspec

from exolink.control.controller import (
    Controller,
    Refused,
    SafeStop,
    State,
    interface,
)
from exolink.protocol.h2 import JOINTS

Joint = Literal["r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"]
JointList = Annotated[list[Joint], msgspec.Meta(min_length=1, max_length=6)]
# Controller.reads of every built-in: positions (and the boards it writes) only.
NO_EXTRA_READS: frozenset[str] = frozenset()


def unique_joints(name: str, joints: list[str]) -> None:
    if len(set(joints)) != len(joints):
        raise ValueError(f"{name}: a joint is listed twice in {joints}")


def _values(name: str, joints: list[str], request: dict[str, Any]) -> dict[str, float]:
    """``{"values": {joint: number}}`` for joints this controller drives, finite numbers only."""
    values = request.get("values")
    if not isinstance(values, dict) or not values:
        raise Refused(f"{name} needs 'values': {{joint: number}} for {', '.join(joints)}")
    out: dict[str, float] = {}
    for j, v in values.items():
        if j not in joints:
            raise Refused(f"{name} does not drive {j!r} (it drives {', '.join(joints)})")
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise Refused(f"{name}: {j} value {v!r} is not a finite number")
        out[j] = float(v)
    return out


# --- forward command ----------------------------------------------------------------------------


class ForwardParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    joints: JointList
    interface: Literal["position", "torque"] = "position"
    # No command for this long (0 = never): 'hold' keeps the last, 'disable' the safe action.
    timeout_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 0.0
    on_timeout: Literal["hold", "disable"] = "hold"
    # First command at activation (the manager's step limit ramps to it); joints not given
    # start where they are (position) or at zero torque.
    initial: dict[Joint, float] = {}


class ForwardCommand(Controller):
    """Starts from ``initial``, else holds the joints where they are (position) or at zero torque."""

    Params = ForwardParams
    reads = NO_EXTRA_READS

    def configure(self) -> None:
        unique_joints(self.name, list(self.params.joints))
        if set(self.params.initial) - set(self.params.joints):
            raise ValueError(f"{self.name}: initial values for joints it does not drive")
        self.keys = {j: interface(j, self.params.interface) for j in self.params.joints}
        self.values: dict[str, float] = {}
        self.last_command = 0.0
        self.timed_out = False

    def claims(self) -> list[str]:
        return list(self.keys.values())

    def activate(self, state: State) -> None:
        hold = self.params.interface == "position"
        start = {j: float(state.of(j)) if hold else 0.0 for j in self.keys} | self.params.initial
        self.values = {self.keys[j]: v for j, v in start.items()}
        self.last_command, self.timed_out = time.monotonic(), False

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        new = _values(self.name, list(self.keys), request)
        # One assignment of a new dict: the loop sees the old or the new, never half of it.
        self.values = {**self.values, **{self.keys[j]: v for j, v in new.items()}}
        self.last_command, self.timed_out = time.monotonic(), False
        return {"values": new}

    def update(self, state: State, time_s: float, period: float) -> dict[str, float]:
        expire(self, "disable")
        return self.values

    def status(self) -> dict[str, Any]:
        return {"command": dict(self.values), "timed_out": self.timed_out}


# --- operator -----------------------------------------------------------------------------------


class OperatorParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    joint: Joint
    mode: Literal["position", "stiffness", "torque"]


class Operator(Controller):
    """One joint in one mode, held at what an operator last sent (``exolink send``).

    The manager makes one per joint and mode on demand (``operator.<joint>.<mode>``), so an
    operator's command claims only the joint it names, and a joint some other controller drives
    (a gait trajectory, say) refuses it with that owner named."""

    Params = OperatorParams
    reads = NO_EXTRA_READS

    def configure(self) -> None:
        j, mode = self.params.joint, self.params.mode
        kinds = {"position": ["position"], "stiffness": ["position", "stiffness"]}
        self.keys = [interface(j, k) for k in kinds.get(mode, ["torque"])]
        self.target: dict[str, float] = {}

    def claims(self) -> list[str]:
        return list(self.keys)

    def activate(self, state: State) -> None:
        if not self.target:  # activated without a command: hold where it is, no torque
            hold = self.params.mode != "torque"
            self.target = {
                k: float(state.of(self.params.joint)) if hold else 0.0 for k in self.keys
            }
            if self.params.mode == "stiffness":
                self.target[self.keys[1]] = 0.0

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        sp, st = request.get("setpoint", 0), request.get("stiffness", 0)
        for what, v in (("setpoint", sp), ("stiffness", st)):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise Refused(f"{self.name}: {what} {v!r} is not a finite number")
        new = {self.keys[0]: float(sp)}
        if self.params.mode == "stiffness":
            new[self.keys[1]] = float(st)
        self.target = new  # one assignment: the loop sees the old or the new
        return {"command": new}

    def update(self, state: State, time_s: float, period: float) -> dict[str, float]:
        return self.target

    def status(self) -> dict[str, Any]:
        return {"command": dict(self.target)}


class PidParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    joints: JointList
    kp: Annotated[float, msgspec.Meta(ge=0)] = 1.0
    ki: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    kd: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    # Torque counts: the output is clamped to +-output_cap (the manager's torque_cap still applies).
    output_cap: Annotated[float, msgspec.Meta(gt=0, le=127)] = 10.0
    # |integral term| never exceeds this (torque counts), whatever ki is.
    i_clamp: Annotated[float, msgspec.Meta(ge=0, le=127)] = 5.0
    setpoints: dict[Joint, float] = {}  # deg; joints not given hold where they are at activation


class Pid(Controller):
    """Position -> torque, per joint: u = kp e + I + kd de/dt, I += ki e dt unless saturated."""

    Params = PidParams
    reads = NO_EXTRA_READS

    def configure(self) -> None:
        p = self.params
        unique_joints(self.name, list(p.joints))
        if set(p.setpoints) - set(p.joints):
            raise ValueError(f"{self.name}: setpoints for joints it does not drive")
        self.keys = {j: interface(j, "torque") for j in p.joints}
        self.setpoints: dict[str, float] = dict(p.setpoints)
        self.integral = dict.fromkeys(p.joints, 0.0)
        self.prev_error: dict[str, float | None] = dict.fromkeys(p.joints, None)

    def claims(self) -> list[str]:
        return list(self.keys.values())

    def activate(self, state: State) -> None:
        self.setpoints = {j: self.params.setpoints.get(j, float(state.of(j))) for j in self.keys}
        self.integral = dict.fromkeys(self.keys, 0.0)
        self.prev_error = dict.fromkeys(self.keys, None)

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        new = _values(self.name, list(self.keys), request)
        self.setpoints = {**self.setpoints, **new}
        return {"setpoints": new}

    def update(self, state: State, time_s: float, period: float) -> dict[str, float]:
        p = self.params
        out: dict[str, float] = {}
        for j, key in self.keys.items():
            e = self.setpoints[j] - state.of(j)
            prev = self.prev_error[j]
            d = p.kd * (e - prev) / period if prev is not None and period > 0 else 0.0
            self.prev_error[j] = e
            i_old = self.integral[j]
            i_new = max(-p.i_clamp, min(p.i_clamp, i_old + p.ki * e * period))
            u = p.kp * e + i_new + d
            if abs(u) > p.output_cap and (u > 0) == (e > 0):
                i_new = i_old  # anti-windup: no integration that would push further into the cap
                u = p.kp * e + i_new + d
            self.integral[j] = i_new
            out[key] = max(-p.output_cap, min(p.output_cap, u))
        return out

    def status(self) -> dict[str, Any]:
        return {"setpoints": dict(self.setpoints), "integral": dict(self.integral)}


# --- joint trajectory -------------------------------------------------------------------------


class Point(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    time_s: Annotated[float, msgspec.Meta(gt=0)]  # from activation
    positions: list[float]  # deg, in the order of ``joints``


class TrajectoryParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    joints: JointList
    points: Annotated[list[Point], msgspec.Meta(min_length=1, max_length=10_000)]
    loop: bool = False  # start again from the first point after the last (from where it ended)


class JointTrajectory(Controller):
    """Linear interpolation in controller time (the frames' kernel stamps) from the joints'
    positions at activation through every way-point; holds the last point at the end."""

    Params = TrajectoryParams
    reads = NO_EXTRA_READS
    planned = True

    def configure(self) -> None:
        p = self.params
        unique_joints(self.name, list(p.joints))
        last = 0.0
        for n, pt in enumerate(p.points):
            if pt.time_s <= last:
                raise ValueError(f"{self.name}: points[{n}].time_s must increase")
            if len(pt.positions) != len(p.joints):
                raise ValueError(
                    f"{self.name}: points[{n}] has {len(pt.positions)} positions "
                    f"for {len(p.joints)} joints"
                )
            if not all(math.isfinite(v) for v in pt.positions):
                raise ValueError(f"{self.name}: points[{n}] has a non-finite position")
            last = pt.time_s
        self.keys = [interface(j, "position") for j in p.joints]
        self.t0: float | None = None
        self.start: list[float] = []
        self.index = 0

    def claims(self) -> list[str]:
        return list(self.keys)

    def activate(self, state: State) -> None:
        self.start = [float(state.of(j)) for j in self.params.joints]
        self.t0, self.index = None, 0

    def update(self, state: State, time_s: float, period: float) -> dict[str, float]:
        pts = self.params.points
        if self.t0 is None:
            self.t0 = time_s
        t = time_s - self.t0
        end = pts[-1].time_s
        if t >= end and self.params.loop:
            self.t0 += end * (t // end)
            t -= end * (t // end)
            self.start = list(pts[-1].positions)
            self.index = 0
        while self.index < len(pts) and pts[self.index].time_s <= t:
            self.index += 1
        # Planned ahead and then run by the cycle loop (the manager left the kernel's timer):
        # a time before the way-point already passed goes back to its segment.
        while self.index and pts[self.index - 1].time_s > t:
            self.index -= 1
        if self.index >= len(pts):
            target = pts[-1].positions
        else:
            t_prev = pts[self.index - 1].time_s if self.index else 0.0
            a = self.start if self.index == 0 else pts[self.index - 1].positions
            b = pts[self.index].positions
            f = (t - t_prev) / (pts[self.index].time_s - t_prev)
            target = [x + (y - x) * f for x, y in zip(a, b, strict=True)]
        return dict(zip(self.keys, target, strict=True))

    def status(self) -> dict[str, Any]:
        return {"point": self.index, "points": len(self.params.points)}


__all__ = [
    "JOINTS",
    "ForwardCommand",
    "JointTrajectory",
    "Pid",
]


def expire(ctrl: Any, stop: str) -> None:
    """A command controller's timeout (``params.timeout_s``, ``params.on_timeout``): past it
    with ``on_timeout`` = ``stop`` the controller stops (its joints or board get the safe
    action); otherwise it holds the last command and says so in its status."""
    p = ctrl.params
    if p.timeout_s and time.monotonic() - ctrl.last_command > p.timeout_s:
        if p.on_timeout == stop:
            raise SafeStop(f"no command for {p.timeout_s:g} s (on_timeout: {stop})")
        ctrl.timed_out = True
