"""The H2 exoskeleton with its MACCEPA boards on one CAN bus (shared/protocol/h2-can.md,
maccepa-can.md), as the watchdog knows it: the joint-angle stream (id 110) is its pulse, joint
control (id 70) in a moving mode is motion, and MACCEPA board 0's controller frame, which shares
id 70 at length 8, is the other protocol's traffic, not a malformed H2 frame."""

from __future__ import annotations

from typing import TYPE_CHECKING

from exolink.config import ApplianceConfig, NodeConfig, WatchdogConfig
from exolink.hardware import Seen
from exolink.protocol import h2, maccepa

if TYPE_CHECKING:
    import can

    from exolink.protocol.dbc import Received

MOTION_MODES = frozenset({h2.MODES["position"], h2.MODES["stiffness"], h2.MODES["torque"]})
_PULSE, _MOTION, _OTHER = (Seen.PULSE, ""), (Seen.MOTION, ""), (Seen.OTHER, "")


class H2Exoskeleton:
    pulse = "h2 data"
    pulse_id = h2.JOINT_ANGLES
    command_id = h2.JOINT_CONTROL
    command_mask = h2.MODE_MASK

    def safe_action(self, cfg: WatchdogConfig) -> list[can.Message]:
        """Every joint disabled or stopped (``safe_action``), each configured board stopped."""
        return h2.safe_action(cfg.safe_action) + [
            maccepa.encode_stop(b) for b in cfg.maccepa_boards
        ]

    def judge(self, msg: Received) -> tuple[Seen, str]:
        frame = h2.decode(msg)
        if isinstance(frame, h2.JointAngles):
            return _PULSE
        if isinstance(frame, h2.JointControl):
            return _MOTION if frame.mode in MOTION_MODES else _OTHER
        if isinstance(frame, h2.Unknown) and isinstance(maccepa.decode(msg), maccepa.Unknown):
            return Seen.MALFORMED, frame.reason
        return _OTHER

    def simulator(self, cfg: ApplianceConfig) -> NodeConfig:
        """exolink.nodes.simulator, with the MACCEPA boards the watchdog stops on a trip."""
        params = {"maccepa_boards": list(cfg.watchdog.maccepa_boards)}
        return NodeConfig(name="simulator", plugin="simulator", params=params)
