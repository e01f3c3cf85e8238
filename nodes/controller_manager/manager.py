"""The controller manager's logic, free of any bus or Zenoh session (so tests feed it states).

One ``Manager`` owns the loaded controllers, the claims on command interfaces (one owner each),
the switches waiting for a cycle boundary, and turns one H2 cycle into the joint commands and the
MACCEPA board commands to write (``maccepa<N>/setpoint|duty|gains``, each inside that board's
``BoardLimits``). The node around it (``ControllerManagerNode``) reads the bus, checks arming and writes.
Everything that changes what is active happens inside ``cycle`` (or ``stop_all`` /
``joints_disabled``) under one lock, so no cycle ever sees half a switch. What it holds and
hands out (a loaded controller, a switch, a cycle's writes) is ``slots``; how an update is
judged (its CPU against its budget, the values it returned) is ``budget``; the boards' half of
a cycle is ``boards``.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import Any

import msgspec
import structlog
from exolink.nodes.controller_manager.boards import BoardOutputs
from exolink.nodes.controller_manager.budget import CPU_STEP_S, GC_CLOCK, check_values, overran
from exolink.nodes.controller_manager.slots import (
    PLANNED,
    Cycle,
    ManagerRefused,
    Slot,
    Switch,
    Write,
    check_claims,
)

from exolink.control.controller import (
    Controller,
    SafeStop,
    State,
)
from exolink.limits.joints import POSITION, STIFFNESS, TORQUE, Limits
from exolink.limits.maccepa import BoardLimits, board_of
from exolink.plugins import PluginError, find_controller_class
from exolink.protocol.h2 import JOINTS, PERIOD_S
from exolink.refusal import Refused

log = structlog.get_logger()


class Manager:
    def __init__(
        self,
        limits: Limits,
        budget_ms: float,
        boards: list[BoardLimits] | None = None,
        cycles_per_update: int = 1,
    ) -> None:
        self.limits = limits  # in force: the config's, narrowed by an operator (set_limits)
        self.mc = BoardOutputs(boards or [], cycles_per_update)  # the boards' writes (boards.py)
        self.boards = self.mc.limits
        # Rate limits are per 10 ms H2 cycle: an update every n cycles may move n steps (the
        # same speed limit); a held MACCEPA set-point is re-sent every ~100 ms either way.
        self.cycles_per_update = cycles_per_update
        self._steps = cycles_per_update  # of the update being composed (``cycle``)
        self.update_period_s = cycles_per_update * PERIOD_S
        self._period_s = self.update_period_s
        self.default_budget_s = budget_ms / 1e3
        self.lock = threading.Lock()
        self.slots: dict[str, Slot] = {}
        self.owners: dict[str, str] = {}  # interface -> active controller
        self.held: dict[str, Any] = {}  # interface -> last value (a gains triple for gains)
        self.last_pos: list[int | None] = [None] * len(JOINTS)  # last position written
        self.last_torque: list[int | None] = [None] * len(JOINTS)  # last torque written
        self.pending: list[Switch] = []
        self.cycles = 0
        self.gaps = 0  # cycles where a claimed joint got no frame (no value yet)
        self.overhead_s: deque[float] = deque(maxlen=2000)
        self.version = 0  # counts loads, unloads and state changes: what `activity` describes

    def set_limits(self, limits: Limits) -> None:
        """The limits in force from the next cycle on (an operator narrowed or reset them)."""
        with self.lock:
            self.limits = limits
            self.version += 1

    # --- loading ----------------------------------------------------------------------------

    def load(
        self, name: str, kind: str, params: dict[str, Any] | None, budget_ms: float | None = None
    ) -> dict[str, Any]:
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
        return slot.ctrl.command(request)  # a controller's Refused is the caller's

    def state_of(self, name: str) -> dict[str, Any]:
        """One controller's state and why it stopped: what a node that follows a controller
        (the pattern player) asks several times a second. ``status`` sorts the overhead window
        and describes every controller, a millisecond of the manager's GIL its loop waited on."""
        with self.lock:
            slot = self.slots.get(name)
            if slot is None:
                return {"name": name, "state": None, "error": f"no controller {name!r}"}
            return {"name": name, "state": slot.state, "error": slot.error, "written": slot.written}

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

    # --- switching --------------------------------------------------------------------------

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

    # --- the loop ---------------------------------------------------------------------------

    def idle(self, not_armed: str | None) -> None:
        """A loop tick without an H2 cycle: deactivations still apply."""
        with self.lock:
            if self.pending:
                self._apply(None, not_armed)

    def busy(self) -> bool:
        """A controller is active or a switch is queued: the node must be reading the bus."""
        with self.lock:
            return bool(self.pending) or any(s.state == "active" for s in self.slots.values())

    def driving(self) -> bool:
        """A controller is active: the manager writes motion each cycle."""
        with self.lock:
            return any(s.state == "active" for s in self.slots.values())

    def active(self) -> list[str]:
        with self.lock:
            return [s.name for s in self.slots.values() if s.state == "active"]

    def stop_all(self, reason: str) -> Cycle:
        """A trip or a silent H2: every controller inactive until an operator activates it
        again. Returns the joints and MACCEPA boards that were claimed (for the safe action)."""
        out = Cycle()
        with self.lock:
            for slot in self.slots.values():
                if slot.state == "active":
                    out.safe |= slot.joints()
                    out.safe_boards |= slot.boards()
                    self._release(slot, reason)
                    log.warning("controller_stopped", controller=slot.name, reason=reason)
        return out

    def joints_disabled(self, joints: set[int], why: str) -> None:
        """Someone (the watchdog, an operator) disabled or stopped these joints on the bus: the
        next set-point would switch them back on, so their controllers stop now."""
        with self.lock:
            for slot in self.slots.values():
                if slot.state == "active" and slot.joints() & joints:
                    self._release(slot, why)
                    log.warning("controller_stopped", controller=slot.name, reason=why)

    def boards_stopped(self, boards: set[int], why: str) -> None:
        """Someone (the watchdog, an operator through the bridge) stopped these MACCEPA boards'
        control on the bus: the next set-point would switch them back on, so their controllers
        stop now."""
        with self.lock:
            for slot in self.slots.values():
                if slot.state == "active" and slot.boards() & boards:
                    self._release(slot, why)
                    log.warning("controller_stopped", controller=slot.name, reason=why)

    def _planned(self) -> frozenset[str]:
        """Under ``lock``: the active controllers whose set-points can be planned ahead (their
        outputs a function of time, joint positions only)."""
        return frozenset(
            s.name
            for s in self.slots.values()
            if s.state == "active"
            and type(s.ctrl).planned
            and all(c.endswith("/position") for c in s.claims)
        )

    def plannable(self) -> bool:
        """An active controller is ``planned`` and no switch waits: its set-points can be
        planned ahead and left to the kernel's timer (the others, feedback controllers, stay
        in the cycle loop: ``cycle(part=UNPLANNED)``)."""
        with self.lock:
            return not self.pending and bool(self._planned())

    def unplanned(self) -> bool:
        """An active controller is not planned: the cycle loop runs beside the timer."""
        with self.lock:
            planned = self._planned()
            return any(s.state == "active" and s.name not in planned for s in self.slots.values())

    def repeats_slots(self, slot_s: float) -> int | None:
        """The slots after which every planned controller's outputs repeat (the least common
        multiple of their periods), or None: one does not repeat, or not in whole slots."""
        with self.lock:
            slots = 1
            for name in self._planned():
                period = self.slots[name].ctrl.repeats_s()
                if period is None:
                    return None
                k = round(period / slot_s)
                if k < 1 or abs(k * slot_s - period) > 1e-6:
                    return None
                slots = math.lcm(slots, k)
            return slots

    def position_joints(self) -> tuple[int, ...]:
        """The joints whose position a planned controller owns (indices, in order)."""
        with self.lock:
            planned = self._planned()
            return tuple(
                j for j, (key, _t, _s) in enumerate(_JOINT_KEYS) if self.owners.get(key) in planned
            )

    def written_back(self, positions: dict[int, int]) -> None:
        """Slots planned ahead were never sent (the plan was stopped): the step limit goes on
        from the last position that was (joint index -> degrees)."""
        with self.lock:
            for j, v in positions.items():
                if self.last_pos[j] is not None:
                    self.last_pos[j] = v

    def cycle(
        self,
        state: State,
        t: float,
        period: float,
        not_armed: str | None,
        steps: int | None = None,
        switches: bool = True,
        part: str | None = None,
    ) -> Cycle:
        """One H2 cycle (or one planned slot): apply switches, update active controllers,
        saturate, compose frames. ``steps``: the 10 ms step limits this update may move
        (default ``cycles_per_update``; a 20 ms slot: 2). ``switches`` False: a slot planned
        ahead is no boundary (an activation needs where the joints are now). ``part``: only
        the PLANNED controllers (a slot planned for the timer) or only the UNPLANNED ones (the
        cycle loop beside the timer), their joints and boards; None: all.

        Not armed: every active controller stops, and its MACCEPA boards get "stop control"
        from here too (the watchdog stops only the boards in ``watchdog.maccepa_boards``)."""
        out = Cycle()
        with self.lock:
            self.cycles += 1
            self._steps = steps or self.cycles_per_update
            self._period_s = self._steps * PERIOD_S  # an update longer than this is late
            if not_armed:
                for slot in self.slots.values():
                    if slot.state == "active":
                        out.safe_boards |= slot.boards()
                        self._release(slot, not_armed)
                        log.warning("controller_stopped", controller=slot.name, reason=not_armed)
            if self.pending and switches:
                self._apply(state, not_armed)
            if not_armed:
                return out
            planned = self._planned() if part is not None else frozenset()
            for slot in list(self.slots.values()):
                if slot.state == "active" and (
                    part is None or (slot.name in planned) == (part == PLANNED)
                ):
                    self._update(slot, state, t, period, out)
            self._compose(state, out, None if part is None else (planned, part == PLANNED))
        return out

    def _update(self, slot: Slot, state: State, t: float, period: float, out: Cycle) -> None:
        g0, c0, w0 = GC_CLOCK.of_this_thread(), time.thread_time(), time.perf_counter()
        try:
            values = slot.ctrl.update(state, t, period)
            cpu = time.thread_time() - c0 - (GC_CLOCK.of_this_thread() - g0)
            out.controller_s += time.perf_counter() - w0
            bad = check_values(slot, values)
        except SafeStop as exc:
            self._fail(slot, f"asked for the safe action: {exc}", out, error=False)
            return
        except Exception as exc:
            self._fail(slot, f"update raised {type(exc).__name__}: {exc}", out)
            return
        slot.updates += 1
        slot.cpu_s_total += cpu
        slot.cpu_s_max = max(slot.cpu_s_max, cpu)
        if (surely := cpu - CPU_STEP_S) > slot.budget_s:
            slot.overruns += 1
            if why := overran(slot, surely, self._period_s):
                self._fail(slot, why, out)
                return
        else:
            slot.overran_last = 0.0
        if bad:
            self._fail(slot, bad, out)
            return
        self.held.update(values)

    def _fail(self, slot: Slot, reason: str, out: Cycle, error: bool = True) -> None:
        """Deactivate ``slot``; its joints get the safe action, so any other controller driving
        one of them stops too (a disabled joint must not be switched back on by a neighbour)."""
        joints, boards = slot.joints(), slot.boards()
        self._release(slot, reason)
        (log.error if error else log.warning)(
            "controller_failed", controller=slot.name, reason=reason
        )
        for other in self.slots.values():
            if other.state == "active" and (other.joints() & joints or other.boards() & boards):
                what = "a joint" if other.joints() & joints else "a MACCEPA board"
                self._release(other, f"shares {what} with {slot.name}, which failed")
                joints |= other.joints()
                boards |= other.boards()
        out.safe |= joints
        out.safe_boards |= boards

    def _compose(
        self, state: State, out: Cycle, part: tuple[frozenset[str], bool] | None = None
    ) -> None:
        """One frame per claimed joint, inside the limits; a joint whose values are not all
        known yet gets no frame (the H2 keeps what it had). ``part`` (the planned controllers,
        and whether to compose theirs or the others'): only those joints, and the boards only
        with the others."""
        owners, held, limits = self.owners, self.held, self.limits
        if not owners:
            return
        for j, (pos_key, torque_key, stiff_key) in enumerate(_JOINT_KEYS):
            if j in out.safe:
                continue
            torque_owner = owners.get(torque_key)
            if torque_owner is not None:
                v = held.get(torque_key)
                if v is None:
                    self.gaps += 1
                    continue
                mode, sp, st, owner = TORQUE, round(v), 0, torque_owner
            elif (pos_owner := owners.get(pos_key)) is not None:
                stiff = stiff_key in owners
                v = held.get(pos_key)
                s = held.get(stiff_key) if stiff else 0
                if v is None or s is None:
                    self.gaps += 1
                    continue
                sp, st, owner = round(v), round(s), pos_owner
                mode = STIFFNESS if stiff else POSITION
            else:
                continue
            if part is not None and (owner in part[0]) != part[1]:
                continue
            last = self.last_pos[j] if mode != TORQUE else self.last_torque[j]
            sp2, st2 = limits.saturate(j, mode, sp, st, last, self._steps)
            if sp2 != sp or st2 != st:
                self.slots[owner].limited += 1
            if limits.violation(j, mode, sp2, st2) is not None:  # cannot happen: belt
                continue
            if mode != TORQUE:
                self.last_pos[j] = sp2
            else:
                self.last_torque[j] = sp2
            self.slots[owner].written += 1
            out.writes.append(Write(j + 1, mode, sp2, st2))
        if self.boards and not (part is not None and part[1]):
            self.gaps += self.mc.compose(out, owners, held, self.slots)


# Each joint's command interfaces, formatted once: _compose looks them up for six joints each
# cycle (the f-strings were a third of its CPU).
_JOINT_KEYS = tuple((f"{n}/position", f"{n}/torque", f"{n}/stiffness") for n in JOINTS)
