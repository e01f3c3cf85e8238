"""The dashboard's commands are `exolink` command lines: parsed by the CLI's own parser.

A form on the page becomes an argv (``["send", "position", "r_knee", "30"]``), so the dashboard
accepts exactly what the CLI accepts, with the same argument checks (numbers, choices, six
angles, labels) and the same request bodies (exolink.cli.remote.h2_body and friends). What the
appliance then refuses (ranges, limits, not armed, role) comes back as the node's own reason.
A command the parser refuses is never sent.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

from exolink.cli import parser as cli_parser
from exolink.cli.motion import START_TIMEOUT_S, maccepa_body, pattern_body, timing_body
from exolink.cli.recordings import record_body
from exolink.cli.remote import control_body, h2_body, params_body, trigger_body, watchdog_body


class CommandError(Exception):
    """A command line the dashboard will not send; the text says why."""


class _RaisingParser(cli_parser.Parser):
    """The CLI's parser, raising instead of printing usage and exiting the server."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise CommandError(f"{self.prog}: {message}")

    def exit(self, status: int = 0, message: str | None = None) -> None:  # type: ignore[override]
        raise CommandError(message or f"{self.prog}: exit {status}")


# The options that choose an appliance or a login belong to the dashboard's own command line.
_FORBIDDEN_FLAGS = ("--at", "--device", "--zenoh-config", "--timeout", "--domain", "--ns", "-h")
# Commands the page may send (the rest of the CLI reads files or holds a terminal).
ALLOWED = {"send", "maccepa", "pattern", "record", "arm", "disarm", "estop"}
ALLOWED |= {"start", "stop", "restart", "trigger", "timing", "params"}
# Sub-actions with nothing to do in a page: a terminal plot, a local file upload.
_REFUSED_ACTIONS = {("maccepa", "watch"), ("pattern", "load"), ("record", "status")}


@dataclass(frozen=True)
class Command:
    """One parsed command: where it goes, what it says, and whether it moves a joint."""

    argv: tuple[str, ...]
    path: tuple[str, ...]
    body: dict[str, Any]
    motion: bool
    timeout_s: float | None = None

    @property
    def text(self) -> str:
        return "exolink " + " ".join(self.argv)


_parser: argparse.ArgumentParser | None = None


def _get_parser() -> argparse.ArgumentParser:
    global _parser
    if _parser is None:
        _parser = cli_parser.build_parser(_RaisingParser)
    return _parser


def parse(argv: list[str]) -> Command:
    """argv -> Command, or CommandError naming what is wrong (nothing is sent then)."""
    if not argv or not all(isinstance(a, str) for a in argv):
        raise CommandError("a command is a non-empty list of words")
    if argv[0] not in ALLOWED:
        raise CommandError(f"`exolink {argv[0]}` is not a dashboard command")
    for word in argv:
        if word.split("=", 1)[0] in _FORBIDDEN_FLAGS or word == "--help":
            raise CommandError(f"{word}: the dashboard's own options choose the appliance")
    args = _get_parser().parse_args(argv)
    cmd = args.command
    action = (
        getattr(args, "what", None) or getattr(args, "action", None) or getattr(args, "kind", None)
    )
    if (cmd, action) in _REFUSED_ACTIONS:
        raise CommandError(f"`exolink {cmd} {action}` is not a dashboard command")
    return _route(tuple(argv), args)


def _route(argv: tuple[str, ...], args: argparse.Namespace) -> Command:
    cmd = args.command
    if cmd == "send":
        body = h2_body(args)
        motion = body.get("mode") in ("position", "stiffness", "torque")
        return Command(argv, ("h2", "command"), body, motion)
    if cmd == "maccepa":
        body = maccepa_body(args)
        return Command(argv, ("maccepa",), body, body["kind"] in ("setpoint", "duty"))
    if cmd == "pattern":
        body = pattern_body(args)
        wait = START_TIMEOUT_S if body["action"] == "start" else None
        return Command(argv, ("pattern",), body, body["action"] in ("start", "restart"), wait)
    if cmd == "record":
        try:
            body = record_body(args)
        except ValueError as exc:
            raise CommandError(str(exc)) from None
        return Command(argv, ("record",), body, False)
    if cmd in ("arm", "disarm", "estop"):
        return Command(argv, ("watchdog",), watchdog_body(cmd), False)
    if cmd in ("start", "stop", "restart"):
        return Command(argv, ("control",), control_body(cmd, args.node), False)
    if cmd == "params":
        return Command(argv, ("nodes", args.node, "params"), params_body(args), False)
    if cmd == "trigger":
        return Command(argv, ("trigger",), trigger_body(bool(args.action)), False)
    # timing: the monitor measures for `seconds` before it answers
    return Command(argv, ("timing",), timing_body(args), False, timeout_s=args.seconds + 5)
