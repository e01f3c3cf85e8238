"""Planned set-points on a leased timer: ``exolink.canbus.leases.ThreadLease`` on python-can's real
virtual bus (the kernel's broadcast manager is tested in the UML guest: tests/kernel/), and the
controller manager's plan (nodes/controller_manager/timed.py) through the real ``Manager``."""

from __future__ import annotations

import itertools
import time

import can
import pytest
from exolink.nodes.controller_manager.manager import Manager
from exolink.nodes.controller_manager.slots import Switch
from exolink.nodes.controller_manager.timed import Timed

from exolink.canbus.leases import ThreadLease
from exolink.control.controller import State
from exolink.limits.joints import Limits, LimitsConfig
from exolink.protocol import h2

ID, PERIOD, LEASE = 0x46, 0.010, 6


def slot(n: int) -> bytes:
    return n.to_bytes(4, "big") + b"\xee\xee"


def slots_of(frames: list[can.Message]) -> list[int]:
    return [int.from_bytes(m.data[:4], "big") for m in frames]


@pytest.fixture
def buses():  # type: ignore[no-untyped-def]
    channel = f"lease-{time.monotonic_ns()}"
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    yield tx, rx
    tx.shutdown()
    rx.shutdown()


def drain(bus: can.BusABC, seconds: float) -> list[can.Message]:
    out, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        if (m := bus.recv(left)) is not None:
            out.append(m)
    return out


def test_a_renewed_lease_sends_every_slot_once_in_order(buses) -> None:  # type: ignore[no-untyped-def]
    tx, rx = buses
    op = ThreadLease(tx, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], LEASE)
        for _ in range(40):  # the owner renews every second period, as the manager
            time.sleep(2 * PERIOD)
            n = op.sent()
            op.renew({k: slot(k) for k in range(n, n + 8)}, LEASE)
        op.stop()
        got = slots_of(drain(rx, 0.2))
    finally:
        op.close()
    steps = [b - a for a, b in itertools.pairwise(got)]
    assert got[0] == 0 and set(steps) <= {0, 1}, steps  # never a skip, never backwards
    assert len(got) >= 60, len(got)  # ~80 in 0.8 s; a loaded machine may lose a few periods


def test_an_owner_that_stops_renewing_gets_its_lease_and_no_more(buses) -> None:  # type: ignore[no-untyped-def]
    tx, rx = buses
    op = ThreadLease(tx, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], LEASE)
        got = slots_of(drain(rx, 0.3))
        assert got == list(range(LEASE)), got  # the lease ran out: the timer ended
        assert op.sent() == LEASE
        n = op.renew({k: slot(k) for k in range(LEASE, LEASE + 8)}, LEASE)
        assert n == LEASE and drain(rx, 0.1) == []  # a lapsed lease is not restarted
    finally:
        op.close()


def test_a_lapsed_lease_resumes_at_its_next_slot_in_order(buses) -> None:  # type: ignore[no-untyped-def]
    """ThreadLease as CyclicLease.resume (tests/kernel/test_lease.py): a renewal after the lease
    ran out, or of a count already set on an ended timer, then ``resume``: the next frame is
    the next slot."""
    tx, rx = buses
    op = ThreadLease(tx, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], 3)
        assert slots_of(drain(rx, 0.1)) == [0, 1, 2]
        assert op.renew({k: slot(k) for k in range(3, 11)}, 3) == 3  # on an ended timer
        op.resume()
        assert slots_of(drain(rx, 0.1)) == [3, 4, 5]
        op.renew({k: slot(k) for k in range(6, 14)}, 3)
        assert drain(rx, 0.05) == []
        assert op.renew({k: slot(k) for k in range(6, 14)}, 4) == 6
        op.resume()
        assert slots_of(drain(rx, 0.1)) == [6, 7, 8, 9]
    finally:
        op.close()


def test_stop_is_immediate_and_a_bad_lease_is_refused(buses) -> None:  # type: ignore[no-untyped-def]
    tx, rx = buses
    op = ThreadLease(tx, ID, PERIOD)
    try:
        with pytest.raises(ValueError, match=r"lease of 9 frames: must be 1\.\.8"):
            op.start([slot(k) for k in range(8)], 9)
        assert drain(rx, 0.05) == []  # refused whole: nothing started
        op.start([slot(k) for k in range(8)], LEASE)
        time.sleep(0.015)
        op.stop()
        after = drain(rx, 0.1)
        assert len(after) <= 3, slots_of(after)  # what went out before the stop
        assert drain(rx, 0.1) == []
    finally:
        op.close()


# --- the manager's plan --------------------------------------------------------------------------

ROWS = [[v, 0, 0, 0, 0, 0] for v in (40, 50, 60, 70, 60, 50)]  # r_hip, 10 deg a row
STATE = State((0,) * 6, (0,) * 6)  # the joints where they are: r_hip 40 deg below the pattern


def gait_manager() -> Manager:
    m = Manager(Limits.configured(LimitsConfig(max_step_deg=10)), budget_ms=50)
    params = {"rows": ROWS, "joints": ["r_hip"], "speed": 10, "interpolate": False}
    m.load("gait", "gait_pattern", params)
    m.request(Switch(["gait"], []))
    m.cycle(STATE, 1000.0, h2.PERIOD_S, None)  # the activation's cycle: where it starts
    return m


def gait_timed(tx: can.BusABC, lease_slots: int, ring: int, t0: float) -> tuple[Manager, Timed]:
    """The gait's manager and a Timed on a ThreadLease of ``ring`` frames over ``tx`` (20 ms
    slots, ``lease_slots`` a lease, slot 0 at controller time ``t0``)."""
    m = gait_manager()
    lease = ThreadLease(tx, h2.JOINT_CONTROL, 0.02, ring=ring)
    return m, Timed(lease, m.position_joints(), 0.02, lease_slots, t0, time.monotonic())


def test_the_plan_is_the_patterns_rows_one_per_slot_through_the_managers_limits(buses) -> None:  # type: ignore[no-untyped-def]
    tx, rx = buses
    m = gait_manager()
    assert m.plannable()
    lease = ThreadLease(tx, h2.JOINT_CONTROL, 0.02, ring=8)
    # slot 0 a millisecond after the activation's cycle (never before it)
    timed = Timed(lease, m.position_joints(), 0.02, 3, 1000.001, time.monotonic())
    try:
        assert timed.begin(m, STATE, None) is None
        got = [h2.decode(f) for f in drain(rx, 0.15)]
    finally:
        timed.abort()
    # three slots of the lease, a frame each for r_hip (motor 1), a 20 ms slot moving at most
    # two 10 ms step limits: from where the activation's cycle wrote (10, one step from 0) to
    # row 0 (40) saturated to 30, then the rows 50 and 60
    assert [f.motor for f in got] == [1, 1, 1], got  # type: ignore[union-attr]
    assert [f.setpoint for f in got] == [30, 50, 60], got  # type: ignore[union-attr]


def test_the_node_is_alive_before_the_first_slot_is_planned_and_after_each(buses) -> None:  # type: ignore[no-untyped-def]
    """The node beats (by its leased deadline) as planning begins, not only after a slot: a
    first slot preempted past the node's own 50 ms tripped the watchdog at the gait's start on
    a capped CPU. No frame is on the bus before the op starts."""
    tx, rx = buses
    m = gait_manager()
    seen: list[tuple[int, int]] = []  # (slots planned, frames on the bus) at each beat
    lease = ThreadLease(tx, h2.JOINT_CONTROL, 0.02, ring=8)
    timed = Timed(lease, m.position_joints(), 0.02, 3, 1000.001, time.monotonic())
    timed.alive = lambda: seen.append((timed.plan.slots, len(drain(rx, 0.0))))
    try:
        assert timed.begin(m, STATE, None) is None
    finally:
        timed.abort()
    assert seen[0] == (0, 0), seen  # before any slot, nothing sent
    assert [k for k, _ in seen[1:]] == list(range(1, len(seen))), seen  # then after each


def test_leaving_the_timer_gives_the_step_limit_what_was_sent(buses) -> None:  # type: ignore[no-untyped-def]
    tx, rx = buses
    m, timed = gait_timed(tx, 3, 8, 1000.0)
    assert timed.begin(m, STATE, None) is None
    time.sleep(0.03)  # two slots out (0 and 1), five planned
    back = timed.leave()
    sent = [h2.decode(f).setpoint for f in drain(rx, 0.05)]  # type: ignore[union-attr]
    assert back == {0: sent[-1]}, (back, sent)
    assert timed.plan.slots > len(sent)  # planned ahead of what went out


def test_a_controller_that_fails_in_a_planned_slot_ends_the_plan_with_its_safe_action(
    buses,
) -> None:  # type: ignore[no-untyped-def]
    tx, _rx = buses
    m = gait_manager()
    ctrl = m.slots["gait"].ctrl

    def boom(*_a: object) -> dict:
        raise RuntimeError("planned slot broke")

    ctrl.update = boom  # type: ignore[method-assign]
    timed = Timed(ThreadLease(tx, h2.JOINT_CONTROL, 0.02, ring=8), (0,), 0.02, 3, 1000.0, 0.0)
    try:
        broke = timed.begin(m, STATE, None)
    finally:
        timed.abort()
    assert broke is not None and broke.safe == {0}
    assert m.slots["gait"].state == "inactive" and "planned slot broke" in m.slots["gait"].error


def test_a_gait_is_planned_for_one_cycle_then_replayed_frame_for_frame(buses) -> None:  # type: ignore[no-untyped-def]
    tx, _rx = buses
    full, replay = gait_manager(), gait_manager()
    period = replay.repeats_slots(0.02)
    assert period == len(ROWS)  # speed 10: a row per 20 ms slot
    ring = ThreadLease(tx, h2.JOINT_CONTROL, 0.02, ring=8)
    try:
        every = Timed(ring, (0,), 0.02, 3, 1000.001, 0.0)
        assert every._plan_until(full, STATE, 40, None) is None
        timed = Timed(ring, (0,), 0.02, 3, 1000.001, 0.0, period=period)
        assert timed._plan_until(replay, STATE, 40, None) is None
    finally:
        ring.close()
    # the ramp from 0 deg (two slots saturated by the step limit), then one cycle computed
    # until a slot equals the one a period before it; the rest replayed
    assert timed.computed < 40 and timed.plan.cycle_from is not None, timed.computed
    assert [timed.plan[i] for i in range(40)] == [every.plan.frames[i] for i in range(40)]
    assert timed.plan.position(39) == every.plan.positions[39]
    assert len(timed.plan.frames) <= timed.computed  # memory: one cycle, not the whole walk


def test_outputs_that_do_not_repeat_in_whole_slots_are_planned_every_slot() -> None:
    m = gait_manager()
    assert m.repeats_slots(0.025) is None  # 6 rows x 20 ms is no whole number of 25 ms slots
    m.load(
        "reach",
        "joint_trajectory",
        {"joints": ["l_hip"], "points": [{"time_s": 1.0, "positions": [5]}]},
    )
    m.request(Switch(["reach"], []))
    m.cycle(STATE, 1000.01, h2.PERIOD_S, None)
    assert m.repeats_slots(0.02) is None  # a trajectory does not repeat


def test_a_renewal_late_by_slots_still_grants_a_whole_lease(buses) -> None:  # type: ignore[no-untyped-def]
    """A renewal grants a whole lease however long since the last wake: the plan is ahead of
    it. Three slots planned a wake fell behind wakes 60-110 ms apart under a 50 % cap: the
    lease shrank to the plan and ran out, and every restart planned again (the board proxy: a
    lapse every ~0.3 s for 8 s, then a trip)."""
    tx, _rx = buses
    m, timed = gait_timed(tx, 5, 16, 1000.001)
    try:
        assert timed.begin(m, STATE, None) is None
        time.sleep(0.07)  # 3.5 slots: the first lease (5) still holds
        assert timed.keep(m, STATE, None, time.monotonic()) is None
        assert not timed.lapsed
        assert timed.lease_frames == 5, timed.lease_frames  # three slots a wake left 3 (or 2)
    finally:
        timed.abort()


def test_planning_never_holds_up_a_renewal(buses) -> None:  # type: ignore[no-untyped-def]
    """Slots planned slowly (15 ms each here; a gait's first cycle on the proxy under a 50 %
    cap: 40-110 ms of wall time for five) after the op started: the lease is renewed first and
    between two slots when due, so the op never runs out while the plan grows (planned before
    the renewal, the lease ran out and every restart planned again: D64, E64); and planning
    comes back to the node's loop after a chunk, so a disable on the bus is read meanwhile."""
    tx, rx = buses
    m, timed = gait_timed(tx, 5, 16, 1000.001)
    timed.alive = lambda: time.sleep(0.015)
    try:
        t = time.monotonic()
        assert timed.begin(m, STATE, None) is None  # 5 slots, the op, a chunk of the plan ahead
        calls = [time.monotonic() - t]
        while timed.behind:  # the node's loop: it reads the bus, then plans on at once
            t = time.monotonic()
            assert timed.keep(m, STATE, None, t) is None
            calls.append(time.monotonic() - t)
            assert not timed.lapsed, timed.lapsed
        assert timed.plan.slots >= 5 + 5, timed.plan.slots  # longer than the first lease
        assert timed.renewals >= 2, timed.renewals
        assert max(calls[1:]) < 0.1, calls  # a chunk (20 ms) and a slot, not the whole plan
        stamps = [m.timestamp for m in iter(lambda: rx.recv(0), None)]  # what went out
    finally:
        timed.abort()
    assert len(stamps) >= 5, stamps
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert max(gaps) < 0.1, gaps  # never a lease's silence


def test_a_lease_whose_timer_ended_at_a_renewal_is_resumed_not_a_silent_gait(buses) -> None:  # type: ignore[no-untyped-def]
    """The kernel's race (CyclicLease): the lease's last frame goes out between a renewal's
    TX_READ and its SETTIMER, which sets the new count on a timer that has ended. The op is
    then silent with a full count, and each later renewal reads no progress. Timed calls that a
    lapse, not a gait that runs with nothing on the bus (the board proxy under a CPU cap: 73 s
    of renewals, no frame), and resumes it from the slot after the last one sent: the
    positions on the bus go on in the plan's order, nothing skipped or repeated."""
    tx, rx = buses
    m, timed = gait_timed(tx, 3, 8, 1000.0)
    lease = timed.lease
    assert isinstance(lease, ThreadLease)
    try:
        assert timed.begin(m, STATE, None) is None
        time.sleep(0.03)
        with lease._cond:  # the timer ends with a count left, as the race leaves the kernel's op
            lease._running = False
        before = [h2.decode(f).setpoint for f in drain(rx, 0.01)]  # type: ignore[union-attr]
        time.sleep(0.04)
        assert timed.keep(m, STATE, None, time.monotonic()) is None
        assert not timed.lapsed and not timed.resumed  # frames went out: a renewal like any
        assert drain(rx, 0.05) == []  # the renewal set a count, the timer stays ended
        assert timed.keep(m, STATE, None, time.monotonic()) is None
        assert not timed.lapsed and [how for how, _ in timed.resumed] == ["stalled"]
        after = [h2.decode(f).setpoint for f in drain(rx, 0.05)]  # type: ignore[union-attr]
        timed.abort()  # every stop and trip path (TimerLoop.abort): the resumed op ends at once
        assert drain(rx, 0.05) == []
    finally:
        timed.abort()
    ref = Timed(ThreadLease(tx, h2.JOINT_CONTROL, 0.02, ring=8), (0,), 0.02, 3, 1000.0, 0.0)
    try:  # the same gait planned on its own: what the bus should carry, in order
        assert ref._plan_until(gait_manager(), STATE, 20, None) is None
    finally:
        ref.abort()
    planned = [ref.plan.position(k)[0] for k in range(len(before) + len(after))]  # type: ignore[index]
    assert after and before + after == planned, (before, after, planned)


def test_an_op_deleted_under_the_owner_is_lost_not_resumed(buses) -> None:  # type: ignore[no-untyped-def]
    """The supervisor's copy of the op deletes it at a safe action (CyclicLease: the next
    renewal finds no count, OpLost; tests/kernel/test_lease.py). Timed does not wait for more
    plan or resume it however soon it renews: ``lapsed`` "op lost", the node leaves the timer,
    and the bus stays silent."""
    tx, rx = buses
    m, timed = gait_timed(tx, 3, 8, 1000.0)
    try:
        assert timed.begin(m, STATE, None) is None
        time.sleep(0.03)
        timed.lease.stop()  # the safe action's TX_DELETE, as the sim's lease takes it
        t = time.monotonic()
        assert timed.keep(m, STATE, None, t) is None
        assert timed.lapsed == "op lost" and not timed.resumed
        assert drain(rx, 0.01) and drain(rx, 0.1) == []  # what went before; then nothing
    finally:
        timed.abort()


def test_a_plan_slower_than_the_op_waits_and_resumes_in_order(buses) -> None:  # type: ignore[no-untyped-def]
    """Slots planned slower than the op sends them (30 ms a slot against 20 ms slots: a gait's
    first cycle under a 50 % cap): a renewal that finds too little planned is not made, the op
    stops at the plan's end and is resumed once more is planned. No lapse, and the bus carries
    the plan's positions in order, each once (before, a lapse that planned it all again)."""
    tx, rx = buses
    m, timed = gait_timed(tx, 3, 8, 1000.0)
    timed.alive = lambda: time.sleep(0.03)
    try:
        assert timed.begin(m, STATE, None) is None
        end = time.monotonic() + 0.6
        while time.monotonic() < end:  # the node's loop: a wake every 10 ms while behind
            assert timed.keep(m, STATE, None, time.monotonic()) is None
            assert not timed.lapsed, timed.lapsed
            time.sleep(0.01)
        got = [h2.decode(f).setpoint for f in drain(rx, 0.01)]  # type: ignore[union-attr]
    finally:
        timed.abort()
    assert timed.resumed, "the op never ran short"  # the point of the test: it did, and went on
    ref = Timed(ThreadLease(tx, h2.JOINT_CONTROL, 0.02, ring=8), (0,), 0.02, 3, 1000.0, 0.0)
    try:
        assert ref._plan_until(gait_manager(), STATE, 60, None) is None
    finally:
        ref.abort()
    assert got == [ref.plan.position(k)[0] for k in range(len(got))]  # type: ignore[index]


def test_a_lapse_longer_than_two_leases_hands_the_joints_back(buses) -> None:  # type: ignore[no-untyped-def]
    """A renewal that comes two leases after the last is no hiccup: ``lapsed``, and the node
    leaves the timer (its cycle loop starts over from the bus)."""
    tx, rx = buses
    m, timed = gait_timed(tx, 3, 8, 1000.0)
    try:
        assert timed.begin(m, STATE, None) is None
        time.sleep(0.15)  # the 60 ms lease ran out 90 ms ago: 150 ms > two leases (120 ms)
        assert drain(rx, 0.01)  # the lease's slots (three, unless planning renewed it)
        assert timed.keep(m, STATE, None, time.monotonic()) is None
        assert timed.lapsed == "ran out" and not timed.resumed
        assert drain(rx, 0.05) == []  # not restarted
    finally:
        timed.abort()


def test_a_lease_renewed_after_it_ran_out_stays_silent_with_its_count(buses) -> None:  # type: ignore[no-untyped-def]
    """ThreadLease as the kernel's op: a renewal of an ended timer sets the count (TX_READ
    says so) and sends nothing; ``sent`` no longer moves."""
    tx, rx = buses
    op = ThreadLease(tx, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], LEASE)
        assert slots_of(drain(rx, 0.3)) == list(range(LEASE))
        assert op.renew({k: slot(k) for k in range(LEASE, LEASE + 8)}, LEASE) == LEASE
        assert op.remaining() == LEASE and drain(rx, 0.1) == []
        assert op.sent() == LEASE
    finally:
        op.close()


def test_a_plan_is_stale_once_its_controller_is_commanded_not_when_a_neighbour_fails() -> None:
    """``Manager.plan_key``, what the timer's plan was made from: a speed given to a gait whose
    cycle the timer replayed changed nothing on the bus (it must end the plan), while a PID's
    failure beside the gait ended the gait's timer for nothing (a 108 ms stall on the board
    proxy, A67): only whether the cycle loop runs beside it changes."""
    m = gait_manager()
    key = m.plan_key()
    m.load("pid", "pid", {"joints": ["l_ankle"]})
    m.request(Switch(["pid"], []))
    m.cycle(STATE, 1000.01, h2.PERIOD_S, None)
    assert m.slots["pid"].state == "active" and m.unplanned()
    assert m.plan_key() == key  # a feedback controller beside the plan: it stands

    def boom(*_a: object) -> dict:
        raise RuntimeError("the PID broke")

    m.slots["pid"].ctrl.update = boom  # type: ignore[method-assign]
    m.cycle(STATE, 1000.02, h2.PERIOD_S, None)
    assert m.slots["pid"].state == "inactive" and not m.unplanned()
    assert m.plan_key() == key and m.slots["gait"].state == "active"
    m.command("gait", {"speed": 5})  # the gait's own command: its plan is stale
    assert m.plan_key() != key
    key = m.plan_key()
    m.set_limits(Limits.configured(LimitsConfig(max_step_deg=5)))  # narrower: planned again
    assert m.plan_key() != key
    key = m.plan_key()
    m.request(Switch([], ["gait"]))
    m.cycle(STATE, 1000.03, h2.PERIOD_S, None)
    assert m.plan_key() != key and not m.plannable()
