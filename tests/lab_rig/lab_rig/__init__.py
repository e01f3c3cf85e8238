"""A lab's one-joint test rig: its DBC (rig.dbc) and what exolink's watchdog needs of it
(exolink.hardware.Device). The rig streams its angle every 10 ms (its pulse) and takes a mode
and a set-point (motion unless the mode is off)."""

from __future__ import annotations

from pathlib import Path

import can
import cantools

from exolink.config import ApplianceConfig, NodeConfig, WatchdogConfig
from exolink.hardware import Seen
from exolink.protocol.dbc import Received

DB = cantools.database.load_file(str(Path(__file__).with_name("rig.dbc")))
ANGLE, COMMAND = DB.get_message_by_name("RigAngle"), DB.get_message_by_name("RigCommand")
PERIOD_S = 0.01
OFF, POSITION = 0, 1


def angle_frame(deg: float) -> can.Message:
    data = ANGLE.encode({"angle": round(deg, 1)})
    return can.Message(arbitration_id=ANGLE.frame_id, data=data, is_extended_id=False)


def command_frame(mode: int, setpoint: float = 0.0) -> can.Message:
    data = COMMAND.encode({"mode": mode, "setpoint": round(setpoint, 1)})
    return can.Message(arbitration_id=COMMAND.frame_id, data=data, is_extended_id=False)


class Rig:
    pulse = "rig data"
    pulse_id = ANGLE.frame_id
    command_id = COMMAND.frame_id
    command_mask = bytes([0xFF, 0, 0])  # the mode: what tells motion from its absence

    def safe_action(self, cfg: WatchdogConfig) -> list[can.Message]:
        return [command_frame(OFF)]

    def judge(self, msg: Received) -> tuple[Seen, str]:
        try:
            m = DB.get_message_by_frame_id(msg.arbitration_id)
        except KeyError:
            return Seen.MALFORMED, "unknown id"
        if msg.is_extended_id or len(msg.data) != m.length:
            return Seen.MALFORMED, "bad length"
        if m is ANGLE:
            return Seen.PULSE, ""
        mode = m.decode(bytes(msg.data), decode_choices=False)["mode"]
        if mode > 2:  # a lab's bug on purpose: the watchdog must live with a judge that raises
            raise ValueError(f"rig: mode {mode}")
        return (Seen.MOTION, "") if mode != OFF else (Seen.OTHER, "")

    def simulator(self, cfg: ApplianceConfig) -> NodeConfig:
        return NodeConfig(name="rig_sim", plugin="rig_sim")
