"""The command line's stdout for a reader that may leave early; the exit codes and the guarded
run are exolink.errors', shared with the node runtime."""

from __future__ import annotations

import _thread
import os
import threading
from typing import Any, TextIO

from exolink.errors import (
    EXIT_CONFIG,
    EXIT_HARDWARE,
    EXIT_REFUSED,
    EXIT_UNREACHABLE,
    EXIT_USAGE,
    fail,
    run_guarded,
)

__all__ = [
    "EXIT_CONFIG",
    "EXIT_HARDWARE",
    "EXIT_REFUSED",
    "EXIT_UNREACHABLE",
    "EXIT_USAGE",
    "Stdout",
    "fail",
    "run_guarded",
]


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
