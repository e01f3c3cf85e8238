"""The controller manager's cycle loop: read -> update -> write once per H2 cycle, paced by
the joint-angle frame (id 110), while a controller needs it (a feedback controller, a switch
being applied; the planned ones go on the kernel's timer: ``on_timer``). The reader is opened
for the loaded controllers' frames and its kernel filter follows them; with
``cycles_per_update`` > 1 the loop sleeps until the frame of the next update is due. The node
(``node.ControllerManagerNode``) owns one and runs a ``step`` per turn of its loop while busy."""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

import can
from exolink.nodes.controller_manager.frames import EXTRA_IDS, board_frame, joint_frame
from exolink.nodes.controller_manager.slots import UNPLANNED

from exolink.canbus import open_reader
from exolink.control.controller import State
from exolink.protocol import ProtocolError, h2

if TYPE_CHECKING:
    from exolink.nodes.controller_manager.node import ControllerManagerNode

WARM_S = 0.1  # a fresh reader's wait for the boards' position frames before activations apply


class CycleLoop:
    """The node's cycle side; its state (the reader, the last angle frame's stamps, the
    counters in the node's status) stays on the node, which the timer side shares."""

    def __init__(self, node: ControllerManagerNode, beat_s: float) -> None:
        self.node = node
        self.beat_s = beat_s  # the longest wait for a frame
        self.update_every_s = node.params.cycles_per_update * h2.PERIOD_S
        self._reads_version = -1
        self._controller_s = 0.0  # the last cycle's time inside controllers' update

    def step(self, stop: threading.Event) -> None:
        """One turn of the cycle loop: the reader opened for the loaded controllers' frames,
        a read, each cycle's update and its frames, and the H2's silence judged."""
        n, clock = self.node, self.node.clock
        timeout = n.params.h2_timeout_ms / 1e3
        self.update_reads()
        if n.reader is None:
            self._open_reader()
        self._until_due()
        try:
            frames = n.reader.read(self.beat_s)  # type: ignore[union-attr]
        except (can.CanError, OSError) as exc:
            n.log.error("bus_read_error", error=str(exc))
            n._silent("CAN read error: " + str(exc))
            stop.wait(self.beat_s)
            return
        clock.mark("read")
        self._on_frames(frames)
        clock.mark("frames")
        if time.monotonic() - n.last_angle_mono > timeout:
            n._silent(f"no H2 joint angles for {n.params.h2_timeout_ms} ms")
            n.manager.idle(n.not_armed())
        if not n.manager.busy():
            n._close_reader()
        clock.mark("rest")

    def _not_due(self, stamp: float) -> bool:
        """With ``cycles_per_update`` > 1: this angle frame came too soon after the last
        update's (by the frames' own kernel stamps; a clock stepped back makes it due)."""
        last, every = self.node.last_angle_ts, self.node.params.cycles_per_update
        return every > 1 and last is not None and 0 <= stamp - last < (every - 0.5) * h2.PERIOD_S

    def _until_due(self) -> None:
        """With ``cycles_per_update`` > 1: sleep until the frame of the next update is due
        (queued a quarter period ago), instead of waking for the angle frames in between: on
        the board a wake-up costs more than the frames it brings. Frames that come meanwhile
        (a disable from anyone) are read before that update's set-points are computed."""
        n = self.node
        last = n.last_angle_ts  # the last update's frame (or a cold reader's last)
        if n.params.cycles_per_update > 1 and last is not None:
            wait = last + self.update_every_s + h2.PERIOD_S / 4 - time.time()
            if wait > 0:  # never longer than one update (a wall clock stepped back); a plain
                # sleep: an Event's timed wait makes a lock and a condition per call
                time.sleep(min(wait, self.update_every_s + h2.PERIOD_S / 4))

    def update_reads(self) -> None:
        """The frames to read for the loaded controllers (``Controller.reads``), applied to an
        open reader's kernel filter at once; a kind no longer read is forgotten, so a later
        reader of it never sees an old value. Between a load and its first frame (one cycle)
        a new reader of torque sees zeros, as every controller does after the reader opens."""
        n = self.node
        if n.manager.version == self._reads_version:  # an int read: no lock per cycle
            return
        self._reads_version, reads = n.manager.reads()
        ids = sorted(n.base_ids | {EXTRA_IDS[k] for k in reads if k in EXTRA_IDS})
        if ids == n.read_ids:
            return
        n.read_ids = ids
        if "torque" not in reads:
            n.view.torque = (0,) * 6
        if "feet" not in reads:
            n.view.feet = None
        if n.reader is not None and n.reader.quiet_bus is None and not n._one_socket():
            n._close_reader(forget=False)  # the new ids must not wake it: reopened below
        elif n.reader is not None:
            n.reader.set_ids(ids)
        n.log.info("read_ids", ids=ids)

    def _open_reader(self) -> None:
        n = self.node
        parked = n.parked
        if parked is not None and (parked.quiet_bus is None) == n._one_socket():
            n.parked = None  # the same sockets: unparked, with the ids of now
            parked.unpark()
            parked.set_ids(n.read_ids)
            n.reader = parked
        else:
            n._close_parked()
            # Only the angle frame, which starts a cycle, wakes the loop; the cycle's other
            # frames (torques, feet, the boards') are read with the next one, in arrival order
            # and before that cycle's set-points: one wake-up per cycle, not 4-6. Anyone's
            # disable or stop alone is rare: then one socket (_one_socket).
            n.reader = open_reader(
                n.ctx.config.can,
                n.read_ids,
                wake_on=None if n._one_socket() else [h2.JOINT_ANGLES],
                drop=n.drops,
            )
        n.opened = n.last_angle_mono = time.monotonic()
        n.reader_opens += 1

    def _warm(self) -> bool:
        """A fresh reader has seen every configured board's positions (or waited WARM_S)."""
        n = self.node
        return time.monotonic() - n.opened >= WARM_S or n.view.warm()

    def _on_frames(self, frames: list[Any]) -> None:
        n = self.node
        decoded = [(f, n.view.decode(f)) for f in frames]
        n._stops(decoded)
        newest = max(
            (i for i, (_f, d) in enumerate(decoded) if isinstance(d, h2.JointAngles)), default=-1
        )
        for i, (f, d) in enumerate(decoded):
            if isinstance(d, h2.JointAngles):
                if not self._warm():  # nothing is active while cold: activations wait
                    n.last_angle_ts, n.last_angle_mono = f.timestamp, time.monotonic()
                    n.manager.idle(n.not_armed())
                    continue
                if i != newest:  # read late, a newer cycle behind it: see _cycle
                    n.skipped += 1
                    continue
                if self._not_due(f.timestamp):
                    n.skipped += 1
                    n.last_angle_mono = time.monotonic()  # the H2 is not silent
                    continue
                # an update every n cycles skips n - 1 by design; more were read late
                n.late_cycles += max(0, n.skipped - n.params.cycles_per_update + 1)
                n.skipped = 0
                n.last_state = n.view.state(d)
                self._cycle(f.timestamp, n.last_state)
            else:
                n.view.take(d, f.timestamp)

    def _cycle(self, stamp: float, state: State) -> None:
        """One H2 cycle, for the newest angle frame of a read. A read that finds several (the
        loop ran late: a starved manager may read twenty cycles at once) runs only the last
        and counts the others in ``late_cycles``: replaying them wrote their set-points back to
        back, each a step limit from the one before, so a joint's set-point could move 22 steps
        within a millisecond. The controllers get the measured period since the last cycle run."""
        n = self.node
        t0 = time.perf_counter()
        period = stamp - n.last_angle_ts if n.last_angle_ts is not None else h2.PERIOD_S
        n.last_angle_ts = stamp
        n.clock.mark("frames")  # the batch's decoding up to this cycle
        with n.io_lock:
            self._cycle_io(state, stamp, period)
        n.clock.mark("send")
        # The H2-silence clock restarts when the cycle ends, not when it began: a cycle that
        # took long (an activation on the board: hundreds of ms) is the manager's lateness, and
        # the angle frames queued meanwhile are read next, before silence is judged.
        n.last_angle_mono = time.monotonic()
        n.manager.overhead_s.append(time.perf_counter() - t0 - self._controller_s)

    def _cycle_io(self, state: State, stamp: float, period: float) -> None:
        """The cycle's outputs and their frames, decided and sent under ``io_lock``."""
        n = self.node
        timed = n.timer.sending  # beside the timer: its controllers are planned there
        out = n.manager.cycle(
            state,
            stamp,
            period,
            n.not_armed(),
            switches=not timed,
            # the timer's controllers are its own, also before its op starts
            part=UNPLANNED if timed or n.timer_takes_planned() else None,
        )
        self._controller_s = out.controller_s
        n.clock.mark("cycle")
        frames = n._safe_frames(out)  # safe actions first, in the cycle's one send
        for w in out.writes:
            frames.append(joint_frame(w.motor, w.mode, w.setpoint, w.stiffness))
            n.written += 1
        for m in out.maccepa:
            try:
                frame = board_frame(m.board, m.kind, m.value, m.controller)
            except ProtocolError as exc:  # cannot happen after the limits: belt
                n.log.error("maccepa_encode_refused", write=str(m), error=str(exc))
                continue
            frames.append(frame)
            n.mc_written += 1
        if out.writes or out.maccepa:
            n.beat()  # driving from this cycle on: its own deadline, before it drives
        n._send(frames)
