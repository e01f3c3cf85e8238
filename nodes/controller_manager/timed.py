"""Set-points planned ahead and sent on a timer the manager does not run: the kernel's
broadcast manager on SocketCAN (``exolink.canbus.leases.CyclicLease``), a thread elsewhere.

While every active controller is ``planned`` (its outputs are a function of time: the gait
pattern, a trajectory), the manager computes each slot's set-points a few slots ahead, through
the same ``Manager.cycle`` (limits, caps, step limit, budgets) the cycle loop uses, and hands
the frames to one send op on the joint-control id: the joints of a slot one after another,
``slot_s / joints`` apart, so each joint's frames are ``slot_s`` apart on the timer. Python
then runs once per renewal (every second slot), not per frame.

The op is leased: it sends at most ``lease_slots`` slots after the last renewal. Renewals come
before the loop's heartbeat, so a manager stopped, hung, starved or killed stops renewing
before it stops beating, and the op ends at most ``lease_slots x slot_s`` after the last beat.
Its beats meanwhile are judged by the leased deadline (exolink.liveness), at least the lease:
stock, 200 ms both, so the op has ended by the watchdog's first disable frame (a frame's
interval later at most: the count a renewal reads may be one short). Any stop, trip or switch
deletes the op first (``abort``), and on SocketCAN the watchdog deletes it itself before its
first disable frame, whatever the manager is doing (exolink.canbus.held): the lease then bounds
only what no watchdog can end.

A renewal that finds the lease lapsed (the loop came after it ran out, or the kernel's race
left the timer ended) resumes the op from the plan's next slot, in a new phase, when the last
renewal was at most ``RESUME_WITHIN_LEASES`` leases ago: the H2 held the last set-point
meanwhile, and the next one is a slot's step from it, as planned and checked. The gait is
late by the lapse, nothing else. A renewal that finds too little planned (a gait's first
cycle planned slower than the op sends it) is not made: the op stops at the plan's end, and a
later renewal resumes it. On the board proxy under a 50 % CPU cap, leaving the timer
instead (the cycle loop, then a new op that planned the gait's cycle again: 13-21 ms of the
core at nice -20 each) made lapses come in cascades that starved the h2 reader into a trip
(M65, B66).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping

import structlog
from exolink.nodes.controller_manager.manager import Manager
from exolink.nodes.controller_manager.slots import PLANNED, Cycle

from exolink.canbus.leases import Lease, OpLost
from exolink.control.controller import State
from exolink.protocol import h2

log = structlog.get_logger()
# A renewal once this many slots passed since the last: a 100 ms lease then reaches at least
# three slots past the next renewal.
RENEW_AFTER_SLOTS = 1.5
STALLED_SLOTS = 2  # no frame sent in this many slots since a renewal: the op's timer ended
# A lapse found by a renewal at most this many leases after the last is resumed in place (the
# plan's next slot now: ``_renew``), a plan that ran short waited for; a later one is no
# hiccup, and the node leaves the timer.
RESUME_WITHIN_LEASES = 2
# Planning ahead stops after this much wall time (after a slot at least), and the loop reads
# the bus before it goes on (``behind``: after as long again): anyone's disable ends the op
# within this, whatever a gait's first cycle costs (1-4 ms of the proxy's CPU a slot).
PLAN_CHUNK_S = 0.02


class Plan(Mapping[int, bytes]):
    """Frames by index on the op's timer (slot k, joint i: ``k x joints + i``) and, per slot,
    the positions they carry (to give the step limit back what was really sent).

    Outputs that repeat every ``period`` slots (a gait) are planned through the manager until
    one slot equals the slot a period before it: from there every slot is the one a period
    earlier (the manager's output is a function of its last position and the controllers',
    and both then repeat), so the plan is that cycle, replayed. On the board a planned slot is
    milliseconds of CPU; a replayed one is an index."""

    def __init__(self, joints: tuple[int, ...], period: int | None = None) -> None:
        self.joints = joints  # joint indices, in the order they go out within a slot
        self.per_slot = len(joints)
        self.period = period  # slots after which the outputs repeat; None: they do not
        self.frames: dict[int, bytes] = {}
        self.positions: dict[int, tuple[int, ...]] = {}  # slot -> degrees
        self.slots = 0  # slots planned so far (replayed ones included)
        self.cycle_from: int | None = None  # the first slot of the replayed cycle
        self._kept_from = 0  # no slot before this one is held (forget_before)

    def add(self, k: int, frames: list[bytes], positions: tuple[int, ...]) -> None:
        """Slot ``k`` (the next), planned through the manager."""
        n = self.per_slot
        for i, f in enumerate(frames):
            self.frames[k * n + i] = f
        self.positions[k] = positions
        self.slots = k + 1
        p = self.period
        if p is None or k < p or self.positions.get(k - p) != positions:
            return
        if all(self.frames.get((k - p) * n + i) == f for i, f in enumerate(frames)):
            self.cycle_from = k - p
            for i in range(n):
                del self.frames[k * n + i]
            del self.positions[k]

    def _fold(self, k: int) -> int:
        first = self.cycle_from
        if first is None or self.period is None or k < first + self.period:
            return k
        return first + (k - first) % self.period

    def position(self, k: int) -> tuple[int, ...] | None:
        return self.positions.get(self._fold(k)) if k < self.slots else None

    def __getitem__(self, index: int) -> bytes:
        k, i = divmod(index, self.per_slot)
        if k >= self.slots:
            raise KeyError(index)
        return self.frames[self._fold(k) * self.per_slot + i]

    def get(self, index: int, default: bytes | None = None) -> bytes | None:  # type: ignore[override]
        """``Mapping.get`` without its KeyError: a renewal looks up each slot it places."""
        k, i = divmod(index, self.per_slot)
        if index < 0 or k >= self.slots:
            return default
        return self.frames.get(self._fold(k) * self.per_slot + i, default)

    def __contains__(self, index: object) -> bool:
        if not isinstance(index, int) or index < 0:
            return False
        k, i = divmod(index, self.per_slot)
        return k < self.slots and self._fold(k) * self.per_slot + i in self.frames

    def __iter__(self) -> Iterator[int]:
        return iter(self.frames)

    def __len__(self) -> int:
        return len(self.frames)

    def forget_before(self, slot: int) -> None:
        """Slots before ``slot`` are needed no more, except the last period's while the plan
        looks for its repeat, and the replayed cycle."""
        if self.cycle_from is not None:
            slot = min(slot, self.cycle_from)
        elif self.period is not None:
            slot = min(slot, self.slots - self.period)
        if slot <= self._kept_from:  # nothing older held: no walk over the whole cycle
            return
        self._kept_from = slot
        n = self.per_slot
        for i in [i for i in self.frames if i < slot * n]:
            del self.frames[i]
        for k in [k for k in self.positions if k < slot]:
            del self.positions[k]


class Timed:
    """One leased op for the planned controllers' joints; made when they all are planned and
    ended (``abort``/``leave``) when anything changes. Not thread-safe: the node calls it
    under its ``io_lock``."""

    def __init__(
        self,
        lease: Lease,
        joints: tuple[int, ...],
        slot_s: float,
        lease_slots: int,
        t0: float,
        now: float,
        encode: Callable[[int, int, int, int], bytes] | None = None,
        alive: Callable[[], None] | None = None,
        period: int | None = None,
    ) -> None:
        """``encode(motor, mode, setpoint, stiffness)``: a joint-control payload (the node's
        cache of encoded frames; default the H2 codec's); ``alive``: called as planning begins
        and after each slot planned (the node's heartbeat: the first plan of a process can take
        longer than the manager's deadline on the board); ``period``: slots after which the
        outputs repeat (``Manager.repeats_slots``), None: plan every slot."""
        self.alive = alive or (lambda: None)
        self.lease, self.slot_s, self.lease_slots = lease, slot_s, lease_slots
        self.encode = encode or _encode
        self.plan = Plan(joints, period)
        self.t0 = t0  # controller time (epoch s) of slot 0
        self.started = now  # monotonic time of slot 0
        self.base = 0  # the op's frame the last start or renewal put first
        self.lease_frames = 0  # and how many it allowed
        self.renewed_at = now  # monotonic
        self.since_renewal_s = 0.0  # between the last two renewals (a lapse: how late)
        self.renewals = 0
        self.credited = 0  # the op's frames counted as their controllers' (TimerLoop.credit)
        self.computed = 0  # slots planned through the manager (the rest replayed)
        self.plan_cpu_s = 0.0  # this thread's CPU spent planning them
        # why the lease lapsed ("ran out", "stalled", "plan ran short", "op lost"); "" holds
        self.lapsed = ""
        self.resumed: list[tuple[str, float]] = []  # lapses resumed in place: why, the gap (s)
        self.sending = False  # the op started
        self.horizon = 0  # the slot the plan is to reach (``_plan_ahead``)

    @property
    def per_slot(self) -> int:
        return len(self.plan.joints)

    @property
    def behind(self) -> bool:
        """The plan has not reached its horizon: the loop reads the bus and plans on soon."""
        return self.plan.cycle_from is None and self.plan.slots < self.horizon

    def _plan_until(
        self,
        manager: Manager,
        state: State,
        slot: int,
        not_armed: str | None,
        until_s: float = float("inf"),
    ) -> Cycle | None:
        """Plan slots up to ``slot`` (exclusive), stopping after the one that ends past
        ``until_s`` (monotonic); a Cycle when one cannot be planned (a controller failed, or
        wrote other joints): the plan ends there and the caller acts on it (safe frames,
        leaving the timer)."""
        plan = self.plan
        if plan.cycle_from is not None:  # replayed: nothing to compute, no CPU clock to read
            plan.slots = max(plan.slots, slot)  # (a system call, ~0.4 ms under TCG)
            return None
        steps = max(1, round(self.slot_s / h2.PERIOD_S))
        c0 = time.thread_time()
        try:
            return self._plan_slots(manager, state, slot, not_armed, steps, until_s)
        finally:
            self.plan_cpu_s += time.thread_time() - c0

    def _plan_slots(
        self,
        manager: Manager,
        state: State,
        slot: int,
        not_armed: str | None,
        steps: int,
        until_s: float,
    ) -> Cycle | None:
        plan = self.plan
        while plan.slots < slot:
            if plan.cycle_from is not None:  # replayed: nothing to compute
                plan.slots = slot
                break
            k = plan.slots
            out = manager.cycle(
                state,
                self.t0 + k * self.slot_s,
                self.slot_s,
                not_armed,
                steps,
                switches=False,
                part=PLANNED,
            )
            writes = sorted(out.writes, key=lambda w: w.motor)
            if out.safe or out.safe_boards or tuple(w.motor - 1 for w in writes) != plan.joints:
                return out
            frames = [self.encode(w.motor, w.mode, w.setpoint, w.stiffness) for w in writes]
            plan.add(k, frames, tuple(w.setpoint for w in writes))
            self.computed += 1
            now = time.monotonic()
            if self.sending and not self.lapsed and self._late(now):  # a long plan holds none up
                self._renew(now)
            self.alive()  # after the renewal: the op never outlives the last beat's deadline
            if now >= until_s or self.lapsed:
                break
        return None

    def begin(self, manager: Manager, state: State, not_armed: str | None) -> Cycle | None:
        """Plan a lease's worth of slots, start the op (slot 0 now), then plan what the first
        renewal needs (``_plan_ahead``). Not fewer before the start: a first lease of three
        slots (60 ms) ran out before the first renewal at most gait starts under a 50 % CPU
        cap, and each restart planned again (three lapses in 0.6 s, then the manager 108 ms
        late: J63)."""
        first = self.lease_slots
        # Alive before the first slot is planned too: the loop's last beat was by its own
        # deadline (50 ms on the board), and a first slot preempted for that long (a CPU capped
        # by its quota: docs/performance.md) tripped the watchdog at every gait start. Nothing
        # is sent until the op starts below, so nothing moves meanwhile.
        self.alive()
        if (broke := self._plan_until(manager, state, first, not_armed)) is not None:
            return broke
        n = self.per_slot
        frames = [self.plan[i] for i in range(min(self.lease.ring, self.plan.slots * n))]
        self.lease.start(frames, first * n)
        self.lease_frames = first * n
        self.renewed_at = time.monotonic()  # the op's start, not before its planning
        self.sending = True
        return self._plan_ahead(manager, state, not_armed)

    def _plan_ahead(self, manager: Manager, state: State, not_armed: str | None) -> Cycle | None:
        """After a start or a renewal, never before one: the plan reaches what the next
        renewal needs for a whole lease, even a lease late. Planned before the renewal, a
        gait's first cycle (1-4 ms of the proxy's CPU a slot, 40-110 ms of wall time for five
        under a 50 % cap) held the renewal up until the lease ran out, and every restart
        planned again: a lapse every ~0.3 s for 8 s, the manager at 20 % of CPU 0 and the h2
        reader starved into a trip (D64, E64). A renewal that falls due meanwhile is made
        between two slots; after ``PLAN_CHUNK_S`` the loop reads the bus (a disable ends the
        op) and comes back after as long while ``behind``."""
        now = time.monotonic()
        at = int((now - self.started) / self.slot_s)  # the slot going out about now
        self.horizon = max(self.horizon, at + 2 * self.lease_slots + 2)
        return self._plan_until(manager, state, self.horizon, not_armed, now + PLAN_CHUNK_S)

    def due(self, now: float) -> bool:
        """At each wake while the lease is short (a new op's first), then every second slot
        by the time since the last renewal (with wakes every slot: every second wake). Not by
        the op's count against the clock: the kernel's timer runs late under load, and that
        made every wake a renewal."""
        return self.lease_frames < self.lease_slots * self.per_slot or self._late(now)

    def _late(self, now: float) -> bool:
        """``RENEW_AFTER_SLOTS`` since the last renewal (between two planned slots, only this:
        a short lease would otherwise be renewed after every slot)."""
        return now - self.renewed_at >= RENEW_AFTER_SLOTS * self.slot_s

    def keep(
        self, manager: Manager, state: State, not_armed: str | None, now: float
    ) -> Cycle | None:
        """Renew the lease if due, from what is planned, then plan ahead for the next renewal
        (also when not due, while ``behind``). A Cycle when the plan broke (see
        ``_plan_until``)."""
        if self.due(now):
            self._renew(now)
            if self.lapsed:
                return None
        elif not self.behind:
            return None
        return self._plan_ahead(manager, state, not_armed)

    def _renew(self, now: float) -> None:
        """A lease of up to ``lease_slots`` from where the op is, as far as the plan goes; a
        lapse resumed in place when it is short (module docstring), else ``lapsed`` and the
        node leaves the timer."""
        if self.lapsed:
            return
        n = self.per_slot
        last_end = self.lease.ends_at
        gap = now - self.renewed_at
        resumable = gap <= RESUME_WITHIN_LEASES * self.lease_slots * self.slot_s
        try:
            sent = self.lease.renew(self.plan, self.lease_slots * n)
        except OpLost:  # deleted (a safe action) or its place not known: no resume
            self.lapsed = "op lost"
            return
        except ValueError:  # under two frames planned past the op's: no renewal yet
            # The op sends out its lease (never past the plan) and stops; planning goes on and
            # a later renewal resumes it. A gait's first cycle planned under a 50 % cap fell
            # behind the op this way, and leaving planned it all again (M64, M65, D66).
            if not resumable:
                self.lapsed = "plan ran short"
            return
        lapse = ""
        if sent >= last_end:
            lapse = "ran out"  # the loop came later than the lease: nothing went out since
        elif sent == self.base and gap >= STALLED_SLOTS * self.slot_s:
            # Not one frame in slots' time: the op's timer ended between the last renewal's
            # read and its setup (CyclicLease), and it would stay silent with a full count
            # while this loop renewed it, the gait "running" with nothing on the bus.
            lapse = "stalled"
        if lapse and not resumable:
            self.lapsed = lapse
        elif lapse:
            self.lease.resume()  # slot `sent` now, with the count this renewal set
            self.started = now - sent / n * self.slot_s  # the new phase (``_plan_ahead``)
            self.resumed.append((lapse, gap))
        self.since_renewal_s, self.renewed_at = gap, now
        self.base = sent
        self.lease_frames = self.lease.ends_at - sent  # as set: bounded by the plan
        self.renewals += 1
        self.plan.forget_before(sent // n - 1)

    def abort(self) -> None:
        """Nothing more from the op, now (TX_DELETE): every stop and trip path."""
        self.lease.stop()
        self.lease.close()

    def leave(self) -> dict[int, int]:
        """End the op at once and return each joint's last sent position, so the cycle loop's
        step limit goes on from it (slots planned but not sent are dropped). The op's count
        can be a frame short (a renewal's race, or a frame sent after the read): the kernel's
        count of its frames makes it good (``Lease.settled``), else the cycle loop would step
        from the slot before the one the joint is at, a slot's step past the limit."""
        try:
            counted = self.lease.sent()
            self.lease.stop()
            sent = self.lease.settled(counted)
        finally:
            self.abort()
        n, out = self.per_slot, {}
        for i, j in enumerate(self.plan.joints):
            last = (sent - 1 - i) // n if sent - 1 - i >= 0 else None
            if last is not None and (pos := self.plan.position(last)) is not None:
                out[j] = pos[i]
        return out


def _encode(motor: int, mode: int, setpoint: int, stiffness: int) -> bytes:
    return bytes(h2.encode_joint_control(motor, mode, setpoint, stiffness).data)
