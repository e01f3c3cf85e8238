"""The controller manager's loop while its set-points go out on a timer (``timed``): the op
started once every active controller is planned, the loop's wake while it sends (anyone's
disable, the lease, the heartbeat, the holder), and the joints handed back to the cycle loop
when anything changes (``leave``) or ended at once on every stop and trip path (``abort``).
The node (``node.ControllerManagerNode``) owns one and calls it under its ``io_lock`` where
the methods say so."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import can
from exolink.nodes.controller_manager.frames import joint_payload
from exolink.nodes.controller_manager.timed import PLAN_CHUNK_S, Timed

from exolink import logs
from exolink.canbus import CanOpenError
from exolink.canbus.held import held_socket
from exolink.canbus.leases import open_lease
from exolink.liveness import Pace
from exolink.protocol import h2

if TYPE_CHECKING:
    from exolink.nodes.controller_manager.node import ControllerManagerNode

# Renewals between two credits of the op's frames to their controllers' ``written`` (~2 s at
# the stock renewal every 80 ms): a credit each renewal was ~4 % of a wake's CPU (cProfile on the
# board proxy, E65), for a count the pattern player reads every 2 s.
CREDIT_EVERY = 25


class TimerLoop:
    """The node's timer side: one ``Timed`` op at a time (``timed``: None while the cycle
    loop writes), and its counters for the node's status."""

    def __init__(self, node: ControllerManagerNode, beat_s: float, lease_ms: int) -> None:
        self.node = node
        self.beat_s = beat_s  # the loop's wake while the timer sends
        self.lease_ms = lease_ms  # ManagerParams.lease_for
        self.timed: Timed | None = None
        self.runs = 0
        self.plan_key: tuple[object, ...] = ()  # what the op was planned from (Manager.plan_key)
        self.beside = False  # the cycle loop runs beside the timer (see ``start``)
        self.refused = ""
        self.refusals = 0
        self.lapses = 0
        self.resumes = 0  # of the lapses, resumed in place (Timed._renew)
        self.renewals = 0  # of the ops that ended
        self.sent = 0  # frames the ops that ended sent, by the kernel's count

    @property
    def sending(self) -> bool:
        return self.timed is not None

    def status(self) -> dict[str, Any]:
        """The ``timer`` part of the node's status."""
        timed = self.timed
        return {
            "sending": timed is not None,
            "runs": self.runs,
            "renewals": self.renewals + (timed.renewals if timed else 0),
            # frames the timer sent: the running op's as of its last renewal
            "sent": self.sent + (timed.base if timed else 0),
            "lapses": self.lapses,
            "resumes": self.resumes,
            "refused": self.refused,
            # slots computed through the manager, and the cycle replayed (0: none yet)
            "computed": timed.computed if timed else 0,
            "plan_cpu_ms": round(timed.plan_cpu_s * 1e3, 1) if timed else 0,
            # the op's frames its count had lost and the kernel's own count found, and the
            # kernel's interval (trimmed)
            "recounted": timed.lease.recounted if timed else 0,
            "restarted": timed.lease.restarted if timed else 0,
            "interval_us": round(timed.lease.interval_s * 1e6, 1) if timed else 0,
            "repeating": timed.plan.period or 0
            if timed and timed.plan.cycle_from is not None
            else 0,
        }

    def start(self) -> None:
        """Every active controller is planned: from now their set-points go out on a timer,
        planned a few slots ahead, and this loop wakes only to renew the lease."""
        n = self.node
        state, not_armed = n.last_state, n.not_armed()
        if state is None or not_armed:
            return
        p, can_cfg = n.params, n.ctx.config.can
        with n.io_lock:
            joints = n.manager.position_joints()
            if not joints or self.timed is not None:
                return
            # Feedback controllers beside the plan: the cycle loop runs too, and the node is
            # judged by its own deadline (followed by ``keep`` as they come and go). Alone, the
            # lease bounds a hang's motion, and it is judged by that from here: nothing is sent
            # until the op starts, and the op's opening and first slots, preempted on a capped
            # CPU, outlasted its own 50 ms.
            beside = n.manager.unplanned()
            pace = Pace.OWN if beside else Pace.LEASED
            n.beat(pace)
            ival_us = round(p.slot_ms * 1e3 / len(joints))  # the joints of a slot spread over it
            lease_slots = self.lease_ms // p.slot_ms
            # two leases and a slot each side: a renewal's count is bounded by the slots placed
            # past the old count's end (CyclicLease.renew), and stays a whole lease
            ring = min(2 * lease_slots + 2, 256 // len(joints)) * len(joints)
            t0 = time.perf_counter()
            try:
                lease = open_lease(
                    can_cfg.interface,
                    can_cfg.channel,
                    n.bus,
                    h2.JOINT_CONTROL,
                    ival_us / 1e6,
                    ring,
                    # the supervisor's copy: its watchdog deletes the op at every safe action
                    held_socket() if can_cfg.interface == "socketcan" else None,
                )
            except (CanOpenError, ValueError) as exc:  # the cycle loop goes on writing them
                self.refused = str(exc)
                self.refusals += 1  # tried again each cycle: logged rarely
                if logs.rarely(self.refusals):
                    n.log.error("timer_unavailable", error=str(exc))
                return
            opened = time.perf_counter()
            slot_s = ival_us * len(joints) / 1e6
            timed = Timed(
                lease,
                joints,
                slot_s,
                lease_slots,
                time.time(),
                time.monotonic(),
                joint_payload,
                lambda: n.beat(pace),
                n.manager.repeats_slots(slot_s),
            )
            broke = timed.begin(n.manager, state, not_armed)  # beats after each slot
            if broke is not None:
                timed.abort()
                n._send(n._safe_frames(broke))
                return
            self.timed, self.plan_key = timed, n.manager.plan_key()
            self.runs += 1
            self._beside(beside)
        n.log.info(
            "timer_started",
            joints=[h2.JOINTS[j] for j in joints],
            slot_ms=p.slot_ms,
            open_ms=round((opened - t0) * 1e3, 2),
            plan_ms=round((time.perf_counter() - opened) * 1e3, 2),
            plan_cpu_ms=round(self.timed.plan_cpu_s * 1e3, 2) if self.timed else None,
        )
        # Alive after the start's last slot and its log line, not only at the next wake's
        # beat after a read: under a 50 % cap the line and the wait took the gap since the
        # last slot's beat to 119 ms, over the lease's 100 (H69, a trip at the gait's start).
        n.beat(pace)

    def wake(self) -> None:
        """One wake of the loop while the timer sends: anyone's disable read at once, the lease
        renewed when due, then the heartbeat (after the renewal: the lease never outlives the
        last beat by more than itself), the holder, arming. Anything else that changed (a switch
        waiting, a controller stopped, the limits) hands the joints back to the cycle loop."""
        n, clock = self.node, self.node.clock  # its phases: "timer <phase>" in loop_cpu
        reader, timed = n.reader, self.timed
        assert reader is not None and timed is not None
        try:  # a chunk's wait while the plan is behind (a gait's first cycle): planning takes
            # half the loop's time, not all of it (at nice -20 that starved the h2 reader: H64)
            frames = reader.read(PLAN_CHUNK_S if timed.behind else self.beat_s)
        except (can.CanError, OSError) as exc:
            n.log.error("bus_read_error", error=str(exc))
            self.leave(orderly=False)
            return
        clock.mark("timer read")  # the wait's wake-up and the sockets' drain
        if frames:
            n._stops(self._decoded(frames))
        if self.timed is None:
            return
        # Alive before the renewal's planning too (a gait's first cycle is planned slot by slot,
        # beating after each): any beat after the last renewal keeps the lease's bound. Judged
        # by the leased deadline (exolink.liveness): the op ends with its lease.
        n.beat(Pace.LEASED)
        clock.mark("timer beat")
        self.keep()
        clock.mark("timer keep")  # the lease's renewal when due
        if self.timed is not None:  # ended meanwhile: the main loop's next beat says how
            n.beat(Pace.LEASED)
        n.api.check_presence()
        n.maybe_tell()
        clock.mark("timer rest")

    def _beside(self, beside: bool) -> None:
        """Whether the cycle loop runs beside the timer (a feedback controller is active), and
        the frames that wake the node with it: alone, no angle frame (with a feedback
        controller, every cycle's)."""
        n, self.beside = self.node, beside
        if n.reader is not None and n._one_socket():
            skip = () if beside else (h2.JOINT_ANGLES,)
            n.reader.set_ids([i for i in n.read_ids if i not in skip])

    def keep(self) -> None:
        """The timer's lease renewed when due; anything the plan was made from that changed
        (arming, a switch waiting, a planned controller stopped or commanded, the limits)
        hands the joints back to the cycle loop first. A feedback controller that stops
        beside it changes only whether the cycle loop runs too."""
        n = self.node
        timed = self.timed
        if timed is None:
            return
        not_armed = n.not_armed()
        changed = n.manager.plan_key() != self.plan_key
        if not_armed or changed or not n.manager.plannable():
            why = not_armed or ("the controllers changed" if changed else "not all planned")
            n.log.info("timer_left", why=why, renewals=timed.renewals)
            self.leave(orderly=not not_armed)
            return
        if (beside := n.manager.unplanned()) != self.beside:
            with n.io_lock:
                self._beside(beside)
        with n.io_lock:
            if self.timed is None:
                return
            broke = timed.keep(n.manager, n.last_state, None, time.monotonic())  # type: ignore[arg-type]
            if broke is not None:
                self.abort()
                n._send(n._safe_frames(broke))
        if timed.renewals % CREDIT_EVERY == 0:
            self.credit(timed)
        for how, gap_s in timed.resumed:
            self._lapse(how, gap_s, timed.renewals, resumed=True)
        timed.resumed.clear()
        if timed.lapsed:
            self._lapse(timed.lapsed, timed.since_renewal_s, timed.renewals, resumed=False)
            self.leave(orderly=True)

    def _lapse(self, how: str, gap_s: float, renewals: int, resumed: bool) -> None:
        """A lapse counted and logged: resumed in place, or the joints handed back."""
        self.lapses += 1
        self.resumes += resumed
        self.node.log.warning(
            "timer_lease_lapsed",
            how=how,
            resumed=resumed,
            renewals=renewals,
            renewal_gap_ms=round(gap_s * 1e3, 1),
            lease_ms=self.lease_ms,
        )

    def credit(self, timed: Timed) -> None:
        """The frames the op sent since the last credit (by its count at the last renewal)
        to their controllers' ``written``: frame k of the op is joint k mod n's."""
        a, b, joints = timed.credited, timed.base, timed.plan.joints
        if b <= a:
            return
        n = len(joints)
        self.node.manager.credit_sent(
            {j: (b - i + n - 1) // n - (a - i + n - 1) // n for i, j in enumerate(joints)}
        )
        timed.credited = b

    def _decoded(self, frames: list[Any]) -> list[tuple[Any, Any]]:
        """Frames read while the timer sends (anyone's disable or stop), decoded for the
        caller's ``_stops``; the angle frames, read only beside a feedback controller, are not
        news here."""
        view = self.node.view
        return [(f, view.decode(f)) for f in frames if f.arbitration_id != h2.JOINT_ANGLES]

    def drives(self, joints: set[int]) -> bool:
        """The op sends set-points for one of ``joints`` (indices)."""
        return self.timed is not None and not joints.isdisjoint(self.timed.plan.joints)

    def abort(self) -> None:
        """Under ``io_lock``: the timer's op ends now (every stop and trip path)."""
        if self.timed is not None:
            self.timed.abort()
            self._end()

    def leave(self, orderly: bool) -> None:
        """Back to the cycle loop; ``orderly``: its step limit goes on from what was sent, by
        the op's count made good by the kernel's once it is deleted (``Timed.leave``)."""
        n = self.node
        with n.io_lock:
            if self.timed is None:
                return
            if not orderly:
                self.timed.abort()
                self._end()
                return
            n.manager.written_back(self.timed.leave())
            self._end()

    def _end(self) -> None:
        n = self.node
        if self.timed is not None:
            self.credit(self.timed)
            self.renewals += self.timed.renewals
            self.sent += self.timed.base
        self.timed = None
        if n.reader is not None and n.reader.ids != frozenset(n.read_ids):
            n.reader.set_ids(n.read_ids)
        # the angle frames the loop did not read meanwhile are no silence, and no period
        n.last_angle_ts, n.last_angle_mono = None, time.monotonic()
