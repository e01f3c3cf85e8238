"""The node runtime in-process on a real (peer, no network) Zenoh session: when a node's loop
counts as stalled, and what the journal says about it."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import can
import msgspec
import pytest
import zenoh
from structlog.testing import capture_logs

from exolink import config, messaging
from exolink.node import Node
from exolink.runtime import NodeRunner


class SlowStart(Node):
    """Configure longer than stall_s (an A8 core opening buses), then a loop that beats."""

    def configure(self) -> None:
        time.sleep(self.stall_s * 2)

    def run(self, stop: threading.Event) -> None:
        self.healthy_when_run_started = self.healthy()
        while not stop.wait(0.05):
            self.beat()


class StallsOnce(Node):
    """A loop that goes quiet for 0.8 s once, then beats again."""

    def run(self, stop: threading.Event) -> None:
        self.beat()
        time.sleep(0.8)
        while not stop.wait(0.05):
            self.beat()


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    cfg = config.parse(config.bundled("sim").read_text())
    s = zenoh.open(messaging.session_config(cfg.zenoh))
    yield s
    s.close()


def run_for(cls: type[Node], session: zenoh.Session, seconds: float) -> tuple[Node, list[dict]]:
    cfg = config.parse(config.bundled("sim").read_text())
    with capture_logs() as logs:
        runner = NodeRunner(cls, cfg, "h2_reader", session)  # any configured name
        t = threading.Thread(target=runner.run)
        t.start()
        time.sleep(seconds)
        runner.stop.set()
        t.join(5)
    return runner.node, [e for e in logs if e["event"] == "loop_stalled"]


def test_slow_configure_is_not_a_stalled_loop(session: zenoh.Session) -> None:
    node, events = run_for(SlowStart, session, 1.5)
    assert node.healthy_when_run_started  # type: ignore[attr-defined]
    assert events == []


def test_a_stalled_loop_is_logged_with_its_length(session: zenoh.Session) -> None:
    _, events = run_for(StallsOnce, session, 1.5)
    assert [e["event"] for e in events] == ["loop_stalled"]  # when it beat again
    assert events[0]["stalled_s"] >= 0.8
    assert events[0]["limit_s"] == StallsOnce.stall_s


class StallsOften(Node):
    """A loop on a saturated core: quiet past stall_s again and again."""

    stall_s = 0.1

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self.beat()
            time.sleep(0.25)


def test_repeated_stalls_are_logged_once_then_counted(session: zenoh.Session) -> None:
    _, events = run_for(StallsOften, session, 2.0)
    assert [e["event"] for e in events] == ["loop_stalled"]
    assert events[0]["stalls_not_logged"] == 0


class BeatsOnce(Node):
    """A loop that beat once and may stay quiet for long (stall_s 10 s): only the runtime's
    heartbeat thread vouches for it, where its deadline is shorter than that."""

    stall_s = 10.0

    def run(self, stop: threading.Event) -> None:
        self.beat()
        stop.wait()


class HangsAfterBeating(Node):
    """A loop that beats for a while, then hangs with its process (and heartbeat thread) alive:
    a deadlock, not a SIGSTOP. Its stall limit is under its deadline."""

    stall_s = 0.2

    def run(self, stop: threading.Event) -> None:
        for _ in range(10):
            self.beat()
            time.sleep(0.02)
        self.hung_at = self.last_beat
        stop.wait()


def beats_in(
    cls: type[Node], session: zenoh.Session, deadline_ms: int, secs: float
) -> tuple[Node, list[float]]:
    """The beat times the supervisor's pipe got from a node run for ``secs``."""
    from exolink.liveness import _RECORD, Beater, Channel

    cfg = config.parse(config.bundled("sim").read_text())
    cfg = msgspec.structs.replace(
        cfg, watchdog=msgspec.structs.replace(cfg.watchdog, heartbeat_deadline_ms=deadline_ms)
    )
    channel = Channel()
    runner = NodeRunner(cls, cfg, "h2_reader", session)  # no deadline of its own
    runner.node.liveness = Beater(channel.child_fd)
    t = threading.Thread(target=runner.run)
    t.start()
    try:
        time.sleep(secs)
        data = os.read(channel.fileno(), 65536)
    finally:
        runner.stop.set()
        t.join(5)
        channel.close()
    return runner.node, [r[0] for r in _RECORD.iter_unpack(data)]


@pytest.mark.parametrize(("deadline_ms", "beats"), [(1500, range(4, 8)), (60_000, range(2, 3))])
def test_the_heartbeat_thread_vouches_only_for_a_loop_allowed_past_its_deadline(
    session: zenoh.Session, deadline_ms: int, beats: range
) -> None:
    """stall_s 10 s against 1.5 s: the thread beats three times per deadline (every 0.5 s, not
    at 10 Hz: each wake costs ~1 ms of the board's core). Against a minute, the loop's own
    beats (the runtime's idle one, then the loop's) are all: 2 s gives 2, not 20."""
    _, times = beats_in(BeatsOnce, session, deadline_ms, 2.0)
    assert len(times) in beats, times


def test_a_hung_loop_gets_no_beat_after_its_last_from_the_heartbeat_thread(
    session: zenoh.Session,
) -> None:
    """A vouch at the thread's own time, while the loop was within stall_s of its last beat,
    moved the deadline by up to stall_s: the controller manager's loop could hang 40 + 50 ms
    before the watchdog knew. The deadline now runs from the loop's own last beat."""
    node, times = beats_in(HangsAfterBeating, session, 300, 1.0)
    assert len(times) >= 2
    assert max(times) <= node.hung_at  # type: ignore[attr-defined]


class Busy(Node):
    """A loop with a function of its own to find in a profile."""

    def run(self, stop: threading.Event) -> None:
        while not stop.wait(0.01):
            self.beat()
            self.work()

    def work(self) -> int:
        return sum(range(1000))


def test_a_profiled_node_writes_its_loops_profile_and_only_the_named_ones_do(
    session: zenoh.Session, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """EXOLINK_PROFILE_DIR (the board proxy's --cprofile): the loop's cProfile, readable by
    pstats, written when the loop ends; EXOLINK_PROFILE_NODES leaves the others unprofiled."""
    import pstats

    monkeypatch.setenv("EXOLINK_PROFILE_DIR", str(tmp_path))
    monkeypatch.setenv("EXOLINK_PROFILE_NODES", "simulator,h2_reader")
    run_for(Busy, session, 0.5)
    (written,) = tmp_path.glob("h2_reader-*.prof")  # one per spawn, named by its pid
    stats = pstats.Stats(str(written)).stats  # type: ignore[attr-defined]
    calls = {fn: v[1] for (_file, _line, fn), v in stats.items()}
    assert calls["work"] >= 10 and calls["run"] == 1
    monkeypatch.setenv("EXOLINK_PROFILE_NODES", "simulator")
    written.unlink()
    run_for(Busy, session, 0.2)
    assert list(tmp_path.iterdir()) == []


def test_phase_clock_charges_cpu_to_the_phase_that_used_it_not_to_a_sleep() -> None:
    """The loop figures the board proxy reports (manager, h2 reader): a phase that sleeps is
    charged (almost) nothing however long it waits; one that computes, its CPU; only sampled
    iterations count, and two readings give the window between them."""
    from exolink import phaseclock

    clock = phaseclock.PhaseClock(every=2)
    first = clock.counters()
    for _ in range(6):
        clock.start()
        time.sleep(0.02)
        clock.mark("sleep")
        t = time.thread_time()
        while time.thread_time() - t < 0.005:
            pass
        clock.mark("work")
    c = clock.counters()
    assert (c["iterations"], c["sampled"]) == (6, 3)
    assert c["us_per_iteration"]["work"] >= 5000
    assert c["us_per_iteration"]["sleep"] < c["us_per_iteration"]["work"] / 2
    w = phaseclock.window(first, c)
    assert w["iterations"] == 6 and w["us_per_iteration"]["work"] >= 5000
    assert phaseclock.window(c, c) == {"iterations": 0, "us_per_iteration": {}}
    with pytest.raises(ValueError, match="every must be >= 1"):
        phaseclock.PhaseClock(every=0)
    assert "wall_max_ms" not in c  # only asked for


def test_phase_clock_walls_say_where_a_slow_iteration_waited_and_start_over() -> None:
    """``walls``: each phase's longest wall time since the last reading, on every iteration
    (sampled or not): a phase that waited shows its wait, which its CPU figure cannot."""
    from exolink import phaseclock

    clock = phaseclock.PhaseClock(every=100, walls=True)  # no iteration CPU-sampled
    for wait in (0.005, 0.06, 0.01):
        clock.start()
        time.sleep(wait)
        clock.mark("read")
        clock.mark("handle")
    walls = clock.counters()["wall_max_ms"]
    assert walls["read"] >= 60 and walls["handle"] < walls["read"] / 2, walls
    assert clock.counters()["wall_max_ms"] == {}  # read: from scratch


class Released:
    """Records when it is released (the order is what is checked); ``fails``: its close raises."""

    def __init__(self, log: list[str], name: str, fails: bool = False) -> None:
        self.log, self.name, self.fails = log, name, fails

    def close(self) -> None:
        self.log.append(self.name)
        if self.fails:
            raise OSError(f"{self.name} would not close")


class RefusesHalfWay(Node):
    """Opens a real bus and two more resources, one whose release fails, then refuses to start."""

    def configure(self) -> None:
        self.order: list[str] = []
        self.bus = self.own(can.Bus(interface="virtual", channel="own-test"))
        self.own(Released(self.order, "first"))
        self.own(Released(self.order, "breaks", fails=True))
        self.own(Released(self.order, "last"))
        raise ValueError("refused after opening")


def test_what_a_node_owns_is_released_last_first_even_when_configure_refuses(
    session: zenoh.Session,
) -> None:
    cfg = config.parse(config.bundled("sim").read_text())
    runner = NodeRunner(RefusesHalfWay, cfg, "h2_reader", session)
    with capture_logs() as logs, pytest.raises(ValueError, match="refused after opening"):
        runner.run()
    node = runner.node
    assert node.order == ["last", "breaks", "first"]  # type: ignore[attr-defined]
    assert node.bus._is_shutdown  # type: ignore[attr-defined]  # python-can's own flag
    failed = [e for e in logs if e["event"] == "release_failed"]
    assert [(e["resource"], e["error"]) for e in failed] == [("Released", "breaks would not close")]
    node.release()  # again: nothing is released twice
    assert node.order == ["last", "breaks", "first"]  # type: ignore[attr-defined]


def test_own_refuses_what_it_could_not_release(session: zenoh.Session) -> None:
    cfg = config.parse(config.bundled("sim").read_text())
    node = NodeRunner(StallsOnce, cfg, "h2_reader", session).node
    with pytest.raises(TypeError, match="int has none of close, undeclare, shutdown, stop"):
        node.own(42)


class SlowLoopStart(Node):
    """Configured, then its loop's first beat comes late (a motion node on a busy core)."""

    def run(self, stop: threading.Event) -> None:
        time.sleep(0.2)
        while not stop.wait(0.02):
            self.beat()


def test_the_beat_after_configure_is_idle_until_the_loop_beats(session: zenoh.Session) -> None:
    """The runtime's beat after configure says idle (the default deadline): nothing is driven
    before the loop runs, whose first beat is not idle. A motion node held to its own 50 ms
    from there was killed when its loop first beat 67 ms later (board proxy, a restart)."""
    from exolink.liveness import _RECORD, Beater, Channel, Pace

    cfg = config.parse(config.bundled("sim").read_text())
    channel = Channel()
    runner = NodeRunner(SlowLoopStart, cfg, "h2_reader", session)
    runner.node.liveness = Beater(channel.child_fd)
    t = threading.Thread(target=runner.run)
    t.start()
    try:
        time.sleep(0.5)
        data = os.read(channel.fileno(), 65536)
    finally:
        runner.stop.set()
        t.join(5)
        channel.close()
    paces = [rec[1] for rec in _RECORD.iter_unpack(data[: len(data) - len(data) % _RECORD.size])]
    assert paces[0] == Pace.IDLE and paces[-1] == Pace.OWN, paces
