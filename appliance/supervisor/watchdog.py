"""The safety watchdog: one latch between the software and the patient's joints.

It owns its own CAN socket, so no node (and no Zenoh hiccup) stands between a detected failure
and the disable frames. Any trip sends the safe action at once and again shortly after (a frame
lost on a lossy bus must not leave a joint powered), latches, and refuses motion until an
operator re-arms. It also listens to the bus itself: H2 data silence while armed trips it, and
a motion frame seen while not armed is answered with the safe action again.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import can
import structlog
from exolink.config import WatchdogConfig
from exolink.protocol import h2, maccepa

REPEAT_AFTER_S = (0.05, 0.25)
MOTION_MODES = {h2.MODES["position"], h2.MODES["stiffness"], h2.MODES["torque"]}


class ArmRefused(Exception):
    pass


@dataclass
class WatchdogState:
    state: str  # disarmed | armed | tripped
    reason: str
    detail: str
    since_ns: int
    trips: int
    frames_sent: int
    violations: int


Publish = Callable[[WatchdogState], None]


class Watchdog:
    def __init__(self, cfg: WatchdogConfig, bus: can.BusABC, publish: Publish) -> None:
        self.cfg = cfg
        self.bus = bus
        self.publish = publish
        self.log = structlog.get_logger().bind(node="watchdog")
        self.lock = threading.RLock()
        self.frames = h2.safe_action(cfg.safe_action) + [
            maccepa.encode_stop(b) for b in cfg.maccepa_boards
        ]
        self._s = WatchdogState("disarmed", "startup", "", time.time_ns(), 0, 0, 0)
        self._repeats: list[float] = []
        self.last_h2: float | None = None  # monotonic time of the last H2 angle frame
        self.first_trip_ns: int | None = None
        self._stop = threading.Event()
        self._rx = threading.Thread(target=self._listen, daemon=True, name="watchdog-rx")

    def start(self) -> None:
        """Safe action first, before any node exists: the board may be in any state."""
        self.send_safe_action()
        self._rx.start()
        self.publish(self.snapshot())

    def snapshot(self) -> WatchdogState:
        with self.lock:
            return WatchdogState(**vars(self._s))

    @property
    def armed(self) -> bool:
        return self._s.state == "armed"

    def send_safe_action(self) -> int:
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
            if first:
                self._s.state, self._s.reason, self._s.detail = "tripped", reason, detail
                self._s.since_ns = time.time_ns()
                self._s.trips += 1
            self._repeats = [now + d for d in REPEAT_AFTER_S]
        if first:
            self.log.error("watchdog_tripped", reason=reason, detail=detail)
            self.publish(self.snapshot())
        else:
            self.log.warning("watchdog_trip_while_tripped", reason=reason, detail=detail)

    def arm(self, blockers: list[str]) -> None:
        if blockers:
            raise ArmRefused("cannot arm: " + "; ".join(blockers))
        with self.lock:
            self._s.state, self._s.reason, self._s.detail = "armed", "operator", ""
            self._s.since_ns = time.time_ns()
        self.log.warning("watchdog_armed")
        self.publish(self.snapshot())

    def disarm(self, reason: str = "operator") -> None:
        self.send_safe_action()
        with self.lock:
            self._s.state, self._s.reason, self._s.detail = "disarmed", reason, ""
            self._s.since_ns = time.time_ns()
        self.log.info("watchdog_disarmed", reason=reason)
        self.publish(self.snapshot())

    def h2_silent_for(self) -> float | None:
        return None if self.last_h2 is None else time.monotonic() - self.last_h2

    def check(self) -> None:
        """Periodic: repeat the safe action after a trip; H2 silence while armed."""
        now = time.monotonic()
        with self.lock:
            due = [t for t in self._repeats if t <= now]
            self._repeats = [t for t in self._repeats if t > now]
        if due:
            self.send_safe_action()
        if self.armed:
            silent = self.h2_silent_for()
            limit = self.cfg.h2_silence_ms / 1000
            if silent is None or silent > limit:
                shown = "never received" if silent is None else f"{silent * 1000:.0f} ms"
                self.trip(
                    "h2 data silent",
                    f"no joint-angle frame for {shown} (limit {self.cfg.h2_silence_ms} ms)",
                )

    def _listen(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.1)
            except can.CanError as exc:
                self.log.error("watchdog_rx_error", error=str(exc))
                time.sleep(0.1)
                continue
            if msg is None:
                continue
            if msg.arbitration_id == h2.JOINT_ANGLES:
                self.last_h2 = time.monotonic()
            elif msg.arbitration_id == h2.JOINT_CONTROL and not self.armed:
                frame = h2.decode(msg)
                if isinstance(frame, h2.JointControl) and frame.mode in MOTION_MODES:
                    with self.lock:
                        self._s.violations += 1
                    self.log.error("motion_frame_while_not_armed", frame=msg.data.hex())
                    self.send_safe_action()

    def close(self) -> None:
        self._stop.set()
        if self._rx.is_alive():
            self._rx.join(1)
