"""The dashboard's live data: the 100 Hz topics (joint states, foot switches, the MACCEPA
boards' states) kept in Zenoh's own ring buffers while a page is open (Rust: no Python runs per
sample), the newest of each taken at the display rate and decoded into one frame for the pages,
and each topic's rate from its publisher's sequence numbers (the rmw_zenoh attachment)."""

from __future__ import annotations

import contextlib
import math
import time
from typing import Any

import structlog
import zenoh

from exolink import messaging
from exolink.client import Remote

log = structlog.get_logger("exolink.dashboard")

JOINT_STATE = "sensor_msgs/msg/JointState"
FOOT_SWITCHES = "exolink_msgs/msg/FootSwitches"
# Samples a data subscriber keeps between ticks (the newest win): one per topic it matches,
# with room for MACCEPA boards' three topics each.
RING = 64


class LiveData:
    """The data subscribers of one appliance (``remote``), open only while a page is."""

    def __init__(self, remote: Remote) -> None:
        self.remote = remote
        self._rings: list[Any] = []  # data subscribers with a ring buffer, drained per tick
        self.seq: dict[str, int] = {}  # topic -> newest publisher sequence number seen
        self._names: dict[str, tuple[str, str]] = {}  # key -> (topic, type), parsed once
        self._rate_at, self._rate_seq = time.monotonic(), dict(self.seq)  # see ``rates``

    def open(self) -> None:
        """The 100 Hz data topics, subscribed only while a page is open: otherwise the router
        forwards ~300 samples/s here and the tick drains them for nobody (measured:
        docs/performance.md)."""
        r = self.remote
        for selector in (
            messaging.topic_key(r.domain, r.ns, "joint_states", JOINT_STATE),
            messaging.topic_key(r.domain, r.ns, "foot_switches", FOOT_SWITCHES),
            messaging.topic_selector(r.domain, r.ns, "maccepa/*/*"),
        ):
            self._rings.append(
                r.session.declare_subscriber(selector, zenoh.handlers.RingChannel(RING))
            )
        self._rate_at, self._rate_seq = time.monotonic(), dict(self.seq)

    def rates(self, now: float) -> dict[str, float] | None:
        """Each topic's samples a second since the last rates (at least a second ago; None
        before that), from its publisher's sequence numbers: what it sent, not what this
        subscriber happened to get."""
        took = now - self._rate_at
        if took < 1.0:
            return None
        out = {
            k: round(max(0, v - self._rate_seq.get(k, v)) / took, 1) for k, v in self.seq.items()
        }
        self._rate_at, self._rate_seq = now, dict(self.seq)
        return out

    def close(self) -> None:
        for sub in self._rings:
            with contextlib.suppress(Exception):  # the session may already be closed
                sub.undeclare()
        self._rings.clear()

    def drain(self) -> dict[str, tuple[str, Any]]:
        """The newest sample of each data topic since the last tick: topic -> (type, sample)."""
        newest: dict[str, tuple[str, Any]] = {}
        for sub in self._rings:
            while (sample := sub.try_recv()) is not None:
                key = str(sample.key_expr)
                if (named := self._names.get(key)) is None:
                    try:
                        topic, typename = messaging.parse_key(key)
                    except ValueError:
                        continue
                    # h2/maccepa/b0/state -> maccepa/b0/state
                    named = self._names[key] = (topic.split("/", 1)[-1], typename)
                name, typename = named
                newest[name] = (typename, sample)
                if sample.attachment is not None:
                    with contextlib.suppress(ValueError):
                        self.seq[name] = messaging.decode_attachment(sample.attachment.to_bytes())[
                            0
                        ]
        return newest

    def frame(self, newest: dict[str, tuple[str, Any]]) -> dict[str, Any] | None:
        if not newest:
            return None
        out: dict[str, Any] = {"now_ns": time.time_ns()}
        for name, (typename, sample) in newest.items():
            payload = sample.payload.to_bytes()
            try:
                if name == "joint_states":
                    out["js"] = joint_state(payload)
                elif name == "foot_switches":
                    out["fs"] = foot_switches(payload)
                elif name.startswith("maccepa/"):
                    board_topic = name.removeprefix("maccepa/")  # b0/state
                    out.setdefault("maccepa", {})[board_topic] = plain(
                        messaging.deserialize(payload, typename)
                    )
            except Exception as exc:  # one bad sample must not stop the page
                log.warning("dashboard_decode_failed", topic=name, error=str(exc))
        return out


def joint_state(payload: bytes) -> dict[str, Any]:
    msg = messaging.deserialize(payload, JOINT_STATE)
    return {
        "stamp_ns": messaging.stamp_ns(msg.header.stamp),
        "name": list(msg.name),
        "pos_deg": [round(math.degrees(v), 2) for v in msg.position.tolist()],
        "eff_nm": [round(v, 3) for v in msg.effort.tolist()],
    }


def foot_switches(payload: bytes) -> dict[str, Any]:
    msg = messaging.deserialize(payload, FOOT_SWITCHES)
    return {
        "stamp_ns": messaging.stamp_ns(msg.header.stamp),
        "r_heel": bool(msg.r_heel),
        "r_toe": bool(msg.r_toe),
        "l_heel": bool(msg.l_heel),
        "l_toe": bool(msg.l_toe),
        "battery_raw": int(msg.battery_raw),
        "battery_volts": round(float(msg.battery_volts), 2),
    }


def plain(msg: Any) -> dict[str, Any]:
    """A small message (a MACCEPA board's state) as plain fields, without its header."""
    out: dict[str, Any] = {}
    for k in msg.__dataclass_fields__:
        if k.startswith("__"):  # rosbags' __msgtype__
            continue
        if k == "header":
            out["stamp_ns"] = messaging.stamp_ns(msg.header.stamp)
            continue
        v = getattr(msg, k)
        out[k] = v.tolist() if hasattr(v, "tolist") else v
    return out
