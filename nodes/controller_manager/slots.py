"""What the controller manager holds and hands out: a loaded controller (``Slot``), a switch
waiting for a cycle boundary, one cycle's writes, and the rule a controller's claims obey."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

from exolink.control.controller import INTERFACES, MACCEPA_INTERFACES, Controller
from exolink.control.replies import ControllerInfo
from exolink.limits.maccepa import board_of
from exolink.limits.maccepa import target as board_name
from exolink.protocol.h2 import JOINTS
from exolink.refusal import Refused

# ``Manager.cycle``'s parts: the controllers planned for the timer, or the cycle loop's others.
PLANNED, UNPLANNED = "planned", "unplanned"


class ManagerRefused(Refused):
    """A management request the manager refuses; the text names what is in the way."""


class Held:
    """What every part of ``Manager`` (``Loaded``, ``Switching``, the cycle) shares, set in
    ``Manager.__init__``: declared once, for the type checker."""

    lock: threading.Lock
    slots: dict[str, Slot]
    owners: dict[str, str]  # interface -> active controller
    version: int


@dataclass
class Slot:
    """A loaded controller and what the manager knows of it."""

    name: str
    kind: str
    ctrl: Controller
    claims: tuple[str, ...]
    budget_s: float
    state: str = "inactive"
    error: str = ""
    updates: int = 0
    cpu_s_total: float = 0.0
    cpu_s_max: float = 0.0
    overruns: int = 0
    overran_last: float = 0.0  # CPU of the last update if it overran the budget, else 0
    limited: int = 0
    written: int = 0  # joint set-points written for it
    revision: int = 0  # its activations and commands taken (a gait's speed, index): a plan
    # made before is stale (Manager.plan_key)

    def joints(self) -> set[int]:
        return {JOINTS.index(t) for t in (c.split("/")[0] for c in self.claims) if t in JOINTS}

    def boards(self) -> set[int]:
        """The MACCEPA boards this controller writes (any of their interfaces)."""
        return {b for c in self.claims if (b := board_of(c.split("/")[0])) is not None}

    def status(self) -> ControllerInfo:
        return ControllerInfo(
            name=self.name,
            type=self.kind,
            state=self.state,
            claims=list(self.claims),
            error=self.error,
            updates=self.updates,
            update_ms_mean=round(self.cpu_s_total / self.updates * 1e3, 4)
            if self.updates
            else None,
            update_ms_max=round(self.cpu_s_max * 1e3, 4),
            budget_ms=round(self.budget_s * 1e3, 3),
            overruns=self.overruns,
            limited=self.limited,
            written=self.written,
            own=self.ctrl.status(),
        )


@dataclass(frozen=True, slots=True)
class Write:
    """One joint's command for this cycle, inside every limit (motor 1..6)."""

    motor: int
    mode: int
    setpoint: int
    stiffness: int


@dataclass(frozen=True, slots=True)
class MaccepaWrite:
    """One MACCEPA frame for this cycle, inside the board's limits: ``kind`` is setpoint, duty,
    kp, ki or kd; ``controller`` the board's configured controller type (setpoint and gains)."""

    board: int
    kind: str
    value: float
    controller: str


@dataclass
class Switch:
    """Deactivate some, activate others: applied whole at one cycle boundary, or refused whole."""

    activate: list[str]
    deactivate: list[str]
    done: threading.Event = field(default_factory=threading.Event)
    error: str | None = None


@dataclass
class Cycle:
    """What one cycle asks of the node: frames to write and joints to put in the safe action."""

    writes: list[Write] = field(default_factory=list)
    safe: set[int] = field(default_factory=set)
    maccepa: list[MaccepaWrite] = field(default_factory=list)
    safe_boards: set[int] = field(default_factory=set)  # MACCEPA boards to stop
    controller_s: float = 0.0  # wall time inside controllers' update (the rest is overhead)


def check_claims(name: str, claims: list[str], boards: Any = ()) -> tuple[str, ...]:
    """A controller's own claims: known interfaces, no repeats, not torque and position on one
    joint (the H2 runs one mode per joint), not set-point and duty on one MACCEPA board (a
    set-point frame switches the board to closed loop, a duty frame to open loop); ``boards``:
    the MACCEPA boards the manager is configured to drive."""
    seen: set[str] = set()
    for c in claims:
        target, _, kind = c.partition("/") if isinstance(c, str) else (c, "", "")
        b = board_of(target)
        if b is not None and kind in MACCEPA_INTERFACES:
            if b not in boards:
                configured = ", ".join(board_name(x) for x in sorted(boards)) or "none"
                raise ManagerRefused(
                    f"{name} claims {c}: MACCEPA board {b} is not in the manager's "
                    f"params.maccepa (configured: {configured})"
                )
        elif target not in JOINTS or kind not in INTERFACES:
            raise ManagerRefused(
                f"{name} claims {c!r}: interfaces are <joint>/<{'|'.join(INTERFACES)}> "
                f"with joint one of {', '.join(JOINTS)}, or "
                f"maccepa<board>/<{'|'.join(MACCEPA_INTERFACES)}>"
            )
        if c in seen:
            raise ManagerRefused(f"{name} claims {c} twice")
        seen.add(c)
    for j in JOINTS:
        if f"{j}/torque" in seen and ({f"{j}/position", f"{j}/stiffness"} & seen):
            raise ManagerRefused(f"{name} claims {j}/torque with {j}'s position or stiffness")
    for b in boards:
        if {f"{board_name(b)}/setpoint", f"{board_name(b)}/duty"} <= seen:
            raise ManagerRefused(
                f"{name} claims {board_name(b)}/setpoint with {board_name(b)}/duty"
            )
    return tuple(claims)
