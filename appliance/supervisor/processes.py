"""Node processes: spawn, watch, restart by policy, apply priority, capture output.

Each node is its own OS process (``python -m exolink.runtime NAME``) so a crash takes only itself down.
A waiter thread per process blocks in ``wait()``: the exit is known within a millisecond, which
is what lets the watchdog put the disable frames on the bus right after a ``kill -9``.
"""

from __future__ import annotations

import collections
import contextlib
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
from exolink.config import NodeConfig

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
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0  # monotonic
    restarts: int = 0
    last_exit: str = ""
    next_start: float = 0.0
    heartbeat_at: float | None = None
    # When the supervisor's loop next judges it (monotonic; 0: at its next wake). Another
    # thread that changes ``state`` sets it to 0, under ``lock``.
    due_at: float = 0.0
    idle: bool = False  # its last beat said it has nothing to drive (exolink.liveness)
    start_s: float | None = None  # spawn to first heartbeat: how close a slow card is to the grace
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
    deadlines: tuple[float, float] | None = None  # (own, idle) s: its beats set the timer by them
    zygote: Zygote | None = None  # forks the node from a pre-imported runtime; else exec

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
            self.proc = self._spawn(env)
            self.spawns += 1
            self.stopping_pids.clear()  # an older spawn's exit is judged not current anyway
            self.channel.spawned()
            self.state, self.started_at = "running", time.monotonic()
            self.heartbeat_at, self.start_s = None, None
            self.idle, self.due_at = False, 0.0
            plain_priority(self.proc.pid)
            threading.Thread(
                target=self._wait,
                args=(self.proc, self.spawns),
                daemon=True,
                name=f"wait-{self.name}",
            ).start()
            threading.Thread(
                target=self._read, args=(self.proc,), daemon=True, name=f"log-{self.name}"
            ).start()

    def _spawn(self, env: dict[str, str]) -> subprocess.Popen[bytes] | Forked:
        assert self.channel is not None
        if self.zygote is not None:
            try:
                return self.zygote.spawn(
                    self.name, self.config_path, env, [self.channel.child_fd, self.channel.timer]
                )
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
            },
            stdin=subprocess.DEVNULL,
            process_group=0,  # not a session of its own: see zygote.own_process_group
            pass_fds=(self.channel.child_fd, self.channel.timer),
        )

    def _wait(self, proc: subprocess.Popen[bytes] | Forked, spawn: int) -> None:
        """The exit of spawn number ``spawn``, reported under the node's lock: whether it is
        still the node's current spawn and what the supervisor makes of its exit are one step,
        so a restart can never start a successor in between (it then saw its predecessor's exit
        taken for its own: "stopped", with its process running unwatched)."""
        rc = proc.wait()
        sig = signal.Signals(-rc).name if rc < 0 else None
        with self.lock:
            deliberate = proc.pid in self.stopping_pids
            self.stopping_pids.discard(proc.pid)
            current = spawn == self.spawns
            if current:
                self.last_exit = sig or f"exit {rc}"
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
            if alive:
                self._end(proc, timeout)  # type: ignore[arg-type]
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
        self.heartbeat_at, self.idle = beat
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

    def describe(self) -> dict[str, Any]:
        pid = self.pid
        info: dict[str, Any] = {
            "name": self.name,
            "plugin": self.cfg.plugin,
            "critical": self.cfg.critical,
            "enabled": self.cfg.enabled,
            "state": self.state,
            "pid": pid,
            "uptime_s": round(time.monotonic() - self.started_at, 1) if pid else 0.0,
            "restarts": self.restarts,
            "last_exit": self.last_exit,
            "health": self.health,
            **({"receive": self.receive} if self.receive else {}),
            **({"card": self.card} if self.card else {}),
            "heartbeat_age_s": round(time.monotonic() - self.heartbeat_at, 3)
            if self.heartbeat_at
            else None,
            "idle": self.idle,  # held to the default deadline meanwhile (exolink.liveness)
            "start_s": None if self.start_s is None else round(self.start_s, 2),
        }
        if pid:
            info.update(proc_usage(pid))
        return info


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


class Forked:
    """A node forked by the zygote and re-parented to this process: the part of Popen's
    interface the supervisor uses. One thread reaps it; everyone else reads the result."""

    def __init__(self, pid: int, stdout_fd: int | None) -> None:
        self.pid = pid
        self.stdout = os.fdopen(stdout_fd, "rb") if stdout_fd is not None else None
        self.returncode: int | None = None
        self._done = threading.Event()
        threading.Thread(target=self._reap, daemon=True, name=f"reap-{pid}").start()

    def _reap(self) -> None:
        try:
            _, status = os.waitpid(self.pid, 0)
            self.returncode = os.waitstatus_to_exitcode(status)
        except ChildProcessError:  # not re-parented to us: nothing to wait with
            self.returncode = -signal.SIGKILL
        self._done.set()

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self._done.wait(timeout):
            raise subprocess.TimeoutExpired(f"node pid {self.pid}", timeout or 0)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


PR_SET_CHILD_SUBREAPER = 36


def become_subreaper() -> None:
    """Orphans of this process' descendants (a forked node, whatever a node left behind)
    become its children instead of init's, so none escapes the stray sweep (kill_strays)."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER)")


class Zygote:
    """The supervisor's end of ``exolink.zygote``: one request at a time, a node pid back.

    The zygote is a fork of the supervisor made before it opens anything or starts a thread
    (Supervisor.start calls this first): the runtime both import is then one set of pages
    shared by the supervisor, the zygote and every node, and no second interpreter imports it
    again (seconds on the A8)."""

    def __init__(self) -> None:
        become_subreaper()  # the zygote's forks come to us
        self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.proc = Forked(_fork_zygote(self._sock, theirs), None)
        plain_priority(self.proc.pid)  # its forks must not inherit the supervisor's nice
        self._lock = threading.Lock()
        self.broken = False
        self._sock.settimeout(ZYGOTE_READY_S)  # its gc.collect of the forked heap, then ready
        try:
            ready = json.loads(self._sock.recv(4096) or b"{}").get("ready")
        except (OSError, ValueError) as exc:
            self._retire()
            raise OSError(f"zygote not ready: {exc}") from None
        if not ready:
            self._retire()
            raise OSError("zygote exited before it was ready")
        self._sock.settimeout(ZYGOTE_TIMEOUT_S)

    def spawn(self, name: str, config: str, env: dict[str, str], live_fds: list[int]) -> Forked:
        """A forked node; any failure retires the zygote for good (a late reply must never be
        taken as the answer to a later request) and the caller starts the node by exec."""
        if self.broken:
            raise RuntimeError("zygote retired after an earlier failure")
        r, w = os.pipe2(os.O_CLOEXEC)
        try:
            req = json.dumps({"name": name, "config": config, "env": env}).encode()
            with self._lock:
                socket.send_fds(self._sock, [req], [w, *live_fds])
                reply = json.loads(self._sock.recv(4096) or b"{}")
        except (OSError, ValueError) as exc:
            os.close(r)
            self._retire()
            raise RuntimeError(f"zygote: {exc}") from None
        finally:
            os.close(w)
        if "pid" not in reply:
            os.close(r)
            self._retire()
            raise RuntimeError(f"zygote: {reply.get('error', 'no reply')}")
        return Forked(int(reply["pid"]), r)

    def _retire(self) -> None:
        """At once, from the supervisor's loop: no waiting on a zygote that misbehaves."""
        self.broken = True
        self._sock.close()
        self.proc.kill()

    def close(self) -> None:
        self.broken = True
        self._sock.close()  # the zygote sees EOF and exits
        try:
            self.proc.wait(3)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _fork_zygote(ours: socket.socket, theirs: socket.socket) -> int:
    from exolink import zygote  # heavy: preloads the node runtime; the forked child's only

    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            ours.close()
            zygote.own_process_group()
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, signal.SIG_DFL)
            zygote.set_comm("exo-zygote")
            zygote.serve(theirs.fileno())
            code = 0
        finally:
            os._exit(code)
    theirs.close()
    return pid


ZYGOTE_TIMEOUT_S = 2.0  # a fork takes milliseconds; the supervisor's loop waits on this
ZYGOTE_READY_S = 120.0


def plain_priority(pid: int) -> None:
    """A node imports and configures at plain priority; its configured one comes with its first
    heartbeat. Under emulation a SCHED_FIFO node importing for seconds starved the supervisor
    until systemd's watchdog killed it; on the board's single core that would be the same."""
    with contextlib.suppress(OSError):  # already lower (a niced supervisor): leave it
        os.setpriority(os.PRIO_PROCESS, pid, max(0, os.getpriority(os.PRIO_PROCESS, 0)))


def _threads(pid: int) -> list[int]:
    """Scheduling is per thread in Linux; a running node has Zenoh's threads besides its own."""
    try:
        return sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return [pid]


def apply_priority(cfg: NodeConfig, pid: int) -> None:
    """Nice / SCHED_FIFO / affinity as configured, on every thread of the node; a clear warning
    where not permitted."""
    log = structlog.get_logger().bind(node=cfg.name)
    pr = cfg.priority
    tids = _threads(pid)
    try:
        for tid in tids:
            with contextlib.suppress(ProcessLookupError):  # ended meanwhile: skip it, not the rest
                if pr.fifo is not None:
                    os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(pr.fifo))
                elif pr.nice is not None:
                    os.setpriority(os.PRIO_PROCESS, tid, pr.nice)
    except PermissionError:
        log.warning(
            "priority_not_permitted",
            fifo=pr.fifo,
            nice=pr.nice,
            fix="run the supervisor with CAP_SYS_NICE (the systemd unit grants it)",
        )
    except OSError as exc:
        log.warning("priority_failed", error=str(exc))
    if pr.cpus:
        try:
            for tid in tids:
                with contextlib.suppress(ProcessLookupError):
                    os.sched_setaffinity(tid, pr.cpus)
        except OSError as exc:
            log.warning("affinity_failed", cpus=pr.cpus, error=str(exc))


_CLK = os.sysconf("SC_CLK_TCK")
_PAGE = os.sysconf("SC_PAGE_SIZE")


def proc_state(pid: int) -> str:
    """The kernel's word on a process (``State:`` and ``wchan``), for a stop that hangs."""
    try:
        with open(f"/proc/{pid}/status") as f:
            state = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("State:")), "?")
        with open(f"/proc/{pid}/wchan") as f:
            return f"{state}, wchan {f.read().strip() or '-'}"
    except OSError as exc:
        return f"gone ({exc.strerror})"


def children(pid: int) -> dict[int, tuple[str, str]]:
    """Every child of ``pid`` -> (state letter, comm), from each of its threads' list: a
    subreaper's orphans are re-parented to one of its threads."""
    out: dict[int, tuple[str, str]] = {}
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                kids = [int(c) for c in f.read().split()]
        except OSError:
            continue
        for kid in kids:
            try:
                with open(f"/proc/{kid}/stat") as f:
                    head, _, rest = f.read().rpartition(")")
                out[kid] = (rest.split()[0], head.partition("(")[2])
            except (OSError, IndexError):
                continue  # gone meanwhile
    return out


NODE_COMM = "exo-"  # a forked node's process name (exolink.zygote.set_comm)


def kill_strays(known: Callable[[], set[int]]) -> list[tuple[int, str]]:
    """Node processes among this process' children that no node counts as its own (and the
    zombies of such), killed and reaped: a node process the supervisor does not watch must not
    run. ``known`` is asked after the children are listed, so a node forked meanwhile is
    either not listed yet or already known."""
    kids = children(os.getpid())
    mine = known()
    strays = []
    for pid, (state, name) in kids.items():
        if pid in mine or not name.startswith(NODE_COMM):
            continue
        if state not in ("Z", "X"):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
            strays.append((pid, name))
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)
    return strays


def proc_usage(pid: int) -> dict[str, float]:
    """CPU seconds and resident memory from /proc (no psutil on a 512 MB board)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        with open(f"/proc/{pid}/statm") as f:
            rss_pages = int(f.read().split()[1])
    except (OSError, IndexError, ValueError):
        return {}
    cpu = (int(fields[11]) + int(fields[12])) / _CLK
    return {"cpu_s": round(cpu, 2), "rss_mb": round(rss_pages * _PAGE / 2**20, 1)}


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
