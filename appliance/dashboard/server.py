"""The dashboard's web server (aiohttp): one page, one WebSocket per page, a small JSON API.

Laptop (`exolink dashboard`) and board (the `dashboard` node) run this same server around a
Hub; only who owns the Zenoh session differs. The page and its libraries are files in this
package (static/), served as they are: no CDN (the field has no internet), no build step.
"""

from __future__ import annotations

import asyncio
import json
import threading
import webbrowser
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import structlog
from aiohttp import WSMsgType, web
from exolink.dashboard import hub as hub_module
from exolink.dashboard.hub import Hub

log = structlog.get_logger("exolink.dashboard")
STATIC = Path(__file__).resolve().parent / "static"
HUB: web.AppKey[Hub] = web.AppKey("hub", Hub)

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def _foreign(request: web.Request) -> bool:
    origin = request.headers.get("Origin")
    return origin is not None and origin.split("://", 1)[-1] != request.host


@web.middleware
async def same_origin(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Commands and the live socket only for the dashboard's own page: a JSON body and no
    foreign Origin, so another web site open in the same browser can neither post a command
    (an e-stop, a motion) nor read the live data (WebSockets are not bound by CORS)."""
    if (request.method == "POST" or request.path == "/ws") and _foreign(request):
        return web.json_response({"ok": False, "error": "cross-origin request"}, status=403)
    if request.method == "POST" and request.content_type != "application/json":
        return web.json_response({"ok": False, "error": "JSON body expected"}, status=415)
    return await handler(request)


async def index(_request: web.Request) -> web.StreamResponse:
    return web.FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})


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
    lines = int(request.query.get("lines", "100") or 100)
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


def _recording(request: web.Request) -> Path:
    """A recording the recorder lists, when its file is on this machine (the board node, or
    a laptop running the sim); a name the recorder did not list is never opened."""
    hub = request.app[HUB]
    name = request.query.get("file", "")
    files = (hub.record or {}).get("files") or []
    if name not in files:
        raise web.HTTPNotFound(text=f"{name!r} is not one of the recorder's files")
    path = Path(name)
    if not path.is_file():
        raise web.HTTPNotFound(
            text=f"{name} is on the board, not here: copy it with "
            f"scp exo@<board>:{name} . (the board's own dashboard serves it)"
        )
    return path


async def download(request: web.Request) -> web.StreamResponse:
    path = _recording(request)
    return web.FileResponse(
        path, headers={"Content-Disposition": f'attachment; filename="{path.name}"'}
    )


async def recording_plot(request: web.Request) -> web.StreamResponse:
    from exolink.recording import RecordingError

    path = _recording(request)
    try:
        data = await asyncio.to_thread(hub_module.recording_plot, str(path))
    except RecordingError as exc:
        return web.json_response({"ok": False, "error": str(exc)})
    except Exception as exc:  # a file still being written (no summary yet), or damaged
        return web.json_response(
            {"ok": False, "error": f"{path.name} cannot be read ({type(exc).__name__}: {exc})"}
        )
    return web.json_response({"ok": True, **data})


def make_app(hub: Hub) -> web.Application:
    app = web.Application(middlewares=[same_origin])
    app[HUB] = hub
    app.router.add_get("/", index)
    app.router.add_get("/ws", websocket)
    app.router.add_post("/api/command", command)
    app.router.add_post("/api/estop", estop)
    app.router.add_get("/api/logs", logs)
    app.router.add_get("/api/params", params)
    app.router.add_get("/api/pattern/points", pattern_points)
    app.router.add_get("/api/recordings/download", download)
    app.router.add_get("/api/recordings/plot", recording_plot)
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
) -> None:
    """Serve until ``stop`` is set (an asyncio.Event, or a threading.Event from a node)."""
    runner = web.AppRunner(make_app(hub), access_log=None)
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
