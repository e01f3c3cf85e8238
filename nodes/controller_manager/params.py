"""The controller manager's params (config ``nodes[].params``): checked with the config file,
before anything starts."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec

from exolink.limits.maccepa import BoardLimits
from exolink.protocol import h2

# A planned set-point may reach the bus at most this long after the watchdog's first disable
# frame (hung detection's own budget): lease_ms <= leased heartbeat deadline + this.
LEASE_PAST_TRIP_MS = 60
# An unset lease_ms: the leased deadline, and never under this (five 20 ms slots: a renewal every
# 1.5 slots keeps three ahead).
LEASE_MIN_MS = 100
# On the timer, the loop wakes every this much of the shorter of its lease and its leased
# deadline (exolink.liveness): both then hold against a wake 60 % of them late.
TIMED_WAKE = 0.4


class ControllerSpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    name: str
    type: str
    params: dict[str, Any] = {}
    budget_ms: Annotated[float, msgspec.Meta(gt=0, le=1000)] | None = None


class ManagerParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    # (Joint limits, caps and the step limit are the config's `limits:` section.)
    # Send the accepted angles in force to the H2 at start (the operator's, if they sent any).
    send_limits_on_start: bool = True
    # CPU one controller's update may take per cycle before it is deactivated.
    update_budget_ms: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 2.0
    h2_timeout_ms: Annotated[int, msgspec.Meta(ge=15, le=1000)] = 50
    # The cycle loop (feedback controllers: PID, impedance, MACCEPA) runs read -> update ->
    # write once per this many H2 cycles (10 ms each), on the newest angle frame; the loop
    # sleeps in between instead of waking per frame. Planned controllers use slot_ms instead.
    cycles_per_update: Annotated[int, msgspec.Meta(ge=1, le=5)] = 1
    # Planned controllers (the gait, trajectories) put a set-point per joint on the bus every
    # slot_ms on the kernel's timer (timed.py); leased for lease_ms after the manager's last
    # renewal, so a manager that stops renewing stops moving within that (it must not exceed
    # the manager's heartbeat deadline + 60 ms: checked at start). Unset: the deadline it is
    # judged by while only the timer sends (``leased_deadline_ms``, 200 in the configs).
    slot_ms: Annotated[int, msgspec.Meta(ge=10, le=100, multiple_of=10)] = 20
    # False: planned controllers run in the cycle loop like the others, one set-point per
    # update (no send op is made).
    timer: bool = True
    lease_ms: Annotated[int, msgspec.Meta(ge=20, le=500)] | None = None
    safe_action: Literal["disable", "stop"] = "disable"
    require_armed: bool = True
    # MACCEPA boards this manager drives (maccepa<N>/setpoint|duty|gains) and their limits.
    maccepa: list[BoardLimits] = []
    controllers: list[ControllerSpec] = []  # loaded (inactive) at start

    def lease_for(self, deadline_ms: int) -> int:
        """The lease (ms) of a manager judged by ``deadline_ms`` while only its timer sends:
        ``lease_ms``, else that deadline, at least ``LEASE_MIN_MS`` where the deadline allows
        it (a manager judged by its own 50 ms: the 100 ms it had before leases followed the
        deadline), at most 500 ms."""
        if self.lease_ms is not None:
            return self.lease_ms
        floor = min(LEASE_MIN_MS, deadline_ms + LEASE_PAST_TRIP_MS)
        return min(500, max(2 * self.slot_ms, floor, deadline_ms))

    def timed_wake_s(self, deadline_ms: int, shortest_s: float) -> float:
        """How often the loop wakes while the timer sends, judged by ``deadline_ms`` then (its
        leased deadline): ``TIMED_WAKE`` of the shorter of lease and deadline, each wake
        renewing, never under ``shortest_s``. Stock (200 ms both): every 80 ms. A lease that
        would outlast the watchdog's disable by more than ``LEASE_PAST_TRIP_MS``: ValueError."""
        lease_ms = self.lease_for(deadline_ms)
        if lease_ms > deadline_ms + LEASE_PAST_TRIP_MS:
            raise ValueError(
                f"lease_ms {lease_ms} exceeds the leased heartbeat deadline {deadline_ms} ms "
                f"+ {LEASE_PAST_TRIP_MS}: a hung manager's set-points would outlast the "
                f"watchdog's disable by more than {LEASE_PAST_TRIP_MS} ms"
            )
        return max(shortest_s, TIMED_WAKE * min(lease_ms, deadline_ms) / 1000)

    def __post_init__(self) -> None:
        gap_ms = (self.cycles_per_update + 1) * h2.PERIOD_S * 1e3  # the longest between reads
        if self.cycles_per_update > 1 and self.h2_timeout_ms <= gap_ms:
            raise ValueError(
                f"h2_timeout_ms {self.h2_timeout_ms} must exceed {gap_ms:g} ms with "
                f"cycles_per_update {self.cycles_per_update}"
            )
        if self.lease_ms is not None and self.lease_ms < 2 * self.slot_ms:
            raise ValueError(
                f"lease_ms {self.lease_ms} must hold two slots (slot_ms {self.slot_ms}): "
                "the lease is renewed every second slot"
            )
