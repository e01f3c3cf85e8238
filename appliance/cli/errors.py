"""Turns the errors an operator can fix into one line on stderr and an exit code."""

from __future__ import annotations

import _thread
import argparse
import os
import sys
import threading
from collections.abc import Callable
from typing import Any, TextIO

EXIT_USAGE, EXIT_CONFIG, EXIT_UNREACHABLE, EXIT_REFUSED = 2, 3, 4, 5
# Apart from a bad config: CAN or GPIO missing may pass (a driver still probing at boot), so
# systemd restarts on it; a bad config never fixes itself, so systemd must not (exolink.service).
EXIT_HARDWARE = 6


def fail(message: str, code: int) -> int:
    sys.stderr.write(f"exolink: {message}\n")
    return code


def run_guarded(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    from exolink.canbus import CanOpenError
    from exolink.config import ConfigError
    from exolink.messaging import Unreachable
    from exolink.plugins import PluginError
    from exolink.protocol import ProtocolError
    from exolink.supervisor.canlink import CanLinkError
    from exolink.supervisor.trigger import TriggerError

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
    except ProtocolError as exc:
        return fail(f"refused: {exc}", EXIT_REFUSED)
    except KeyboardInterrupt:
        return 130


class Stdout:
    """sys.stdout for a command whose reader may leave early (`exolink status | head -1`,
    `exolink logs -f | head`): the command ends quietly, as a tool ended by SIGPIPE does,
    without a traceback (SIGPIPE itself stays ignored: a socket's EPIPE must not kill us).

    Written from the main thread, BrokenPipeError is raised once and main() ends the command
    with it; written from a callback thread (Zenoh's: logs -f, maccepa watch), the main thread
    is interrupted as Ctrl-C would (every streaming command stops cleanly on it). Either way
    stdout then points at /dev/null, so no later write or the final flush raises again."""

    def __init__(self, inner: TextIO) -> None:
        self.inner = inner
        self._lock = threading.Lock()
        self._finished = False
        self.gone = False

    def write(self, text: str) -> int:
        try:
            return self.inner.write(text)
        except BrokenPipeError:
            self._reader_gone()
        return len(text)

    def flush(self) -> None:
        try:
            self.inner.flush()
        except BrokenPipeError:
            self._reader_gone()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def quiet(self) -> bool:
        """Point stdout at /dev/null (once): nothing written later, nor the interpreter's last
        flush, raises again. True the first time."""
        with self._lock:
            if self.gone:
                return False
            self.gone = True
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self.inner.fileno())
            os.close(devnull)
            return True

    def _reader_gone(self) -> None:
        first = self.quiet()
        if threading.current_thread() is threading.main_thread():
            if first:
                raise BrokenPipeError("stdout's reader is gone")
            return
        with self._lock:
            if first and not self._finished:
                _thread.interrupt_main()

    def finish(self) -> None:
        """The command is over: no interrupt from here on; what is buffered is written."""
        with self._lock:
            self._finished = True
        try:
            self.inner.flush()
        except BrokenPipeError:
            self._reader_gone()
