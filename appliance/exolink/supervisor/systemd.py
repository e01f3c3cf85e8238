"""sd_notify: READY=1 and WATCHDOG=1 to systemd over its datagram socket.

Ten lines of the documented protocol (sd_notify(3)); the maintained binding, python-systemd,
needs libsystemd headers to build, which a plain pip install on a laptop does not have.
"""

from __future__ import annotations

import os
import socket


class Notifier:
    def __init__(self) -> None:
        addr = os.environ.get("NOTIFY_SOCKET", "")
        self.addr = "\0" + addr[1:] if addr.startswith("@") else addr
        usec = os.environ.get("WATCHDOG_USEC", "")
        # Ping at half the period systemd expects, as sd_watchdog_enabled(3) advises.
        self.ping_interval_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 else None

    @property
    def enabled(self) -> bool:
        return bool(self.addr)

    def notify(self, state: str) -> None:
        if not self.addr:
            return
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.sendto(state.encode(), self.addr)

    def ready(self) -> None:
        self.notify("READY=1")

    def ping(self) -> None:
        self.notify("WATCHDOG=1")

    def stopping(self) -> None:
        self.notify("STOPPING=1")
