"""The rig's nodes: its simulator (what ``exolink up --sim`` runs in the rig's place) and its
driver, which sweeps the joint while the watchdog says armed."""

from __future__ import annotations

import math
import threading
import time
from typing import Annotated, Any

import can
import msgspec

from exolink.canbus import open_bus
from exolink.control.arming import ArmingState
from exolink.messaging import msg_class
from exolink.node import Node
from lab_rig import ANGLE, COMMAND, OFF, PERIOD_S, POSITION, angle_frame, command_frame


def _decode(msg: can.Message | None, what: Any) -> dict[str, float] | None:
    """A frame of ``what``'s (a cantools message) id and length, decoded; None for anything
    else: a frame on the bus may be anyone's."""
    if msg is None or msg.arbitration_id != what.frame_id or msg.is_extended_id:
        return None
    if len(msg.data) != what.length:
        return None
    return dict(what.decode(bytes(msg.data), decode_choices=False))


class SimParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    rate_deg_s: Annotated[float, msgspec.Meta(gt=0, le=720)] = 90.0  # the motor's top speed


class RigSim(Node):
    """The rig on a simulated bus: its angle every 10 ms; in position mode the joint moves
    toward the set-point at ``rate_deg_s``, in any other it stays where it is."""

    Params = SimParams

    def configure(self) -> None:
        self.bus = self.own(open_bus(self.ctx.config.can))
        self.angle, self.mode, self.setpoint = 0.0, OFF, 0.0

    def run(self, stop: threading.Event) -> None:
        due = time.monotonic()
        while not stop.is_set():
            self.beat()
            while (left := due - time.monotonic()) > 0:
                cmd = _decode(self.bus.recv(left), COMMAND)
                if cmd is not None:
                    self.mode, self.setpoint = int(cmd["mode"]), float(cmd["setpoint"])
            if self.mode == POSITION:
                step = self.params.rate_deg_s * PERIOD_S
                self.angle += max(-step, min(step, self.setpoint - self.angle))
            self.bus.send(angle_frame(self.angle))
            due = max(due + PERIOD_S, time.monotonic())


class DriverParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    amplitude_deg: Annotated[float, msgspec.Meta(ge=0, le=45)] = 20.0
    period_s: Annotated[float, msgspec.Meta(ge=0.5, le=60)] = 4.0


class RigDriver(Node):
    """One set-point per angle frame while armed: a sine sweep from where the arm found it at
    zero. Not armed, it sends nothing (the watchdog's safe action holds the rig off). The
    rig's angle goes out on ``rig/angle`` (std_msgs/Float64): ``exolink echo rig/angle``."""

    Params = DriverParams
    stall_s = 0.05  # paced by the rig's 10 ms pulse

    def configure(self) -> None:
        m = self.ctx.messaging
        self.arming = self.own(ArmingState(m))
        self.bus = self.own(
            open_bus(self.ctx.config.can, [{"can_id": ANGLE.frame_id, "can_mask": 0x7FF}])
        )
        self.pub = self.own(m.publisher("rig/angle", "std_msgs/msg/Float64"))
        self.Float64 = msg_class("std_msgs/msg/Float64")
        self.since: float | None = None  # when the sweep began (armed)

    def run(self, stop: threading.Event) -> None:
        p = self.params
        while not stop.is_set():
            self.beat()
            angle = _decode(self.bus.recv(self.stall_s / 2), ANGLE)
            if angle is None:
                continue  # no pulse: the watchdog trips on its silence
            self.pub.publish(self.Float64(data=float(angle["angle"])))
            if self.arming.check() is not None:
                self.since = None
                continue
            now = time.monotonic()
            self.since = self.since or now
            phase = 2 * math.pi * (now - self.since) / p.period_s
            self.bus.send(command_frame(POSITION, p.amplitude_deg * math.sin(phase)))

    def shutdown(self) -> None:
        self.bus.send(command_frame(OFF))
