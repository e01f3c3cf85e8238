"""JSON queries: commands and management requests, their admission, logging and replies."""

from __future__ import annotations

import contextlib
import inspect
import json
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import structlog
import zenoh

from exolink import logs, roles
from exolink.messaging.sessions import Unreachable
from exolink.refusal import Refused
from exolink.wire import cdr, replies


class Putter(Protocol):
    """Where the command log puts its entries (a raw ``commands`` publisher: pubsub)."""

    def put(self, payload: bytes, source_ns: int | None = None) -> None: ...


DEFAULT_QUERY_TIMEOUT_S = 2.0

# --- JSON queries (commands and management) --------------------------------------------------


class Unlogged(dict[str, Any]):
    """A handler's reply that the command log leaves out: a keep-alive that repeats what was
    logged when it began (an operator's presence, renewed twice a second)."""


@dataclass(frozen=True, slots=True)
class Caller:
    """Who sent a request: the login its key ends with (``exolink/<device>/<path>/<login>``).

    On a board with logins Zenoh's access control lets a login query only keys that end in its
    own name, so this is the login Zenoh proved; anything in the request itself (a ``by``) is
    text the client chose. A handler that takes a second parameter gets it (``serve``): the
    e-stop's detail names it. An appliance without logins believes any key (exolink.roles)."""

    login: str


Handler = Callable[..., Any]  # (request) or (request, Caller) -> wire.replies struct or dict
# The role a request needs: one for the whole key, or chosen from the request (its action).
Needs = str | Callable[[dict[str, Any]], str]
# Whether a request is acted on at once, before any rate limit or queue (an e-stop).
Urgent = Callable[[dict[str, Any]], bool]
COMMANDS_TOPIC = "commands"
COMMANDS_TYPE = "std_msgs/msg/String"
# A node's Admission refusals (JSON in a std_msgs/String), put when they change: the
# supervisor shows them in `exolink status` (the node's ``api``).
API_TOPIC = "nodes/{node}/api"
API_TYPE = "std_msgs/msg/String"
_LOGGED_VALUE_CHARS = 200
_LOGGED_FIELDS = 20
ERROR_CHARS = 300  # an error (reply, command log) may quote what was sent: cut here
URGENT_BYTES = 4096  # an e-stop is a few dozen bytes; anything larger waits its turn
# Per login and process, every key together: a dashboard polls status once a second, an attached
# CLI too, an operator's presence renews up to 4 times a second, and tests send bursts of
# commands back to back; a flood gets 20 answers a second and cheap refusals for the rest.
RATE_PER_S = 20.0
RATE_BURST = 60
URGENT_LOG_PER_S = 1.0
URGENT_LOG_BURST = 10
# Admitted requests waiting for a key's handler: a handler is one thread, one at a time.
QUEUE_LEN = 32
QUEUE_BYTES = 4 << 20
_log = structlog.get_logger("exolink.commands")


def clip(text: str, limit: int = ERROR_CHARS) -> str:
    """``text`` cut to ``limit`` characters, saying how long it was: what a client sent is
    never echoed whole (into a reply, a log line, a counter's key)."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} chars)"


def _summary(request: dict[str, Any]) -> dict[str, Any]:
    """The request as the command log keeps it: uploaded content by size, long values cut,
    at most _LOGGED_FIELDS fields."""
    out: dict[str, Any] = {}
    for k, v in list(request.items())[:_LOGGED_FIELDS]:
        if k == "content" and isinstance(v, str):
            out[clip(k, 40)] = f"<{len(v)} chars>"
        else:
            text = json.dumps(v)
            keep = v if len(text) <= _LOGGED_VALUE_CHARS else text[:_LOGGED_VALUE_CHARS] + "..."
            out[clip(k, 40)] = keep
    if len(request) > _LOGGED_FIELDS:
        out["..."] = f"{len(request) - _LOGGED_FIELDS} more fields"
    return out


class CommandLog:
    """Every command a role above observer sent, with the login that sent it: in the process'
    log and on the ``commands`` topic (std_msgs/String, JSON), which the recorder records."""

    def __init__(self, pub: Putter) -> None:
        # Declared before the first command (by Messaging): a recorder learns topics from the
        # graph, and a publisher born with its first message would lose that message to it.
        self._pub = pub
        self._lock = threading.Lock()

    def write(self, user: str, key: str, request: dict[str, Any], reply: dict[str, Any]) -> None:
        entry = {"by": user, "key": key, "request": _summary(request), "ok": reply["ok"]}
        if not reply["ok"]:
            entry["error"] = clip(str(reply.get("error", "")))
        _log.info("command", **entry)
        with self._lock:
            self._pub.put(cdr.string_msg(json.dumps(entry)))


def takes_caller(handler: Handler) -> bool:
    """Whether ``handler`` has room for a second argument (the Caller)."""
    try:
        params = list(inspect.signature(handler).parameters.values())
    except (TypeError, ValueError):
        return False
    positional = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    return any(p.kind == inspect.Parameter.VAR_POSITIONAL for p in params) or (
        sum(p.kind in positional for p in params) >= 2
    )


class Admission:
    """What a process' queryables share: each login's token bucket (RATE_PER_S, RATE_BURST)
    and the counts of what they did with requests (``counters``: handled, urgent, and each
    reason a request was refused before or by its handler's checks)."""

    REASONS = ("too_large", "rate", "busy", "unknown_login", "not_json", "forbidden", "failed")

    def __init__(self, rate: float = RATE_PER_S, burst: int = RATE_BURST) -> None:
        self.rate, self.burst = rate, burst
        self._lock = threading.Lock()
        self._buckets: dict[str, tuple[float, float]] = {}  # login -> (tokens, monotonic)
        self._counts = dict.fromkeys(("handled", "urgent", "urgent_unlogged", *self.REASONS), 0)

    def allow(self, login: str) -> bool:
        """One token of ``login``'s bucket (only known logins get one: the dict stays small)."""
        return self._take(login, self.rate, self.burst)

    def urgent_logged(self, login: str) -> bool:
        """Whether an urgent request goes into the command log. Every e-stop is acted on (any
        login may send one), so a flood of them is bounded here instead: URGENT_LOG_BURST in a
        row, then URGENT_LOG_PER_S, the rest counted (``urgent_unlogged``). The watchdog's
        own trip is logged whatever this says."""
        if self._take(f"urgent {login}", URGENT_LOG_PER_S, URGENT_LOG_BURST):
            return True
        self.count("urgent_unlogged")
        return False

    def _take(self, key: str, rate: float, burst: int) -> bool:
        now = time.monotonic()
        with self._lock:
            tokens, then = self._buckets.get(key, (float(burst), now))
            tokens = min(float(burst), tokens + (now - then) * rate)
            ok = tokens >= 1.0
            self._buckets[key] = (tokens - 1.0 if ok else tokens, now)
            return ok

    def count(self, what: str) -> int:
        with self._lock:
            n = self._counts[what] = self._counts[what] + 1
            return n

    def counters(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    def refused(self) -> dict[str, int]:
        """The refusals alone, those that happened (what a node reports: ``API_TOPIC``)."""
        with self._lock:
            return {r: n for r in self.REASONS if (n := self._counts[r])}


class Served:
    """One management queryable: ``key/<login>`` (see ``serve``).

    Zenoh hands each queryable's queries to a Python thread of its own through a 256-query FIFO,
    and blocks its network thread while that FIFO is full: with the router's single thread that
    stopped every client, e-stops included (a flood of status queries held an e-stop 15 s).
    So that thread only does what is cheap: the caller's login, the request's size against the
    login's limit (roles.MAX_REQUEST_BYTES, before parsing), an urgent request (``urgent``: an
    e-stop) acted on at once, the login's rate (Admission) and a bounded queue; the handler runs
    on a worker thread of this key, one request at a time as before. Every refusal is a short
    error reply, counted, and logged rarely (logs.rarely)."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        handler: Handler,
        needs: Needs,
        log: CommandLog | None,
        admission: Admission,
        urgent: Urgent | None,
    ) -> None:
        self.key, self._handler, self._needs = key, handler, needs
        self._with_caller = takes_caller(handler)
        self._log, self._admission, self._urgent = log, admission, urgent
        self._queue: queue.SimpleQueue[tuple[zenoh.Query, str, bytes] | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._queued, self._queued_bytes = 0, 0
        self._worker: threading.Thread | None = None
        self._queryable = session.declare_queryable(f"{key}/*", self._on_query)

    def undeclare(self) -> None:
        self._queryable.undeclare()
        with self._lock:
            worker, self._worker = self._worker, None
        if worker is not None:
            self._queue.put(None)
            worker.join(1)

    def _on_query(self, query: zenoh.Query) -> None:
        """On Zenoh's callback thread of this queryable: nothing here may be slow."""
        try:
            self._triage(query)
        except Exception as exc:  # a bug here must not end Zenoh's thread for this key
            self._refuse(query, "?", "failed", f"internal error: {type(exc).__name__}")

    def _triage(self, query: zenoh.Query) -> None:
        login = str(query.key_expr).rsplit("/", 1)[-1]
        if not roles.known(login):
            error = f"unknown caller {clip(login, 40)!r} (logins: {', '.join(roles.ROLES)})"
            self._refuse(query, login, "unknown_login", error)
            return
        payload = query.payload
        size = len(payload) if payload is not None else 0
        limit = roles.MAX_REQUEST_BYTES[login]
        if size > limit:
            error = f"request of {size} bytes refused: the {login} login may send {limit}"
            self._refuse(query, login, "too_large", error)
            return
        raw = None  # copied out of Zenoh's buffer only for a request that goes further
        if self._urgent is not None and size <= URGENT_BYTES:
            raw = payload.to_bytes() if payload is not None and size else b""
            request = _json_object(raw)
            if request is not None and self._urgent(request):
                self._admission.count("urgent")
                logged = self._admission.urgent_logged(login)
                self._answer(query, login, raw, request, logged)
                return
        if not self._admission.allow(login):
            error = f"too many requests from {login}: over {self._admission.rate:g} a second"
            self._refuse(query, login, "rate", error)
            return
        if raw is None:
            raw = payload.to_bytes() if payload is not None and size else b""
        with self._lock:
            full = self._queued >= QUEUE_LEN or self._queued_bytes + size > QUEUE_BYTES
            if not full:
                self._queued, self._queued_bytes = self._queued + 1, self._queued_bytes + size
                if self._worker is None:
                    self._worker = threading.Thread(
                        target=self._work, daemon=True, name=f"api-{self.key.split('/', 2)[-1]}"
                    )
                    self._worker.start()
        if full:
            self._refuse(query, login, "busy", f"busy: {QUEUE_LEN} requests wait for {self.key}")
            return
        self._queue.put((query, login, raw))

    def _work(self) -> None:
        while (item := self._queue.get()) is not None:
            query, login, raw = item
            with self._lock:
                self._queued, self._queued_bytes = self._queued - 1, self._queued_bytes - len(raw)
            try:
                self._answer(query, login, raw)
            except Exception as exc:  # the worker outlives any one request
                n = self._admission.count("failed")
                if logs.rarely(n):
                    _log.error("request_failed", key=self.key, error=repr(exc)[:ERROR_CHARS])

    def _answer(
        self,
        query: zenoh.Query,
        login: str,
        raw: bytes,
        parsed: dict[str, Any] | None = None,
        logged: bool = True,
    ) -> None:
        """Parse, check the role, run the handler, reply; a command goes into the log
        (``logged``: an urgent one only within its login's own budget, see Admission)."""
        request: dict[str, Any] = {}
        needed = roles.OBSERVER
        try:
            if parsed is None:
                body = json.loads(raw or b"{}")
                if not isinstance(body, dict):
                    self._admission.count("not_json")
                    raise Refused(f"request must be a JSON object, not a {type(body).__name__}")
                parsed = body
            request = parsed
            needed = self._needs(request) if callable(self._needs) else self._needs
            action = clip(str(request.get("action", "")), 40)
            roles.check(login, needed, f"{self.key.split('/', 2)[-1]} {action}".strip())
            self._admission.count("handled")  # by its handler, which may still refuse it
            if self._with_caller:
                result = self._handler(request, Caller(login))
            else:
                result = self._handler(request)
            logged = logged and not isinstance(result, Unlogged)
            reply = {"ok": True, **replies.plain(result)}
        except (Refused, roles.Forbidden) as exc:
            if isinstance(exc, roles.Forbidden):
                self._admission.count("forbidden")
            reply = {"ok": False, "error": clip(str(exc))}
        except json.JSONDecodeError as exc:
            self._admission.count("not_json")
            reply = {"ok": False, "error": f"request is not valid JSON: {exc}"}
        except Exception as exc:  # never leave a caller waiting on a handler bug
            reply = {"ok": False, "error": clip(f"internal error: {type(exc).__name__}: {exc}")}
            if logs.rarely(self._admission.count("failed")):
                _log.error("handler_failed", key=self.key, error=reply["error"])
        _send(query, reply)
        command = needed != roles.OBSERVER or request.get("action") not in (None, "status")
        if self._log is not None and command and logged and login != roles.APPLIANCE_USER:
            self._log.write(login, self.key, request, reply)

    def _refuse(self, query: zenoh.Query, login: str, why: str, error: str) -> None:
        n = self._admission.count(why)
        if logs.rarely(n):
            _log.warning("request_refused", key=self.key, login=clip(login, 40), why=why, count=n)
        _send(query, {"ok": False, "error": error})


def _json_object(raw: bytes) -> dict[str, Any] | None:
    """The request if it is a JSON object, else None (the worker then says what is wrong)."""
    try:
        body = json.loads(raw or b"{}")
    except ValueError:
        return None
    return body if isinstance(body, dict) else None


def _send(query: zenoh.Query, reply: dict[str, Any]) -> None:
    """The reply, then the query's end: Zenoh sends that when the query is dropped, and the
    caller's ``get`` (consolidating replies) hands them over only then, so a query still held
    by the worker's loop left its caller waiting for its timeout."""
    with contextlib.suppress(zenoh.ZError):
        query.reply(query.key_expr, json.dumps(reply).encode())
        query.drop()


def serve(
    session: zenoh.Session,
    key: str,
    handler: Handler,
    needs: Needs = roles.OBSERVER,
    log: CommandLog | None = None,
    admission: Admission | None = None,
    urgent: Urgent | None = None,
) -> Served:
    """A JSON queryable at ``key/<login>``: the login (proven by Zenoh's access control on a
    board with logins) must hold the role the request needs; refusals and bugs become errors.
    ``handler(request)``, or ``handler(request, caller)`` with the Caller. Requests over the
    login's size, over its rate (``admission``, shared by a process' queryables), or beyond a
    full queue are refused before parsing; ``urgent`` requests are never (see Served).
    Commands (more than observer needed, or an action such as e-stop) go into ``log`` with the
    login that sent them, accepted or not."""
    return Served(session, key, handler, needs, log, admission or Admission(), urgent)


class RequestTooLarge(Refused):
    """A request refused before it was sent (``request``): too large for the caller's login."""


def request(
    session: zenoh.Session,
    key: str,
    body: dict[str, Any] | None = None,
    timeout_s: float = DEFAULT_QUERY_TIMEOUT_S,
    user: str = roles.ANONYMOUS_USER,
) -> dict[str, Any]:
    """One JSON query as login ``user`` with a deadline; Unreachable when nothing answers.
    A request over the login's size (roles.MAX_REQUEST_BYTES) is not sent: the appliance would
    refuse it, and past the router's own limit (MAX_MESSAGE_BYTES) drop it without an answer."""
    payload = json.dumps(body or {}).encode()
    if (limit := roles.MAX_REQUEST_BYTES.get(user)) is not None and len(payload) > limit:
        raise RequestTooLarge(
            f"{key}: a request of {len(payload)} bytes is over the {user} login's limit of "
            f"{limit} bytes; not sent"
        )
    for reply in session.get(f"{key}/{user}", payload=payload, timeout=timeout_s):
        if reply.ok is not None:
            result: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return result
        why = reply.err.payload.to_bytes().decode(errors="replace") if reply.err else "?"
        raise Unreachable(f"{key}: error reply: {why}")
    raise Unreachable(f"no answer from {key} within {timeout_s:g} s")
