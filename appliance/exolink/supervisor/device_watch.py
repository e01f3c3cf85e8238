"""What the watchdog reads of the device (exolink.hardware): its pulse and its command frames.

On SocketCAN the kernel's broadcast manager watches both (exolink.canbus.bcm: a silent pulse and
any command frame wake the watchdog, with no Python per frame) and the watchdog's own socket
only sends. The simulated bus has no such thing: a reader of both ids that only a command
wakes, the pulse judged by its silence deadline.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from exolink.canbus import FrameReader, open_reader
from exolink.config import ApplianceConfig
from exolink.hardware import Device

if TYPE_CHECKING:
    from exolink.canbus.bcm import CyclicWatch


@dataclass(frozen=True)
class DeviceWatch:
    reader: FrameReader
    pulse: CyclicWatch | None = None  # None: the simulated bus
    command: CyclicWatch | None = None
    reopen: Callable[[], CyclicWatch] | None = None  # the command's watch made again


def watch_device(cfg: ApplianceConfig, dev: Device) -> DeviceWatch:
    """The watchdog's reader and watches; nothing left open when one of them fails."""
    if cfg.can.interface != "socketcan":  # the pulse never wakes it; a command does
        reader = open_reader(cfg.can, [dev.pulse_id, dev.command_id], wake_on=[dev.command_id])
        return DeviceWatch(reader)
    from exolink.canbus.bcm import CyclicWatch  # Linux only (the module's constants too)

    watches: list[CyclicWatch] = []
    try:
        watches.append(CyclicWatch(cfg.can.channel, dev.pulse_id, cfg.watchdog.silence_ms / 1e3))
        reopen = functools.partial(
            CyclicWatch, cfg.can.channel, dev.command_id, mask=dev.command_mask
        )
        watches.append(reopen())  # the first now: no can-bcm fails the start here
        return DeviceWatch(open_reader(cfg.can, []), watches[0], watches[1], reopen)
    except BaseException:
        for w in watches:
            w.close()
        raise
