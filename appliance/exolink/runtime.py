"""The node runtime: one node in one OS process, as the supervisor spawns it.

``python -m exolink.runtime NAME -c FILE`` is what the supervisor runs for each node: it imports
only that node's plugin and validates only its params (not every plugin's, which would load
numpy, mcap and zstandard into every node). The same ``NodeRunner`` runs a node in-process in
tests, or standalone (``exolink node run NAME``). It gives every node a Zenoh session, a liveliness
token and a heartbeat that stops when the node's own loop stops calling ``beat()``, so a wedged
loop looks dead to the watchdog even while the process is alive.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

import msgspec
import structlog
import zenoh

from exolink import liveness, logs, messaging, roles
from exolink.config import ApplianceConfig, load, node_params
from exolink.errors import run_guarded
from exolink.node import (
    HEARTBEAT_TOPIC,
    HEARTBEAT_TYPE,
    TELEMETRY_PERIOD_S,
    Node,
    NodeContext,
    beat_period_s,
    vouches,
)
from exolink.plugins import find_node_class
from exolink.wire import cdr, management, replies

STALL_LOG_EVERY_S = 10.0


class NodeRunner:
    """Everything around a node: session, liveliness, heartbeat, params queryable, signals."""

    def __init__(
        self, cls: type[Node], cfg: ApplianceConfig, name: str, session: zenoh.Session | None = None
    ) -> None:
        self.cfg = cfg
        self.name = name
        self.stop = threading.Event()
        self._own_session = session is None
        self.session = session or messaging.open_node_session(cfg)
        # The node is also a ROS 2 node of that name: its graph token now, before configure()
        # declares the publishers whose tokens hang under it.
        self.msg = messaging.Messaging(self.session, cfg, ros_node=name)
        log = structlog.get_logger().bind(node=name)
        ctx = NodeContext(name, cfg, self.session, self.msg, log)
        self.node = cls(ctx, node_params(cfg, name))
        self.node.liveness = liveness.Beater.from_env()
        self.log = log
        self._decls: list[Any] = []
        self._count = 0
        self._stall_quiet_until = 0.0
        self._stalls_unlogged = 0

    def _heartbeat(self) -> None:
        """The telemetry (``nodes/<name>/heartbeat`` for people, the API's refusals), and, for a
        loop whose stall limit is longer than its deadline, a vouch while it beat within it
        (``exolink.node.beat_period_s``): every other loop is judged on its own beats alone."""
        pub = self.msg.publisher(f"nodes/{self.name}/{HEARTBEAT_TOPIC}", HEARTBEAT_TYPE, raw=True)
        api = self.msg.publisher(
            messaging.API_TOPIC.format(node=self.name), messaging.API_TYPE, raw=True
        )
        refused: dict[str, int] = {}  # as last put: nothing is put while nothing is refused
        beat = cdr.HeartbeatCdr(self.name, os.getpid())
        deadline = self.cfg.deadline_s(self.cfg.node(self.name))
        vouch = vouches(deadline, self.node.stall_s)
        period = beat_period_s(deadline, self.node.stall_s)
        next_t = next_telemetry = time.monotonic()
        while not self.stop.is_set():
            healthy = self.node.healthy()
            if healthy and vouch:
                self.node.liveness.beat()
            if healthy and time.monotonic() >= next_telemetry:
                next_telemetry += TELEMETRY_PERIOD_S
                self._count += 1
                now = time.time_ns()
                pub.put(beat.encode(now, self._count), now)
                if (now_refused := self.msg.admission.refused()) != refused:
                    refused = now_refused
                    api.put(cdr.string_msg(json.dumps(refused)), now)
            next_t += period
            self.stop.wait(max(0.0, next_t - time.monotonic()))
        pub.close()
        api.close()

    def _on_stall(self, gap_s: float, limit_s: float) -> None:
        """A loop beat again after ``gap_s`` without (its limit: ``limit_s``): logged at most once
        per ``STALL_LOG_EVERY_S``, the rest counted; on a saturated core a motion node's 40 ms
        limit otherwise floods the journal (and the supervisor, which relays every line). A loop
        that never beats again is the supervisor's (``node_hung_killed``, with its threads)."""
        now = time.monotonic()
        if now < self._stall_quiet_until:
            self._stalls_unlogged += 1
            return
        self._stall_quiet_until = now + STALL_LOG_EVERY_S
        self.log.warning(
            "loop_stalled",
            stalled_s=round(gap_s, 3),
            limit_s=limit_s,
            stalls_not_logged=self._stalls_unlogged,
        )
        self._stalls_unlogged = 0

    def _params(self, req: dict[str, Any]) -> replies.ParamSet | replies.NodeParams:
        ask = management.convert(req, management.Params, "params")
        if ask.set is not None:
            key = ask.set.key
            return replies.ParamSet(key, self.node.set_param(key, ask.set.value))
        return replies.NodeParams(msgspec.to_builtins(self.node.params))

    def run(self) -> int:
        """Blocking: configure, run, shut down. Returns the process exit code."""
        try:
            self.node.configure()
        except BaseException:
            self.node.release()  # what it opened before refusing
            raise
        self._decls.append(
            self.session.liveliness().declare_token(self.msg.mgmt("nodes", self.name, "alive"))
        )
        self._decls.append(
            self.msg.serve(("nodes", self.name, "params"), self._params, roles.ADMIN)
        )
        # The loop's stall clock starts now, not at construction. Idle: nothing is driven
        # before the loop runs, whose first beat that is not idle comes before it drives
        # anything; a motion node's own 50 ms from here would kill a restarted controller
        # manager whose loop beats first a little later (docs/performance.md, exolink.liveness).
        self.node.on_stall = self._on_stall
        self.node.restart_stall_clock()
        self.node.beat(liveness.Pace.IDLE)
        hb = threading.Thread(target=self._heartbeat, name="heartbeat", daemon=True)
        hb.start()
        self.log.info("node_running", pid=os.getpid())
        code = 0
        try:
            with profiled(self.name):
                self.node.run(self.stop)
        except Exception:
            self.log.exception("node_failed")
            code = 1
        finally:
            self.stop.set()
            self.node.shutdown()
            self.node.release()
            hb.join(1.0)
            for d in self._decls:
                d.undeclare()
            self.msg.close()
            if self._own_session:
                self.session.close()
            self.log.info("node_stopped", code=code)
        return code


@contextlib.contextmanager
def profiled(name: str) -> Iterator[None]:
    """``EXOLINK_PROFILE_DIR``: the node's loop (its main thread) under cProfile, written to
    ``DIR/<name>-<pid>.prof`` when the loop ends (before shutdown, which a slow stop may not
    finish; a file per spawn: one restarted after a bench's window overwrote the window's);
    ``EXOLINK_PROFILE_NODES`` (comma-separated): only these nodes. In-process: py-spy sampling
    from outside falls minutes behind under qemu and takes the simulator's CPU."""
    where = os.environ.get("EXOLINK_PROFILE_DIR")
    only = os.environ.get("EXOLINK_PROFILE_NODES")
    if not where or (only and name not in only.split(",")):
        yield
        return
    import cProfile  # lazy: only with EXOLINK_PROFILE_DIR

    prof = cProfile.Profile()
    prof.enable()
    try:
        yield
    finally:
        prof.disable()
        os.makedirs(where, exist_ok=True)
        prof.dump_stats(os.path.join(where, f"{name}-{os.getpid()}.prof"))


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
    """One node in this process until SIGTERM/SIGINT (``exolink node run``, and supervised)."""
    node_cfg = cfg.node(name)
    cls = find_node_class(node_cfg.plugin)
    messaging.zenoh_runtime(cfg.zenoh)  # as the supervisor does; a supervised node inherits it
    session = zenoh.open(messaging.session_config(cfg.zenoh, listen=listen)) if listen else None
    runner = NodeRunner(cls, cfg, name, session)

    stop_on_signals(runner.stop, runner.log)
    try:
        return runner.run()
    finally:
        if session is not None:
            session.close()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m exolink.runtime NAME -c FILE``: the process the supervisor spawns per node."""
    p = argparse.ArgumentParser(prog="python -m exolink.runtime", description=__doc__)
    p.add_argument("name")
    p.add_argument("--config", "-c", required=True)
    p.add_argument("--listen", action="append", help="also listen on a Zenoh endpoint")
    args = p.parse_args(argv)
    return run_guarded(lambda a: start(a.config, a.name, a.listen), args)


def start(config_path: str, name: str, listen: list[str] | None = None) -> int:
    """Load the config checking this node's params only (its plugin alone loads), then run it."""
    cfg = load(config_path, check=[name])
    logs.setup(name)
    pin_to_cpus(cfg.node(name).priority.cpus)
    return run_standalone(cfg, name, listen)


def pin_to_cpus(cpus: list[int] | None) -> None:
    """The configured CPUs for the whole process, set before any thread exists, which then all
    inherit them. A later per-thread pass alone races with the threads Zenoh starts while a
    session opens: a node pinned to one CPU keeps threads on another (the simulator pinned to
    CPU 1 in `make bench-board` kept threads on CPU 0, the core that is measured)."""
    if not cpus:
        return
    try:
        os.sched_setaffinity(0, cpus)
    except OSError as exc:
        structlog.get_logger().warning("affinity_failed", cpus=cpus, error=str(exc))


if __name__ == "__main__":
    sys.exit(main())
