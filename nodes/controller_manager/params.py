"""The controller manager's params (config ``nodes[].params``): checked with the config file,
before anything starts."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec

from exolink.limits.maccepa import BoardLimits
from exolink.protocol import h2


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
    # the manager's heartbeat deadline + 60 ms: checked at start).
    slot_ms: Annotated[int, msgspec.Meta(ge=10, le=100, multiple_of=10)] = 20
    # False: planned controllers run in the cycle loop like the others, one set-point per
    # update (no send op is made).
    timer: bool = True
    lease_ms: Annotated[int, msgspec.Meta(ge=20, le=500)] = 100
    safe_action: Literal["disable", "stop"] = "disable"
    require_armed: bool = True
    # MACCEPA boards this manager drives (maccepa<N>/setpoint|duty|gains) and their limits.
    maccepa: list[BoardLimits] = []
    controllers: list[ControllerSpec] = []  # loaded (inactive) at start

    def __post_init__(self) -> None:
        gap_ms = (self.cycles_per_update + 1) * h2.PERIOD_S * 1e3  # the longest between reads
        if self.cycles_per_update > 1 and self.h2_timeout_ms <= gap_ms:
            raise ValueError(
                f"h2_timeout_ms {self.h2_timeout_ms} must exceed {gap_ms:g} ms with "
                f"cycles_per_update {self.cycles_per_update}"
            )
        if self.lease_ms < 2 * self.slot_ms:
            raise ValueError(
                f"lease_ms {self.lease_ms} must hold two slots (slot_ms {self.slot_ms}): "
                "the lease is renewed every second slot"
            )
