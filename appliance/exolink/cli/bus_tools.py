"""Commands that sit directly on a CAN bus: the simulator and a decoded candump."""

from __future__ import annotations

import argparse
import sys
import threading
from datetime import UTC, datetime

from exolink import logs
from exolink.canbus import open_bus, open_reader
from exolink.config import INTERFACE_ALIASES, SIM_INTERFACE, SIM_MULTICAST_GROUP, CanConfig
from exolink.protocol import h2, maccepa


def bus_config(args: argparse.Namespace) -> CanConfig:
    default = {SIM_INTERFACE: SIM_MULTICAST_GROUP, "socketcan": "can0", "virtual": "exolink"}
    interface = INTERFACE_ALIASES.get(args.interface, args.interface)
    return CanConfig(
        interface=args.interface, channel=args.channel or default[interface], bring_up=False
    )


def cmd_sim(args: argparse.Namespace) -> int:
    from exolink.nodes.simulator import SimParams, Simulator  # a node plugin: `sim` only
    from exolink.runtime import stop_on_signals  # the node runtime: `sim` only

    log = logs.setup("sim")
    params = SimParams(maccepa_boards=args.maccepa)
    with open_reader(bus_config(args), Simulator.command_ids(params)) as reader:
        sim = Simulator(reader.bus, params, reader)
        stop = threading.Event()
        stop_on_signals(stop, log)
        info = reader.bus.channel_info
        log.info("sim_running", bus=f"{args.interface}:{info}", maccepa=args.maccepa)
        try:
            sim.run(stop)
        finally:
            log.info("sim_stopped", **vars(sim.stats))
    return 0


def describe(msg) -> str:
    """One decoded line: H2 frames first, MACCEPA otherwise, 'unknown' for the rest."""

    f = h2.decode(msg)
    if isinstance(f, h2.Unknown):
        f2 = maccepa.decode(msg)
        if isinstance(f2, maccepa.Unknown):
            return f"{f2.reason} {f2.data.hex(' ')}"
        return f"maccepa {type(f2).__name__} " + " ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in f2._asdict().items()
        )
    fields = " ".join(f"{k}={v}" for k, v in f._asdict().items())
    return f"h2 {type(f).__name__} {fields}"


def cmd_candump(args: argparse.Namespace) -> int:

    bus = open_bus(bus_config(args))
    n = 0
    try:
        while args.count == 0 or n < args.count:
            msg = bus.recv(timeout=0.5)
            if msg is None:
                continue
            n += 1
            t = datetime.fromtimestamp(msg.timestamp, UTC).strftime("%H:%M:%S.%f")
            raw = f" [{len(msg.data)}] {msg.data.hex(' ').upper()}" if args.raw else ""
            sys.stdout.write(f"{t} {msg.arbitration_id:03X}{raw}  {describe(msg)}\n")
            sys.stdout.flush()
    finally:
        bus.shutdown()
    return 0
