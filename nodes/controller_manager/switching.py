"""Switches between controllers (``Manager`` is one of these): checked when asked (names,
states, one owner per command interface, one mode per joint, one drive per board), queued, and
applied only at a cycle boundary (``Manager.cycle``), under the manager's lock, so no cycle sees
half a switch. A claim handed over continues its step limit from what the previous owner last
wrote; one nobody was writing starts from where the joint or board is."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import structlog
from exolink.nodes.controller_manager.boards import BoardOutputs
from exolink.nodes.controller_manager.slots import Held, ManagerRefused, Slot, Switch

from exolink.control.controller import State
from exolink.limits.maccepa import board_of
from exolink.protocol.h2 import JOINTS

log = structlog.get_logger()


class Switching(Held):
    pending: list[Switch]
    held: dict[str, Any]
    last_pos: list[int | None]
    last_torque: list[int | None]
    mc: BoardOutputs

    if TYPE_CHECKING:

        def _slot(self, name: str) -> Slot: ...

    def request(self, switch: Switch) -> None:
        """Check what can be checked now (names, states) and queue for the next boundary."""
        with self.lock:
            self._precheck(switch)
            self.pending.append(switch)

    def withdraw(self, switch: Switch) -> bool:
        """Take back a switch no cycle applied; False when one did meanwhile."""
        with self.lock:
            if switch in self.pending:
                self.pending.remove(switch)
                return True
            return False

    def _precheck(self, sw: Switch) -> None:
        if not sw.activate and not sw.deactivate:
            raise ManagerRefused("nothing to switch: name controllers to activate or deactivate")
        if set(sw.activate) & set(sw.deactivate):
            raise ManagerRefused("a controller cannot be activated and deactivated at once")
        for n in sw.deactivate:
            if self._slot(n).state != "active":
                raise ManagerRefused(f"{n} is not active")
        for n in sw.activate:
            if self._slot(n).state == "active":
                raise ManagerRefused(f"{n} is already active")
        self._conflicts(sw)

    def _conflicts(self, sw: Switch) -> None:
        """The claims after the switch: one owner per interface, one mode per joint."""
        owners = {i: o for i, o in self.owners.items() if o not in sw.deactivate}
        for n in sw.activate:
            for c in self.slots[n].claims:
                if c in owners:
                    raise ManagerRefused(f"cannot activate {n}: {c} is owned by {owners[c]}")
                owners[c] = n
        self.mc.conflicts(owners)
        for j in JOINTS:
            t, p, s = (owners.get(f"{j}/{k}") for k in ("torque", "position", "stiffness"))
            if t and (p or s):
                raise ManagerRefused(
                    f"cannot switch: {j}/torque ({t}) and {j}/{'position' if p else 'stiffness'} "
                    f"({p or s}) would both drive {j}"
                )
            if s and not p:
                raise ManagerRefused(
                    f"cannot switch: {j}/stiffness ({s}) needs {j}/position claimed too "
                    "(stiffness mode carries a position set-point)"
                )

    def _apply(self, state: State | None, not_armed: str | None) -> None:
        """Pending switches, at this boundary. Without a state (no H2 cycle) only switches that
        just deactivate apply: activating needs where the joints are."""
        keep: list[Switch] = []
        for sw in self.pending:
            if sw.activate and state is None:
                keep.append(sw)
                continue
            try:
                self._precheck(sw)
                if sw.activate and not_armed:
                    raise ManagerRefused(not_armed)
                for n in sw.activate:
                    for b in sorted(self.slots[n].boards()):
                        got = state.board(b)  # type: ignore[union-attr]
                        if got is None or got.positions is None:
                            raise ManagerRefused(
                                f"cannot activate {n}: no position frame from MACCEPA board {b} "
                                "yet (is it powered and on the bus?)"
                            )
                started: list[Slot] = []
                try:
                    for n in sw.activate:
                        slot = self.slots[n]
                        slot.ctrl.activate(state)  # type: ignore[arg-type]
                        started.append(slot)
                except Exception as exc:
                    for slot in started:
                        self._safe_deactivate(slot)
                    raise ManagerRefused(
                        f"{n} refused to activate: {type(exc).__name__}: {exc}"
                    ) from None
                written = list(self.last_pos)  # before the releases clear them
                written_t = list(self.last_torque)
                written_sp = dict(self.mc.last_sp)
                for n in sw.deactivate:
                    self._release(self.slots[n], "")
                for slot in started:
                    self._claim(slot, state, written, written_sp, written_t)  # type: ignore[arg-type]
            except ManagerRefused as exc:
                sw.error = str(exc)
            sw.done.set()
            log.info(
                "controllers_switched" if sw.error is None else "switch_refused",
                activate=sw.activate,
                deactivate=sw.deactivate,
                error=sw.error,
            )
        self.pending = keep

    def _claim(
        self,
        slot: Slot,
        state: State,
        written: list[int | None],
        written_sp: dict[int, float],
        written_t: list[int | None],
    ) -> None:
        """The step limit of a joint (or a MACCEPA set-point) handed over in this switch
        continues from what its previous owner last wrote; one nobody was writing starts from
        where it is (a board's lever; 0 for a velocity controller; a torque from 0)."""
        slot.state, slot.error = "active", ""
        slot.revision += 1
        self.version += 1
        for c in slot.claims:
            self.owners[c] = slot.name
            target, _, kind = c.partition("/")
            b = board_of(target)
            if b is not None:
                self.mc.claim(b, kind, state, written_sp)
                continue
            j = JOINTS.index(target)
            if kind == "position":
                self.last_pos[j] = written[j] if written[j] is not None else state.position[j]
            elif kind == "torque":
                self.last_torque[j] = written_t[j]

    def _safe_deactivate(self, slot: Slot) -> None:
        try:
            slot.ctrl.deactivate()
        except Exception as exc:  # a broken deactivate must not keep claims
            log.error("controller_deactivate_failed", controller=slot.name, error=str(exc))

    def _release(self, slot: Slot, error: str) -> None:
        self._safe_deactivate(slot)
        slot.state, slot.error = "inactive", error
        self.version += 1
        for c in slot.claims:
            if self.owners.get(c) == slot.name:
                del self.owners[c]
                self.held.pop(c, None)
                target, _, kind = c.partition("/")
                b = board_of(target)
                if b is not None:
                    self.mc.release(b, kind)
                    continue
                if kind == "position":
                    self.last_pos[JOINTS.index(target)] = None
                elif kind == "torque":
                    self.last_torque[JOINTS.index(target)] = None
