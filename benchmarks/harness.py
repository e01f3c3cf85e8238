"""The one harness of the tests and the benchmarks: a simulated appliance, its bus, its processes.

Both start ``exolink up`` on a multicast group and a Zenoh port of their own, listen to that bus
beside it and talk to it as a laptop would; this module is the only place that does. It lives in
``benchmarks`` because both import it from the repository's root without any path set-up:
``python -m benchmarks`` and ``python -m pytest`` (``make bench``, ``make test``) put the root on
``sys.path``, and pyproject's ``[tool.pytest.ini_options] pythonpath`` does for a bare
``pytest``. It is never in the wheel, so never on a card: the board proxy's guest gets the wheel
and standalone scripts (benchmarks/board/probe.py, benchmarks/estop.py), which import none of
this. The pytest fixtures over it are in tests/conftest.py.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import random
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

import can
import numpy as np
import structlog
import yaml
import zenoh

from exolink import messaging
from exolink.canbus import Frame, open_reader
from exolink.config import CanConfig, bundled, load
from exolink.control.holder import Holder

log = structlog.get_logger("harness")

EXOLINK = [sys.executable, "-m", "exolink.cli.main"]
# Multicast blocks (239.X.*.*): a benchmark run beside a test run never hears the tests' frames.
TEST_GROUPS, BENCH_GROUPS = 74, 75


def pct(values: list[float] | np.ndarray, scale: float = 1.0, digits: int = 3) -> dict[str, float]:
    """mean/p50/p99/max of values times scale (e.g. 1e3 for ms)."""
    a = np.asarray(values, dtype=float) * scale
    if a.size == 0:
        return {"n": 0}
    return {
        "n": int(a.size),
        "mean": round(float(a.mean()), digits),
        "p50": round(float(np.percentile(a, 50)), digits),
        "p99": round(float(np.percentile(a, 99)), digits),
        "max": round(float(a.max()), digits),
    }


def pss_mb(pid: int) -> float | None:
    """Proportional set size: shared pages split among the processes that map them, so the
    appliance's total is what it really takes of the board's 512 MB."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        return None
    return None


def cpu_s(pid: int) -> float:
    """On-CPU time of every thread, in ns precision (schedstat): tick-sampled utime/stime alias
    with a 100 Hz loop woken at the tick rate and misreport it by a factor of two either way."""
    total = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                total += int(f.read().split()[0])
        except OSError:
            continue
    return total / 1e9


def free_port() -> int:
    """A TCP port free on loopback now: each appliance listens on its own, so runs never meet."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def group(block: int = BENCH_GROUPS) -> str:
    """A multicast group of its own (the sim bus's channel), so concurrent or leftover traffic
    never mixes; ``block``: TEST_GROUPS or BENCH_GROUPS."""
    return f"239.{block}.{random.randint(1, 254)}.{random.randint(1, 254)}"


def motion_nodes(
    *extra: dict[str, Any],
    deadline_ms: int = 50,
    h2_timeout_ms: int | None = None,
    leased_deadline_ms: int = 200,
    params: dict[str, Any] | None = None,
    **manager: Any,
) -> list[dict[str, Any]]:
    """The simulated H2, its reader and the controller manager (the one writer of motion), then
    ``extra`` nodes. Defaults as shipped; a test not about stalls passes limits above a loaded
    machine's (``deadline_ms``: the manager's heartbeat deadline, ``h2_timeout_ms`` its H2
    silence; ``leased_deadline_ms``: its deadline while only the timer sends, never under
    ``deadline_ms``); ``params`` and ``manager`` (priority, restart, ...) go to the manager's
    entry."""
    params = dict(params or {})
    if h2_timeout_ms is not None:
        params["h2_timeout_ms"] = h2_timeout_ms
    controller_manager: dict[str, Any] = {
        "name": "controller_manager",
        "plugin": "controller_manager",
        "critical": True,
        "heartbeat_deadline_ms": deadline_ms,
        "leased_deadline_ms": max(deadline_ms, leased_deadline_ms),
        **manager,
        **({"params": params} if params else {}),
    }
    return [
        {"name": "simulator", "plugin": "simulator"},
        {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
        controller_manager,
        *extra,
    ]


def sim_config(
    path: Path, channel: str, /, nodes: list[dict[str, Any]] | None = None, **overrides: Any
) -> Path:
    """The bundled sim config at ``path`` on bus group ``channel`` and a free Zenoh port, with
    ``nodes`` and top-level ``overrides`` (a dict is merged into the section it names)."""
    data = yaml.safe_load(bundled("sim").read_text())
    data["can"]["channel"] = channel
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    if nodes is not None:
        data["nodes"] = [_as_hardware(n, data["nodes"]) for n in nodes]
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key].update(value)
        else:
            data[key] = value
    path.write_text(yaml.safe_dump(data))
    return path


def _as_hardware(node: dict[str, Any], bundled_nodes: list[dict[str, Any]]) -> dict[str, Any]:
    """A simulator given no priority runs at the bundled config's: it plays the hardware, whose
    10 ms stream does not pause for the host's load. At the default nice, the test host's other
    processes starved it past the watchdog's 100 ms H2 silence now and then: a trip no test asked
    for (CI, stop 51: a kill -9 test's re-armed motion never reached the joint)."""
    if node.get("plugin") != "simulator" or "priority" in node:
        return node
    shipped = next(n for n in bundled_nodes if n.get("plugin") == "simulator")
    return {**node, "priority": shipped["priority"]} if "priority" in shipped else node


RATE_RETRY_S = 0.1  # a request the appliance refused for its rate limit is asked again after this


def board_cycles_per_read() -> int:
    """The h2 reader's ``cycles_per_read`` in board.yaml: what the board runs."""
    nodes = yaml.safe_load(bundled("board").read_text())["nodes"]
    reader = next(n for n in nodes if n["plugin"] == "h2_reader")
    return int(reader.get("params", {}).get("cycles_per_read", 1))


def wait_for(
    pred: Callable[[], object],
    timeout: float = 10.0,
    step: float = 0.02,
    explain: Callable[[], object] | None = None,
) -> object:
    """``pred``'s first true value, polled: processes come up at their own pace. ``explain``:
    what the failure message adds (e.g. the watchdog's state), so a rare failure in CI says why."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(step)
    raise AssertionError(
        f"condition not met within {timeout} s" + (f": {explain()}" if explain else "")
    )


def connect(endpoint: str, timeout: float = 30.0, login: Path | None = None) -> zenoh.Session:
    """A client session to a process just spawned, with a laptop login file or none: it listens
    once its imports are done, which took longer than one connect attempt (3 s) on a host busy
    with other test runs."""
    end = time.monotonic() + timeout
    while True:
        try:
            return messaging.open_client_session(endpoint, str(login) if login else None)
        except messaging.Unreachable:
            if time.monotonic() > end:
                raise


class Receiver(Protocol):
    """What ``collect`` reads: a python-can bus or a DrainedBus."""

    def recv(self, timeout: float | None = None) -> Any: ...


def collect(bus: Receiver, seconds: float, ids: set[int] | None = None) -> list[Any]:
    """Every frame (of ``ids``, or all) ``bus`` receives for ``seconds``."""
    out = []
    end, until = time.monotonic() + seconds, time.time() + seconds
    while (left := end - time.monotonic()) > 0:
        m = bus.recv(timeout=left)
        if m is not None and (ids is None or m.arbitration_id in ids):
            out.append(m)
    if isinstance(bus, DrainedBus):  # the window's frames the listener had not handed over
        out += [m for m in bus.caught_up(until) if ids is None or m.arbitration_id in ids]
    return out


class FrameStream:
    """``frames`` sent every ``period_s`` on ``bus`` from a thread, as a device's periodic
    stream (pausable: ``sending``); ``close`` stops it and shuts the bus down."""

    def __init__(self, bus: can.BusABC, frames: list[can.Message], period_s: float = 0.01) -> None:
        self.bus, self.frames, self.period_s = bus, frames, period_s
        self.sending, self.stop = threading.Event(), threading.Event()
        self.sending.set()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        while not self.stop.wait(self.period_s):
            if self.sending.is_set():
                for f in self.frames:
                    self.bus.send(f)

    def close(self) -> None:
        self.stop.set()
        self.t.join()
        self.bus.shutdown()


class DrainedBus:
    """A listener on a sim-bus group, read continuously by a thread into a queue, with an exact
    loss count.

    At 600 frames/s a socket left unread while a test waits on a CLI call (or a benchmark loop
    is busy) overflows its kernel buffer and silently drops the newest frames: exactly the ones
    looked for. The thread reads through the appliance's own FrameReader (its large receive
    queue), and ``dropped`` is the kernel's count of what this listener lost, so a caller can
    tell "not on the bus" from "not seen"."""

    def __init__(self, channel: str) -> None:
        self.reader = open_reader(CanConfig(interface="udp_multicast", channel=channel))
        self.q: queue.Queue[Frame] = queue.Queue()
        self._stop = threading.Event()
        self._passed = threading.Event()  # set after each read's frames are queued
        self._t = threading.Thread(target=self._drain, daemon=True)
        self._t.start()

    def _drain(self) -> None:
        while not self._stop.is_set():
            for m in self.reader.read(0.05):
                self.q.put(m)
            self._passed.set()

    @property
    def dropped(self) -> int:
        """Frames the kernel dropped for this listener (its receive buffer full)."""
        return self.reader.dropped or 0

    def recv(self, timeout: float | None = None) -> Frame | None:
        """The next frame, or None after ``timeout``: a can.BusABC's recv, for ``collect``."""
        try:
            return self.q.get(timeout=timeout)
        except queue.Empty:
            return None

    def caught_up(self, until: float) -> Iterator[Frame]:
        """The frames received by wall time ``until`` (their kernel stamps) that the reading
        thread had not handed over yet, after one more read by it: a host stalled for longer
        than a window (CI's did) wakes the waiting thread first, and frames already received
        were otherwise missed as if never sent. Taken one at a time: a later frame, and what a
        caller stops before, stays queued."""
        self._passed.clear()
        self._passed.wait(1.0)
        held = self.q.queue  # only this thread takes from it
        while held and held[0].timestamp <= until:
            yield self.q.get_nowait()

    def wait_for(self, pred: Callable[[Frame], bool], timeout: float) -> Frame | None:
        """The first frame from now on that ``pred`` accepts, or None after ``timeout``."""
        end, until = time.monotonic() + timeout, time.time() + timeout
        while (left := end - time.monotonic()) > 0:
            m = self.recv(timeout=left)
            if m is not None and pred(m):
                return m
        return next((m for m in self.caught_up(until) if pred(m)), None)

    def collect(self, seconds: float) -> list[Frame]:
        """Every frame received for ``seconds``."""
        return collect(self, seconds)

    def clear(self) -> None:
        """Forget what was received so far: the next frame is one sent after this."""
        self.q.queue.clear()

    def send(self, msg: can.Message) -> None:
        """Put a frame on the bus, as the H2 or a board would."""
        self.reader.bus.send(msg)

    def close(self) -> None:
        """The thread stopped, then the socket closed (never read from a closed one)."""
        self._stop.set()
        self._t.join(1)
        self.reader.close()


class Proc:
    """A real exolink process whose output is kept in a file for the failure message."""

    def __init__(self, args: list[str], log: Path, unbuffered: bool = True) -> None:
        self.log = log
        self._f = log.open("wb")
        env = {**os.environ, "EXOLINK_LOG_JSON": "1"}
        if unbuffered:  # every line in the file as it is written, for a failure's message
            env["PYTHONUNBUFFERED"] = "1"
        self.p = subprocess.Popen(
            [*EXOLINK, *args], stdout=self._f, stderr=subprocess.STDOUT, env=env
        )

    @property
    def pid(self) -> int:
        """The process's pid, to read its /proc figures or signal it."""
        return self.p.pid

    def stop(self, timeout: float = 10.0) -> int:
        """Terminated, killed if it will not end within ``timeout``; its exit code."""
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self._f.close()
        return self.p.returncode

    def output(self) -> str:
        """What it wrote so far, for an assertion's message."""
        return self.log.read_text(errors="replace")


class Spawner:
    """Starts exolink processes (``spawn("up", "-c", cfg, name="up")``) with their logs in one
    folder, and ends them all: ``cleanups`` (holders, sessions) first, then the processes,
    newest first, so nothing is left running behind a failed test or benchmark."""

    def __init__(self, logs: Path, unbuffered: bool = True) -> None:
        self.logs, self.unbuffered = logs, unbuffered
        self.procs: list[Proc] = []
        self.cleanups: list[Callable[[], None]] = []

    def __call__(self, *args: str, name: str = "proc") -> Proc:
        p = Proc(list(args), self.logs / f"{name}-{len(self.procs)}.log", self.unbuffered)
        self.procs.append(p)
        return p

    def close(self) -> None:
        for c in reversed(self.cleanups):
            with contextlib.suppress(Exception):
                c()
        self.cleanups.clear()
        for p in reversed(self.procs):
            p.stop()


class Appliance:
    """``exolink up -c cfg_path`` started by ``spawn``, ready once its status answers and (with
    ``wait_nodes``) every node beats; then talked to as a laptop: the CLI (``cli``), management
    requests over one session (``call``), arming and holding motion. ``login``: the laptop
    login file of a board with logins; ``what``: who holds motion, as its holder shows it;
    ``sim``: ``exolink up --sim`` (``make sim``: the device's simulator added).
    ``sim`` starts one on a config and group of its own."""

    def __init__(
        self,
        cfg_path: Path,
        spawn: Spawner,
        *,
        wait_nodes: bool = True,
        login: Path | None = None,
        what: str = "test",
        sim: bool = False,
    ) -> None:
        self.cfg = load(cfg_path, check=())  # its nodes' plugins: the supervisor's to check
        self.at = messaging.local_endpoint(self.cfg.zenoh)
        self.group, self.dir = self.cfg.can.channel, Path(cfg_path).parent
        self.login, self.what = login, what
        self.user = messaging.client_login(str(login) if login else None)
        self._spawn = spawn
        self._session: zenoh.Session | None = None
        self._holder: Holder | None = None
        self.proc = spawn("up", *(["--sim"] if sim else []), "-c", str(cfg_path), name="up")
        wait_for(lambda: self._status() is not None, timeout=20, step=0.2)
        if wait_nodes:
            wait_for(self._beating, timeout=20, step=0.2)

    @classmethod
    def sim(cls, nodes: list[dict[str, Any]] | None = None, **overrides: Any) -> Appliance:
        """The bundled sim config with ``nodes`` and ``overrides`` in a temporary folder (the
        config and up-0.log), on a group and port of its own; ``close()`` ends it."""
        folder = Path(tempfile.mkdtemp(prefix="exolink-bench-"))
        spawn = Spawner(folder, unbuffered=False)
        try:
            cfg = sim_config(folder / "appliance.yaml", group(), nodes, **overrides)
            return cls(cfg, spawn, what="benchmark")
        except BaseException:  # never leave an appliance running behind a failed benchmark
            log.error("appliance did not come up", folder=str(folder))
            spawn.close()
            raise

    def _status(self) -> dict[str, Any] | None:
        """The supervisor's status over a session opened for it alone, or None while it is
        still starting (unreachable, or not ok yet)."""
        try:
            s = connect(self.at, 0, self.login)
        except messaging.Unreachable:
            return None
        try:
            st = messaging.request(s, self._key("status"), {}, 1, self.user)
        except messaging.Unreachable:
            return None
        finally:
            s.close()
        return st if st.get("ok") else None

    def _beating(self) -> bool:
        """Every node has beaten once (a node beats after its configure())."""
        nodes = (self._status() or {}).get("nodes")
        return bool(nodes) and all(n["heartbeat_age_s"] is not None for n in nodes)

    def _key(self, path: str) -> str:
        """The management key of ``path`` on this appliance's device."""
        return messaging.mgmt_key(self.cfg.device, path)

    @property
    def session(self) -> zenoh.Session:
        """One client session for ``call``, opened at the first, closed with the appliance."""
        if self._session is None:
            self._session = connect(self.at, login=self.login)
            self._spawn.cleanups.append(self._session.close)
        return self._session

    def call(
        self, path: str, body: dict[str, Any] | None = None, timeout: float = 3.0
    ) -> dict[str, Any]:
        """A management request (``status``, ``watchdog``, ``controllers``, ...) as the login;
        patient with the appliance's rate limit as the laptop's clients are (a test polling
        ``node()`` every 20 ms asks 50 times a second, over a login's 20)."""
        end = time.monotonic() + timeout
        while True:
            reply = messaging.request(self.session, self._key(path), body or {}, timeout, self.user)
            why = str(reply.get("error", ""))
            if reply.get("ok", True) or not why.startswith(("too many requests", "busy")):
                return reply
            if time.monotonic() > end:
                return reply
            time.sleep(RATE_RETRY_S)

    def cli(self, *args: str, login: Path | None = None) -> subprocess.CompletedProcess[str]:
        """``exolink ARGS --at`` this appliance, as ``login`` or the appliance's login."""
        who = login or self.login
        opts = ["--zenoh-config", str(who)] if who else []
        return subprocess.run(
            # 10 s, not the CLI's 3: the connect waits that long too (a --timeout above 3 s
            # does), and on this 2-core host with chromium and an appliance running, one
            # connect of the dashboard test timed out at 3 s twice in ~8 full-suite runs
            [*EXOLINK, *args, "--at", self.at, "--timeout", "10", *opts],
            capture_output=True,
            text=True,
            timeout=30,
        )

    def status(self) -> dict[str, Any]:
        """``exolink status --json``: the supervisor's status with the CLI's additions (the
        controllers, the clock's offset)."""
        r = self.cli("status", "--json")
        assert r.returncode == 0, r.stderr
        result: dict[str, Any] = json.loads(r.stdout)
        return result

    def node(self, name: str) -> dict[str, Any]:
        """One node's entry of the supervisor's status."""
        return next(n for n in self.call("status")["nodes"] if n["name"] == name)

    def arm(self) -> None:
        """Armed as the appliance's login (``arm_as``)."""
        self.arm_as(None)

    def arm_as(self, login: Path | None) -> None:
        """``exolink arm`` until it answers (a watchdog still in its start grace refuses)."""
        r = wait_for(lambda: (x := self.cli("arm", login=login)).returncode == 0 and x, timeout=10)
        assert "armed" in r.stdout  # type: ignore[union-attr]

    def hold(self, login: Path | None = None, take_over: bool = False) -> Holder:
        """Motion held from here, as `exolink hold` holds it (renewed from a thread until the
        appliance ends): nothing moves a joint without a holder. Held once per appliance."""
        held = self._holder
        if held is not None and held.holding and not take_over:
            return held
        who = login or self.login
        session = connect(self.at, login=who)
        user = messaging.client_login(str(who) if who else None)
        key = self._key("controllers")

        def call(body: dict[str, Any]) -> dict[str, Any]:
            return messaging.request(session, key, body, 10.0, user)

        holder = Holder(call, self.what)
        holder.acquire(take_over)
        self._spawn.cleanups += [session.close, holder.release]
        self._holder = holder
        return holder

    def arm_and_hold(self) -> Holder:
        """Armed, and motion held: what moving a joint needs."""
        self.arm()
        return self.hold()

    def close(self) -> None:
        """Motion released, sessions closed, the supervisor and its nodes ended."""
        self._spawn.close()
