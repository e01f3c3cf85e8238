"""The hardware the supervisor guards, as its watchdog needs to know it (``Device``): which
frame is the device's pulse (its silence: the device is gone), which frame moves it and whether
a given one does, and the frames of its safe action. The supervisor and the watchdog speak of
"the device" only; a new exoskeleton is a new ``Device`` registered under the
``exolink.hardware`` entry point (config: ``hardware: <name>``), not edits to them.

Implementations: ``h2`` (the H2 with MACCEPA boards on one bus: exolink.hardware.h2). The
boards' frames as their state, for the nodes that read them: exolink.hardware.maccepa.
"""

from __future__ import annotations

from enum import Enum
from functools import cache
from typing import TYPE_CHECKING, Protocol

from exolink import entrypoints
from exolink.config import ApplianceConfig, ConfigError, NodeConfig, WatchdogConfig

if TYPE_CHECKING:
    import can

    from exolink.protocol.dbc import Received

GROUP = "exolink.hardware"


class Seen(Enum):
    """What a frame on the bus is to the watchdog."""

    PULSE = "pulse"  # the device's periodic frame: it is there
    MOTION = "motion"  # a command that moves a motor (refused unless armed)
    OTHER = "other"  # anything else of the device's protocols
    MALFORMED = "malformed"  # an id or length no protocol on the bus has (counted, skipped)


class Device(Protocol):
    """What the supervisor and its watchdog know of the hardware (see the module docstring)."""

    pulse: str  # what falls silent, for a trip's reason ("h2 data" -> "h2 data silent")
    pulse_id: int  # the periodic frame whose silence trips the watchdog
    command_id: int  # the frame that moves the device
    # The command frame's bits whose change the kernel's watch reports (SocketCAN's broadcast
    # manager, exolink.canbus.bcm): those that tell motion from its absence.
    command_mask: bytes

    def safe_action(self, cfg: WatchdogConfig) -> list[can.Message]:
        """The frames that leave the device safe, sent on every trip and repeated."""
        ...

    def judge(self, msg: Received) -> tuple[Seen, str]:
        """What ``msg`` is, and for a malformed one why (never raises: any frame may come)."""
        ...

    def simulator(self, cfg: ApplianceConfig) -> NodeConfig:
        """The node that plays the device on a simulated bus: ``exolink up --sim`` (``make sim``)
        adds it to a config that runs no node of its plugin, so a config written for the board
        runs on the laptop as it is."""
        ...


@cache
def load(name: str) -> Device:
    """The device named in the config; a ConfigError names the ones installed."""
    try:
        cls, _where = entrypoints.load(GROUP, name, "device")
    except entrypoints.PluginError as exc:
        raise ConfigError(f"hardware: {exc}") from None
    device: Device = cls()
    return device


__all__ = ["GROUP", "Device", "Seen", "load"]
