"""The controller manager's loaded controllers (``Manager`` is one of these): a controller
prepared (imported, its params checked, configured) before it is loaded, so a replacement is
checked before the one it replaces is touched; unloaded only while inactive; looked up and
described for requests and for the followers (``activity``) that are told of every change."""

from __future__ import annotations

from collections import deque
from typing import Any

import msgspec
import structlog
from exolink.nodes.controller_manager.boards import BoardOutputs
from exolink.nodes.controller_manager.slots import Held, ManagerRefused, Slot, check_claims

from exolink.control.controller import Controller
from exolink.control.replies import ControllerInfo, StateOf
from exolink.limits.joints import Limits
from exolink.limits.maccepa import BoardLimits
from exolink.plugins import PluginError, find_controller_class
from exolink.refusal import Refused

log = structlog.get_logger()


class Loaded(Held):
    limits: Limits
    boards: dict[int, BoardLimits]
    mc: BoardOutputs
    default_budget_s: float
    cycles: int
    gaps: int
    overhead_s: deque[float]

    def load(
        self, name: str, kind: str, params: dict[str, Any] | None, budget_ms: float | None = None
    ) -> ControllerInfo:
        """Import, validate params, configure: the controller is then inactive. Every error
        refuses the load and names the controller and what is wrong."""
        slot = self.prepare(name, kind, params, budget_ms)
        self.add(slot)
        return slot.status()

    def prepare(
        self,
        name: str,
        kind: str,
        params: dict[str, Any] | None,
        budget_ms: float | None = None,
        replacing: bool = False,
    ) -> Slot:
        """A configured controller, not loaded yet (``add``): so a replacement is checked
        before the one it replaces is touched."""
        if not name or not isinstance(name, str) or "/" in name:
            raise ManagerRefused(f"controller name {name!r}: give a plain name")
        with self.lock:
            if name in self.slots and not replacing:
                raise ManagerRefused(f"a controller named {name} is already loaded")
        try:
            cls = find_controller_class(kind)
        except PluginError as exc:
            raise ManagerRefused(str(exc)) from None
        try:
            p = msgspec.convert(params or {}, cls.Params)  # type: ignore[attr-defined]
        except msgspec.ValidationError as exc:
            raise ManagerRefused(f"controller {name} ({kind}) params: {exc}") from None
        if budget_ms is not None and not (
            isinstance(budget_ms, int | float) and 0 < budget_ms <= 1000
        ):
            raise ManagerRefused(f"controller {name}: budget_ms must be in (0, 1000]")
        ctrl: Controller = cls(name, p)
        ctrl.boards = dict(self.boards)
        ctrl.limits = self.limits  # a controller that knows its plan checks it whole
        try:
            ctrl.configure()
            claims = check_claims(name, ctrl.claims(), self.boards)
        except (Refused, ValueError) as exc:
            raise ManagerRefused(f"controller {name} ({kind}): {exc}") from None
        budget = budget_ms / 1e3 if budget_ms is not None else self.default_budget_s
        return Slot(name, kind, ctrl, claims, budget)

    def add(self, slot: Slot, replace: bool = False) -> Slot | None:
        """Load a prepared controller, inactive; ``replace``: in place of an inactive one of
        that name, which is returned (for ``put_back``)."""
        with self.lock:
            old = self.slots.get(slot.name)
            if old is not None and not replace:
                raise ManagerRefused(f"a controller named {slot.name} is already loaded")
            if old is not None and old.state == "active":
                raise ManagerRefused(f"{slot.name} is active: deactivate it first")
            self.slots[slot.name] = slot
            self.version += 1
        log.info(
            "controller_loaded", controller=slot.name, type=slot.kind, claims=list(slot.claims)
        )
        return old

    def put_back(self, slot: Slot, old: Slot | None) -> None:
        """Undo ``add`` of an inactive ``slot`` (its activation was refused): the one it
        replaced comes back, inactive, or nothing of that name."""
        with self.lock:
            if self.slots.get(slot.name) is not slot or slot.state == "active":
                return  # changed meanwhile by another request: that one stands
            if old is None:
                del self.slots[slot.name]
            else:
                self.slots[slot.name] = old
            self.version += 1

    def unload(self, name: str) -> None:
        with self.lock:
            slot = self._slot(name)
            if slot.state == "active":
                raise ManagerRefused(f"{name} is active: deactivate it first")
            del self.slots[name]
            self.version += 1
        log.info("controller_unloaded", controller=name)

    def _slot(self, name: str) -> Slot:
        slot = self.slots.get(name)
        if slot is None:
            names = ", ".join(self.slots) or "none loaded"
            raise ManagerRefused(f"no controller {name!r} (loaded: {names})")
        return slot

    def names(self) -> list[str]:
        with self.lock:
            return list(self.slots)

    def superseded(self, names: list[str], prefix: str) -> list[str]:
        """The active controllers named ``prefix...`` (the operator's one-off holds) that own a
        joint or board one of ``names`` claims."""
        with self.lock:
            wanted = set()
            for n in names:
                slot = self._slot(n)
                wanted |= {c.split("/")[0] for c in slot.claims}
            return sorted(
                {
                    owner
                    for c, owner in self.owners.items()
                    if owner.startswith(prefix) and owner not in names and c.split("/")[0] in wanted
                }
            )

    def owners_of(self, joint: str) -> dict[str, str]:
        """The interfaces of ``joint`` (or of a board, ``maccepa0``) that an active controller
        owns, and who owns them."""
        with self.lock:
            return {k: v for k, v in self.owners.items() if k.split("/")[0] == joint}

    def command(self, name: str, request: dict[str, Any]) -> dict[str, Any]:
        with self.lock:
            slot = self._slot(name)
        reply = slot.ctrl.command(request)  # a controller's Refused is the caller's
        with self.lock:
            slot.revision += 1
        return reply

    def state_of(self, name: str) -> StateOf:
        """One controller's state and why it stopped: what a node that follows a controller
        (the pattern player) asks several times a second. ``status`` sorts the overhead window
        and describes every controller, a millisecond of the manager's GIL its loop waited on."""
        with self.lock:
            slot = self.slots.get(name)
            if slot is None:
                return StateOf(name, None, f"no controller {name!r}")
            return StateOf(name, slot.state, slot.error, slot.written)

    def reads(self) -> tuple[int, frozenset[str]]:
        """(version, what of State beyond positions the loaded controllers read): the node
        reads torque and foot-switch frames only for those (``Controller.reads``)."""
        with self.lock:
            out: frozenset[str] = frozenset()
            for slot in self.slots.values():
                out |= type(slot.ctrl).reads
            return self.version, out

    def activity(self) -> tuple[int, list[tuple[str, str, str, str]]]:
        """(version, (name, type, state, error) per controller): what followers are told on
        every change, so they need not ask several times a second."""
        with self.lock:
            return self.version, [(s.name, s.kind, s.state, s.error) for s in self.slots.values()]

    def status(self) -> dict[str, Any]:
        with self.lock:  # copies only: the loop waits on this lock, so no work inside it
            slots, owners, cycles = list(self.slots.values()), dict(self.owners), self.cycles
            gaps = self.gaps
            over = list(self.overhead_s)
            boards = self.mc.status()
        over.sort()
        return {
            "controllers": [s.status() for s in slots],
            "owners": owners,
            "maccepa": boards,
            "cycles": cycles,
            "gaps": gaps,
            "overhead_us": {
                "n": len(over),
                "p50": round(over[len(over) // 2] * 1e6, 1) if over else None,
                "p99": round(over[int(len(over) * 0.99)] * 1e6, 1) if over else None,
                "max": round(over[-1] * 1e6, 1) if over else None,
            },
        }
