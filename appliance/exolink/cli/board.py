"""Board-side commands: validate a config, run a node standalone, list plugins."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import msgspec

from exolink import hardware, logs
from exolink.config import bundled, check_all_apart, load
from exolink.plugins import available

DEFAULT_CONFIG = "/etc/exolink/appliance.yaml"


def config_path(args: argparse.Namespace) -> str:
    return getattr(args, "config", None) or DEFAULT_CONFIG


def cmd_config(args: argparse.Namespace) -> int:
    cfg = load(args.file)
    hardware.load(cfg.hardware)  # an unknown device is a config error (it names those installed)
    out = msgspec.json.format(msgspec.json.encode(cfg), indent=2)
    sys.stdout.write(out.decode() + "\n")
    return 0


def cmd_node_run(args: argparse.Namespace) -> int:
    from exolink.runtime import start  # board-side: the node runtime, for `node run` only

    return start(config_path(args), args.name, args.listen)


def cmd_plugins(args: argparse.Namespace) -> int:
    for name, target in sorted(available().items()):
        sys.stdout.write(f"{name:20} {target}\n")
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    """The supervisor. A bad config starts nothing and exits non-zero (the caller sees why)."""
    from exolink.supervisor.core import run  # heavy: the whole supervisor, `up` only
    from exolink.supervisor.sim import simulated  # with the supervisor: `up` only

    path = args.config or (str(bundled("sim")) if args.sim else DEFAULT_CONFIG)
    cfg = load(path, check=())
    hardware.load(cfg.hardware)  # the device the watchdog guards: known before anything starts
    check_all_apart(path)  # every node's params, without their imports staying in this process
    if args.sim:
        cfg = simulated(cfg)
    logs.setup("supervisor")
    return run(cfg)


def cmd_board_setup(args: argparse.Namespace) -> int:

    from exolink.board import setup as boardsetup  # the board's own setup: `board-setup` only
    from exolink.board.settings import SETTINGS_FILE, load_settings

    logs.setup("board-setup")
    boot = Path(args.boot)
    settings = load_settings(boot / SETTINGS_FILE)
    boardsetup.apply(settings, boot, Path(args.root))
    return 0
