"""The controller manager's logic, free of any bus or Zenoh session (so tests feed it states).

One ``Manager`` owns the loaded controllers, the claims on command interfaces (one owner each),
the switches waiting for a cycle boundary, and turns one H2 cycle into the joint commands and the
MACCEPA board commands to write (``maccepa<N>/setpoint|duty|gains``, each inside that board's
``BoardLimits``). The node around it (``ControllerManagerNode``) reads the bus, checks arming and writes.
Everything that changes what is active happens inside ``cycle`` (or ``stop_all`` /
``joints_disabled``) under one lock, so no cycle ever sees half a switch. What it holds and
hands out (a loaded controller, a switch, a cycle's writes) is ``slots``; how an update is
judged (its CPU against its budget, the values it returned) is ``budget``; the boards' half of
a cycle is ``boards``. A ``Manager`` is also ``Loaded`` (loading, unloading, describing its
controllers: ``loaded``) and ``Switching`` (switches checked, queued and applied: ``switching``);
this module is its cycle.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import Any

import structlog
from exolink.nodes.controller_manager.boards import BoardOutputs
from exolink.nodes.controller_manager.budget import CPU_STEP_S, GC_CLOCK, check_values, overran
from exolink.nodes.controller_manager.loaded import Loaded
from exolink.nodes.controller_manager.slots import (
    PLANNED,
    Cycle,
    Slot,
    Switch,
    Write,
)
from exolink.nodes.controller_manager.switching import Switching

from exolink.control.controller import (
    SafeStop,
    State,
)
from exolink.limits.joints import POSITION, STIFFNESS, TORQUE, Limits
from exolink.limits.maccepa import BoardLimits
from exolink.protocol.h2 import JOINTS, PERIOD_S

log = structlog.get_logger()


class Manager(Loaded, Switching):
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
        self.limits_version = 0  # counts ``set_limits``: part of ``plan_key``
        self._planned_at: tuple[int, frozenset[str]] = (-1, frozenset())  # (version, _planned)

    def set_limits(self, limits: Limits) -> None:
        """The limits in force from the next cycle on (an operator narrowed or reset them)."""
        with self.lock:
            self.limits = limits
            self.version += 1
            self.limits_version += 1

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
        outputs a function of time, joint positions only). Kept per ``version`` (every load,
        unload and state change counts): asked five times a cycle with a feedback controller
        beside the gait, it was ~0.5 ms of each 100 Hz cycle on the board proxy (cProfile, F67)."""
        if self._planned_at[0] != self.version:
            self._planned_at = (
                self.version,
                frozenset(
                    s.name
                    for s in self.slots.values()
                    if s.state == "active"
                    and type(s.ctrl).planned
                    and all(c.endswith("/position") for c in s.claims)
                ),
            )
        return self._planned_at[1]

    def plannable(self) -> bool:
        """An active controller is ``planned`` and no switch waits: its set-points can be
        planned ahead and left to the kernel's timer (the others, feedback controllers, stay
        in the cycle loop: ``cycle(part=UNPLANNED)``)."""
        with self.lock:
            return not self.pending and bool(self._planned())

    def plan_key(self) -> tuple[object, ...]:
        """What a plan on the kernel's timer was made from: the limits, and each planned
        controller with its revision (activations, commands). A speed or index given to a gait
        while its cycle was replayed changed nothing on the bus (the timer went on replaying the
        old speed), so the timer ends when this changes; a feedback controller loaded, stopped
        or failed beside the plan does not change it (its failure ended the gait's timer on the
        board proxy, and the plan's restart was a 108 ms stall: A67)."""
        with self.lock:
            planned = sorted(self._planned())
            return self.limits_version, tuple((n, self.slots[n].revision) for n in planned)

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

    def credit_sent(self, frames: dict[int, int]) -> None:
        """Frames the timer sent (joint index -> how many since the last credit) counted as
        their owner's ``written``: a planned slot is counted when the kernel sends it, not
        when it is planned (a replayed gait's are planned once, and its status stood still)."""
        with self.lock:
            for j, count in frames.items():
                keys = _JOINT_KEYS[j][:2]  # position, torque: a planned write is one of them
                owner = next((o for k in keys if (o := self.owners.get(k)) in self.slots), None)
                if owner is not None and count > 0:
                    self.slots[owner].written += count

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
            if part is None or not part[1]:  # a planned slot counts when sent (credit_sent)
                self.slots[owner].written += 1
            out.writes.append(Write(j + 1, mode, sp2, st2))
        if self.boards and not (part is not None and part[1]):
            self.gaps += self.mc.compose(out, owners, held, self.slots)


# Each joint's command interfaces, formatted once: _compose looks them up for six joints each
# cycle (the f-strings were a third of its CPU).
_JOINT_KEYS = tuple((f"{n}/position", f"{n}/torque", f"{n}/stiffness") for n in JOINTS)
