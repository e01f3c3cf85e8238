"""The liveness pipe on its own: whole records only, the newest wins, never in the future."""

from __future__ import annotations

import os
import struct
import time

from exolink import liveness


def test_newest_whole_beat_wins_and_partial_records_wait() -> None:
    ch = liveness.Channel()
    try:
        beater = liveness.Beater(ch.child_fd)
        assert ch.drain(100.0) is None
        beater.beat(10.0)
        beater.beat(10.001)  # inside MIN_INTERVAL_S: not written
        beater.beat(10.5)
        assert ch.fileno() and liveness.with_beats([ch]) == {ch}
        assert ch.drain(100.0) == (10.5, liveness.Pace.OWN)
        assert liveness.with_beats([ch]) == set()
        raw = struct.pack("=dB", 11.0, 0)
        os.write(ch.child_fd, raw[:3])  # a torn record cannot come from one write, but be strict
        assert ch.drain(100.0) is None
        os.write(ch.child_fd, raw[3:])
        assert ch.drain(100.0) == (11.0, liveness.Pace.OWN)
        beater.beat(500.0)
        assert ch.drain(100.0) == (
            100.0,
            liveness.Pace.OWN,
        )  # a beat from the future is clamped to now
    finally:
        ch.close()


def test_idle_is_said_at_once_and_repeated_by_beats_that_do_not_say() -> None:
    ch = liveness.Channel()
    try:
        beater = liveness.Beater(ch.child_fd)
        beater.beat(10.0, pace=liveness.Pace.IDLE)
        beater.beat(10.5)  # the heartbeat thread: as the loop last said
        assert ch.drain(100.0) == (10.5, liveness.Pace.IDLE)
        beater.beat(10.501, pace=liveness.Pace.OWN)  # inside MIN_INTERVAL_S, but a change: written
        assert ch.drain(100.0) == (10.501, liveness.Pace.OWN)
        beater.beat(10.502, pace=liveness.Pace.OWN)  # no change, inside the interval: not written
        assert ch.drain(100.0) is None
    finally:
        ch.close()


def test_a_lease_is_said_at_once_and_an_unknown_pace_is_judged_strictly() -> None:
    """Leased (the manager while only the kernel's timer sends) goes through the pipe like idle;
    a byte no version writes is judged by the node's own deadline, never a longer one."""
    ch = liveness.Channel()
    try:
        beater = liveness.Beater(ch.child_fd)
        beater.beat(10.0, pace=liveness.Pace.LEASED)
        beater.beat(10.001)  # inside MIN_INTERVAL_S, no change: not written
        assert ch.drain(100.0) == (10.0, liveness.Pace.LEASED)
        beater.beat(10.002, pace=liveness.Pace.OWN)  # the lease ended: at once
        assert ch.drain(100.0) == (10.002, liveness.Pace.OWN)
        os.write(ch.child_fd, struct.pack("=dB", 11.0, 7))
        assert ch.drain(100.0) == (11.0, liveness.Pace.OWN)
    finally:
        ch.close()


def test_without_a_supervisor_beats_go_nowhere(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.delenv(liveness.ENV, raising=False)
    b = liveness.Beater.from_env()
    assert b.fd is None
    b.beat()  # no error


def test_a_gone_supervisor_does_not_break_the_node() -> None:
    ch = liveness.Channel()
    fd = os.dup(ch.child_fd)
    ch.close()
    b = liveness.Beater(fd)
    b.beat(1.0)  # EPIPE is swallowed
    os.close(fd)


class ClosedBehindItsBack(liveness.Channel):
    """A channel whose pipe another thread closes between the supervisor listing it and
    selecting on it: the race a management `stop`/`start` ran into on the board proxy (the fd
    is gone while the channel still reports it, for one look)."""

    def __init__(self) -> None:
        super().__init__()
        self.looks = 0

    def fileno(self) -> int:
        self.looks += 1
        if self.looks == 1:
            fd = self._r
            self.close()
            return fd  # the closed number, as in the window between os.close and _r = -1
        return super().fileno()


def test_a_channel_closed_meanwhile_does_not_stop_the_others_beats() -> None:
    """Before the fix select raised EBADF and the supervisor's loop, and with it the
    appliance, went down (exit 1, systemd restart) when a node was stopped."""
    ok, gone = liveness.Channel(), ClosedBehindItsBack()
    try:
        liveness.Beater(ok.child_fd).beat(1.0)
        assert liveness.with_beats([gone, ok]) == {ok}
    finally:
        ok.close()
        gone.close()


def test_a_wakeup_ends_a_wait_from_another_thread_and_only_once() -> None:
    """The supervisor loop's alarm (exolink.supervisor.wakeup): a set before the wait ends it at once, a
    set during it ends it early, a wait without one runs out; a set is consumed by the wait
    that saw it, and the pipe opens only on first use (after the zygote's fork)."""
    import threading

    from exolink.supervisor.wakeup import Wakeup

    w = Wakeup()
    assert w._fds is None
    assert w.wait(0.01) is False
    w.set()
    w.set()  # two sets before one wait: one wake, then none
    assert w.wait(5.0) is True
    assert w.wait(0.01) is False
    threading.Timer(0.05, w.set).start()
    assert w.wait(30.0) is True
    w.set()
    w.clear()  # seen by a wait on its descriptor among others
    assert w.wait(0.01) is False
    w.close()
    w.set()  # after close: nothing, no error


def test_the_deadline_timer_runs_out_early_never_late_and_is_reset_one_beat_in_two() -> None:
    """Beats every 19 ms under a 50 ms deadline (the controller manager's): a beat whose timer
    is still set 30 ms or more ahead leaves it (a system call saved), the next one sets it (not
    20 ms: the kept timer would be exactly 30 ms ahead, the rule's edge, where the rounding of
    a large monotonic time decides, and the test failed on a host up for 18 hours); an
    end of idle (a shorter deadline) sets it at once. The timer is the kernel's own (timerfd):
    whatever a beat leaves, it runs out no later than the newest beat's deadline."""
    ch = liveness.Channel()
    try:
        beater = liveness.Beater(ch.child_fd, ch.timer, (0.05, 0.5))
        t0 = time.monotonic() + 10.0  # absolute times on the monotonic clock, in the future

        def expires() -> float:
            """When the timer runs out, on the monotonic clock: read between two clock reads
            close together (a preemption between the clock and the timer moved it by as much,
            and a loaded machine called a kept timer reset)."""
            while True:
                before = time.monotonic()
                left = liveness.TIMERS.remaining(ch.timer)
                if time.monotonic() - before < 0.001:
                    return before + left

        reset = []
        for k in range(6):
            t = t0 + 0.019 * k
            before = expires() if k else None
            beater.beat(t, pace=liveness.Pace.OWN)
            now = expires()
            assert now <= t + 0.05 + 0.002  # never later than this beat's deadline
            reset.append(before is None or abs(now - before) > 0.005)
        assert reset == [True, False, True, False, True, False]
        beater.beat(t0 + 0.2, pace=liveness.Pace.IDLE)  # idle: the longer deadline
        assert abs(expires() - (t0 + 0.7)) < 0.005
        beater.beat(t0 + 0.22, pace=liveness.Pace.OWN)  # driving again: its own deadline, at once
        assert abs(expires() - (t0 + 0.27)) < 0.005
        # two deadlines given: leased is the node's own (no leased_deadline_ms)
        beater.beat(t0 + 0.3, pace=liveness.Pace.LEASED)
        assert abs(expires() - (t0 + 0.35)) < 0.005
        leased = liveness.Beater(ch.child_fd, ch.timer, (0.05, 0.5, 0.1))
        leased.beat(t0 + 0.4, pace=liveness.Pace.LEASED)  # the leased deadline
        assert abs(expires() - (t0 + 0.5)) < 0.005
        leased.beat(t0 + 0.44, pace=liveness.Pace.OWN)  # the lease ended: its own, at once
        assert abs(expires() - (t0 + 0.49)) < 0.005
    finally:
        ch.close()
