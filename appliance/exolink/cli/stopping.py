"""How a command that holds motion hears "stop": Ctrl-C, ``kill`` and a closed terminal alike.

A holder (``exolink pattern start``, ``exolink hold``) ends by stopping what it holds and
letting go. Waiting for its silence instead leaves the gait running for the manager's
``operator_lost_ms`` and then trips the watchdog. Python turns only SIGINT into
KeyboardInterrupt, and not even that when the process inherits SIGINT ignored (anything
started in the background of a non-interactive shell, as the board bench's laptop ran its
holder: its Ctrl-C was ignored for 30 s, then it was killed and the watchdog tripped).
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

# SIGHUP: the terminal closed (an ssh session to the laptop dropped, say)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within: each of ``STOP_SIGNALS`` raises KeyboardInterrupt in the main thread once; a
    signal that comes while the stop is being sent is not another interrupt (the stop would
    be cut short). The previous handlers are back afterwards."""
    raised = False

    def interrupt(signum: int, _frame: FrameType | None) -> None:
        nonlocal raised
        if not raised:
            raised = True
            raise KeyboardInterrupt(signal.Signals(signum).name)

    before = {s: signal.signal(s, interrupt) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
