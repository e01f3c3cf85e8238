"""The operator's presence, from the client that holds motion (``exolink hold``, an attached
``exolink pattern start``, the dashboard): a hold taken at the controller manager and renewed
from a thread of its own while the client runs.

The manager stops every motion and trips the watchdog when the renewals stop for
``watchdog.operator_lost_ms`` (a frozen laptop, a Wi-Fi drop, a killed process: Zenoh's own
session lease would take 10 s). A renewal the manager refuses (another client took over) ends
the hold and is told to ``on_end``.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable
from typing import Any

import structlog

from exolink.control import replies, requests
from exolink.refusal import Refused

log = structlog.get_logger("exolink.control.holder")
Call = Callable[[dict[str, Any]], dict[str, Any]]  # a `controllers` request -> its reply


class HoldRefused(Refused):
    """The manager refused the hold (another holds it) or nothing answered."""


def describe(what: str) -> str:
    """What the manager shows of this holder: the command, host and process."""
    return f"{what} on {socket.gethostname()} pid {os.getpid()}"


class Holder:
    """``call`` sends one ``controllers`` request and returns the reply (``ok`` and ``error``
    as the management API gives them); it must not raise for a refusal."""

    def __init__(self, call: Call, what: str, on_end: Callable[[str], None] | None = None):
        self.id = os.urandom(12).hex()
        self._call, self.what = call, what
        self._on_end = on_end
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.renew_s = 0.5
        self.lost_after_s = 2.0
        self.ended = ""  # why the hold ended, when it did (taken over, not renewed)

    def acquire(self, take_over: bool = False) -> replies.Held:
        """Take the hold and start renewing it; HoldRefused names who holds it."""
        raw = self._hold(take_over)
        if not raw.get("ok"):
            raise HoldRefused(str(raw.get("error", "refused")))
        reply = replies.read(raw, replies.Held)
        self.lost_after_s = reply.presence_lost_after_s or self.lost_after_s
        # Four renewals within the manager's limit: one or two lost on a busy link are no loss.
        self.renew_s = max(0.05, min(1.0, self.lost_after_s / 4))
        self._thread = threading.Thread(target=self._renew, daemon=True, name="hold")
        self._thread.start()
        return reply

    def _hold(self, take_over: bool = False) -> dict[str, Any]:
        body = requests.body(requests.Hold(self.id, self.what, take_over))
        return self._call(body)

    def _renew(self) -> None:
        while not self._stop.wait(self.renew_s):
            try:
                reply = self._hold()
            except Exception as exc:  # unreachable now: keep trying; the manager judges
                log.warning("hold_renewal_failed", error=str(exc))
                continue
            if not reply.get("ok"):
                self.ended = str(reply.get("error", "refused"))
                self._stop.set()
                if self._on_end is not None:
                    self._on_end(self.ended)
                return

    @property
    def holding(self) -> bool:
        return self._thread is not None and not self._stop.is_set()

    def abandon(self) -> None:
        """Stop renewing without letting go: as a lost client, so what it holds stops and the
        watchdog trips once the manager's limit passes (the dashboard's last page closed)."""
        self._stop.set()
        self.ended = self.ended or "abandoned"

    def release(self) -> None:
        """Stop renewing and let go (what it held stops, without a trip)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        if not self.ended:
            try:
                self._call(requests.body(requests.Release(self.id)))
            except Exception as exc:  # gone already: the manager's deadline ends it anyway
                log.warning("hold_release_failed", error=str(exc))
