"""The dashboard's web server (aiohttp): one page, one WebSocket per page, a small JSON API.

Laptop (`exolink dashboard`) and board (the `dashboard` node) run this same server around a
Hub; only who owns the Zenoh session differs. The page and its libraries are files in this
package (static/), served as they are: no CDN (the field has no internet), no build step.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import json
import re
import secrets
import socket
import tempfile
import threading
import webbrowser
from collections.abc import Awaitable, Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import structlog
from aiohttp import WSMsgType, web

from exolink import gaitlab
from exolink.dashboard.files import recording_plot as plot_of
from exolink.dashboard.hub import Hub
from exolink.recordings import store as recstore
from exolink.recordings.readback import RecordingError

log = structlog.get_logger("exolink.dashboard")
STATIC = Path(__file__).resolve().parent / "static"
HUB: web.AppKey[Hub] = web.AppKey("hub", Hub)

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


def _index_template() -> str:
    text = (STATIC / "index.html").read_text(encoding="utf-8")
    if text.count(TOKEN_META) != 1:
        raise RuntimeError(f"{STATIC / 'index.html'} must hold {TOKEN_META} once")
    return text


async def index(request: web.Request) -> web.StreamResponse:
    """The page, with a token of its own (not cached: each load gets a fresh one)."""
    token = request.app[TOKENS].issue()
    text = request.app[INDEX].replace(TOKEN_META, TOKEN_META.replace('""', f'"{token}"'))
    return web.Response(
        text=text,
        content_type="text/html",
        headers={"Cache-Control": "no-store", "X-Content-Type-Options": "nosniff"},
    )


async def websocket(request: web.Request) -> web.StreamResponse:
    hub = request.app[HUB]
    ws = web.WebSocketResponse(heartbeat=5.0, max_msg_size=1 << 16)
    await ws.prepare(request)
    await ws.send_str(json.dumps(hub.hello()))
    hub.attach(ws)
    try:
        async for msg in ws:
            if msg.type == WSMsgType.ERROR:
                break
            if msg.type == WSMsgType.TEXT:
                _from_page(hub, ws, msg.data)
    finally:
        hub.detach(ws)
    return ws


def _from_page(hub: Hub, ws: web.WebSocketResponse, text: str) -> None:
    """What a page asks over its socket: only which node's log it follows."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError:
        return
    if isinstance(data, dict) and data.get("t") == "follow":
        node = data.get("node")
        hub.follow(ws, node if isinstance(node, str) else None)


async def _body(request: web.Request) -> dict[str, Any]:
    try:
        data = await request.json()
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise web.HTTPBadRequest(text="request is not valid JSON") from None
    if not isinstance(data, dict):
        raise web.HTTPBadRequest(text="request must be a JSON object")
    return data


async def command(request: web.Request) -> web.StreamResponse:
    data = await _body(request)
    argv = data.get("argv")
    if not isinstance(argv, list):
        return web.json_response({"ok": False, "error": "argv must be a list of words"})
    reply = await request.app[HUB].command([str(a) for a in argv], bool(data.get("confirmed")))
    return web.json_response(reply)


async def estop(request: web.Request) -> web.StreamResponse:
    return web.json_response(await request.app[HUB].command(["estop"]))


async def logs(request: web.Request) -> web.StreamResponse:
    node = request.query.get("node", "")
    text = request.query.get("lines", "100")
    if not re.fullmatch(r"[0-9]{1,6}", text):  # ASCII: int() takes full-width digits too
        return web.json_response({"ok": False, "error": f"lines {text[:20]!r}: not a number"})
    lines = int(text)
    return web.json_response(
        await request.app[HUB].query(("logs",), {"node": node, "lines": lines})
    )


async def params(request: web.Request) -> web.StreamResponse:
    node = request.query.get("node", "")
    if not node or "/" in node:
        return web.json_response({"ok": False, "error": "no node named"})
    return web.json_response(await request.app[HUB].query(("nodes", node, "params"), {}))


async def pattern_points(request: web.Request) -> web.StreamResponse:
    points = request.app[HUB].pattern_points(request.query.get("file", ""))
    return web.json_response({"ok": points is not None, "points": points})


async def _recording(request: web.Request) -> Path:
    """A recording the recorder lists, as a file here: the recorder decides (this dashboard's
    role, the file closed) and a laptop fetches it from the board (Hub.recording); a name the
    recorder did not list is never opened."""
    hub = request.app[HUB]
    name = request.query.get("file", "")
    files = (hub.record or {}).get("files") or []
    if name not in files:
        raise web.HTTPNotFound(text=f"{name!r} is not one of the recorder's files")
    try:
        return await asyncio.to_thread(hub.recording, name)
    except (recstore.Refused, recstore.StoreError) as exc:
        raise web.HTTPForbidden(text=f"{Path(name).name}: {exc}") from None
    except OSError as exc:
        raise web.HTTPInternalServerError(
            text=f"{Path(name).name}: {exc.strerror or exc}"
        ) from None


async def download(request: web.Request) -> web.StreamResponse:
    path = await _recording(request)
    return web.FileResponse(
        path, headers={"Content-Disposition": f'attachment; filename="{path.name}"'}
    )


def _c3d(path: Path, out_dir: str) -> Path:
    trial = gaitlab.build_trial(path)
    return gaitlab.write_c3d(trial, Path(out_dir) / (path.name.removesuffix(".mcap") + ".c3d"))


async def recording_c3d(request: web.Request) -> web.StreamResponse:
    """The recording as C3D for the gait lab (exolink.gaitlab, as `exolink export --c3d`), where
    the dashboard runs with the gaitlab extra (a laptop): on the board, 501 naming the extra."""

    path = await _recording(request)
    try:
        gaitlab.require_ezc3d()
    except gaitlab.MissingExtra as exc:
        raise web.HTTPNotImplemented(text=str(exc)) from None
    with tempfile.TemporaryDirectory(prefix="exolink-c3d-") as d:
        try:
            out = await asyncio.to_thread(_c3d, path, d)
        except RecordingError as exc:
            raise web.HTTPUnprocessableEntity(text=str(exc)) from None
        body = out.read_bytes()
    return web.Response(
        body=body,
        content_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{out.name}"'},
    )


async def recording_plot(request: web.Request) -> web.StreamResponse:
    try:
        path = await _recording(request)
    except web.HTTPException as exc:
        return web.json_response({"ok": False, "error": exc.text})
    try:
        data = await asyncio.to_thread(plot_of, str(path))
    except RecordingError as exc:
        return web.json_response({"ok": False, "error": str(exc)})
    except Exception as exc:  # a file still being written (no summary yet), or damaged
        return web.json_response(
            {"ok": False, "error": f"{path.name} cannot be read ({type(exc).__name__}: {exc})"}
        )
    return web.json_response({"ok": True, **data})


INDEX: web.AppKey[str] = web.AppKey("index", str)


def make_app(hub: Hub, hosts: Hosts) -> web.Application:
    app = web.Application(middlewares=[same_origin])
    app[HUB] = hub
    app[HOSTS] = hosts
    app[TOKENS] = PageTokens()
    app[INDEX] = _index_template()
    app.router.add_get("/", index)
    app.router.add_get("/ws", websocket)
    app.router.add_post("/api/command", command)
    app.router.add_post("/api/estop", estop)
    app.router.add_get("/api/logs", logs)
    app.router.add_get("/api/params", params)
    app.router.add_get("/api/pattern/points", pattern_points)
    app.router.add_get("/api/recordings/download", download)
    app.router.add_get("/api/recordings/plot", recording_plot)
    app.router.add_get("/api/recordings/c3d", recording_c3d)
    app.router.add_static("/static/", STATIC, append_version=False)

    async def on_startup(_app: web.Application) -> None:
        await hub.start()

    async def on_cleanup(_app: web.Application) -> None:
        for ws in list(hub.clients):
            await ws.close()
        await hub.stop()

    app.on_startup.append(on_startup)
    app.on_cleanup.append(on_cleanup)
    return app


async def serve(
    hub: Hub,
    host: str,
    port: int,
    stop: asyncio.Event | threading.Event,
    on_ready: Callable[[str], None] | None = None,
    hosts: Hosts | None = None,
) -> None:
    """Serve until ``stop`` is set (an asyncio.Event, or a threading.Event from a node).
    ``hosts``: the names it answers to (default: loopback on ``port`` only)."""
    hosts = hosts if hosts is not None else Hosts(port)
    runner = web.AppRunner(make_app(hub, hosts), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{port}/"
    log.info("dashboard_serving", url=url, device=hub.remote.device, role=hub.role)
    if on_ready is not None:
        on_ready(url)
    try:
        if isinstance(stop, asyncio.Event):
            await stop.wait()
        else:
            while not stop.is_set():
                await asyncio.sleep(0.1)
    finally:
        await runner.cleanup()


def open_browser(url: str) -> None:
    """The laptop's browser, in a thread: webbrowser may block while a browser starts."""
    threading.Thread(target=webbrowser.open, args=(url,), daemon=True).start()
