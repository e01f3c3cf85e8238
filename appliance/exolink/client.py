"""A laptop's client of one appliance: a Zenoh session, the device found, requests answered.

The command line and the dashboard (on a laptop, or as a node on the board) both talk to the
supervisor through it, so it sits below both.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from exolink import messaging
from exolink.refusal import Refused
from exolink.wire import replies

DEFAULT_AT = "tcp/127.0.0.1:7447"
DEFAULT_TIMEOUT_S = 3.0


class Remote:
    """One session to one appliance; the device name is discovered when not given."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.at = args.at
        self.timeout = args.timeout
        self.domain, self.ns = args.domain, args.ns
        # A longer --timeout also waits longer for the session (a board with a saturated CPU
        # answers Zenoh's handshake late); the default keeps Zenoh's own.
        wait = args.timeout if args.timeout > DEFAULT_TIMEOUT_S else None
        self.session = messaging.open_client_session(self.at, args.zenoh_config, handshake_s=wait)
        self.user = messaging.client_login(args.zenoh_config)
        self._device = args.device

    @property
    def device(self) -> str:
        if self._device is None:
            self._device = self._discover()
        return self._device

    def _discover(self) -> str:
        """Devices announce themselves through their nodes' liveliness tokens."""
        deadline = time.monotonic() + self.timeout
        while True:
            replies = self.session.liveliness().get("exolink/*/nodes/*/alive", timeout=0.5)
            devices = {str(r.ok.key_expr).split("/")[1] for r in replies if r.ok is not None}
            if len(devices) == 1:
                return devices.pop()
            if len(devices) > 1:
                raise messaging.Unreachable(
                    f"several appliances answer at {self.at}: {', '.join(sorted(devices))}; "
                    "choose one with --device"
                )
            if time.monotonic() >= deadline:
                raise messaging.Unreachable(
                    f"no appliance answers at {self.at} within {self.timeout:g} s "
                    "(is it running and reachable? set --at tcp/<board-ip>:7447)"
                )
            time.sleep(0.1)

    def call(self, *path: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
        reply = self.ask(*path, body=body)
        if not reply.get("ok"):
            raise Refused(str(reply.get("error", "refused")))
        return reply

    def ask(self, *path: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
        """The reply as it came, refusals included (``ok``, ``error``); Unreachable when
        nothing answers."""
        key = messaging.mgmt_key(self.device, *path)
        try:
            return messaging.request(self.session, key, body or {}, self.timeout, self.user)
        except messaging.RequestTooLarge as exc:
            raise Refused(str(exc)) from None

    def nodes(self) -> list[replies.NodeInfo]:
        """The supervisor's nodes, typed (Refused if it refuses, ValueError if the reply does
        not fit exolink.wire.replies.Nodes). ``exolink status`` reads ``Status`` from the raw
        reply with ``replies.read``: its ``--json`` prints the reply whole."""
        return replies.read(self.call("nodes"), replies.Nodes).nodes

    def selector(self, topic: str) -> str:
        if topic.startswith("/"):
            return f"{self.domain}/{topic.strip('/')}/*/*"
        return messaging.topic_selector(self.domain, self.ns, topic)

    def close(self) -> None:
        self.session.close()


@contextmanager
def remote(args: argparse.Namespace) -> Iterator[Remote]:
    r = Remote(args)
    try:
        yield r
    finally:
        r.close()
