"""Set-points planned ahead and sent on a timer the manager does not run: the kernel's
broadcast manager on SocketCAN (``exolink.cyclic.CyclicLease``), a thread elsewhere.

While every active controller is ``planned`` (its outputs are a function of time: the gait
pattern, a trajectory), the manager computes each slot's set-points a few slots ahead, through
the same ``Manager.cycle`` (limits, caps, step limit, budgets) the cycle loop uses, and hands
the frames to one send op on the joint-control id: the joints of a slot one after another,
``slot_s / joints`` apart, so each joint's frames are ``slot_s`` apart on the timer. Python
then runs once per renewal (every second slot), not per frame.

The op is leased: it sends at most ``lease_slots`` slots after the last renewal. Renewals come
before the loop's heartbeat, so a manager stopped, hung, starved or killed stops renewing
before it stops beating, and the op ends at most ``lease_slots x slot_s`` after the last beat:
with the stock 100 ms lease and 50 ms heartbeat deadline, at most 50 ms after the watchdog's
first disable frame. Any stop, trip or switch deletes the op first (``abort``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import structlog
from exolink.controller import State
from exolink.cyclic import Lease
from exolink.nodes.controller_manager.manager import Cycle, Manager
from exolink.protocol import h2

log = structlog.get_logger()
# Slots planned at most per wake of the loop (one every 20 ms, renewing every second slot).
PLAN_PER_WAKE = 3


@dataclass
class Plan:
    """Frames by index on the op's timer (slot k, joint i: ``k x joints + i``) and, per slot,
    the positions they carry (to give the step limit back what was really sent)."""

    joints: tuple[int, ...]  # joint indices, in the order they go out within a slot
    frames: dict[int, bytes] = field(default_factory=dict)
    positions: dict[int, tuple[int, ...]] = field(default_factory=dict)  # slot -> degrees
    slots: int = 0  # slots planned so far


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
    ) -> None:
        """``encode(motor, mode, setpoint, stiffness)``: a joint-control payload (the node's
        cache of encoded frames; default the H2 codec's); ``alive``: called after each slot
        planned (the node's heartbeat: on the board proxy the first plan of a process took
        300 ms for three slots, past the manager's 50 ms deadline)."""
        self.alive = alive or (lambda: None)
        self.lease, self.slot_s, self.lease_slots = lease, slot_s, lease_slots
        self.encode = encode or _encode
        self.plan = Plan(joints)
        self.t0 = t0  # controller time (epoch s) of slot 0
        self.started = now  # monotonic time of slot 0
        self.base = 0  # the op's frame the last start or renewal put first
        self.lease_frames = 0  # and how many it allowed
        self.renewed_at = now  # monotonic
        self.since_renewal_s = 0.0  # between the last two renewals (a lapse: how late)
        self.renewals = 0
        self.lapsed = False

    @property
    def per_slot(self) -> int:
        return len(self.plan.joints)

    def _plan_until(
        self, manager: Manager, state: State, slot: int, not_armed: str | None
    ) -> Cycle | None:
        """Plan slots up to ``slot`` (exclusive); a Cycle when one cannot be planned (a
        controller failed, or wrote other joints): the plan ends there and the caller acts on
        it (safe frames, leaving the timer)."""
        steps = max(1, round(self.slot_s / h2.PERIOD_S))
        plan = self.plan
        while plan.slots < slot:
            k = plan.slots
            out = manager.cycle(
                state, self.t0 + k * self.slot_s, self.slot_s, not_armed, steps, switches=False
            )
            writes = sorted(out.writes, key=lambda w: w.motor)
            if out.safe or out.safe_boards or tuple(w.motor - 1 for w in writes) != plan.joints:
                return out
            for i, w in enumerate(writes):
                plan.frames[k * self.per_slot + i] = self.encode(
                    w.motor, w.mode, w.setpoint, w.stiffness
                )
            plan.positions[k] = tuple(w.setpoint for w in writes)
            plan.slots += 1
            self.alive()
        return None

    def begin(self, manager: Manager, state: State, not_armed: str | None) -> Cycle | None:
        """Plan the first slots and start the op (slot 0 now). A few only: each is a cycle of
        the manager's (a lease's worth took tens of ms under TCG, in one wake); the renewals
        catch up, ``PLAN_PER_WAKE`` at a time."""
        first = min(PLAN_PER_WAKE, self.lease_slots)
        if (broke := self._plan_until(manager, state, first, not_armed)) is not None:
            return broke
        n = self.per_slot
        frames = [self.plan.frames[i] for i in range(min(self.lease.ring, self.plan.slots * n))]
        self.lease.start(frames, first * n)
        self.lease_frames = first * n
        return None

    def due(self, now: float) -> bool:
        """Two slots or fewer are left of a full lease (by the clock: no system call): every
        second slot once the plan is a lease ahead, at each wake while it is not (a new op's
        first, short lease)."""
        left = (self.base + self.lease_frames) / self.per_slot - (now - self.started) / self.slot_s
        return left <= self.lease_slots - 2

    def keep(
        self, manager: Manager, state: State, not_armed: str | None, now: float
    ) -> Cycle | None:
        """Renew the lease if due: plan what it needs and hand it over. A Cycle when the plan
        broke (see ``_plan_until``)."""
        if not self.due(now):
            return None
        n = self.per_slot
        at = int((now - self.started) / self.slot_s)  # the slot going out about now
        until = min(at + self.lease_slots + 2, self.plan.slots + PLAN_PER_WAKE)
        if (broke := self._plan_until(manager, state, until, not_armed)) is not None:
            return broke
        last_lease = self.lease_frames
        sent = self.lease.renew(self.plan.frames, self.lease_slots * n)
        if sent >= self.base + last_lease:
            self.lapsed = True  # the loop came later than the lease: nothing went out since
        self.since_renewal_s, self.renewed_at = now - self.renewed_at, now
        self.base = sent
        self.lease_frames = min(self.lease_slots * n, self.plan.slots * n - sent)
        self.renewals += 1
        for i in [i for i in self.plan.frames if i < sent - n]:
            del self.plan.frames[i]
        for k in [k for k in self.plan.positions if k < sent // n - 1]:
            del self.plan.positions[k]
        return None

    def abort(self) -> None:
        """Nothing more from the op, now (TX_DELETE): every stop and trip path."""
        self.lease.stop()
        self.lease.close()

    def leave(self) -> dict[int, int]:
        """End the op at once and return each joint's last sent position, so the cycle loop's
        step limit goes on from it (slots planned but not sent are dropped)."""
        try:
            sent = self.lease.sent()
        finally:
            self.abort()
        n, out = self.per_slot, {}
        for i, j in enumerate(self.plan.joints):
            last = (sent - 1 - i) // n if sent - 1 - i >= 0 else None
            if last is not None and last in self.plan.positions:
                out[j] = self.plan.positions[last][i]
        return out


def _encode(motor: int, mode: int, setpoint: int, stiffness: int) -> bytes:
    return bytes(h2.encode_joint_control(motor, mode, setpoint, stiffness).data)
