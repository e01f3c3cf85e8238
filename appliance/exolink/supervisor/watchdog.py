"""The safety watchdog: one latch between the software and the patient's joints.

It owns its own CAN socket, so no node (and no Zenoh hiccup) stands between a detected failure
and the disable frames. Any trip sends the safe action at once and again shortly after (a frame
lost on a lossy bus must not leave a joint powered), latches, and refuses motion until an
operator re-arms. It also listens to the bus itself: the device's pulse falling silent while
armed trips it, and a motion frame seen while not armed is answered with the safe action again.
What a frame is (pulse, motion, malformed) and what the safe action is are the device's word
(exolink.hardware, ``Device``); the H2's pulse is its joint-angle frame (id 110), its motion
joint control (id 70), as the rest of this docstring describes.

Both bus checks go by when a frame reached the socket (its kernel timestamp), not by when this
process got round to reading it: a supervisor busy for 150 ms (an import, a CLI call, a slow card)
finds the frames queued and must not call that silence, while a real 150 ms gap between two
angle frames trips even if both are read late. A frame already on the bus before the trip is not
a violation either (the safe action went out after it). Should the reader itself stall past
``STALL_BACKSTOP_S`` beyond the limit, the periodic check trips anyway: silence it cannot rule
out counts as silence.

The listener wakes as little as that allows, since each wake-up is most of its CPU on one A8
core: joint-angle frames never wake it (their socket is read when it wakes, judged by their
kernel timestamps); armed, it sleeps until the silence deadline of the last angle frame (about
ten wake-ups a second while the H2 streams, none per frame); not armed, a joint-control frame
(id 70) wakes it at once, since a motion frame then must be answered now, and it looks at least
every half silence limit so that arming sees fresh H2 data. Arming, disarming and trips wake it
through a pipe (exolink.supervisor.wakeup) to switch between the two.

On SocketCAN no frame is read at all: the kernel's broadcast manager (exolink.canbus.bcm) times the
angle frames and this thread hears only of a silence, a resumption or a frame whose length
changed (a silence while armed trips at once); on id 70 it hears of a frame whose mode byte or
length differs from the last one's: the first motion frame after the safe action (which the op
sees too), not MACCEPA board 0's 100 frames/s on the same id. A burst of motion frames while not
armed is answered once, at its first frame, with the safe action; the next motion frame after
that is a change again. Armed, motion is allowed and the id-70 op is closed (``reopen`` opens a
new one on leaving armed, before the listener's next wait): with the gait running, the
controller manager's 6-byte frames and board 0's 8-byte ones alternate on id 70, each a length
change, and the op woke this thread ~200 times a second for news it does not act on. The
simulated bus has no broadcast manager, and there the angle frames are read and judged as
above. Both ways, the periodic check on the
supervisor's loop takes the kernel's news too, so a stalled listener cannot hide a silence.

Only a frame that matches the device's DBC counts: an id-110 frame of the wrong length (or an
extended / remote frame with that id) is not H2 data and does not hold off the silence trip.
Frames neither contract can read are counted by id and reason (``malformed`` in status), never
fatal; an id-70 frame of 8 bytes is MACCEPA board 0's and is left alone.
"""

from __future__ import annotations

import errno
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import can
import structlog

from exolink import logs
from exolink.canbus import Frame, FrameReader
from exolink.config import WatchdogConfig
from exolink.hardware import Device, Seen
from exolink.refusal import Refused
from exolink.supervisor.wakeup import Wakeup

if TYPE_CHECKING:
    from exolink.canbus.bcm import CyclicWatch, Event
    from exolink.canbus.held import HeldOps

REPEAT_AFTER_S = (0.05, 0.25)
STALL_BACKSTOP_S = 0.5
IDLE_POLL_S = 0.1
# While the broadcast manager times a live H2 stream, any news (its timer ran out, an angle
# frame of another length, a mode change on id 70) wakes the listener on those sockets: its own
# timeout only backs that up. Each wake costs ~1 ms of the board's core.
KERNEL_WATCH_POLL_S = 1.0


class ArmRefused(Refused):
    """Arming refused: the blockers are named (a tripped watchdog, a node not running)."""


@dataclass
class WatchdogState:
    state: str  # disarmed | armed | tripped
    reason: str
    detail: str
    since_ns: int
    trips: int
    frames_sent: int
    violations: int
    read_lag_max_ms: float = 0.0  # frame arrival -> read by the watchdog: its margin to the limit
    malformed: dict[str, int] = field(default_factory=dict)  # "110 bad length" -> count
    socket_dropped: int | None = 0  # kernel drops from a full receive buffer (None: not known)


Publish = Callable[[WatchdogState], None]


class Watchdog:
    def __init__(
        self,
        cfg: WatchdogConfig,
        reader: FrameReader,
        publish: Publish,
        device: Device,
        angles: CyclicWatch | None = None,
        control: CyclicWatch | None = None,
        reopen: Callable[[], CyclicWatch] | None = None,
    ) -> None:
        """``angles`` / ``control``: the kernel watches ids 110 and 70 (``reader`` then only
        sends); ``reopen``: a new id-70 watch, with which ``control`` is closed while armed."""
        self.cfg = cfg
        self.reader = reader
        self.angles = angles
        self.control = control
        self._reopen = reopen
        self.control_events = 0  # id-70 news taken from the kernel (see the module's docstring)
        # Re-entrant: a trip found while taking the kernel's news reopens the id-70 watch.
        self._kernel_lock = threading.RLock()
        self._pulse_alive = False  # with ``angles``: the device's pulse streams, per the kernel
        self.bus = reader.bus
        self.publish = publish
        self.log = structlog.get_logger().bind(node="watchdog")
        self.lock = threading.RLock()
        self.device = device
        self.frames = device.safe_action(cfg)
        self._s = WatchdogState("disarmed", "startup", "", time.time_ns(), 0, 0, 0)
        self._repeats: list[float] = []
        self._repeats_by_reason: dict[str, int] = {}  # trips while tripped (reasons: ours)
        self.last_pulse: float | None = None  # monotonic arrival of the device's last pulse
        self._last_arrival = 0.0  # arrivals never go backwards (FIFO socket, clock steps clamped)
        self._armed_at: float | None = None  # monotonic; None while not armed
        self._left_armed_at = time.monotonic()
        self.first_trip_ns: int | None = None
        self.wake: Callable[[], None] = lambda: None  # the periodic check is due sooner
        self._stop = threading.Event()
        # Leased nodes' send ops (exolink.canbus.held): each safe action deletes them first.
        self.held: HeldOps | None = None
        # Wakes the listener when arming changes what it waits for (armed: a deadline; not
        # armed: id-70 frames too).
        self._pokes = Wakeup()  # arming, disarming, trips, close: the listener looks again
        self._rx = threading.Thread(target=self._listen, daemon=True, name="watchdog-rx")

    def start(self) -> None:
        """Safe action first, before any node exists: the board may be in any state."""
        self.send_safe_action()
        self._rx.start()
        self.publish(self.snapshot())

    def snapshot(self) -> WatchdogState:
        with self.lock:
            self._s.socket_dropped = self.reader.dropped
            return WatchdogState(**{**vars(self._s), "malformed": dict(self._s.malformed)})

    @property
    def armed(self) -> bool:
        return self._s.state == "armed"

    def send_safe_action(self) -> int:
        """The nodes' send ops deleted (they may be stopped, hung or starved, and a lease runs
        on after its owner), then the safe action."""
        if self.held is not None:
            self.held.delete()
        sent = 0
        for f in self.frames:
            try:
                self.bus.send(f)
                sent += 1
            except can.CanError as exc:  # keep going: every joint deserves its frame
                self.log.error(
                    "safe_action_send_failed", frame=f"{f.arbitration_id:03X}", error=str(exc)
                )
        with self.lock:
            self._s.frames_sent += sent
        return sent

    def trip(self, reason: str, detail: str = "") -> None:
        """Latch tripped (the first reason stays until re-armed) and send the safe action."""
        self.send_safe_action()
        now = time.monotonic()
        with self.lock:
            first = self._s.state != "tripped"
            self._leave_armed(now)
            if first:
                self._s.state, self._s.reason, self._s.detail = "tripped", reason, detail
                self._s.since_ns = time.time_ns()
                self._s.trips += 1
            self._repeats = [now + d for d in REPEAT_AFTER_S]
        self._open_control()
        self.wake()
        self._poke()
        if first:
            self.log.error("watchdog_tripped", reason=reason, detail=detail)
            self.publish(self.snapshot())
        else:  # each reason logged at its first and every 1000th repeat: anyone may e-stop
            with self.lock:
                n = self._repeats_by_reason[reason] = self._repeats_by_reason.get(reason, 0) + 1
            if logs.rarely(n):
                self.log.warning(
                    "watchdog_trip_while_tripped", reason=reason, detail=detail, count=n
                )

    def arm(self, blockers: list[str]) -> None:
        if blockers:
            raise ArmRefused("cannot arm: " + "; ".join(blockers))
        with self.lock:
            self._s.state, self._s.reason, self._s.detail = "armed", "operator", ""
            self._s.since_ns = time.time_ns()
            self._armed_at = time.monotonic()
        self._close_control()
        self._poke()
        self.log.warning("watchdog_armed")
        self.publish(self.snapshot())

    def disarm(self, reason: str = "operator") -> None:
        self.send_safe_action()
        with self.lock:
            self._leave_armed(time.monotonic())
            self._s.state, self._s.reason, self._s.detail = "disarmed", reason, ""
            self._s.since_ns = time.time_ns()
        self._open_control()
        self._poke()
        self.log.info("watchdog_disarmed", reason=reason)
        self.publish(self.snapshot())

    def _leave_armed(self, now: float) -> None:
        if self._armed_at is not None:
            self._armed_at, self._left_armed_at = None, now

    def _close_control(self) -> None:
        """Armed: the id-70 watch's news up to now judged (by arrival, as the listener would),
        then the watch closed."""
        if self._reopen is None:
            return
        with self._kernel_lock:
            self._take_kernel()
            if not self.armed:  # its news tripped it: the watch stays
                return
            watch, self.control = self.control, None
            if watch is not None:
                watch.close()

    def _open_control(self) -> None:
        """Not armed (any more): a new id-70 watch, whose first frame is news. If the kernel
        refuses it, the periodic check tries again; the safe action has gone out meanwhile."""
        if self._reopen is None or self.armed:
            return
        with self._kernel_lock:
            if self.control is not None or self.armed:
                return
            try:
                self.control = self._reopen()
            except OSError as exc:  # CanOpenError included
                self.log.error("control_watch_failed", error=str(exc))

    def silent_for(self) -> float | None:
        if self.angles is not None:
            self._take_kernel()
            if self._pulse_alive:
                return 0.0
        return None if self.last_pulse is None else time.monotonic() - self.last_pulse

    def _take_kernel(self) -> None:
        """The broadcast manager's news since the last look (either thread may look)."""
        if self.angles is None:
            return
        with self._kernel_lock:
            for ev in self.angles.poll():
                self._angles_event(ev)
            for ev in self.control.poll() if self.control is not None else ():
                self.control_events += 1
                if ev.frame is not None:
                    self._read_lag(max(0.0, time.time() - ev.frame.timestamp))
                    self._judge(ev.frame)

    def _angles_event(self, ev: Event) -> None:
        if ev.frame is None:  # no angle frame for the limit: the kernel's timer ran out
            self._pulse_alive = False
            self.last_pulse = time.monotonic() - self.cfg.silence_ms / 1000
            if self.armed:
                self.trip(
                    f"{self.device.pulse} silent",
                    f"no {self.device.pulse} for {self.cfg.silence_ms} ms (kernel timer)",
                )
            return
        at = self._arrival(ev.frame)
        seen, why = self._see(ev.frame)
        # A malformed frame ends the good stream from its arrival; the kernel's timer takes it
        # as life, so the silence is judged here from then on (``_check_silence``).
        was_alive, self._pulse_alive = self._pulse_alive, seen is Seen.PULSE
        if self._pulse_alive or was_alive:  # good frames streamed up to this one
            self.last_pulse = at
        if seen is Seen.MALFORMED:
            self._malformed(ev.frame, why)

    def behind_s(self) -> float:
        """How far behind the bus its reader is (0: current): a CPU too busy to let it read."""
        return self.reader.behind_s

    def check(self) -> None:
        """Periodic: repeat the safe action after a trip; the backstop for a stalled reader."""
        now = time.monotonic()
        with self.lock:
            due = [t for t in self._repeats if t <= now]
            self._repeats = [t for t in self._repeats if t > now]
        if due:
            self.send_safe_action()
        if self.control is None and not self.armed:
            self._open_control()
        silent = self.silent_for()  # with the kernel timing the frames: its news, taken now
        if self.angles is not None:
            self._check_silence(time.monotonic())
            return
        backstop = self.cfg.silence_ms / 1000 + STALL_BACKSTOP_S
        if self.armed and silent is not None and silent > backstop:
            self.trip(
                f"{self.device.pulse} silent",
                f"watchdog bus reader stalled: no {self.device.pulse} read for "
                f"{silent * 1000:.0f} ms (limit {self.cfg.silence_ms} ms)",
            )

    def next_due(self) -> float:
        """When ``check`` has something to do next (monotonic): a repeat, or the backstop."""
        due = min(self._repeats, default=float("inf"))
        if self.armed and self.last_pulse is not None and self.angles is None:
            due = min(due, self.last_pulse + self.cfg.silence_ms / 1000 + STALL_BACKSTOP_S)
        return due

    def _arrival(self, msg: Frame) -> float:
        """When the frame reached the socket, on the monotonic clock. Its timestamp is wall time
        (kernel SO_TIMESTAMP on SocketCAN and udp_multicast); the age is clamped so a clock step
        while frames wait cannot put an arrival in the future or before the previous one."""
        age = max(0.0, time.time() - msg.timestamp) if msg.timestamp else 0.0
        self._last_arrival = max(self._last_arrival, time.monotonic() - age)
        return self._last_arrival

    def _check_silence(self, at: float) -> None:
        """Silence while armed up to ``at``: a frame's arrival, or now when the socket was found
        empty (every frame that came before ``at`` has then been read)."""
        armed_at = self._armed_at
        if not self.armed or armed_at is None or (self.angles is not None and self._pulse_alive):
            return
        since = armed_at if self.last_pulse is None else max(self.last_pulse, armed_at)
        silent, limit = at - since, self.cfg.silence_ms / 1000
        if silent > limit:
            self.trip(
                f"{self.device.pulse} silent",
                f"no {self.device.pulse} for {silent * 1000:.0f} ms "
                f"(limit {self.cfg.silence_ms} ms)",
            )

    def _was_armed_at(self, t: float) -> bool:
        armed_at = self._armed_at
        if armed_at is not None:  # armed now: unarmed only between the last exit and this arm
            return not self._left_armed_at <= t < armed_at
        return t < self._left_armed_at

    def _poke(self) -> None:
        self._pokes.set()

    def _listen(self) -> None:
        limit = self.cfg.silence_ms / 1000
        while not self._stop.is_set():
            armed = self.armed
            poke = self._wake_fds()
            silent = self.silent_for()
            if self.angles is not None and self._pulse_alive:
                timeout = KERNEL_WATCH_POLL_S
            elif armed and silent is not None:
                timeout = max(0.002, limit - silent)  # the last angle frame's deadline
            else:
                timeout = min(IDLE_POLL_S, limit / 2)  # fresh enough for arming's check
            start = time.monotonic()
            try:
                frames = self.reader.read(timeout, wake_fds=poke, frames_wake=not armed)
            except (can.CanError, OSError) as exc:
                if getattr(exc, "errno", None) == errno.EBADF and poke != self._wake_fds():
                    continue  # the id-70 watch closed by arming while this was about to wait
                self.log.error("watchdog_rx_error", error=str(exc))
                time.sleep(0.1)
                continue
            now = time.monotonic()
            self._pokes.clear()
            # How late it looked: after the deadline it slept to, or after the frame that woke it.
            due = start + timeout
            for msg in frames:
                if msg.arbitration_id == self.device.command_id:
                    due = min(due, self._arrival(msg))
                    break
            self._read_lag(now - due)
            for msg in frames:
                self._judge(msg)
            if self.reader.complete:  # every frame that came before now has been read
                self._check_silence(now)

    def _wake_fds(self) -> list[int]:
        """What ends the listener's wait besides frames: the poke, the kernel's watches (the
        id-70 one comes and goes with arming)."""
        return [self._pokes.fileno()] + [
            w.fileno() for w in (self.angles, self.control) if w is not None
        ]

    def _read_lag(self, lag_s: float) -> None:
        lag_ms = round(lag_s * 1000, 2)
        if lag_ms > self._s.read_lag_max_ms:
            with self.lock:
                self._s.read_lag_max_ms = lag_ms

    def _judge(self, msg: Frame) -> None:
        at = self._arrival(msg)
        self._check_silence(at)
        seen, why = self._see(msg)
        if seen is Seen.MALFORMED:
            self._malformed(msg, why)
        elif seen is Seen.PULSE:
            self.last_pulse = at
        elif seen is Seen.MOTION and not self._was_armed_at(at):
            with self.lock:
                self._s.violations += 1
            self.log.error(
                "motion_frame_while_not_armed",
                frame=msg.data.hex(),
                after_ms=round((at - self._left_armed_at) * 1000, 1),
            )
            self.send_safe_action()

    def _see(self, msg: Frame) -> tuple[Seen, str]:
        """The device's word on ``msg``. Its ``judge`` must not raise, but a lab's new device
        may: an exception must not end the thread that guards the motors. The frame is counted
        malformed, and one with the command's id is taken as motion (the safe action sent for
        nothing costs little; an unjudged command let through while not armed could move a
        joint)."""
        try:
            return self.device.judge(msg)
        except Exception as exc:  # any bug in a device's judge
            reason = f"device judge raised {type(exc).__name__}"
            if msg.arbitration_id != self.device.command_id:
                return Seen.MALFORMED, reason
            self._malformed(msg, reason)
            return Seen.MOTION, reason

    def _malformed(self, msg: Frame, reason: str) -> None:
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            reason = "not a standard data frame"
        key = f"{msg.arbitration_id} {reason}"
        with self.lock:
            n = self._s.malformed.get(key, 0) + 1
            self._s.malformed[key] = n
        if logs.rarely(n):
            self.log.warning("malformed_frame", id=msg.arbitration_id, reason=reason, count=n)

    def close(self) -> None:
        self._stop.set()
        self._poke()
        if self._rx.is_alive():
            self._rx.join(1)
        self._pokes.close()
        with self._kernel_lock:
            self._reopen = None  # a trip while closing opens no new watch
            for watch in (self.angles, self.control):
                if watch is not None:
                    watch.close()
