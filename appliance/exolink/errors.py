"""The errors an operator can fix, and the exit code each ends a process with.

Both the node runtime (on the board) and the command line (on a laptop) end on these the same
way: one line on stderr and an exit code systemd and scripts can act on. The hardware errors are
defined here rather than next to the supervisor code that raises them, so the runtime, which sits
below the supervisor, can name them.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from exolink.refusal import Refused

EXIT_USAGE, EXIT_CONFIG, EXIT_UNREACHABLE, EXIT_REFUSED = 2, 3, 4, 5
# Apart from a bad config: CAN or GPIO missing may pass (a driver still probing at boot), so
# systemd restarts on it; a bad config never fixes itself, so systemd must not (exolink.service).
EXIT_HARDWARE = 6


class CanLinkError(RuntimeError):
    pass


class TriggerError(RuntimeError):
    pass


def fail(message: str, code: int) -> int:
    sys.stderr.write(f"exolink: {message}\n")
    return code


def run_guarded(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    # light: the supervisor's CAN link and trigger import this module for their errors, and the
    # commands for the exit codes; plugins, config and Zenoh load only for a guarded run
    from exolink.canbus import CanOpenError
    from exolink.config import ConfigError
    from exolink.messaging import Unreachable
    from exolink.plugins import PluginError
    from exolink.protocol import ProtocolError

    try:
        return func(args)
    except ConfigError as exc:
        return fail(f"config error: {exc}", EXIT_CONFIG)
    except PluginError as exc:
        return fail(str(exc), EXIT_CONFIG)
    except (CanOpenError, CanLinkError, TriggerError) as exc:
        return fail(str(exc), EXIT_HARDWARE)
    except Unreachable as exc:
        return fail(f"appliance unreachable: {exc}", EXIT_UNREACHABLE)
    except (ProtocolError, Refused) as exc:
        return fail(f"refused: {exc}", EXIT_REFUSED)
    except KeyboardInterrupt:
        return 130
