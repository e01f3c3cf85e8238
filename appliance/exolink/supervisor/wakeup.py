"""A wait that another thread ends, on a file descriptor.

``threading.Event``'s timed wait builds a lock and a condition per call and takes several
more; the supervisor's loop waits many times a second (the controller manager's 50 ms
heartbeat deadline), each wait a fraction of a millisecond of a slow core (docs/performance.md).
A pipe costs one ``select``, and its descriptor can join a wait on other descriptors (the
watchdog's listener waits on its CAN sockets and the broadcast manager's watches with it).
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
from collections.abc import Sequence


class Wakeup:
    """``set`` from any thread ends the current or the next ``wait``. The pipe opens on first
    use: the supervisor makes its own before it forks the zygote, which must inherit nothing."""

    def __init__(self) -> None:
        self._fds: tuple[int, int] | None = None
        self._lock = threading.Lock()

    def _pipe(self) -> tuple[int, int]:
        fds = self._fds
        if fds is None:
            with self._lock:
                if self._fds is None:
                    self._fds = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
                fds = self._fds
        return fds

    def fileno(self) -> int:
        return self._pipe()[0]

    def set(self) -> None:
        with contextlib.suppress(OSError):  # full (a wake is pending anyway) or closed
            os.write(self._pipe()[1], b"!")

    def wait(self, timeout: float) -> bool:
        """Until ``set`` or ``timeout`` (s); True when set, and then no longer set."""
        return self.wait_any(timeout)[0]

    def wait_any(self, timeout: float, fds: Sequence[int] = ()) -> tuple[bool, list[int]]:
        """Until ``set``, one of ``fds`` is readable, or ``timeout``: (set, the readable
        ``fds``). One closed meanwhile by another thread ends the wait with none readable."""
        r = self._pipe()[0]
        try:
            ready = select.select([r, *fds], (), (), max(0.0, timeout))[0]
        except (OSError, ValueError):  # closed meanwhile: the caller looks again
            return False, []
        woke = r in ready
        if woke:
            self.clear()
        return woke, [fd for fd in ready if fd != r]

    def clear(self) -> None:
        """Forget a ``set`` not waited for (a wait on the descriptor among others found it)."""
        with contextlib.suppress(OSError):
            os.read(self._pipe()[0], 4096)

    def close(self) -> None:
        with self._lock:
            fds, self._fds = self._fds, (-1, -1)
        for fd in fds or ():
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
