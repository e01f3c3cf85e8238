"""The command line's stdout for a reader that may leave early; the exit codes and the guarded
run are exolink.errors', shared with the node runtime."""

from __future__ import annotations

import _thread
import os
import signal
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


READER_GONE = signal.SIGUSR2  # never sent: raised in the main thread by interrupt_main


def _reader_gone_interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt("stdout's reader is gone")


class Stdout:
    """sys.stdout for a command whose reader may leave early (`exolink status | head -1`,
    `exolink logs -f | head`): the command ends quietly, as a tool ended by SIGPIPE does,
    without a traceback (SIGPIPE itself stays ignored: a socket's EPIPE must not kill us).

    Written from the main thread, BrokenPipeError is raised once and main() ends the command
    with it; written from a callback thread (Zenoh's: logs -f, maccepa watch), the main thread
    is interrupted as Ctrl-C would (every streaming command stops cleanly on it). Either way
    stdout then points at /dev/null, so no later write or the final flush raises again.

    The interrupt is a signal of its own (``READER_GONE``, handled from ``install``), not
    SIGINT: a command started in the background of a non-interactive shell inherits SIGINT
    ignored, and Python then drops a simulated SIGINT, so `exolink echo ... | head -1` in a
    script ran on forever (the test suite, started that way, waited 10 and 30 s for two)."""

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

    def install(self) -> None:
        """From the main thread, before any callback thread writes: the interrupt's handler."""
        signal.signal(READER_GONE, _reader_gone_interrupt)

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
                _thread.interrupt_main(READER_GONE)

    def finish(self) -> None:
        """The command is over: no interrupt from here on; what is buffered is written."""
        with self._lock:
            self._finished = True
        try:
            self.inner.flush()
        except BrokenPipeError:
            self._reader_gone()
