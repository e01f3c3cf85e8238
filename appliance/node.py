"""The node base class and its runtime: configure -> run -> shutdown, one OS process per node.

The same class runs supervised, in-process in tests (``NodeRunner`` on a thread), or standalone
(``exolink node run NAME``). The runtime gives every node a Zenoh session, a liveliness token and
a heartbeat that stops when the node's own loop stops calling ``beat()``, so a wedged loop looks
dead to the watchdog even while the process is alive.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import msgspec
import structlog
import zenoh
from exolink import messaging
from exolink.config import ApplianceConfig

HEARTBEAT_PERIOD_S = 0.1
HEARTBEAT_TOPIC = "heartbeat"
HEARTBEAT_TYPE = "exolink_msgs/msg/Heartbeat"


class NoParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    pass


@dataclass
class NodeContext:
    name: str
    config: ApplianceConfig
    session: zenoh.Session
    messaging: messaging.Messaging
    log: structlog.typing.FilteringBoundLogger


class Node:
    """Subclass, set ``Params`` to a msgspec Struct, implement ``run``.

    ``configure`` opens what the node needs (buses, publishers, queryables) and may raise to
    refuse to start; ``run`` loops until ``stop`` is set, calling ``beat()`` at least every
    ``stall_s``; ``shutdown`` releases everything and must not raise.
    """

    Params: ClassVar[type[msgspec.Struct]] = NoParams
    stall_s: ClassVar[float] = 0.5

    def __init__(self, ctx: NodeContext, params: Any) -> None:
        self.ctx = ctx
        self.params = params
        self.log = ctx.log
        self._last_beat = time.monotonic()

    @property
    def name(self) -> str:
        return self.ctx.name

    def beat(self) -> None:
        self._last_beat = time.monotonic()

    @property
    def last_beat(self) -> float:
        return self._last_beat

    def healthy(self) -> bool:
        return time.monotonic() - self._last_beat < self.stall_s

    def configure(self) -> None:
        pass

    def run(self, stop: threading.Event) -> None:
        raise NotImplementedError

    def shutdown(self) -> None:
        pass

    def set_param(self, key: str, value: Any) -> Any:
        """Change one param at run time; nodes that allow it override ``apply_params``."""
        data = msgspec.to_builtins(self.params)
        if key not in data:
            raise messaging.CommandRefused(
                f"{self.name} has no param {key!r} (has: {', '.join(data)})"
            )
        data[key] = value
        try:
            new = msgspec.convert(data, type(self.params))
        except msgspec.ValidationError as exc:
            raise messaging.CommandRefused(f"{self.name}.{key}: {exc}") from None
        self.apply_params(new)
        self.params = new
        return getattr(new, key)

    def apply_params(self, new: Any) -> None:
        raise messaging.CommandRefused(f"{self.name} does not change params at run time")


class NodeRunner:
    """Everything around a node: session, liveliness, heartbeat, params queryable, signals."""

    def __init__(
        self, cls: type[Node], cfg: ApplianceConfig, name: str, session: zenoh.Session | None = None
    ) -> None:
        from exolink.config import node_params

        self.cfg = cfg
        self.name = name
        self.stop = threading.Event()
        self._own_session = session is None
        self.session = session or messaging.open_node_session(cfg)
        self.msg = messaging.Messaging(self.session, cfg)
        log = structlog.get_logger().bind(node=name)
        ctx = NodeContext(name, cfg, self.session, self.msg, log)
        self.node = cls(ctx, node_params(cfg, name))
        self.log = log
        self._decls: list[Any] = []
        self._count = 0

    def _heartbeat(self) -> None:
        pub = self.msg.publisher(f"nodes/{self.name}/{HEARTBEAT_TOPIC}", HEARTBEAT_TYPE)
        cls = messaging.msg_class(HEARTBEAT_TYPE)
        pid = os.getpid()
        next_t = time.monotonic()
        stalled_since: float | None = None  # the journal says which loop went quiet, how long
        while not self.stop.is_set():
            before = self.node.last_beat
            healthy = self.node.healthy()
            if not healthy and stalled_since is None:
                stalled_since = before
                self.log.warning("loop_stalled", limit_s=self.node.stall_s)
            elif healthy and stalled_since is not None:
                stalled_s = self.node.last_beat - stalled_since
                self.log.warning("loop_recovered", stalled_s=round(stalled_s, 2))
                stalled_since = None
            if healthy:
                self._count += 1
                now = time.time_ns()
                pub.publish(cls(messaging.stamp(now), self.name, self._count, pid, "running"), now)
            next_t += HEARTBEAT_PERIOD_S
            self.stop.wait(max(0.0, next_t - time.monotonic()))
        pub.close()

    def _params(self, req: dict[str, Any]) -> dict[str, Any]:
        if "set" in req:
            key, value = req["set"].get("key"), req["set"].get("value")
            return {"key": key, "value": self.node.set_param(str(key), value)}
        return {"params": msgspec.to_builtins(self.node.params)}

    def run(self) -> int:
        """Blocking: configure, run, shut down. Returns the process exit code."""
        self.node.configure()
        self._decls.append(
            self.session.liveliness().declare_token(self.msg.mgmt("nodes", self.name, "alive"))
        )
        self._decls.append(
            messaging.serve(self.session, self.msg.mgmt("nodes", self.name, "params"), self._params)
        )
        self.node.beat()  # the loop's stall clock starts now, not at construction
        hb = threading.Thread(target=self._heartbeat, name="heartbeat", daemon=True)
        hb.start()
        self.log.info("node_running", pid=os.getpid())
        code = 0
        try:
            self.node.run(self.stop)
        except Exception:
            self.log.exception("node_failed")
            code = 1
        finally:
            self.stop.set()
            self.node.shutdown()
            hb.join(1.0)
            for d in self._decls:
                d.undeclare()
            if self._own_session:
                self.session.close()
            self.log.info("node_stopped", code=code)
        return code


def stop_on_signals(stop: threading.Event, log: Any) -> None:
    """SIGTERM / SIGINT set ``stop``: every long-running exolink process ends the same clean way.

    The handler only writes the signal number to a pipe; a thread logs it and sets ``stop``.
    Handlers run on the main thread between bytecodes: one calling ``stop.set()`` (or a logger)
    while that thread was inside ``stop.wait()`` holding the same lock deadlocked, and a
    supervisor ignored SIGTERM for good.
    """
    r, w = os.pipe()
    os.set_blocking(w, False)

    def on_signal(signum: int, _frame: Any) -> None:
        with contextlib.suppress(BlockingIOError):  # a full pipe already holds a stop request
            os.write(w, bytes([signum]))

    def relay() -> None:
        while data := os.read(r, 64):
            for signum in data:
                log.info("signal", signal=signal.Signals(signum).name)
            stop.set()

    threading.Thread(target=relay, daemon=True, name="signals").start()
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)


def run_standalone(cfg: ApplianceConfig, name: str, listen: list[str] | None = None) -> int:
    """``exolink node run``: one node in this process until SIGTERM/SIGINT."""
    from exolink.plugins import find_node_class

    node_cfg = cfg.node(name)
    cls = find_node_class(node_cfg.plugin)
    session = zenoh.open(messaging.session_config(cfg.zenoh, listen=listen)) if listen else None
    runner = NodeRunner(cls, cfg, name, session)

    stop_on_signals(runner.stop, runner.log)
    try:
        return runner.run()
    finally:
        if session is not None:
            session.close()
