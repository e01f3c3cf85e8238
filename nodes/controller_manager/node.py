"""The controller manager's node: the only writer of motion (its requests: ``api``).

Two ways out for set-points. While every active controller is ``planned`` (the gait, a
trajectory), they are planned a few slots ahead and sent on a timer the loop only renews
(``timed``: the kernel's broadcast manager on SocketCAN; the loop's side: ``on_timer``), and
the loop wakes a few times per lease (``params.TIMED_WAKE``) for the heartbeat and the lease;
anyone's disable wakes it at once (on SocketCAN its one socket then reads only the disables and
stops of id 70: ``frames.one_socket``). Otherwise
(a feedback controller, a switch being applied) the cycle loop (``cycle_loop``) runs read ->
update -> write once per H2 cycle, paced by the joint-angle frame (id 110).

The node reads the H2 frames itself (one FrameReader: angles, torques, foot switches, and joint
control so it sees a disable from anyone), and the status frames of the MACCEPA boards in
``params.maccepa`` (sensors, positions, controller; their duty/stop frame too, so it sees a stop
from anyone), hands each cycle to ``Manager`` with the angle frame's kernel timestamp and the
measured period, and writes what comes back. MACCEPA frames are decoded by the MACCEPA codec
after the H2 codec had its say (the ids overlap: protocol/README.md); a frame neither decodes is
counted (``malformed`` in ``exolink controllers list --json``) and skipped. Safety around the loop:

- nothing is written unless the watchdog is armed and someone holds motion (``intent``); a trip
  (seen on Zenoh, or as its disable frames on the bus, whichever comes first) deactivates every
  controller, and they stay inactive until an operator re-arms and activates them again; a
  holder lost stops them all and trips the watchdog;
- every output is saturated to the limits in force (the config's ``limits:``, narrowed by an
  operator: ``intent``), which are also sent to the H2 at start;
- a type 4/5 frame for a claimed joint from any sender stops the controllers driving it (their
  next set-point would switch the joint back on); so does "stop control" for a claimed board;
  a disable asked of this node is sent after the cycle in flight, never before its set-points;
- the safe action of a MACCEPA board is "stop control", sent by this node whenever a controller
  on it fails or stops, and on a trip (the watchdog also stops ``watchdog.maccepa_boards``, which
  must include every board configured here: checked at start);
- no angle frame for ``h2_timeout_ms`` while controllers are active: their joints get the safe
  action and every controller stops (the watchdog trips on the same silence a little later;
  on the timer the loop reads no angle frame, and the watchdog's trip ends it);
- on the timer, anything that ends it (a stop, a trip, anyone's disable, not armed, the
  holder lost) deletes the send op before anything else, and a lease bounds what a manager
  that stops renewing (stopped, hung, starved) leaves on the bus;
- the loop beats every cycle and at least every ``BEAT_S``: a hung manager is the watchdog's
  (``heartbeat_deadline_ms: 50`` in the configs); while only the timer sends, its beats say
  so and it is judged by ``leased_deadline_ms`` (200 in the configs): a hang's motion then
  ends with the lease (200 ms), no later than the watchdog's disable; any trip deletes the op
  before its first disable frame (the supervisor holds the op's socket: exolink.canbus.held).

Off the bus while idle: with no controller active and no switch queued the node holds no socket
that frames reach (a send-only bus stays, for commands and safe actions; on SocketCAN the reader
is parked behind an empty id filter, not closed: ``_close_reader``): reading and decoding
every H2 and MACCEPA frame for nothing was the board's largest cost. A queued switch opens the
reader; activations wait until it is warm (every configured board's position frame seen, or
``cycle_loop.WARM_S``) so a controller never starts from a stale or missing state, and the state
from before the reader closed (boards, torques, feet) is dropped with it.
"""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path
from typing import Any

import can
from exolink.nodes.controller_manager.api import ManagerApi
from exolink.nodes.controller_manager.budget import GC_CLOCK
from exolink.nodes.controller_manager.bus_view import BusView
from exolink.nodes.controller_manager.commands import OperatorCommands
from exolink.nodes.controller_manager.cycle_loop import CycleLoop
from exolink.nodes.controller_manager.frames import (
    READ_IDS,
    drop_rules,
    joint_frame,
    one_socket,
)
from exolink.nodes.controller_manager.intent import OperatorLimits, Presence
from exolink.nodes.controller_manager.manager import Manager
from exolink.nodes.controller_manager.on_timer import TimerLoop
from exolink.nodes.controller_manager.params import ManagerParams
from exolink.nodes.controller_manager.slots import Cycle, ManagerRefused

from exolink.canbus import FrameReader, FrameWriter, open_bus
from exolink.config import ConfigError
from exolink.control.arming import ArmingState
from exolink.control.controller import ACTIVITY_TOPIC, ACTIVITY_TYPE, State
from exolink.control.replies import ManagerStatus
from exolink.limits.maccepa import target
from exolink.liveness import Pace
from exolink.node import Node
from exolink.phaseclock import PhaseClock
from exolink.plugins import PluginError, find_controller_class
from exolink.protocol import h2, maccepa
from exolink.wire import cdr

BEAT_S = 0.02
# Nothing active: the loop beats idle this often (exolink.liveness: then held to the appliance's
# default deadline), not 50 times a second: each wake-up costs about a millisecond of the
# board's CPU. It also judges the holder's keep-alive this often.
IDLE_BEAT_S = 0.2
# Every change of a controller's state goes out on ACTIVITY_TOPIC at once, and the whole list
# again after ACTIVITY_REFRESH_S without one: followers (the pattern player) listen instead of
# asking: five state queries a second were four Zenoh hops and a handler each, on one core.
ACTIVITY_REFRESH_S = 60.0
GAIT_TYPE = "gait_pattern"  # the pattern player's controller (pyproject's exolink.controllers)


class ControllerManagerNode(Node):
    Params = ManagerParams
    stall_s = 2 * BEAT_S

    def configure(self) -> None:
        p, cfg = self.params, self.ctx.config
        boards = [b.board for b in p.maccepa]
        if len(set(boards)) != len(boards):
            raise ValueError(f"{self.name} params: maccepa lists a board twice ({boards})")
        guarded = cfg.watchdog.maccepa_boards
        if missing := sorted(set(boards) - set(guarded)):
            raise ValueError(
                f"{self.name} params: maccepa boards {missing} are not in watchdog.maccepa_boards "
                f"({guarded}): the watchdog would not stop them on a trip"
            )
        state_dir = Path(cfg.state_dir) if cfg.state_dir else None
        if state_dir is None:
            self.log.warning("no_state_dir", consequence="operator limits last until a restart")
        self.limits = OperatorLimits(cfg.joint_limits(), state_dir)
        self.presence = Presence(cfg.watchdog.operator_lost_ms / 1000)
        self.manager = Manager(
            self.limits.in_force,
            p.update_budget_ms,
            list(p.maccepa),
            cycles_per_update=p.cycles_per_update,
        )
        try:  # judged by this while only the lease sends (exolink.liveness: Pace.LEASED)
            deadline = round(cfg.deadline_s(cfg.node(self.name), Pace.LEASED) * 1000)
        except ConfigError:  # run outside a config's node list (tests)
            deadline = cfg.watchdog.heartbeat_deadline_ms
        try:
            wake_s = p.timed_wake_s(deadline, BEAT_S)
        except ValueError as exc:  # a lease that would outlast the watchdog's disable
            raise ValueError(f"{self.name} params: {exc}") from None
        self.leased_stall_s = 2 * wake_s
        # planned set-points on a timer (on_timer.py)
        self.timer = TimerLoop(self, wake_s, p.lease_for(deadline))
        self.cycle = CycleLoop(self, BEAT_S)  # read -> update -> write each cycle (cycle_loop.py)
        self.last_state: State | None = None  # the last cycle's: a plan's activation state
        for n, spec in enumerate(p.controllers):
            try:
                self.manager.load(spec.name, spec.type, spec.params, spec.budget_ms)
            except ManagerRefused as exc:
                raise ValueError(f"{self.name} params: controllers[{n}]: {exc}") from None
        # The pattern player's controller type found now, while idle, not at the operator's
        # first gait start (exolink.plugins: a read of every installed package's metadata).
        with contextlib.suppress(PluginError):  # not installed: its load says so
            find_controller_class(GAIT_TYPE)
        self.safe_mode = h2.MODES["disabled" if p.safe_action == "disable" else "stopped"]
        self.board_ids = set(boards)
        # Status frames (50/60/70 + board) and duty/stop (80 + board): a stop from anyone.
        mc_ids = maccepa.data_ids(boards) + [maccepa.DUTY_BASE + b for b in boards]
        self.base_ids = frozenset({*READ_IDS, *mc_ids})
        self.drops = drop_rules(self.board_ids, mc_ids)
        # with the loaded controllers' extras (CycleLoop.update_reads)
        self.read_ids = sorted(self.base_ids)
        self.bus = self.own(open_bus(cfg.can, filters=[]))  # sends, reader closed
        self.writer = FrameWriter(self.bus, cfg.can)
        self.reader: FrameReader | None = None  # open while a controller is active or queued
        self.parked: FrameReader | None = None  # the reader while idle, on SocketCAN (park)
        # A cycle's set-points and a safe action asked by a request go out in the order they
        # were decided: a disable is never overtaken by the set-points of the cycle in flight.
        self.io_lock = threading.Lock()
        self.opened = 0.0  # monotonic time the reader opened
        self.wake = threading.Event()  # a queued switch: open the reader now
        self.reader_opens = 0
        self.view = BusView(self.board_ids, self.log)  # what it knows of the bus (bus_view.py)
        self._forget_state()
        self.mc_written = 0
        self.mc_safe_sent = 0
        self.arming = self.own(ArmingState(self.ctx.messaging)) if p.require_armed else None
        self.written = 0
        self.safe_sent = 0
        self.late_cycles = 0  # angle frames read behind a newer one: not run (see _cycle)
        # Where the loop's CPU goes, by phase (status: loop_cpu). One cycle in 32: a sampled
        # one reads the thread's CPU clock 7 times, each a system call; at 100 cycles/s that
        # is still ~190 samples a minute.
        self.clock = PhaseClock(every=32)
        self.pub_activity = self.own(
            self.ctx.messaging.publisher(ACTIVITY_TOPIC, ACTIVITY_TYPE, raw=True)
        )
        self._told, self._told_at = -1, 0.0
        self._tell_lock = threading.Lock()
        self.maybe_tell()  # the controllers loaded from params
        if p.send_limits_on_start:  # what the H2 enforces itself: the limits in force
            self.send_now(self.limit_frames())
        self.api = ManagerApi(self)  # the requests (api.py)
        self.api.serve()
        self.commands = OperatorCommands(self, self.api)  # the operator's (commands.py)
        self.commands.serve()

    def limit_frames(self) -> list[can.Message]:
        lim = self.limits.in_force
        return [
            h2.encode_accepted_angles("min", list(lim.min_angles)),
            h2.encode_accepted_angles("max", list(lim.max_angles)),
        ]

    # --- management ---------------------------------------------------------------------------

    def status(self) -> ManagerStatus:
        reader = self.reader  # may close meanwhile: its counters stay readable
        return ManagerStatus(
            **self.manager.status(),
            limits=self.limits.describe(),
            presence=self.presence.describe(),
            written=self.written,
            safe=self.safe_sent,
            late_cycles=self.late_cycles,
            cycles_per_update=self.params.cycles_per_update,
            timer=self.timer.status(),  # planned set-points on a timer (on_timer.py)
            maccepa_written=self.mc_written,
            maccepa_safe=self.mc_safe_sent,
            malformed=dict(self.view.malformed),
            reading=self.reader is not None,
            reader_opens=self.reader_opens,
            read_ids=self.read_ids,
            receive=reader.counters() if reader is not None else None,
            watchdog_word=self.arming.counters() if self.arming is not None else None,
            loop_cpu=self.clock.counters(),
            gc=GC_CLOCK.counters(),  # the collector's pauses: stalls of the loop
        )

    def maybe_tell(self) -> None:
        """Publish the controllers' states if they changed (or the refresh is due): one
        comparison per cycle otherwise."""
        if self._told == self.manager.version and (
            time.monotonic() - self._told_at < ACTIVITY_REFRESH_S
        ):
            return
        version, controllers = self.manager.activity()
        with self._tell_lock:
            now = time.monotonic()
            if version < self._told or (
                version == self._told and now - self._told_at < ACTIVITY_REFRESH_S
            ):
                return  # another thread told this version, or a later one, meanwhile
            self._told, self._told_at = version, now
            ns = time.time_ns()
            self.pub_activity.put(cdr.controller_activity(ns, version, controllers), ns)

    # --- writing ------------------------------------------------------------------------------

    def send_now(self, frames: list[can.Message]) -> None:
        """Frames a request asked for (limits, stream), after the cycle in flight."""
        with self.io_lock:
            self._send(frames)

    def stop_joints(self, joints: set[int], mode: int, why: str) -> list[can.Message]:
        """Joints disabled or stopped at a request: their controllers released first, so no
        later cycle writes them, then the frames, after the cycle in flight."""
        frames = [joint_frame(j + 1, mode, 0, 0) for j in sorted(joints)]
        with self.io_lock:
            self.timer.abort()
            self.manager.joints_disabled(joints, why)
            self._send(frames)
        self.maybe_tell()
        return frames

    def stop_boards(self, boards: set[int], why: str) -> list[can.Message]:
        """MACCEPA boards' "stop control" at a request, as ``stop_joints``."""
        frames = [maccepa.encode_stop(b) for b in sorted(boards)]
        with self.io_lock:
            self.timer.abort()
            self.manager.boards_stopped(boards, why)
            self._send(frames)
        self.maybe_tell()
        return frames

    def stop_all(self, why: str) -> None:
        """Every controller stopped, its joints and boards in the safe action."""
        with self.io_lock:
            self.timer.abort()
            self._safe(self.manager.stop_all(why))
        self.maybe_tell()

    def not_armed(self) -> str | None:
        return self.arming.check() if self.arming is not None else None

    def run(self, stop: threading.Event) -> None:
        clock = self.clock
        while not stop.is_set():
            clock.start()
            if self.timer.sending:
                if not self.timer.beside:
                    self.timer.wake()
                    continue
                self.timer.keep()  # a feedback controller beside it: the cycle loop runs too
            busy = self.reader is not None or self.manager.busy()
            # Idle (held to the appliance's default deadline) until a controller drives: the
            # reader's opening and an activation (hundreds of ms on the board: its stock
            # 50 ms deadline tripped the watchdog at every gait start) come before the first
            # set-point, and _send says "not idle" before that one goes out.
            driving = busy and self.cycle_drives()
            self.beat(Pace.OWN if driving else Pace.IDLE)
            self.api.check_presence()
            self.maybe_tell()
            clock.mark("beat")
            if not busy:  # a request (load, switch) wakes it at once
                self.wake.wait(IDLE_BEAT_S)
                self.wake.clear()
                continue
            if (
                self.params.timer
                and not self.timer.sending
                and self.reader is not None
                and self.last_state is not None
                and self.manager.plannable()
            ):
                self.timer.start()  # after this iteration's beat: planning takes CPU
                if self.timer.sending and not self.timer.beside:
                    continue
            self.cycle.step(stop)

    def timer_takes_planned(self) -> bool:
        """Planned controllers' set-points go out on the timer alone: from their activation
        on, the cycle loop writes none (the first goes out with the op's start). Written by
        the cycle loop, the gait's first set-point put the node on its own 50 ms deadline
        for the activation's cycle and the timer's start, and on the board proxy under a
        50 % CPU cap that deadline tripped the watchdog at gait starts (K65, D66); so did the
        stop's leave and switch (I65), the gait still active with nothing on the bus. Nothing
        is sent until the op starts, so a hang meanwhile moves nothing. Without a timer
        (``timer: false``, or refused) the cycle loop writes them, as every controller."""
        return self.params.timer and not self.timer.refused

    def cycle_drives(self) -> bool:
        """The cycle loop writes motion: a feedback controller is active, or a planned one
        the timer does not take (``timer_takes_planned``)."""
        if self.timer_takes_planned():
            return self.manager.unplanned()
        return self.manager.driving()

    def _one_socket(self) -> bool:
        return one_socket(self.ctx.config.can.interface, self.read_ids, self.board_ids)

    def _close_reader(self, forget: bool = True) -> None:
        """Idle: frames no longer reach this process, and what it knew of the bus is dropped
        (a controller activated later starts from fresh frames). On SocketCAN the reader is
        parked, not closed (``FrameReader.park``: a close freed its BPF filter in a kworker
        that held the board proxy's CPU 0 ~94 ms at each gait's stop), and the next activation
        unparks it (``CycleLoop._open_reader``). ``forget=False``: reopened at once with other
        sockets (``CycleLoop.update_reads``), the state stands."""
        with self.io_lock:  # a request's send may be using its socket
            reader, self.reader = self.reader, None
            if reader is not None and forget and reader.parkable and self.parked is None:
                reader.park()
                self.parked = reader
            elif reader is not None:
                reader.close()
        if forget:
            self._forget_state()

    def _close_parked(self) -> None:
        with self.io_lock:
            parked, self.parked = self.parked, None
            if parked is not None:
                parked.close()

    last_angle_ts: float | None  # the kernel stamp of the angle frame the last cycle ran on

    def _forget_state(self) -> None:
        self.view.forget()
        self.last_angle_ts = None
        self.last_angle_mono = time.monotonic()
        self.skipped = 0  # angle frames read since the last update and not run

    def _stops(self, decoded: list[tuple[Any, Any]]) -> None:
        """Safety first: a disable/stop anywhere in the batch stops its joints' controllers
        before any set-point of this batch is computed (and the timer's op at once, if it
        drives one of them; one that drives others goes on, as their controllers do)."""
        stopped, halted = self.view.stops(decoded)
        if stopped:
            names = ", ".join(h2.JOINTS[j] for j in sorted(stopped))
            with self.io_lock:
                if self.timer.drives(stopped):
                    self.timer.abort()
                self.manager.joints_disabled(stopped, f"{names} disabled or stopped on the bus")
        if halted:
            names = ", ".join(target(b) for b in sorted(halted))
            self.manager.boards_stopped(halted, f"{names} stopped on the bus")

    def _safe(self, out: Cycle) -> None:
        """The safe action of the joints and boards ``out`` names, sent now."""
        self._send(self._safe_frames(out))

    def _safe_frames(self, out: Cycle) -> list[can.Message]:
        frames = []
        for j in sorted(out.safe):
            frames.append(joint_frame(j + 1, self.safe_mode, 0, 0))
            self.safe_sent += 1
        for b in sorted(out.safe_boards):
            frames.append(maccepa.encode_stop(b))
            self.mc_safe_sent += 1
        return frames

    def _send(self, frames: list[can.Message]) -> None:
        """A cycle's frames in one system call on SocketCAN (canbus.FrameWriter), through the
        reader's socket while it is open: a socket does not read its own frames back (another
        socket of this process would, six more frames per cycle to decode)."""
        if not frames:
            return
        reader = self.reader
        try:
            (reader.writer if reader is not None else self.writer).send(frames)
        except can.CanError as exc:
            self.log.error("send_failed", error=str(exc), frames=len(frames))

    def _silent(self, reason: str) -> None:
        if not self.manager.active():
            return
        self.stop_all(reason)
        self.log.warning("controllers_stopped_h2_silent", reason=reason)

    def shutdown(self) -> None:
        """The safe action while the bus is open (the runtime releases it next)."""
        self.stop_all("controller manager shutting down")  # followers hear it before we go
        self._close_reader()  # opened while a controller is active, not owned
        self._close_parked()
