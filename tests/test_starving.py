"""Starved or hung (exolink.supervisor.starving): real processes, a real scheduler. A node's loop
kept waiting for the CPU by a busy process on its CPU (at a far higher weight) is starved; one
asleep or stopped is not, and a node without ``starved_deadline_ms`` (the motion nodes) is judged
at its deadline either way."""

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

from exolink.supervisor import starving

SPIN = "import os\nos.nice({nice})\nwhile True: pass\n"
# The main thread asleep in a pipe read (the recorder in C76) while a thread of its own spins
# ({spin}: or sleeps), from a second after: the main thread in its read by then, not waiting for
# the GIL the spinner holds (which, at nice 19 beside a hog, it took more than 20 s to get).
WAIT_ON_OWN = (
    "import os, threading, time\nos.nice({nice})\n"
    "threading.Thread(target=lambda: time.sleep(1) or {spin}, daemon=True).start()\n"
    "r, w = os.pipe()\nos.read(r, 1)\n"
)


def _cpu() -> int:
    return max(os.sched_getaffinity(0))


def _spinner(nice: int, cpu: int, code: str = SPIN) -> subprocess.Popen[bytes]:
    proc = subprocess.Popen([sys.executable, "-c", code.format(nice=nice)])
    os.sched_setaffinity(proc.pid, {cpu})
    return proc


@contextlib.contextmanager
def starved_process(code: str = SPIN) -> Iterator[subprocess.Popen[bytes]]:
    """A busy loop (``code``) at nice 19 and another at nice 0 on one CPU: the first gets
    ~1/70 of it (CFS weights 15 and 1024) and waits on the run queue the rest of the time."""
    cpu = _cpu()
    victim, hog = _spinner(19, cpu, code), _spinner(0, cpu)
    try:
        time.sleep(0.2)  # both imported and spinning
        yield victim
    finally:
        for p in (victim, hog):
            p.kill()
            p.wait()


def _shares(pid: int, span_s: float = 0.4) -> tuple[float, float] | None:
    mark = starving.read(pid, time.monotonic())
    time.sleep(span_s)
    return starving.starved(mark, starving.read(pid, time.monotonic(), states=True))


def test_a_loop_waiting_for_the_cpu_is_starved_one_asleep_or_stopped_is_not() -> None:
    if starving.read(os.getpid(), 0.0) is None:
        pytest.skip("this kernel has no /proc/<pid>/schedstat")
    with starved_process() as victim:
        shares = _shares(victim.pid)
        assert shares is not None and shares[1] < 0.1, shares  # kept off the CPU: starved
        os.kill(victim.pid, signal.SIGSTOP)  # stopped (once it runs to take the signal)
        end = time.monotonic() + 10
        while (st := starving.read(victim.pid, 0.0, True)) is not None and st.state != "T":
            assert time.monotonic() < end, st
            time.sleep(0.02)
        assert _shares(victim.pid) is None
    asleep = subprocess.Popen(["sleep", "60"])
    try:
        assert _shares(asleep.pid) is None
    finally:
        asleep.kill()
        asleep.wait()
    assert starving.read(asleep.pid, 0.0) is None  # gone: not starved
    assert starving.starved(None, starving.read(os.getpid(), 0.0)) is None  # no mark


def _main_asleep(pid: int) -> None:
    """Until ``pid``'s main thread sleeps in its pipe read for good (not for the GIL on the
    way there, which it would leave)."""
    end = time.monotonic() + 20
    while "pipe_read" not in Path(f"/proc/{pid}/wchan").read_text():
        assert time.monotonic() < end, Path(f"/proc/{pid}/wchan").read_text()
        time.sleep(0.05)


def test_a_loop_asleep_on_a_thread_of_its_own_that_waits_for_the_cpu_is_starved() -> None:
    """C76: nodes killed with their loop asleep in a futex or a pipe read while the core was
    full. A main thread asleep in a read while a thread of its process is runnable and kept
    waiting is starved; asleep while every thread of it sleeps, it is not."""
    if starving.read(os.getpid(), 0.0) is None:
        pytest.skip("this kernel has no /proc/<pid>/schedstat")
    with starved_process(WAIT_ON_OWN.replace("{spin}", "any(iter(int, 1))")) as victim:
        _main_asleep(victim.pid)
        time.sleep(1.2)  # its thread spinning (from a second after its start)
        mark = starving.read(victim.pid, time.monotonic())
        time.sleep(0.4)
        now = starving.read(victim.pid, time.monotonic(), states=True)
        assert now is not None and now.state == "S" and now.other_runnable, now
        shares = starving.starved(mark, now)
        assert shares is not None and shares[1] < 0.1, shares  # kept off the CPU: starved
        assert starving.starved(mark, starving.read(victim.pid, time.monotonic())) is None
    with starved_process(WAIT_ON_OWN.replace("{spin}", "time.sleep(60)")) as victim:
        _main_asleep(victim.pid)
        mark = starving.read(victim.pid, time.monotonic())
        time.sleep(0.4)
        now = starving.read(victim.pid, time.monotonic(), states=True)
        assert now is not None and now.state == "S" and not now.other_runnable, now
        assert starving.starved(mark, now) is None  # every thread asleep: blocked, not starved


def _reader_node(sup: Any, proc: subprocess.Popen[bytes]) -> tuple[Any, Any]:
    """The board config's h2 reader (deadline 500 ms, starved_deadline_ms 1500) as ``proc``."""
    from exolink import liveness
    from exolink.supervisor.processes import NodeProcess

    node = NodeProcess(sup.cfg.node("h2_reader"), "", lambda _e: None, lambda _n, _l: None)
    node.channel = liveness.Channel()
    node.proc = proc
    node.state, node.heartbeat_at = "running", time.monotonic()
    sup.nodes[node.name] = node
    return node, liveness.Beater(node.channel.child_fd)


def _until(t: float) -> float:
    time.sleep(max(0.0, t - time.monotonic()))
    return time.monotonic()


def test_a_starved_reader_is_judged_again_up_to_its_limit_then_tripped() -> None:
    """Board config: silent past its 500 ms while it waits for the CPU, the h2 reader is not
    killed (a re-import on a full core) and the watchdog does not trip; silent past its
    1500 ms, it is, and the trip says it was starved."""
    from tests.test_supervisor_parts import _supervisor_recording_trips

    if starving.read(os.getpid(), 0.0) is None:
        pytest.skip("this kernel has no /proc/<pid>/schedstat")
    sup, trips = _supervisor_recording_trips()
    with starved_process() as victim:
        node, beater = _reader_node(sup, victim)
        try:
            beater.beat()
            sup._check_nodes(time.monotonic())  # on time: the scheduler's counts marked
            hb = node.heartbeat_at
            assert node.sched_mark is not None and node.starved == 0
            sup._check_nodes(_until(hb + 0.6))
            assert trips == [] and node.state == "running" and node.starved == 1
            assert hb + 0.6 < node.due_at <= hb + 1.5  # looked at again before its limit
            sup._check_nodes(_until(hb + 1.0))  # the same silence: counted once
            assert trips == [] and node.starved == 1
            sup._check_nodes(_until(hb + 1.55))
            assert len(trips) == 1 and "starved past its limit" in trips[0], trips
            assert trips[0].startswith("h2_reader: no heartbeat for") and node.state == "killed"
        finally:
            node.kill()
            node.channel.close()


def test_an_asleep_reader_and_a_starved_manager_are_judged_at_their_deadlines() -> None:
    """Not starved (asleep: blocked, deadlocked), the reader trips at its 500 ms; the
    controller manager has no starved deadline (it moves the joints): starved, it trips at its
    own 50 ms."""
    from tests.test_supervisor_parts import _supervisor_recording_trips

    sup, trips = _supervisor_recording_trips()
    node, beater = _reader_node(sup, subprocess.Popen(["sleep", "60"]))
    try:
        beater.beat()
        sup._check_nodes(time.monotonic())
        sup._check_nodes(_until(node.heartbeat_at + 0.55))
        assert len(trips) == 1 and trips[0].endswith("(deadline 500 ms)") and node.starved == 0
        assert node.state == "killed"
    finally:
        node.kill()
        node.channel.close()
    assert sup.cfg.starved_deadline_s(sup.cfg.node("controller_manager")) is None
    sup, trips = _supervisor_recording_trips()
    with starved_process() as victim:
        from exolink import liveness
        from exolink.supervisor.processes import NodeProcess

        mgr = NodeProcess(
            sup.cfg.node("controller_manager"), "", lambda _e: None, lambda _n, _l: None
        )
        mgr.channel = liveness.Channel()
        mgr.proc, mgr.state, mgr.heartbeat_at = victim, "running", time.monotonic()
        sup.nodes[mgr.name] = mgr
        try:
            liveness.Beater(mgr.channel.child_fd).beat()
            sup._check_nodes(time.monotonic())
            sup._check_nodes(_until(mgr.heartbeat_at + 0.06))
            assert len(trips) == 1 and trips[0].endswith("(deadline 50 ms)"), trips
        finally:
            mgr.kill()
            mgr.channel.close()


def test_a_motion_node_cannot_be_given_a_starved_deadline() -> None:
    from exolink.config import ConfigError, bundled, parse

    text = bundled("board").read_text()
    bad = text.replace(
        "    leased_deadline_ms: 200", "    starved_deadline_ms: 1000\n    leased_deadline_ms: 200"
    )
    assert bad != text
    with pytest.raises(ConfigError, match="starved_deadline_ms: node 'controller_manager' has a"):
        parse(bad, "board.yaml")


def test_the_rule_runnable_and_kept_off_the_cpu_or_waiting() -> None:
    """The kernel adds a wait when the thread gets the CPU: a loop kept off it since before
    the mark shows no wait yet, only no run (C74's recorder); one that spun on a free CPU ran
    the whole span (hung); one asleep is not runnable."""
    from exolink.supervisor.starving import Sched

    mark = Sched(0.0, "S", 5_000_000, 7_000_000)
    off = Sched(1.0, "R", 5_000_000, 7_000_000)  # neither ran nor had its wait added
    assert starving.starved(mark, off) == (0.0, 0.0)
    spun = Sched(1.0, "R", 1_005_000_000, 7_000_000)
    assert starving.starved(mark, spun) is None
    shared = Sched(1.0, "R", 605_000_000, 407_000_000)  # ran 60 %, waited 40 %: starved
    assert starving.starved(mark, shared) == pytest.approx((0.4, 0.6))
    assert starving.starved(mark, Sched(1.0, "S", 5_000_000, 7_000_000)) is None
    assert starving.starved(mark, Sched(0.01, "R", 5_000_000, 7_000_000)) is None  # too short


def test_the_rule_asleep_on_a_runnable_thread_of_its_own() -> None:
    """The process's threads' waits added up, a thread begun since the mark with all of its
    own; no runnable thread, or too little wait, is not starved; the ran share is not used."""
    from exolink.supervisor.starving import Sched

    mark = Sched(0.0, "R", 0, 0, {11: (10, 100_000_000), 12: (0, 0)})
    waits = {11: (10, 300_000_000), 13: (0, 60_000_000)}  # 12 ended, 13 began since the mark
    now = Sched(1.0, "S", 0, 0, waits, other_runnable=True)
    assert starving.starved(mark, now) == pytest.approx((0.26, 0.0))
    little = Sched(1.0, "S", 0, 0, {11: (10, 200_000_000)}, other_runnable=True)
    assert starving.starved(mark, little) is None  # waited 10 %, ran 0 %: not the ran rule
    assert starving.starved(mark, Sched(1.0, "S", 0, 0, waits)) is None  # none runnable
    assert starving.starved(mark, Sched(1.0, "D", 0, 0, waits, other_runnable=True)) is None
