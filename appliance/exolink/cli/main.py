"""The ``exolink`` command: board-side (up, node run, sim) and laptop-side (status, echo, send...).

Each subcommand imports only what it needs, so ``exolink --help`` and quick laptop commands start
fast; errors are one readable line and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from exolink.cli import parser
from exolink.cli.errors import Stdout, run_guarded
from exolink.cli.options import resolve_appliance_options
from exolink.cli.parser import Handler, Parser
from exolink.dashboard import cli as dashboard_cli

__all__ = ["Handler", "Parser", "build_parser", "main", "parse"]


def build_parser(parser_class: type[Parser] = Parser) -> argparse.ArgumentParser:
    """The whole command line, the dashboard's command included."""
    return parser.build_parser(parser_class, description=__doc__, extra=[dashboard_cli.register])


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line as the command functions get it (appliance options resolved)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    resolve_appliance_options(parser, args)
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. A reader that closes stdout early ends it quietly with 0, whichever
    thread was writing (exolink.cli.errors.Stdout: for the laptop's commands, whose Zenoh
    callbacks print; board-side ones print from the main thread only)."""
    out = Stdout(sys.stdout)
    try:
        try:
            args = parse(argv)
            if getattr(args, "talks_to_appliance", False):
                out.install()
                sys.stdout = out
            code = run_guarded(args.func, args)
        finally:
            sys.stdout = out.inner
            out.finish()
    except BrokenPipeError:
        out.quiet()
        return 0
    except KeyboardInterrupt:
        if not out.gone:
            raise
        return 0
    return 0 if out.gone else code


if __name__ == "__main__":
    sys.exit(main())
