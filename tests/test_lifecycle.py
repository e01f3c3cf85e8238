"""A node's lifecycle under restarts, stops and starts racing each other and the reaper: after
each, the supervisor's word (state, pid) is the truth about the processes it runs.

Real supervisor, real node processes; the processes are counted from /proc, never asked for."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from benchmarks.harness import Appliance, connect, wait_for
from exolink import messaging

CRITICAL = ["h2_reader", "pattern_player", "controller_manager"]
NODES = [
    {"name": "simulator", "plugin": "simulator"},
    {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
    {"name": "pattern_player", "plugin": "pattern_player", "critical": True},
    {
        "name": "controller_manager",
        "plugin": "controller_manager",
        "critical": True,
        "heartbeat_deadline_ms": 50,
    },
]
ROUNDS = 3  # of every phase, per critical node


def children(pid: int) -> list[int]:
    """The live children of ``pid`` (of any of its threads: orphans go to the subreaper's)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return [c for c in out if _state(c) not in ("Z", "X", "")]


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return ""


def comm(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def processes_of(supervisor: int, node: str) -> list[int]:
    return [c for c in children(supervisor) if comm(c) == f"exo-{node}"[:15]]


class Api:
    """The management API over one client session (a CLI process per call would take the
    test minutes)."""

    def __init__(self, app: Appliance) -> None:
        self.session = connect(app.at)
        self.device = app.cfg.device

    def call(self, *path: str, **body: Any) -> dict[str, Any]:
        """One request; one the appliance's rate limit refused (this test asks faster than any
        operator: 20 a second per login) is asked again a little later."""
        key = messaging.mgmt_key(self.device, *path)
        while True:
            reply = messaging.request(self.session, key, body, 10.0)
            if "too many requests" not in str(reply.get("error", "")):
                return reply
            time.sleep(0.05)

    def node(self, name: str) -> dict[str, Any]:
        return next(n for n in self.call("nodes")["nodes"] if n["name"] == name)

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def api(write_config, spawn) -> Iterator[tuple[Appliance, Api]]:  # type: ignore[no-untyped-def]
    app = Appliance(write_config(nodes=NODES), spawn)
    a = Api(app)
    yield app, a
    a.close()


def up(a: Api, name: str) -> dict[str, Any]:
    """The node running and beating (a restart leaves it starting for a while)."""
    seen: list[dict[str, Any]] = []

    def beating() -> dict[str, Any] | None:
        seen[:] = [n := a.node(name)]
        return n if n["state"] == "running" and n["heartbeat_age_s"] is not None else None

    try:
        return wait_for(beating, timeout=30)  # type: ignore[return-value]
    except AssertionError:
        raise AssertionError(f"{name} not running and beating within 30 s: {seen}") from None


def check_one_watched(a: Api, supervisor: int, name: str) -> None:
    """Running, its pid alive and the only process of that node, and arming possible."""
    n = up(a, name)
    procs = processes_of(supervisor, name)
    assert procs == [n["pid"]], (name, n, procs)
    reply = wait_for(lambda: (r := a.call("watchdog", action="arm"))["ok"] and r, timeout=20)
    assert reply["state"] == "armed", reply  # type: ignore[index]
    assert a.call("watchdog", action="disarm")["ok"]


@contextlib.contextmanager
def cpu_hogs(n: int = 2) -> Iterator[None]:
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for h in hogs:
            h.kill()
            h.wait()


def restart(a: Api, name: str) -> dict[str, Any]:
    reply = a.call("control", action="restart", node=name)
    assert reply["ok"], reply
    return reply


def test_restarts_racing_start_grace_first_beat_load_and_the_reaper_leave_one_watched_process(
    api,  # type: ignore[no-untyped-def]
) -> None:
    app, a = api
    supervisor = a.call("status")["pid"]
    made = 0
    for name in CRITICAL:
        for _ in range(ROUNDS):
            # during start grace: a second restart before the first spawn's first beat
            restart(a, name)
            restart(a, name)
            made += 2
            check_one_watched(a, supervisor, name)
            # at its first heartbeat
            restart(a, name)
            wait_for(
                lambda n=name: a.node(n)["heartbeat_age_s"] is not None, timeout=30, step=0.005
            )
            restart(a, name)
            made += 2
            check_one_watched(a, supervisor, name)
            # at rest
            time.sleep(0.5)
            restart(a, name)
            made += 1
            check_one_watched(a, supervisor, name)
            # under load
            with cpu_hogs():
                restart(a, name)
                made += 1
                check_one_watched(a, supervisor, name)
            # racing the reaper: its crash and the restart handled at once
            os.kill(a.node(name)["pid"], signal.SIGKILL)
            restart(a, name)
            made += 1
            check_one_watched(a, supervisor, name)
    assert made == len(CRITICAL) * ROUNDS * 7
    assert app.proc.p.poll() is None, app.proc.output()


def test_stop_and_start_racing_the_reaper_leave_no_unwatched_process(api) -> None:  # type: ignore[no-untyped-def]
    _app, a = api
    supervisor = a.call("status")["pid"]
    for name in CRITICAL:
        for kill_first in (False, True, False):
            if kill_first:  # the crash's exit report races the stop
                os.kill(a.node(name)["pid"], signal.SIGKILL)
            reply = a.call("control", action="stop", node=name)
            assert reply["ok"] and reply["node"]["state"] == "stopped", reply
            wait_for(lambda n=name: processes_of(supervisor, n) == [], timeout=10)
            assert a.node(name)["state"] == "stopped" and a.node(name)["pid"] is None
            arm = a.call("watchdog", action="arm")
            assert not arm["ok"] and f"critical node {name} is stopped" in arm["error"], arm
            assert a.call("control", action="start", node=name)["ok"]
            check_one_watched(a, supervisor, name)


def _named_child(name: str) -> subprocess.Popen[bytes]:
    """A real process named ``name`` (what top shows), as a forked node is."""
    code = (
        "import ctypes, time; "
        f"ctypes.CDLL(None).prctl(15, {name.encode()!r}, 0, 0, 0); "
        "print('ready', flush=True); time.sleep(60)"
    )
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert p.stdout is not None and p.stdout.readline() == b"ready\n"
    return p


@pytest.mark.parametrize("leader_only", [False, True])
def test_node_processes_nobody_counts_are_killed_and_named(leader_only: bool) -> None:
    """Both sweeps: every thread's children, and the main thread's alone (the 5 s one; a
    forked node's parent is the main thread, where the kernel re-parents a subreaper's
    orphans, and these are the main thread's own)."""
    from exolink.supervisor.osproc import kill_strays

    stray, known, other = _named_child("exo-stray"), _named_child("exo-known"), _named_child("x")
    try:
        killed = kill_strays(lambda: {known.pid}, leader_only)
        assert killed == [(stray.pid, "exo-stray")]
        # Ended within 5 s of its 60 s sleep (wait raises otherwise): killed. kill_strays reaps
        # what died at once, and then Popen finds no child to wait for and says 0 (ECHILD).
        assert stray.wait(5) in (-signal.SIGKILL, 0)
        assert known.poll() is None and other.poll() is None
    finally:
        for p in (stray, known, other):
            p.kill()
            p.wait()


def test_a_child_of_another_thread_waits_for_the_full_sweep() -> None:
    """What the main thread's sweep does not see (a child of a worker thread that still
    runs) the full one, every STRAY_FULL_SWEEP_S, does. (Once that thread ends, the kernel
    gives its children to the main thread.)"""
    import threading

    from exolink.supervisor.osproc import kill_strays

    box: list[subprocess.Popen[bytes]] = []
    started, done = threading.Event(), threading.Event()

    def worker() -> None:
        box.append(_named_child("exo-thr"))
        started.set()
        done.wait(30)

    t = threading.Thread(target=worker)
    t.start()
    assert started.wait(30)
    stray = box[0]
    try:
        assert kill_strays(set, leader_only=True) == []
        assert stray.poll() is None
        assert kill_strays(set) == [(stray.pid, "exo-thr")]
    finally:
        done.set()
        t.join()
        stray.kill()
        stray.wait()


def test_a_nodes_orphan_is_killed_by_the_supervisor(write_config, spawn, in_node) -> None:  # type: ignore[no-untyped-def]
    """A child a node left behind (re-parented to the supervisor, a subreaper) runs unwatched:
    the supervisor's sweep kills it and says so."""
    in_node(
        "pattern_player",
        """
import ctypes, os, time
if os.fork() == 0:
    ctypes.CDLL(None).prctl(15, b"exo-orphan", 0, 0, 0)
    time.sleep(120)
    os._exit(0)
""",
    )
    app = Appliance(write_config(nodes=NODES), spawn)
    supervisor = app.status()["pid"]
    os.kill(app.node("pattern_player")["pid"], signal.SIGKILL)  # its child is the supervisor's now
    wait_for(lambda: "stray_node_killed" in app.proc.output(), timeout=20)
    line = next(ln for ln in app.proc.output().splitlines() if "stray_node_killed" in ln)
    assert '"process": "exo-orphan"' in line, line

    def orphans() -> list[int]:
        return [p for p, (_s, n) in _kids(supervisor).items() if n == "exo-orphan"]

    # the line is logged as the SIGKILL is sent; the kernel ends the process a moment later (a
    # busy CI host once still listed it running right after the line)
    wait_for(lambda: not orphans(), timeout=5, explain=orphans)


def _kids(pid: int) -> dict[int, tuple[str, str]]:
    from exolink.supervisor.osproc import children

    return {k: v for k, v in children(pid).items() if v[0] not in ("Z", "X")}
