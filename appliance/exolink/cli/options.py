"""What every command that talks to an appliance shares: its options, the number types of its
arguments, and the guard that turns a refusal into an exit code."""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from typing import Any

from exolink.client import DEFAULT_AT, DEFAULT_TIMEOUT_S, Refused
from exolink.errors import EXIT_REFUSED, fail


def guard(func):
    def wrapped(args: argparse.Namespace) -> int:
        try:
            return int(func(args))
        except Refused as exc:
            return fail(f"refused: {exc}", EXIT_REFUSED)

    return wrapped


# Numbers as a person types them on a keyboard, in ASCII: Python's float() and int() also take
# other scripts' digits (full-width, Arabic-Indic), underscores, padding: a command line must not.
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INTEGER = re.compile(r"[+-]?[0-9]+")
_FRAME_ID = re.compile(r"0[xX][0-9a-fA-F]+|[0-9]+")


def _not_a_number(text: str, what: str) -> argparse.ArgumentTypeError:
    why = " (only ASCII digits 0-9 count)" if not text.isascii() else ""
    return argparse.ArgumentTypeError(f"{text!r} is not {what}{why}")


def decimal(text: str) -> float:
    """A finite decimal number in ASCII (30, -1.5, 2e-3)."""
    if not _DECIMAL.fullmatch(text):
        raise _not_a_number(text, "a number")
    v = float(text)
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def integer(text: str) -> int:
    """A whole number in ASCII digits (a count, a port, a board)."""
    if not _INTEGER.fullmatch(text):
        raise _not_a_number(text, "a whole number")
    return int(text)


def frame_id(text: str) -> int:
    """A CAN id, decimal or 0x hex (70, 0x46)."""
    if not _FRAME_ID.fullmatch(text):
        raise _not_a_number(text, "a CAN id (decimal or 0x hex)")
    return int(text, 0) if text[:2] in ("0x", "0X") else int(text)


def number(text: str) -> float:
    """A protocol value: whole numbers stay int (the protocol checks they are whole)."""
    v = decimal(text)
    return int(v) if v == int(v) else v


def _appliance_options() -> list[tuple[str, dict[str, Any]]]:
    """The options of every command that talks to an appliance: flag -> add_argument keywords."""
    return [
        (
            "--at",
            {
                "default": os.environ.get("EXOLINK_AT", DEFAULT_AT),
                "help": f"Zenoh endpoint of the appliance (env EXOLINK_AT, default {DEFAULT_AT})",
            },
        ),
        (
            "--device",
            {
                "default": os.environ.get("EXOLINK_DEVICE"),
                "help": "device name when several appliances answer (env EXOLINK_DEVICE)",
            },
        ),
        (
            "--zenoh-config",
            {
                "default": os.environ.get("EXOLINK_ZENOH_CONFIG"),
                "help": "Zenoh login for a board that requires one: the card's "
                "exolink-<role>.json5 (env EXOLINK_ZENOH_CONFIG)",
            },
        ),
        (
            "--timeout",
            {
                "type": decimal,
                "default": DEFAULT_TIMEOUT_S,
                "help": "seconds to wait for an answer (default 3); a longer one also waits "
                "that long for the connection",
            },
        ),
        ("--domain", {"type": integer, "default": 0, "help": "ROS domain id of data topics (0)"}),
        ("--ns", {"default": "h2", "help": "namespace of data topics (h2)"}),
    ]


GLOBAL_PREFIX = "global_"


def _dest(flag: str) -> str:
    return flag.lstrip("-").replace("-", "_")


def common() -> argparse.ArgumentParser:
    """Parent of the commands that talk to an appliance: its options after the command.

    Nothing is set unless given, so a value after the command wins over one before it (see
    add_global_options); resolve_appliance_options fills in the defaults.
    """
    p = argparse.ArgumentParser(add_help=False)
    p.set_defaults(talks_to_appliance=True)
    g = p.add_argument_group("appliance (also accepted before the command)")
    for flag, kw in _appliance_options():
        g.add_argument(flag, **{**kw, "default": argparse.SUPPRESS})
    return p


def add_global_options(parser: argparse.ArgumentParser) -> None:
    """The same options before the command: `exolink --at tcp/10.0.0.2:7447 status`."""
    g = parser.add_argument_group("appliance options (before or after the command)")
    for flag, kw in _appliance_options():
        g.add_argument(
            flag,
            **{**kw, "dest": GLOBAL_PREFIX + _dest(flag), "default": argparse.SUPPRESS},
            metavar=_dest(flag).upper(),
        )


def resolve_appliance_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """After the command > before it > environment / default; refused by commands without them."""
    before = {
        flag: getattr(args, GLOBAL_PREFIX + _dest(flag))
        for flag, _kw in _appliance_options()
        if hasattr(args, GLOBAL_PREFIX + _dest(flag))
    }
    for flag in before:
        delattr(args, GLOBAL_PREFIX + _dest(flag))
    if not getattr(args, "talks_to_appliance", False):
        if before:
            parser.error(
                f"{', '.join(before)}: `exolink {args.command}` does not talk to an appliance"
            )
        return
    for flag, kw in _appliance_options():
        if not hasattr(args, _dest(flag)):
            setattr(args, _dest(flag), before.get(flag, kw["default"]))


class Leaves:
    """Sub-subcommands that all take the appliance options (so `--at` may come last)."""

    def __init__(self, sub: argparse._SubParsersAction, parent: argparse.ArgumentParser) -> None:
        self.sub, self.parent = sub, parent

    def add_parser(self, name: str, **kw: Any) -> argparse.ArgumentParser:
        return self.sub.add_parser(name, parents=[self.parent], **kw)


def print_json(data: Any) -> None:
    """A reply as an operator's script reads it (``--json``)."""
    sys.stdout.write(json.dumps(data, indent=2) + "\n")
