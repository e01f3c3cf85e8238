"""H2 sender [thesis: H2rosSender, commandSenderUi]: validated commands -> CAN frames.

Commands arrive as Zenoh queries so the caller gets "ok" or the reason for a refusal. Nothing is
sent unless the whole command is valid; motion (position, stiffness, torque) also needs the
watchdog armed. Disable, stop and stream on/off are always allowed: they can only make things
safer or quieter.

One writer per joint without the controller manager too: a motion command for a joint the gait
pattern drives (running or paused) is refused, naming the pattern, instead of interleaving with
its set-points. The pattern player is asked at each motion command; if it is configured but does
not answer in time the command is refused (it may be playing), if nothing serves ``pattern`` the
command goes out. Left open: a pattern started within the same few ms as the command (the check
and the send are not one step); the pattern player's bus watch stops the pattern only on a
disable or stop frame. With ``motion_via_manager`` the manager owns this (claims).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import can
import msgspec
from exolink import cdr, roles
from exolink.arming import ArmingState
from exolink.canbus import open_bus
from exolink.jointlimits import Angles, Caps, Limits, default_max, default_min
from exolink.messaging import CommandRefused, Unreachable
from exolink.node import Node
from exolink.protocol import ProtocolError, h2

JOINT_COMMAND = "exolink_msgs/msg/JointCommand"
MANAGER_WAIT_S = 2.0  # the manager's switch waits up to 1 s for an H2 cycle
PATTERN_WAIT_S = 0.5  # the pattern player's status answer (ms on x86, ~0.1 s on a busy board)
DRIVING = ("running", "paused")  # pattern states in which it owns its selected joints
MOTION = {h2.MODES["position"], h2.MODES["stiffness"], h2.MODES["torque"]}


class SenderParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    # Joint limits this lab accepts (deg, joint order r_hip..l_ankle), inside the mechanical ranges.
    min_angles: Angles = msgspec.field(default_factory=default_min)
    max_angles: Angles = msgspec.field(default_factory=default_max)
    send_limits_on_start: bool = True
    require_armed: bool = True
    # Per joint: the largest |set-point| accepted in torque mode and stiffness in stiffness mode.
    # The protocol allows 127 and 100; a lab sets what its motors and its patients tolerate.
    torque_cap: Caps = msgspec.field(default_factory=lambda: [127] * 6)
    stiffness_cap: Caps = msgspec.field(default_factory=lambda: [100] * 6)
    # Motion (position, stiffness, torque) goes to the controller manager, which writes it as the
    # joint's operator controller (one writer per joint); this node sends no motion frame then.
    # Disable, stop, limits and stream stay here.
    motion_via_manager: bool = False


class H2Sender(Node):
    Params = SenderParams

    def configure(self) -> None:
        p = self.params
        # Validated with the codec: a bad config starts nothing.
        self.checks = Limits.of(
            p.min_angles, p.max_angles, p.torque_cap, p.stiffness_cap, self.name
        )
        self.limit_frames = [
            h2.encode_accepted_angles("min", p.min_angles),
            h2.encode_accepted_angles("max", p.max_angles),
        ]
        # What the H2 enforces now: the configured limits, until an operator sends stricter ones.
        self.h2_min, self.h2_max = list(p.min_angles), list(p.max_angles)
        self.bus = self.own(open_bus(self.ctx.config.can, filters=[]))
        self.lock = threading.Lock()
        self.arming = self.own(ArmingState(self.ctx.messaging)) if p.require_armed else None
        self.pub = self.own(self.ctx.messaging.publisher("joint_commands", JOINT_COMMAND, raw=True))
        self.sent = 0
        self.refused = 0
        self.own(self.ctx.messaging.serve(("h2", "command"), self.on_command, roles.OPERATOR))
        if p.send_limits_on_start:
            self._send(self.limit_frames)

    def _send(self, frames: list[can.Message]) -> None:
        with self.lock:
            for f in frames:
                self.bus.send(f)
                self.sent += 1

    def build(self, req: dict[str, Any]) -> list[can.Message]:
        """Request -> frames, or CommandRefused naming what is wrong. Sends nothing."""
        kind = req.get("kind")
        try:
            if kind == "joint":
                return self._joint(req)
            if kind == "limits":
                return self._limits(req)
            if kind == "stream":
                on = req.get("on")
                if not isinstance(on, bool):
                    raise CommandRefused("stream needs 'on': true or false")
                return [h2.encode_stream(on)]
        except ProtocolError as exc:
            raise CommandRefused(str(exc)) from None
        raise CommandRefused(f"unknown command kind {kind!r} (joint, limits or stream)")

    def _joint(self, req: dict[str, Any]) -> list[can.Message]:
        joint = req.get("joint")
        mode = h2.mode_id(req.get("mode", ""))
        if joint == "all":
            if mode in MOTION:
                raise CommandRefused("'all' joints is only for disabled or stopped")
            return [h2.encode_joint_control(m, mode) for m in range(1, 7)]
        motor = h2.motor_id(joint)  # type: ignore[arg-type]
        msg = h2.encode_joint_control(motor, mode, req.get("setpoint", 0), req.get("stiffness", 0))
        i = motor - 1
        why = self.checks.violation(
            i,
            mode,
            int(req.get("setpoint", 0)),
            int(req.get("stiffness", 0)),
            self.limits(i),
            " (the stricter of the configured ones and the last sent to the H2)",
        )
        if why is not None:
            raise CommandRefused(why)
        if mode in MOTION and self.arming is not None and (why := self.arming.check()):
            raise CommandRefused(why)
        return [msg]

    def limits(self, i: int) -> tuple[int, int]:
        """Joint i's accepted set-points: the stricter of the configured and the sent limits."""
        p = self.params
        return max(p.min_angles[i], self.h2_min[i]), min(p.max_angles[i], self.h2_max[i])

    def _limits(self, req: dict[str, Any]) -> list[can.Message]:
        frames = []
        for kind in ("min", "max"):
            if kind in req:
                frames.append(h2.encode_accepted_angles(kind, req[kind]))
        if not frames:
            raise CommandRefused("limits needs 'min' and/or 'max' (six angles in degrees)")
        new_min = [int(v) for v in h2.decode(frames[0])] if "min" in req else self.h2_min
        new_max = [int(v) for v in h2.decode(frames[-1])] if "max" in req else self.h2_max
        p = self.params
        for j, lo, hi, cmin, cmax in zip(
            h2.JOINTS, new_min, new_max, p.min_angles, p.max_angles, strict=True
        ):
            if lo >= hi:
                raise CommandRefused(f"{j}: min {lo} must be below max {hi}")
            if lo < cmin or hi > cmax:
                raise CommandRefused(
                    f"{j}: limits {lo}..{hi} reach outside the configured {cmin}..{cmax}"
                )
        return frames

    def on_command(self, req: dict[str, Any]) -> dict[str, Any]:
        try:
            frames = self.build(req)
            if self.params.motion_via_manager and len(frames) == 1:
                jc = h2.decode(frames[0])
                if isinstance(jc, h2.JointControl) and jc.mode in MOTION:
                    return self._via_manager(jc)
            self._check_pattern(frames)
        except CommandRefused as exc:
            self.refused += 1
            self.log.warning("command_refused", request=req, reason=str(exc))
            raise
        self._send(frames)
        for f in frames:
            self._record(f)
            lim = h2.decode(f)
            if isinstance(lim, h2.MinAngles):
                self.h2_min = list(lim)
            elif isinstance(lim, h2.MaxAngles):
                self.h2_max = list(lim)
        self.log.info("command_sent", request=req, frames=len(frames))
        return {"frames": [f"{f.arbitration_id:03X}#{f.data.hex().upper()}" for f in frames]}

    def _check_pattern(self, frames: list[can.Message]) -> None:
        """Refuse motion for a joint the gait pattern drives (see the module docstring)."""
        motion = [
            jc
            for jc in (h2.decode(f) for f in frames)
            if isinstance(jc, h2.JointControl) and jc.mode in MOTION
        ]
        if not motion:
            return
        joints = [h2.JOINTS[jc.motor - 1] for jc in motion]
        t0 = time.monotonic()
        try:
            st = self.ctx.messaging.request(
                "pattern", body={"action": "status"}, timeout_s=PATTERN_WAIT_S
            )
        except Unreachable as exc:
            if time.monotonic() - t0 < PATTERN_WAIT_S * 0.9:  # nothing serves it: no pattern
                return
            raise CommandRefused(
                f"the pattern player did not answer within {PATTERN_WAIT_S:g} s, so it cannot be "
                f"ruled out that the pattern drives {', '.join(joints)}: {exc}"
            ) from None
        driven = [j for j in joints if st.get("state") in DRIVING and j in st.get("selected", [])]
        if driven:
            raise CommandRefused(
                f"{', '.join(driven)} is driven by the gait pattern ({st['state']}): "
                f"`exolink pattern stop` (or `pattern disable {driven[0]}`) first"
            )

    def _via_manager(self, jc: h2.JointControl) -> dict[str, Any]:
        """The checked command, for the controller manager to write; its refusal (another
        controller drives the joint, say) reaches the caller verbatim."""
        body = {
            "action": "operator",
            "joint": h2.JOINTS[jc.motor - 1],
            "mode": h2.MODE_NAMES[jc.mode],
            "setpoint": jc.setpoint,
            "stiffness": jc.stiffness,
        }
        reply = self.ctx.messaging.command("controllers", body=body, timeout_s=MANAGER_WAIT_S)
        self.log.info("command_forwarded", request=body, controller=reply.get("controller"))
        return {"controller": reply.get("controller"), "frames": []}

    def _record(self, frame: can.Message) -> None:
        jc = h2.decode(frame)
        if isinstance(jc, h2.JointControl):
            now = time.time_ns()
            joint = h2.JOINTS[jc.motor - 1]
            payload = cdr.joint_command(now, joint, jc.mode, jc.setpoint, jc.stiffness, self.name)
            self.pub.put(payload, now)

    def run(self, stop: threading.Event) -> None:
        # Commands come on Zenoh's thread; the loop only shows the process alive, well within
        # stall_s (at 10/s it was ~1 % of the board proxy's CPU 0 for nothing).
        while not stop.wait(self.stall_s / 2):
            self.beat()
