"""What a motion-capable node knows of the watchdog: armed, or why not.

The supervisor's watchdog is the authority; it publishes its state on ``watchdog`` on every
change and once a second. A node that has not heard from it recently treats the motors as not
armed: losing the supervisor must never leave a node free to move a joint.
"""

from __future__ import annotations

import threading
import time

from exolink import messaging
from exolink.wire import cdr

WATCHDOG_TOPIC = "watchdog"
WATCHDOG_TYPE = "exolink_msgs/msg/WatchdogEvent"
STALE_S = 3.0


class ArmingState:
    def __init__(self, msg: messaging.Messaging, stale_s: float = STALE_S) -> None:
        self._lock = threading.Lock()
        self._state, self._reason, self._seen = "unknown", "no word from the watchdog yet", 0.0
        self.stale_s = stale_s
        # How the watchdog's word reaches this node: events taken and the longest wait between
        # two (a starved core can stop a pattern for "no word for 3 s" while armed),
        # split by the times the supervisor put them (the sample's attachment) into its side
        # (the longest gap between two puts: it published late) and the way here (the longest
        # receive - put).
        self.received = 0
        self.max_gap_s = 0.0
        self.stamp_gap_max_s = 0.0
        self.delivery_max_s = 0.0
        self._stamp = 0
        self._sub = msg.subscribe_raw(WATCHDOG_TOPIC, WATCHDOG_TYPE, self._on_event, timed=True)
        try:
            reply = msg.request("watchdog")
            if reply.get("ok"):
                self._update(str(reply["state"]), str(reply.get("reason", "")))
        except messaging.Unreachable:
            pass  # stays "unknown" until the first event

    def _on_event(self, payload: bytes, sent_ns: int = 0) -> None:
        try:
            state, reason, _detail, _frames = cdr.watchdog_event(payload)
        except ValueError:
            return  # not a WatchdogEvent: never taken as a state (stale soon means not armed)
        self._update(state, reason, sent_ns)

    def _update(self, state: str, reason: str, stamp: int = 0) -> None:
        """``stamp``: when the supervisor put the word (ns since the epoch; 0: not known)."""
        now = time.monotonic()
        with self._lock:
            if self._seen:
                self.max_gap_s = max(self.max_gap_s, now - self._seen)
            if stamp:  # the board's one clock: publish and receive times compare
                self.delivery_max_s = max(self.delivery_max_s, time.time() - stamp / 1e9)
                if self._stamp:
                    self.stamp_gap_max_s = max(self.stamp_gap_max_s, (stamp - self._stamp) / 1e9)
                self._stamp = max(self._stamp, stamp)
            self.received += 1
            self._state, self._reason, self._seen = state, reason, now

    def counters(self) -> dict[str, float | int | None]:
        """For a node's status: whether its view of the watchdog is fed."""
        with self._lock:
            age = time.monotonic() - self._seen if self._seen else None
            return {
                "received": self.received,
                "max_gap_s": round(self.max_gap_s, 3),
                "stamp_gap_max_s": round(self.stamp_gap_max_s, 3),
                "delivery_max_s": round(self.delivery_max_s, 3),
                "age_s": None if age is None else round(age, 3),
            }

    def check(self) -> str | None:
        """None when motion is allowed, else the reason a caller sees."""
        with self._lock:
            age = time.monotonic() - self._seen
            if self._state == "unknown":
                return f"motors not armed: {self._reason}"
            if age > self.stale_s:
                return f"motors not armed: no word from the watchdog for {age:.1f} s"
            if self._state != "armed":
                why = f" ({self._reason})" if self._reason else ""
                return f"motors not armed: watchdog is {self._state}{why}; run `exolink arm`"
            return None

    def close(self) -> None:
        self._sub.undeclare()
