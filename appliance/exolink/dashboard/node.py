"""The `dashboard` node: the same web app served by the board itself, for a tablet in the field.

Off by default (board.yaml: ``enabled: false``): it costs the board CPU (see `make bench`'s
dashboard figures) and serves HTTP without a login. So its commands go out as the role in its
params, ``observer`` unless a lab sets more: a tablet on the board's network can then watch and
e-stop, nothing else. Its Zenoh session is the node's own (the appliance's login); the role is
applied by the same management handlers that check a laptop's login.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Annotated, Literal

import msgspec

from exolink import roles
from exolink.client import Remote
from exolink.dashboard import guard, server
from exolink.dashboard.hub import Hub
from exolink.loops import Every
from exolink.node import Node


class DashboardParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    host: str = "0.0.0.0"
    port: Annotated[int, msgspec.Meta(ge=1, le=65535)] = 8080
    # Frames per second to each page: the board's CPU follows this, not the 100 Hz data.
    rate_hz: Annotated[float, msgspec.Meta(gt=0, le=60)] = 10.0
    role: Literal["observer", "operator", "admin"] = "observer"
    # The Host names it answers to besides loopback (a web page elsewhere must not reach it
    # under a name of its own): <device> and <hostname> are replaced, <address> is the board's
    # address a request came in on (any interface's, as the tablet reached it).
    allow_hosts: list[str] = msgspec.field(
        default_factory=lambda: [
            guard.DEVICE,
            f"{guard.DEVICE}.local",
            guard.HOSTNAME,
            f"{guard.HOSTNAME}.local",
            guard.ADDRESS,
        ]
    )


class _NodeRemote(Remote):
    """Remote's interface on the node's own session (which the runtime owns and closes)."""

    def __init__(self, node: Node, role: str) -> None:
        cfg = node.ctx.config
        self.at = f"board {cfg.device}"
        self.timeout = 2.0
        self.domain, self.ns = cfg.zenoh.domain_id, cfg.zenoh.namespace
        self.session = node.ctx.session
        self.user = role
        self._device = cfg.device

    def close(self) -> None:
        pass


class DashboardNode(Node):
    Params = DashboardParams

    def configure(self) -> None:
        p = self.params
        assert p.role in roles.ROLES
        self.hosts = guard.Hosts(
            p.port,
            p.allow_hosts,
            how_to_allow="add it to the dashboard node's allow_hosts param (the board's config)",
            placeholders={guard.DEVICE: self.ctx.config.device},
        )
        self.hub = Hub(_NodeRemote(self, p.role), rate_hz=p.rate_hz)
        self._failed: BaseException | None = None

    def _serve(self, stop: threading.Event) -> None:
        try:
            p = self.params
            asyncio.run(server.serve(self.hub, p.host, p.port, stop, hosts=self.hosts))
        except Exception as exc:  # e.g. the port is taken: run() fails, the node is restarted
            self._failed = exc

    def run(self, stop: threading.Event) -> None:
        t = threading.Thread(target=self._serve, args=(stop,), name="dashboard", daemon=True)
        t.start()

        def serving() -> None:
            if not t.is_alive():
                raise RuntimeError(f"dashboard server stopped: {self._failed}")

        Every(0.1, serving).run(self.beat, stop)
        t.join(5)
