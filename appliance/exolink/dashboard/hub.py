"""What the dashboard knows of one appliance, and the one way it sends commands.

Data arrives at 100 Hz on Zenoh; the page needs a few tens of frames a second. The data topics'
subscribers keep only their newest samples in Zenoh's own ring buffer (Rust: no Python runs per
sample); a tick at the display rate takes the newest of each topic, decodes it and sends one JSON
frame to every page (exolink.dashboard.live). So the server's cost follows the display rate, not
the data rate (what matters on the board), and a slow page never queues 100 Hz of data. Rates
come from the publishers' sequence numbers (the rmw_zenoh attachment), not from counting samples.

Events a person must not miss (watchdog state, trigger edges, pattern state) go out at once.
The supervisor's status (nodes, bus, watchdog details) is polled once a second.

Commands go out on the laptop client's session and login (exolink.client.Remote), parsed by
the CLI's own parser (exolink.dashboard.commands): a refusal is the appliance's own text, and a
command the parser refuses is never sent.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog

from exolink import messaging, roles
from exolink.board import clock
from exolink.client import Refused, Remote
from exolink.control.arming import WATCHDOG_TOPIC, WATCHDOG_TYPE
from exolink.control.holder import Holder, HoldRefused, describe
from exolink.dashboard.commands import Command, CommandError, parse
from exolink.dashboard.files import Files, pattern_points
from exolink.dashboard.live import LiveData
from exolink.protocol import h2
from exolink.recordings import requests as reqs
from exolink.wire import cdr
from exolink.wire.replies import ClockStatus, read
from exolink.wire.requests import body as request_body

log = structlog.get_logger("exolink.dashboard")

TRIGGER = "exolink_msgs/msg/TriggerEvent"
PATTERN_STATE = "exolink_msgs/msg/PatternState"


class Hub:
    """One appliance connection shared by every page: subscriptions, decimation, commands."""

    def __init__(self, remote: Remote, rate_hz: float = 25.0, status_period_s: float = 1.0):
        self.remote = remote
        self.rate_hz = rate_hz
        self.status_period_s = status_period_s
        self.role = remote.user if remote.user in roles.ROLES else roles.ADMIN
        self.clients: set[Any] = set()
        self.live = LiveData(remote)  # the 100 Hz topics, while a page is open
        self._follows: dict[str, tuple[Any, set[Any]]] = {}  # node -> (log subscriber, pages)
        self._subs: list[Any] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self.status: dict[str, Any] | None = None
        self.status_error: str | None = None
        self.record: dict[str, Any] | None = None
        self.files = Files(remote)  # recordings and patterns as files for the pages
        self.pattern: dict[str, Any] | None = None
        self.watchdog: dict[str, Any] | None = None
        self.trigger: dict[str, Any] | None = None
        # Motion held from this dashboard: taken when a page first asks for motion and nobody
        # holds it, renewed while a page is open (exolink.control.holder).
        self.holder: Holder | None = None
        self._watched = asyncio.Event()  # a page is open: subscribe, decode and poll

    # --- lifecycle ------------------------------------------------------------------------

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        await asyncio.to_thread(self._subscribe)
        self._tasks = [
            asyncio.create_task(self._tick(), name="dashboard-tick"),
            asyncio.create_task(self._poll_status(), name="dashboard-status"),
            asyncio.create_task(self._poll_record(), name="dashboard-record"),
        ]

    async def stop(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        await asyncio.to_thread(self._unsubscribe)

    def _subscribe(self) -> None:
        r = self.remote
        device = r.device  # discovered here, in a thread: it waits for the appliance
        s = r.session

        def key(topic: str, typename: str) -> str:
            return messaging.topic_key(r.domain, r.ns, topic, typename)

        self._subs.append(
            s.declare_subscriber(key(WATCHDOG_TOPIC, WATCHDOG_TYPE), self._on_watchdog)
        )
        self._subs.append(s.declare_subscriber(key("trigger", TRIGGER), self._on_trigger))
        self._subs.append(
            s.declare_subscriber(key("pattern_state", PATTERN_STATE), self._on_pattern)
        )
        log.info("dashboard_connected", device=device, at=r.at, role=self.role)

    def _unsubscribe(self) -> None:
        self.live.close()
        for sub in self._subs:
            with contextlib.suppress(Exception):  # the session may already be closed
                sub.undeclare()
        for sub, _pages in self._follows.values():
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._follows.clear()
        self._subs.clear()
        self._release_hold()

    # --- Zenoh callbacks (Zenoh's threads: keep them short) -------------------------------

    def _emit(self, message: dict[str, Any]) -> None:
        """From a Zenoh thread: send an event to every page now."""
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._broadcast, message)

    def _on_watchdog(self, sample: Any) -> None:
        try:
            state, reason, detail, frames = cdr.watchdog_event(sample.payload.to_bytes())
        except ValueError:
            return
        self.watchdog = {"state": state, "reason": reason, "detail": detail, "frames": frames}
        self._emit({"t": "watchdog", **self.watchdog})

    def _on_trigger(self, sample: Any) -> None:
        try:
            msg = messaging.deserialize(sample.payload.to_bytes(), TRIGGER)
        except Exception:
            return
        self.trigger = {
            "stamp_ns": messaging.stamp_ns(msg.stamp),
            "count": int(msg.count),
            "edge": msg.edge,
        }
        self._emit({"t": "trigger", **self.trigger})

    def _on_pattern(self, sample: Any) -> None:
        try:
            msg = messaging.deserialize(sample.payload.to_bytes(), PATTERN_STATE)
        except Exception:
            return
        self.pattern = {
            "state": msg.state,
            "reason": msg.reason,
            "index": int(msg.index),
            "length": int(msg.length),
            "speed": int(msg.speed),
            "period_ms": round(float(msg.period_ms), 3),
            "selected": [j for j, s in zip(h2.JOINTS, msg.selected, strict=True) if s],
            "file": msg.file,
            "operator": msg.operator,
            "timing": msg.timing_mode,
        }
        self._emit({"t": "pattern", **self.pattern})

    # --- pages ----------------------------------------------------------------------------

    def hello(self) -> dict[str, Any]:
        """What a page gets first: who we are, what we may do, what is known so far."""
        return {
            "t": "hello",
            "device": self.remote.device,
            "at": self.remote.at,
            "role": self.role,
            "joints": list(h2.JOINTS),
            "ranges": {j: list(h2.RANGES[j]) for j in h2.JOINTS},
            "rate_hz": self.rate_hz,
            "status": self.status,
            "status_error": self.status_error,
            "watchdog": self.watchdog,
            "trigger": self.trigger,
            "pattern": self.pattern,
            "record": self.record,
        }

    def attach(self, ws: Any) -> None:
        self.clients.add(ws)
        self._watched.set()

    def detach(self, ws: Any) -> None:
        self.clients.discard(ws)
        self.follow(ws, None)
        if not self.clients:
            # Nobody is watching: what this dashboard started must not go on without its
            # operator: the manager stops it and trips once the renewals have stopped.
            if self.holder is not None:
                self.holder.abandon()
            self._watched.clear()

    def follow(self, ws: Any, node: str | None) -> None:
        """Send ``node``'s log lines to this page as they come (None: stop). One subscriber
        per followed node, shared by the pages following it; the board's access control gives
        the log keys to admin logins only (`exolink logs -f` does the same)."""
        for name, (sub, pages) in list(self._follows.items()):
            if ws in pages and name != node:
                pages.discard(ws)
                if not pages:
                    with contextlib.suppress(Exception):
                        sub.undeclare()
                    del self._follows[name]
        if node is None or not node.isidentifier():
            return
        if node not in self._follows:
            key = messaging.mgmt_key(self.remote.device, "log", node)
            sub = self.remote.session.declare_subscriber(key, self._log_line(node))
            self._follows[node] = (sub, set())
        self._follows[node][1].add(ws)

    def _log_line(self, node: str) -> Callable[[Any], None]:
        def on(sample: Any) -> None:
            line = sample.payload.to_bytes().decode(errors="replace")
            if self._loop is not None and not self._loop.is_closed():
                self._loop.call_soon_threadsafe(self._send_log, node, line)

        return on

    def _send_log(self, node: str, line: str) -> None:
        pages = self._follows.get(node, (None, set()))[1]
        text = json.dumps({"t": "log", "node": node, "line": line})
        for ws in list(pages):
            if not ws.closed:
                asyncio.ensure_future(ws.send_str(text)).add_done_callback(_ignore_result)

    def _hold(self) -> None:
        """Hold motion for the page that asks for it, unless this dashboard holds it already
        or someone else does (then that holder watches it; the manager refuses motion when
        nobody does)."""
        if self.role == roles.OBSERVER or (self.holder is not None and self.holder.holding):
            return

        def call(body: dict[str, Any]) -> dict[str, Any]:
            key = messaging.mgmt_key(self.remote.device, "controllers")
            return messaging.request(
                self.remote.session, key, body, self.remote.timeout, self.remote.user
            )

        def ended(why: str) -> None:  # taken over by another holder: the pages are told
            self._emit({"t": "notice", "text": f"this dashboard no longer holds motion: {why}"})

        holder = Holder(call, describe("exolink dashboard"), ended)
        try:
            holder.acquire()
        except (HoldRefused, messaging.Unreachable) as exc:
            log.info("dashboard_not_holding", reason=str(exc))
            return
        self.holder = holder
        log.info("dashboard_holding_motion")

    def _release_hold(self) -> None:
        if self.holder is not None:
            self.holder.release()
            self.holder = None

    def _broadcast(self, message: dict[str, Any]) -> None:
        if not self.clients:
            return
        text = json.dumps(message, separators=(",", ":"))
        for ws in list(self.clients):
            if ws.closed:
                self.clients.discard(ws)
                continue
            # send_str only queues on a healthy socket; a stalled page is dropped, not waited for
            task = asyncio.ensure_future(ws.send_str(text))
            task.add_done_callback(_ignore_result)

    # --- decimation -----------------------------------------------------------------------

    async def _tick(self) -> None:
        period = 1.0 / self.rate_hz
        next_at = time.monotonic()
        live = self.live
        rates: dict[str, float] = {}
        while True:
            if not self.clients:  # nobody to draw for: no subscription, no wake-ups
                live.close()
                await self._watched.wait()
                live.open()
                next_at = time.monotonic()
            next_at += period
            await asyncio.sleep(max(0.0, next_at - time.monotonic()))
            if time.monotonic() - next_at > period:  # fell behind (a busy CPU): skip, not burst
                next_at = time.monotonic()
            newest = live.drain()
            if (now_rates := live.rates(time.monotonic())) is not None:
                rates = now_rates
            if not self.clients:
                continue  # nobody to draw for: nothing decoded
            frame = live.frame(newest)
            if frame is not None or rates:
                self._broadcast({"t": "live", **(frame or {}), "rates": rates})

    # --- polling --------------------------------------------------------------------------

    async def _poll_status(self) -> None:
        while True:
            await self._watched.wait()  # polled for open pages only (a status costs the supervisor)
            try:
                t0 = time.time()
                status = await asyncio.to_thread(self.remote.call, "status")
                self.status, self.status_error = _with_clock_offset(status, t0, time.time()), None
            except (Refused, messaging.Unreachable) as exc:
                self.status_error = str(exc)
            self._broadcast({"t": "status", "status": self.status, "error": self.status_error})
            await asyncio.sleep(self.status_period_s)

    async def _poll_record(self) -> None:
        while True:
            await self._watched.wait()
            try:
                reply = await asyncio.to_thread(
                    self._call,
                    ("record",),
                    request_body(reqs.RecordStatus()),
                    min(self.remote.timeout, 1.0),
                )
                reply.pop("ok", None)
                self.record = reply
            except (Refused, messaging.Unreachable) as exc:
                self.record = {"error": str(exc)}
            self._broadcast({"t": "record", **self.record})
            await asyncio.sleep(2.0)

    # --- commands -------------------------------------------------------------------------

    def _call(self, path: tuple[str, ...], body: dict[str, Any], timeout: float) -> dict[str, Any]:
        key = messaging.mgmt_key(self.remote.device, *path)
        reply = messaging.request(self.remote.session, key, body, timeout, self.remote.user)
        if not reply.get("ok"):
            raise Refused(str(reply.get("error", "refused")))
        return reply

    async def command(self, argv: list[str], confirmed: bool = False) -> dict[str, Any]:
        """An `exolink` command line from a page: the reply, the refusal, or a question.

        Motion asks first: without ``confirmed`` the answer is what would be sent, not sent.
        """
        try:
            cmd = parse(argv)
        except CommandError as exc:
            log.info("dashboard_command_refused", argv=argv, reason=str(exc))
            return {"ok": False, "error": str(exc)}
        if cmd.motion and not confirmed:
            return {"ok": False, "confirm": f"{cmd.text}: this moves a joint. Send it?"}
        return await self.send(cmd)

    async def send(self, cmd: Command) -> dict[str, Any]:
        body = dict(cmd.body)
        if cmd.motion or (cmd.path == ("maccepa",) and body.get("kind") == "gains"):
            await asyncio.to_thread(self._hold)
        timeout = cmd.timeout_s or self.remote.timeout
        try:
            reply = await asyncio.to_thread(self._call, cmd.path, body, timeout)
        except Refused as exc:
            log.info("dashboard_command_refused", command=cmd.text, reason=str(exc))
            return {"ok": False, "error": str(exc), "command": cmd.text}
        except messaging.Unreachable as exc:
            return {"ok": False, "error": f"appliance unreachable: {exc}", "command": cmd.text}
        reply.pop("ok", None)
        log.info("dashboard_command", command=cmd.text)
        if cmd.path == ("watchdog",):
            self.watchdog = {k: reply.get(k) for k in ("state", "reason", "detail")}
            self._broadcast({"t": "watchdog", **self.watchdog})
        return {"ok": True, "reply": reply, "command": cmd.text}

    def recording(self, board_path: str) -> Path:
        """A recording the recorder names, as a file here (``Files.recording``)."""
        return self.files.recording(board_path)

    def pattern_points(self, name: str) -> list[list[int]] | None:
        return pattern_points(name)

    async def query(self, path: tuple[str, ...], body: dict[str, Any]) -> dict[str, Any]:
        """A read for a page (logs, params): the appliance checks the role."""
        try:
            reply = await asyncio.to_thread(self._call, path, body, self.remote.timeout)
        except (Refused, messaging.Unreachable) as exc:
            return {"ok": False, "error": str(exc)}
        return reply


def _ignore_result(task: asyncio.Future[Any]) -> None:
    if not task.cancelled():
        task.exception()  # a page gone mid-send: its socket's close handler removes it


def _with_clock_offset(status: dict[str, Any], t0: float, t1: float) -> dict[str, Any]:
    """The board's clock minus this laptop's, from the status round trip (exolink.board.clock: the
    page warns when the board's time cannot be trusted for a trial's recordings)."""
    c = status.get("clock")
    if not isinstance(c, dict):  # an older board's status has none
        return status
    try:
        now = read(c, ClockStatus)
    except ValueError:  # not a clock's status: nothing to say of it
        return status
    off = clock.Offset(now.now - (t0 + t1) / 2, (t1 - t0) / 2)
    c.update(offset_ms=round(off.offset_s * 1e3, 1), error_ms=round(off.error_s * 1e3, 1))
    c["warning"] = (
        "not synchronised"
        if clock.unset(now)
        else f"{off.offset_s * 1e3:+.0f} ms off this laptop"
        if off.off()
        else ""
    )
    return status
