"""ROS 2 services the rmw_zenoh way, for the commands a ROS 2 user would call.

rmw_zenoh (rmw_service_data.cpp, rmw_client_data.cpp) serves a service as a Zenoh queryable
(``complete``) on ``<domain>/<service name>/<pkg>::srv::dds_::<Type>_/<service type hash>``: the
query carries the CDR request and an attachment (the client's sequence number, timestamp and
GID); the reply, on the service's key, carries the CDR response and the same sequence number and
client GID, which is how the client pairs it with its call. An ``SS`` graph token makes the
service show in ``ros2 service list -t``.

The handlers are the JSON management API's own (same validation, same refusals), reached with
the request rewritten as the JSON API's; what the caller may call is decided by Zenoh's access
control on the service's key (exolink.roles), since a ROS 2 client cannot add its login to the
key the way exolink's CLI does. Every call lands in the command log, by ``ros2`` and the
client's GID.

Type hashes of services come from the table ``make msgs`` writes (rosbags is slow to import on
the board); exolink.wire.srvtypes.service_fielddefs is what both the table and the CDR use.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import structlog
import zenoh

from exolink import logs, messaging, roles
from exolink.wire import replies, rosgraph

_log = structlog.get_logger("exolink.ros2")

ROS2_USER = "ros2"


# --- serving ---------------------------------------------------------------------------------

Handler = Callable[[Any], dict[str, Any]]


MAX_PENDING = 32  # calls of one service waiting for the workers; more are refused ("busy")


class ServiceServer:
    """One ROS 2 service: queryable, SS token, and the calls handed to a worker thread (a
    handler may query a node; Zenoh's callback threads are not for blocking), at most
    MAX_PENDING waiting (an unbounded queue held every call a flood sent). ``urgent`` (the
    e-stop): the handler runs at once on the callback thread, before the request is decoded
    (it needs none: the first call would otherwise load the typestore first, seconds on the
    board), never behind another service's calls."""

    def __init__(
        self,
        msg: Any,  # exolink.messaging.Messaging with a graph (ros_node)
        name: str,
        srv_type: str,
        handler: Handler,
        workers: ThreadPoolExecutor,
        urgent: bool = False,
    ) -> None:
        self._messaging = messaging
        self.msg, self.name, self.srv_type, self.handler = msg, name, srv_type, handler
        self.urgent = urgent
        self.pending = self.refused = 0
        self.key = msg.key(name, srv_type)
        self.request_type, self.response_type = f"{srv_type}_Request", f"{srv_type}_Response"
        self._store: Any = None  # the typestore, at the first call (see _codec)
        self._workers = workers
        self._lock = threading.Lock()
        self._q = msg.session.declare_queryable(self.key, self._on_query, complete=True)
        self._token = msg.graph.declare(
            rosgraph.SERVICE,
            rosgraph.fq_name(msg.namespace, name),
            srv_type,
            self.key.rsplit("/", 1)[-1],
            rosgraph.SERVICE_QOS,
        )

    def _on_query(self, query: zenoh.Query) -> None:
        if self.urgent:
            self._answer(query)
            return
        with self._lock:
            full = self.pending >= MAX_PENDING
            self.pending += not full
            self.refused += full
            refused = self.refused
        if full:
            if logs.rarely(refused):
                _log.warning("ros2_service_busy", service=self.name, refused=refused)
            query.reply_err(f"{self.name}: busy ({MAX_PENDING} calls wait)".encode())
            return
        self._workers.submit(self._pending_answer, query)

    def _pending_answer(self, query: zenoh.Query) -> None:
        try:
            self._answer(query)
        finally:
            with self._lock:
                self.pending -= 1

    def _answer(self, query: zenoh.Query) -> None:
        try:
            att = query.attachment
            if att is None:
                raise ValueError("no rmw_zenoh attachment (sequence number, client GID)")
            seq, _, gid = rosgraph.decode_attachment(att.to_bytes())
            payload = query.payload.to_bytes() if query.payload is not None else b""
            fields = self.handler(None) if self.urgent else None  # acted on before decoding
            store = self._codec()
            request = store.deserialize_cdr(payload, self.request_type)
        except (ValueError, KeyError, IndexError) as exc:  # not a ROS 2 call: say so, no reply
            query.reply_err(f"{self.key}: not a ROS 2 request: {exc}".encode()[:300])
            return
        try:
            if fields is None:
                fields = self.handler(request)
            response = store.types[self.response_type](**fields)
            body = bytes(store.serialize_cdr(response, self.response_type))
        except Exception as exc:  # a caller never waits out its timeout on a bug of ours
            _log.exception("ros2_service_failed", service=self.name)
            query.reply_err(f"{self.name}: internal error: {type(exc).__name__}: {exc}".encode())
            return
        query.reply(self.key, body, attachment=rosgraph.encode_attachment(seq, time.time_ns(), gid))

    def _codec(self) -> Any:
        """rosbags' typestore, prepared at the first call, not at start: the supervisor serves
        these services, and the store (with numpy) is ~13 MB and seconds of start on the A8
        that an appliance without a ROS 2 caller never needs. Calls run on worker threads."""
        if self._store is None:
            store = self._messaging.prepare(self.request_type)
            self._messaging.prepare(self.response_type)
            self._store = store
        return self._store

    def close(self) -> None:
        self._q.undeclare()
        self.msg.graph.release(self._token)


def outcome(reply: dict[str, Any], summary: Callable[[dict[str, Any]], str]) -> dict[str, Any]:
    """A JSON API reply as std_srvs' (success, message): the refusal verbatim, or a summary."""
    if not reply.get("ok"):
        return {"success": False, "message": str(reply.get("error", "refused"))}
    return {"success": True, "message": summary(reply)}


def run_json(handler: Callable[[dict[str, Any]], Any], request: dict[str, Any]):
    """A JSON API handler called in-process, its outcome shaped as ``messaging.serve`` shapes
    it (ok, or the refusal's text)."""
    try:
        return {"ok": True, **replies.plain(handler(request))}
    except (messaging.Refused, roles.Forbidden, messaging.Unreachable) as exc:
        return {"ok": False, "error": str(exc)}
    except Exception as exc:  # a caller never waits on a handler bug
        return {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}
