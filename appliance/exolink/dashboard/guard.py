"""Who may drive the dashboard: only its own page, under a name of ours. Every request names a
known Host (``Hosts``: DNS rebinding); commands and the live socket also carry no foreign
Origin and the page's token (``PageTokens``), so another web site open in the same browser can
neither post a command (an e-stop, a motion) nor read the live data. The server
(exolink.dashboard.server) puts ``same_origin`` in front of every route."""

from __future__ import annotations

import contextlib
import hmac
import ipaddress
import re
import secrets
import socket
from collections.abc import Awaitable, Callable, Iterable, Mapping

import structlog
from aiohttp import web

log = structlog.get_logger("exolink.dashboard")
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

TOKEN_HEADER = "X-Exolink-Token"
TOKEN_META = '<meta name="exolink-token" content="">'
LOOPBACK = ("127.0.0.1", "localhost", "[::1]")
# In an allowed host name: the machine's host name, the board's device name, and "the address
# this request came in on" (any of the machine's interface addresses, as the client reached it).
HOSTNAME, DEVICE, ADDRESS = "<hostname>", "<device>", "<address>"
_HOST = re.compile(
    r"(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<name>[A-Za-z0-9._-]+))(?::(?P<port>[0-9]{1,5}))?"
)


def _parse_host(text: str) -> tuple[str, int | None] | None:
    """A Host header (or an allowed name) as (lower-case name or canonical address, port);
    None for anything else (two names, user info, a bare IPv6 address without brackets)."""
    m = _HOST.fullmatch(text)
    if m is None:
        return None
    port = int(m["port"]) if m["port"] is not None else None
    if m["v6"] is not None:
        try:
            return ipaddress.IPv6Address(m["v6"]).compressed, port
        except ValueError:
            return None
    name = m["name"].lower()
    with contextlib.suppress(ValueError):  # 127.0.0.1 as the address it is
        name = ipaddress.IPv4Address(name).compressed
    return name, port


class Hosts:
    """The Host names this server answers to: loopback on its own port, plus those given.

    A web page elsewhere can point a name of its own at this machine (DNS rebinding): the
    browser then sends that name as Host, and treats the dashboard as the page's own origin
    (reads its data, posts commands). Answering only to known names stops that; the Origin
    check cannot, since the page controls Origin and Host alike.
    """

    def __init__(
        self,
        port: int,
        names: Iterable[str] = (),
        how_to_allow: str = "start it with `exolink dashboard --allow-host NAME`",
        placeholders: Mapping[str, str] | None = None,
    ) -> None:
        self.port = port
        self.how_to_allow = how_to_allow
        self.by_address = False
        self.allowed: set[tuple[str, int]] = set()
        known = {HOSTNAME: socket.gethostname(), **(placeholders or {})}
        for entry in (*LOOPBACK, *names):
            if entry.strip() == ADDRESS:
                self.by_address = True
                continue
            text = entry.strip()
            for key, value in known.items():
                text = text.replace(key, value)
            with contextlib.suppress(ValueError):  # an IPv6 address as a Host header has it
                text = f"[{ipaddress.IPv6Address(text)}]"
            parsed = _parse_host(text)
            if parsed is None:
                allowed = ", ".join([*known, ADDRESS])
                raise ValueError(
                    f"allowed host {entry!r} is not a host name, address or name:port "
                    f"(placeholders: {allowed})"
                )
            name, entry_port = parsed
            self.allowed.add((name, port if entry_port is None else entry_port))

    def allows(self, header: str, local_address: str | None) -> bool:
        """Whether a request with this Host header, arriving on this local address, is ours."""
        parsed = _parse_host(header)
        if parsed is None:
            return False
        name, port = parsed[0], 80 if parsed[1] is None else parsed[1]
        if (name, port) in self.allowed:
            return True
        return self.by_address and port == self.port and name == _address(local_address)


def _address(text: str | None) -> str | None:
    """A socket's local address as a Host header names it (an IPv4-mapped one as IPv4)."""
    if not text:
        return None
    try:
        a = ipaddress.ip_address(text.split("%", 1)[0])
    except ValueError:
        return None
    if isinstance(a, ipaddress.IPv6Address) and a.ipv4_mapped is not None:
        a = a.ipv4_mapped
    return a.compressed


class PageTokens:
    """A fresh random token for each page load, checked without keeping a table of them: a
    nonce and its HMAC under a key that lives as long as this server. Only a page this server
    served can know one: another origin cannot read the page (same-origin policy), and cannot
    be served it under a name of its own (Hosts)."""

    def __init__(self) -> None:
        self._key = secrets.token_bytes(32)

    def issue(self) -> str:
        nonce = secrets.token_urlsafe(18)
        return f"{nonce}.{self._mac(nonce)}"

    def valid(self, token: str | None) -> bool:
        if not token or len(token) > 200 or not token.isascii():
            return False
        nonce, _, mac = token.partition(".")
        return bool(nonce) and hmac.compare_digest(mac.encode(), self._mac(nonce).encode())

    def _mac(self, nonce: str) -> str:
        return hmac.new(self._key, nonce.encode(), "sha256").hexdigest()


HOSTS: web.AppKey[Hosts] = web.AppKey("hosts", Hosts)
TOKENS: web.AppKey[PageTokens] = web.AppKey("tokens", PageTokens)


def _refused_host(request: web.Request, hosts: Hosts) -> web.Response | None:
    """A 403 naming the Host and how to allow it, or None: the Host is one of ours."""
    headers = request.headers.getall("Host", [])
    sockname = request.transport.get_extra_info("sockname") if request.transport else None
    if len(headers) == 1 and hosts.allows(headers[0], sockname[0] if sockname else None):
        return None
    if len(headers) != 1:
        what, name = f"{len(headers)} Host headers", "NAME"
    else:
        what, parsed = repr(headers[0][:100]), _parse_host(headers[0])
        name = "NAME" if parsed is None else _as_entry(parsed, hosts.port)
    log.warning("dashboard_host_refused", host=what, path=request.path)
    text = (
        f"exolink dashboard: refused host {what}: this dashboard answers only to its own "
        f"names (loopback on port {hosts.port} and those allowed), so that a web page "
        f"elsewhere cannot reach it under a name of its own. If {name} is this machine's, "
        f"{hosts.how_to_allow.replace('NAME', name)}.\n"
    )
    return web.Response(status=403, text=text, headers={"X-Content-Type-Options": "nosniff"})


def _as_entry(parsed: tuple[str, int | None], own_port: int) -> str:
    """An allowed-host entry for a parsed Host: the port only when it is not ours."""
    name, port = parsed
    if ":" in name:
        name = f"[{name}]"
    return name if (80 if port is None else port) == own_port else f"{name}:{port or 80}"


def _foreign(request: web.Request) -> bool:
    origin = request.headers.get("Origin")
    return origin is not None and origin.split("://", 1)[-1] != request.host


def _page_token(request: web.Request) -> str | None:
    """A page proves it was served here: a header on a POST, a query parameter on the socket
    (a browser's WebSocket cannot set headers)."""
    if request.path == "/ws":
        return request.query.get("token")
    return request.headers.get(TOKEN_HEADER)


@web.middleware
async def same_origin(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Only the dashboard's own page, under a name of ours, may talk to it: every request
    names a known Host; commands and the live socket also carry no foreign Origin, the
    page's token and (commands) a JSON body, so another web site open in the same browser can
    neither post a command (an e-stop, a motion) nor read the live data (WebSockets are not
    bound by CORS)."""
    refused = _refused_host(request, request.app[HOSTS])
    if refused is not None:
        return refused
    if request.method == "POST" or request.path == "/ws":
        if _foreign(request):
            return web.json_response({"ok": False, "error": "cross-origin request"}, status=403)
        if not request.app[TOKENS].valid(_page_token(request)):
            return web.json_response(
                {
                    "ok": False,
                    "error": "no valid page token: load the dashboard's page again",
                    "stale_token": True,
                },
                status=403,
            )
    if request.method == "POST" and request.content_type != "application/json":
        return web.json_response({"ok": False, "error": "JSON body expected"}, status=415)
    return await handler(request)
