"""The dashboard's web server (aiohttp): one page, one WebSocket per page, a small JSON API.

Laptop (`exolink dashboard`) and board (the `dashboard` node) run this same server around a
Hub; only who owns the Zenoh session differs. The page and its libraries are files in this
package (static/), served as they are: no CDN (the field has no internet), no build step.
"""

from __future__ import annotations

import asyncio
import json
import re
import tempfile
import threading
import webbrowser
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog
from aiohttp import WSMsgType, web

from exolink import gaitlab
from exolink.dashboard.files import recording_plot as plot_of
from exolink.dashboard.guard import (
    HOSTS,
    TOKEN_META,
    TOKENS,
    Hosts,
    PageTokens,
    same_origin,
)
from exolink.dashboard.hub import Hub
from exolink.recordings.readback import RecordingError
from exolink.recordings.store import StoreError
from exolink.refusal import Refused

log = structlog.get_logger("exolink.dashboard")
STATIC = Path(__file__).resolve().parent / "static"
HUB: web.AppKey[Hub] = web.AppKey("hub", Hub)


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
    except (Refused, StoreError) as exc:
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
