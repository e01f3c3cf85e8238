"""``exolink up --sim``: the same appliance on the simulated bus, with the device's simulator
(exolink.hardware: ``Device.simulator``) and a fake trigger, from the board's own config."""

from __future__ import annotations

import msgspec

from exolink import hardware
from exolink.config import SIM_MULTICAST_GROUP, ApplianceConfig, ConfigError


def simulated(cfg: ApplianceConfig) -> ApplianceConfig:
    """``--sim``: the same appliance on a udp_multicast bus with the device's simulator
    (exolink.hardware: ``Device.simulator``) and a fake trigger."""
    can = msgspec.structs.replace(
        cfg.can,
        interface="udp_multicast",
        channel=cfg.can.channel if cfg.can.simulated else SIM_MULTICAST_GROUP,
        bring_up=False,
        require_overlay=False,
    )
    trig = msgspec.structs.replace(cfg.trigger, source="simulated", output=None)
    nodes = list(cfg.nodes)
    play = getattr(hardware.load(cfg.hardware), "simulator", None)
    if play is None:  # a lab's device written before Device.simulator
        raise ConfigError(
            f"hardware {cfg.hardware!r} names no simulator (Device.simulator): --sim cannot "
            "play it; add one, or list its simulator node in the config"
        )
    sim = play(cfg)
    if not any(n.plugin == sim.plugin for n in nodes):
        nodes.insert(0, sim)
    return msgspec.structs.replace(cfg, can=can, trigger=trig, nodes=nodes)
