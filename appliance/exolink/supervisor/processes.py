"""Node processes: spawn, watch, restart by policy, apply priority, capture output.

Each node is its own OS process (``python -m exolink.runtime NAME``) so a crash takes only itself down.
A waiter thread per process blocks in ``wait()``: the exit is known within a millisecond, which
is what lets the watchdog put the disable frames on the bus right after a ``kill -9``.
"""

from __future__ import annotations

import collections
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import structlog

from exolink import liveness
from exolink.canbus import CanOpenError
from exolink.canbus.held import HELD_ENV, HeldOps
from exolink.config import NodeConfig
from exolink.supervisor.forking import Forked, Zygote
from exolink.supervisor.osproc import plain_priority, proc_state, proc_usage
from exolink.supervisor.starving import Sched, Threads
from exolink.wire import replies

LOG_LINES = 500
# What the supervisor keeps and relays of a node's output (journal, ``log/<node>`` on Zenoh, the
# last LOG_LINES for `exolink logs`): lines cut at LOG_LINE_BYTES (a line without a newline
# was read whole before, however long), and at most LOG_RATE_PER_S a second after a burst of
# LOG_BURST; the lines dropped are counted in a line of their own. An admin flood of commands
# with 100 KB node names wrote 1.1 GB of journal in 5 minutes.
LOG_LINE_BYTES = 4096
LOG_RATE_PER_S = 100.0
LOG_BURST = 500
REAP_WAIT_S = 5.0  # after SIGKILL: a stop never holds the management API longer


@dataclass
class Exit:
    node: str
    code: int | None  # None: killed by a signal
    signal: str | None
    deliberate: bool  # a stop or restart asked this spawn to go
    pid: int | None = None
    # The node's current spawn: False for one a restart has already replaced, whose exit
    # must not change the state of its successor.
    current: bool = True


@dataclass
class NodeProcess:
    cfg: NodeConfig
    config_path: str
    on_exit: Callable[[Exit], None]
    on_line: Callable[[str, str], None]
    state: str = "stopped"  # running | stopping | stopped | killed | backoff | failed | exited
    proc: subprocess.Popen[bytes] | Forked | None = None
    started_at: float = 0.0  # monotonic
    restarts: int = 0
    last_exit: str = ""
    next_start: float = 0.0
    heartbeat_at: float | None = None
    # When the supervisor's loop next judges it (monotonic; 0: at its next wake). Another
    # thread that changes ``state`` sets it to 0, under ``lock``.
    due_at: float = 0.0
    # the deadline its last beat asked to be judged by (exolink.liveness: own, idle, leased)
    pace: liveness.Pace = liveness.Pace.OWN
    start_s: float | None = None  # spawn to first heartbeat: how close a slow card is to the grace
    # Starved, not hung (exolink.supervisor.starving): its loop as last read while on time, the
    # beat a starved silence began after (None: none now), and such silences counted.
    sched_mark: Sched | None = None
    sched: Threads | None = None  # this spawn's threads' counts, read again (not reopened)
    starved_after: float | None = None
    starved: int = 0
    # Spawns counted, and the pids asked to stop: an exit is judged by its own spawn, never by
    # whatever the node is by the time its report comes (see _wait).
    spawns: int = 0
    stopping_pids: set[int] = field(default_factory=set)
    health: str = ""  # from the node's own diagnostics, if it publishes any
    # A bus reader's receive losses and backlog: its diagnostics values named rx_* (dropped,
    # late, lag_max_ms, ...), as of its last report.
    receive: dict[str, Any] = field(default_factory=dict)
    # The recordings card (the recorder's card_* values: free, total, reserve, rate_bps,
    # hours_left), for `exolink status`.
    card: dict[str, Any] = field(default_factory=dict)
    restart_times: collections.deque[float] = field(default_factory=collections.deque)
    logs: collections.deque[str] = field(
        default_factory=lambda: collections.deque(maxlen=LOG_LINES)
    )
    lock: threading.RLock = field(default_factory=threading.RLock)
    channel: liveness.Channel | None = None  # this spawn's liveness pipe and deadline timer
    deadlines: tuple[float, ...] | None = None  # by Pace, s: its beats set the timer by them
    zygote: Zygote | None = None  # forks the node from a pre-imported runtime; else exec
    # A leased node's broadcast-manager sockets, the watchdog's copies (exolink.canbus.held):
    # one per spawn, released at its exit. None: the node gets none.
    held: HeldOps | None = None

    @property
    def name(self) -> str:
        return self.cfg.name

    def note_diagnostics(self, statuses: Any) -> None:
        """Keep the rx_* and card_* values of the node's diagnostics
        (diagnostic_msgs/DiagnosticStatus); at most a few dozen short values are kept (anyone
        may put on the key)."""
        rx: dict[str, Any] = {}
        card: dict[str, Any] = {}
        for st in statuses:
            for kv in st.values:
                for prefix, into in (("rx_", rx), ("card_", card)):
                    if kv.key.startswith(prefix) and len(into) < 32:
                        into[kv.key[len(prefix) : 40]] = _number(kv.value[:40])
        if rx:
            self.receive = rx
        if card:
            self.card = card

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None and self.proc.poll() is None else None

    def start(self) -> None:
        with self.lock:
            if self.pid is not None:
                return
            if self.channel is not None:
                self.channel.close()
            self.channel = liveness.Channel()
            env = {**os.environ, "EXOLINK_LOG_JSON": "1", "PYTHONUNBUFFERED": "1"}
            if self.deadlines is not None:
                env[liveness.DEADLINES_ENV] = ",".join(f"{d:g}" for d in self.deadlines)
            op_sock = self._held_socket()
            try:
                self.proc = self._spawn(env, op_sock)
            except BaseException:
                if op_sock is not None and self.held is not None:
                    self.held.release(op_sock)
                raise
            self.spawns += 1
            self.stopping_pids.clear()  # an older spawn's exit is judged not current anyway
            self.channel.spawned()
            self.state, self.started_at = "running", time.monotonic()
            self.heartbeat_at, self.start_s = None, None
            self.sched_mark = self.starved_after = None
            self.pace, self.due_at = liveness.Pace.OWN, 0.0
            plain_priority(self.proc.pid)
            threading.Thread(
                target=self._wait,
                args=(self.proc, self.spawns, op_sock),
                daemon=True,
                name=f"wait-{self.name}",
            ).start()
            threading.Thread(
                target=self._read, args=(self.proc,), daemon=True, name=f"log-{self.name}"
            ).start()

    def _held_socket(self) -> socket.socket | None:
        """This spawn's broadcast-manager socket, if the node leases (None if refused: the node
        then opens its own, and only the lease bounds its op; said in the log)."""
        if self.held is None:
            return None
        try:
            return self.held.open()
        except CanOpenError as exc:
            structlog.get_logger().error("held_op_socket_failed", node=self.name, error=str(exc))
            return None

    def _spawn(
        self, env: dict[str, str], op_sock: socket.socket | None
    ) -> subprocess.Popen[bytes] | Forked:
        assert self.channel is not None
        fds = [self.channel.child_fd, self.channel.timer]
        if op_sock is not None:
            fds.append(op_sock.fileno())
        if self.zygote is not None:
            try:
                return self.zygote.spawn(self.name, self.config_path, env, fds)
            except (OSError, RuntimeError) as exc:  # a start is worth more than a fast one
                structlog.get_logger().warning("zygote_failed", node=self.name, error=str(exc))
        cmd = [sys.executable, "-m", "exolink.runtime", self.name, "-c", self.config_path]
        return subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={
                **env,
                liveness.ENV: str(self.channel.child_fd),
                liveness.TIMER_ENV: str(self.channel.timer),
                **({HELD_ENV: str(op_sock.fileno())} if op_sock is not None else {}),
            },
            stdin=subprocess.DEVNULL,
            process_group=0,  # not a session of its own: see zygote.own_process_group
            pass_fds=fds,
        )

    def _wait(
        self, proc: subprocess.Popen[bytes] | Forked, spawn: int, op_sock: socket.socket | None
    ) -> None:
        """The exit of spawn number ``spawn``, reported under the node's lock: whether it is
        still the node's current spawn and what the supervisor makes of its exit are one step,
        so a restart can never start a successor in between (it then saw its predecessor's exit
        taken for its own: "stopped", with its process running unwatched)."""
        rc = proc.wait()
        if op_sock is not None and self.held is not None:  # its ops end with it, as its own
            self.held.release(op_sock)  # socket's would (exolink.canbus.held)
        sig = signal.Signals(-rc).name if rc < 0 else None
        with self.lock:
            deliberate = proc.pid in self.stopping_pids
            self.stopping_pids.discard(proc.pid)
            current = spawn == self.spawns
            if current:
                self.last_exit = sig or f"exit {rc}"
                if self.sched is not None:
                    self.sched.close()  # its files: a respawn opens its own
            exit_ = Exit(self.name, None if rc < 0 else rc, sig, deliberate, proc.pid, current)
            self.on_exit(exit_)

    def _read(self, proc: subprocess.Popen[bytes] | Forked) -> None:
        """Each line of the node's output, bounded (LOG_LINE_BYTES, LOG_RATE_PER_S)."""
        assert proc.stdout is not None
        rate = LineRate(LOG_RATE_PER_S, LOG_BURST)
        cut = False  # the rest of a line that was cut is skipped up to its newline
        while raw := proc.stdout.readline(LOG_LINE_BYTES):
            whole = raw.endswith(b"\n")
            if cut:
                cut = not whole
                continue
            line = raw.decode(errors="replace").rstrip("\n")
            if not whole and len(raw) == LOG_LINE_BYTES:
                cut, line = True, f"{line}... (line cut at {LOG_LINE_BYTES} bytes)"
            dropped = rate.take()
            if dropped is None:
                continue
            self._tell_dropped(dropped)
            self._keep(line)
        self._tell_dropped(rate.flush())

    def _tell_dropped(self, dropped: int) -> None:
        if dropped:
            self._keep(
                f"exolink: {dropped} lines of {self.name} dropped (over {LOG_RATE_PER_S:g} a second)"
            )

    def _keep(self, line: str) -> None:
        self.logs.append(line)
        self.on_line(self.name, line)

    def stop(self, timeout: float = 3.0) -> None:
        """SIGTERM, then SIGKILL after ``timeout``: a node never outlives a stop request. The
        node is "stopping" until its process is gone, then "stopped"."""
        with self.lock:
            proc, spawn = self.proc, self.spawns
            if proc is not None:  # exited already or not: its report is of a deliberate stop
                self.stopping_pids.add(proc.pid)
            alive = proc is not None and proc.poll() is None
            self.state, self.due_at = ("stopping" if alive else "stopped"), 0.0
        try:
            if alive and proc is not None:  # (alive says so: for the type checker)
                self._end(proc, timeout)
        finally:
            with self.lock:
                if self.spawns == spawn and self.state == "stopping":
                    self.state = "stopped"

    def _end(self, proc: subprocess.Popen[bytes] | Forked, timeout: float = 3.0) -> None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            try:
                proc.wait(REAP_WAIT_S)
            except subprocess.TimeoutExpired:
                # Seen twice in native ladder runs (a stop that returned after 206 s / 11 min,
                # the management API queued behind it): say what the process was doing instead
                # of holding every later request; its waiter thread still reports the exit.
                structlog.get_logger().error(
                    "node_not_reaped",
                    node_name=self.name,
                    pid=proc.pid,
                    seconds=timeout + REAP_WAIT_S,
                    state=proc_state(proc.pid),
                )

    def threads(self) -> Threads | None:
        """This spawn's threads' counts (exolink.supervisor.starving), opened at first use;
        under ``lock``."""
        pid = self.pid
        if pid is None:
            return None
        if self.sched is None or self.sched.pid != pid:
            if self.sched is not None:
                self.sched.close()
            self.sched = Threads(pid)
        return self.sched

    def kill(self) -> None:
        """SIGKILL (a hung node); the exit is handled like a crash, restart policy included."""
        with self.lock:
            if self.proc is not None and self.proc.poll() is None:
                self.proc.kill()
                self.state, self.due_at = "killed", 0.0

    def poll_liveness(self, now: float) -> bool:
        """Takes the beats that arrived since the last tick; True on this spawn's first one."""
        beat = self.channel.drain(now) if self.channel is not None else None
        if beat is None or self.pid is None:
            return False
        first = self.heartbeat_at is None
        self.heartbeat_at, self.pace = beat
        return first

    def failed_by_policy(self, code: int | None) -> bool:
        policy = self.cfg.restart.policy
        return policy == "always" or (policy == "on-failure" and code != 0)

    def schedule_restart(self, now: float) -> bool:
        """Backoff doubles per restart in the window; past the cap the node is marked failed."""
        r = self.cfg.restart
        while self.restart_times and now - self.restart_times[0] > r.window_s:
            self.restart_times.popleft()
        if len(self.restart_times) >= r.max_restarts:
            self.state = "failed"
            return False
        delay_ms = min(r.backoff_initial_ms * 2 ** len(self.restart_times), r.backoff_max_ms)
        self.restart_times.append(now)
        self.restarts += 1
        self.state, self.next_start, self.due_at = "backoff", now + delay_ms / 1000, 0.0
        return True

    def describe(self) -> replies.NodeInfo:
        pid = self.pid
        usage = proc_usage(pid) if pid else {}
        return replies.NodeInfo(
            name=self.name,
            plugin=self.cfg.plugin,
            critical=self.cfg.critical,
            enabled=self.cfg.enabled,
            state=self.state,
            pid=pid,
            uptime_s=round(time.monotonic() - self.started_at, 1) if pid else 0.0,
            restarts=self.restarts,
            last_exit=self.last_exit,
            health=self.health,
            receive=self.receive or replies.UNSET,
            card=self.card or replies.UNSET,
            heartbeat_age_s=round(time.monotonic() - self.heartbeat_at, 3)
            if self.heartbeat_at
            else None,
            # held to the default deadline meanwhile, or to its lease's (exolink.liveness)
            idle=self.pace == liveness.Pace.IDLE,
            leased=self.pace == liveness.Pace.LEASED,
            start_s=None if self.start_s is None else round(self.start_s, 2),
            starved=self.starved,
            cpu_s=usage.get("cpu_s", replies.UNSET),
            rss_mb=usage.get("rss_mb", replies.UNSET),
        )


class LineRate:
    """A token bucket for one node's output lines: ``take`` is None for a line to drop, else
    how many were dropped since the last one kept (0 mostly)."""

    def __init__(self, rate: float, burst: int) -> None:
        self.rate, self.burst = rate, burst
        self._tokens, self._at, self._dropped = float(burst), time.monotonic(), 0

    def take(self) -> int | None:
        now = time.monotonic()
        self._tokens = min(float(self.burst), self._tokens + (now - self._at) * self.rate)
        self._at = now
        if self._tokens < 1.0:
            self._dropped += 1
            return None
        self._tokens -= 1.0
        return self.flush()

    def flush(self) -> int:
        """Lines dropped since the last one kept: told at the end of the output, or the
        count of a burst that ended the node's output would be lost."""
        dropped, self._dropped = self._dropped, 0
        return dropped


def relay(log: structlog.typing.FilteringBoundLogger, node: str, line: str) -> None:
    """A node's output into the supervisor's log: JSON lines pass through, the rest is wrapped."""
    try:
        rec = json.loads(line)
        if not isinstance(rec, dict):
            raise ValueError
    except ValueError:
        log.info("node_output", node=node, line=line)
        return
    sys.stderr.write(line + "\n")


def _number(text: str) -> int | float | str | None:
    """A diagnostics value (always a string) back as the number it was."""
    if text == "None":
        return None
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            continue
    return text
