"""Plausible physics of the H2 HAL board and of MACCEPA boards, free of any bus or clock.

Kept apart from the node so tests can step the models deterministically and so a new board model
is a new class here, not an edit to the loop that drives it.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

import can

from exolink.protocol import h2, maccepa

MODE = h2.MODES


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


@dataclass
class Joint:
    name: str
    lo: float
    hi: float
    pos: float = 0.0
    vel: float = 0.0
    mode: int = MODE["stopped"]
    setpoint: float = 0.0
    stiffness: float = 0.0
    torque: float = 0.0


@dataclass
class H2Board:
    """The HAL board: streams only after a start frame, follows joint control within limits.

    Position control is a first-order approach to the set-point (time constant ``tau_s``) capped
    at ``max_speed_dps``; stiffness control is the same pull scaled by the stiffness percentage;
    torque control drives the joint at a speed proportional to the torque; a disabled joint goes
    limp (drifts slowly toward 0), a stopped joint holds.
    """

    max_speed_dps: float = 120.0
    tau_s: float = 0.15
    battery: float = 225.0
    drain_per_min: float = 1.0
    seed: int = 0
    streaming: bool = False
    ignored_setpoints: int = 0
    joints: list[Joint] = field(default_factory=list)
    min_accepted: list[float] = field(default_factory=list)
    max_accepted: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)
        self.joints = [Joint(n, *h2.RANGES[n]) for n in h2.JOINTS]
        self.min_accepted = [float(h2.RANGES[n][0]) for n in h2.JOINTS]
        self.max_accepted = [float(h2.RANGES[n][1]) for n in h2.JOINTS]

    def handle(self, msg: can.Message) -> None:
        frame = h2.decode(msg)
        if isinstance(frame, h2.StreamControl):
            self.streaming = frame.start == 1
        elif isinstance(frame, h2.MinAngles):
            self.min_accepted = [float(v) for v in frame]
        elif isinstance(frame, h2.MaxAngles):
            self.max_accepted = [float(v) for v in frame]
        elif isinstance(frame, h2.JointControl):
            self._control(frame)

    def _control(self, c: h2.JointControl) -> None:
        if not 1 <= c.motor <= 6 or c.mode not in h2.MODE_NAMES:
            self.ignored_setpoints += 1
            return
        i = c.motor - 1
        j = self.joints[i]
        if c.mode in (MODE["position"], MODE["stiffness"]):
            lo = max(self.min_accepted[i], j.lo)
            hi = min(self.max_accepted[i], j.hi)
            if not lo <= c.setpoint <= hi:
                self.ignored_setpoints += 1
                return
        if c.mode == MODE["stiffness"] and c.stiffness > 100:
            self.ignored_setpoints += 1
            return
        j.mode, j.setpoint, j.stiffness = c.mode, float(c.setpoint), float(c.stiffness)

    def step(self, dt: float) -> None:
        for j in self.joints:
            if j.mode == MODE["position"]:
                j.vel = _clamp(
                    (j.setpoint - j.pos) / self.tau_s, -self.max_speed_dps, self.max_speed_dps
                )
                j.torque = 0.4 * (j.setpoint - j.pos)
            elif j.mode == MODE["stiffness"]:
                k = j.stiffness / 100.0
                j.vel = _clamp(
                    k * (j.setpoint - j.pos) / self.tau_s, -self.max_speed_dps, self.max_speed_dps
                )
                j.torque = 0.5 * k * (j.setpoint - j.pos)
            elif j.mode == MODE["torque"]:
                j.vel = _clamp(4.0 * j.setpoint, -self.max_speed_dps, self.max_speed_dps)
                j.torque = j.setpoint
            elif j.mode == MODE["disabled"]:
                j.vel = _clamp(-j.pos, -5.0, 5.0)
                j.torque = 0.0
            else:  # stopped: hold
                j.vel = 0.0
                j.torque = 0.0
            j.pos = _clamp(j.pos + j.vel * dt, j.lo, j.hi)
        self.battery = max(0.0, self.battery - self.drain_per_min * dt / 60.0)

    def feet(self) -> tuple[int, int, int, int]:
        """Heel/toe contacts: gait phase from hip motion when walking, posture when still."""
        rh, rk, _, lh, lk, _ = self.joints
        walking = max(abs(rh.vel), abs(lh.vel)) > 5.0
        out: list[int] = []
        for hip, knee in ((rh, rk), (lh, lk)):
            if walking:
                stance = hip.vel <= 0.0 and knee.pos < 40
                out += [int(stance and hip.pos > 5), int(stance and hip.pos <= 20)]
            else:
                down = int(knee.pos < 30)
                out += [down, down]
        return out[0], out[1], out[2], out[3]

    def frames(self) -> list[can.Message]:
        angles = [round(j.pos) for j in self.joints]
        torques = [
            int(_clamp(round(j.torque + self.rng.uniform(-0.6, 0.6)), -128, 127))
            for j in self.joints
        ]
        return [
            h2.model_message(h2.JointAngles(*angles)),
            h2.model_message(h2.JointTorques(*torques)),
            h2.model_message(h2.FootSwitches(*self.feet(), int(self.battery))),
        ]


@dataclass
class MaccepaBoard:
    """One actuator board: lever arm on a ball screw under its own PID, link 2 pulled by a spring.

    Nothing moves until a gain, set-point or duty frame arrives; stop control zeroes actuation.
    """

    board: int
    controller: int = 0
    kp: float = 0.0
    ki: float = 0.0
    kd: float = 0.0
    setpoint: float = 0.0
    enabled: bool = False
    duty: float | None = None
    lever: float = 0.0
    link: float = 0.0
    lever_vel: float = 0.0
    actuation: float = 0.0
    temperature: float = 30.0
    _integral: float = 0.0
    _prev_err: float | None = None

    def handle(self, msg: can.Message) -> None:
        f = maccepa.decode(msg)
        if isinstance(f, maccepa.Unknown) or f.board != self.board:
            return
        if isinstance(f, maccepa.Gain):
            setattr(self, f.which, f.value)
            self._select(f.controller)
        elif isinstance(f, maccepa.Setpoint):
            self.setpoint = f.value
            self._select(f.controller)
            self.enabled, self.duty = True, None
        elif isinstance(f, maccepa.Duty):
            if f.action == 1:
                self.duty, self.enabled = float(f.duty), True
            else:
                self.enabled, self.duty = False, None

    def _select(self, controller: int) -> None:
        if controller != self.controller:
            self.controller, self._integral, self._prev_err = controller, 0.0, None

    def step(self, dt: float) -> None:
        if not self.enabled:
            u = 0.0
        elif self.duty is not None:
            u = self.duty
        else:
            pv = self.lever if self.controller == 0 else self.lever_vel
            err = self.setpoint - pv
            self._integral = _clamp(self._integral + err * dt, -1000.0, 1000.0)
            de = 0.0 if self._prev_err is None else (err - self._prev_err) / dt
            self._prev_err = err
            u = self.kp * err + self.ki * self._integral + self.kd * de
        self.actuation = _clamp(u, -100.0, 100.0)
        self.lever_vel = 3.0 * self.actuation  # deg/s: 100 % actuation = 300 deg/s
        self.lever = _clamp(self.lever + self.lever_vel * dt, -120.0, 120.0)
        self.link += (self.lever - self.link) * min(1.0, dt / 0.05)
        self.temperature += (30.0 + 0.2 * abs(self.actuation) - self.temperature) * dt / 60.0

    def frames(self) -> list[can.Message]:
        b = self.board
        pv = self.lever if self.controller == 0 else self.lever_vel

        def i16(x: float) -> int:
            return int(_clamp(round(x), -32768, 32767))

        return [
            maccepa.model_message(
                maccepa.Sensors(
                    b,
                    i16(abs(self.actuation) * 20),
                    i16(self.temperature),
                    i16(self.lever_vel * 10 / 6),
                    i16(2.0 * (self.lever - self.link)),
                )
            ),
            maccepa.model_message(maccepa.Positions(b, i16(self.link), i16(self.lever), 0, 0)),
            maccepa.model_message(
                maccepa.Controller(b, i16(self.setpoint), i16(self.actuation), i16(pv))
            ),
        ]
