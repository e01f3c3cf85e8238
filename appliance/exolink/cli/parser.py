"""The ``exolink`` command line's parser: every subcommand's options and handler.

Below both the entry point (exolink.cli.main) and the dashboard, which parses the commands its
page sends with this same parser.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Sequence
from typing import Any

from exolink import __version__
from exolink.cli import (
    board,
    bus_tools,
    clock,
    controllers,
    data,
    files,
    motion,
    options,
    recordings,
    remote,
    status,
    update,
)

Handler = Callable[[argparse.Namespace], int]


def _add_config(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", help="appliance YAML (default: /etc/exolink/appliance.yaml)")


def _add_bus(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--interface",
        "-i",
        default="udp_multicast",
        choices=["socketcan", "exolink_sim", "udp_multicast", "virtual"],
    )
    p.add_argument("--channel", default=None, help="can0 / vcan0 / multicast group")


class Parser(argparse.ArgumentParser):
    """Any word starting with a minus and a digit is a value, not an option: `--min -10,0,-20,...`.

    Python 3.11 only takes `-10` or `-1.5` for a number (3.13 takes any `-<digit>...`); the
    subcommands' parsers are made from this class too.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")


def build_parser(
    parser_class: type[Parser] = Parser,
    description: str | None = None,
    extra: Sequence[Callable[[Any], None]] = (),
) -> argparse.ArgumentParser:
    """The command line of the laptop and board commands, then `extra` registrations (the
    dashboard's, added by exolink.cli.main, which sits above the dashboard); the dashboard parses
    its forms with a parser_class that raises."""
    parser = parser_class(prog="exolink", description=description)
    parser.add_argument("--version", action="version", version=f"exolink {__version__}")
    options.add_global_options(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("up", help="run the appliance: supervisor, nodes, watchdog (board side)")
    _add_config(p)
    p.add_argument(
        "--sim",
        action="store_true",
        help="simulated hardware: udp_multicast bus, simulator node, fake trigger",
    )
    p.set_defaults(func=board.cmd_up)

    p = sub.add_parser("config", help="validate an appliance config and print it")
    p.add_argument("file")
    p.set_defaults(func=board.cmd_config)

    p = sub.add_parser(
        "board-setup", help="apply the card's exolink-settings.yaml to the board (at boot)"
    )
    p.add_argument("--boot", default="/boot/firmware", help="where the card's FAT partition is")
    p.add_argument("--root", default="/", help="root to write into (a scratch dir for checks)")
    p.set_defaults(func=board.cmd_board_setup)

    p = sub.add_parser("node", help="run one node standalone")
    nsub = p.add_subparsers(dest="node_cmd", required=True)
    q = nsub.add_parser("run", help="run NAME from the config in this process")
    q.add_argument("name")
    _add_config(q)
    q.add_argument(
        "--listen", action="append", help="also listen on a Zenoh endpoint (no supervisor)"
    )
    q.set_defaults(func=board.cmd_node_run)
    q = nsub.add_parser("plugins", help="list installed node plugins")
    q.set_defaults(func=board.cmd_plugins)

    p = sub.add_parser("sim", help="run the hardware simulator on a bus (no Zenoh)")
    _add_bus(p)
    p.add_argument("--maccepa", type=options.integer, action="append", default=[], metavar="BOARD")
    p.set_defaults(func=bus_tools.cmd_sim)

    p = sub.add_parser("candump", help="live decoded view of a CAN bus (H2 + MACCEPA DBC)")
    _add_bus(p)
    p.add_argument("--raw", action="store_true", help="also print the raw bytes")
    p.add_argument("--count", type=options.integer, default=0, help="stop after N frames")
    p.set_defaults(func=bus_tools.cmd_candump)

    data.register(sub)
    remote.register(sub)
    status.register(sub)
    remote.register_management(sub)
    motion.register(sub)
    recordings.register(sub)
    files.register(sub)
    clock.register(sub)
    update.register(sub)
    controllers.register(sub)
    for register in extra:
        register(sub)
    return parser
