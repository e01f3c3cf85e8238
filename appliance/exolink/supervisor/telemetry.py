"""What the supervisor hears from its nodes on Zenoh and says of itself there: each node's
diagnostics (its health in ``exolink status``, a bus reader's receive losses), the requests its
API refused, the watchdog's events and the supervisor's own diagnostics. Anyone on the network
may put on these keys: a sample that does not read is counted by topic and error, never
trusted and never fatal. ``Supervisor`` is a ``NodeTelemetry``."""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Any

from exolink import logs, messaging
from exolink.wire import cdr

if TYPE_CHECKING:
    from exolink.config import ApplianceConfig
    from exolink.supervisor.canlink import LinkHealth
    from exolink.supervisor.processes import NodeProcess
    from exolink.supervisor.watchdog import Watchdog, WatchdogState

DIAGNOSTICS_TYPE = messaging.DIAGNOSTICS_TYPE
BAD_SAMPLE_KINDS = 64  # distinct "<topic>: <error>" counted one by one (_bad_sample)
BAD_SAMPLE_CHARS = 160
BAD_SAMPLE_OTHER = "other kinds"


class NodeTelemetry:
    """The telemetry half of the supervisor: the state it shares with it, declared here."""

    cfg: ApplianceConfig
    log: Any
    msg: messaging.Messaging
    session: Any
    nodes: dict[str, NodeProcess]
    watchdog: Watchdog
    health: LinkHealth | None
    trigger_count: int
    bad_samples: dict[str, int]  # "<topic>: <error>" -> count (see _bad_sample)
    node_api: dict[str, dict[str, int]]  # each node's Admission counters
    pub_wd: Any
    pub_diag: Any

    def _hear_nodes(self) -> list[Any]:
        """The subscriptions to every node's diagnostics and API refusals (to undeclare)."""
        diag_key = self.msg.key("nodes/*/diagnostics", DIAGNOSTICS_TYPE)
        api_key = self.msg.key(messaging.API_TOPIC.format(node="*"), messaging.API_TYPE)
        return [
            self.session.declare_subscriber(api_key, self._on_node_api),
            self.session.declare_subscriber(
                diag_key,
                lambda s: self._node_diagnostics(str(s.key_expr), s.payload.to_bytes()),
            ),
        ]

    def _publish_watchdog(self, s: WatchdogState) -> None:
        self.pub_wd.put(
            cdr.watchdog_event_msg(s.since_ns, s.state, s.reason, s.detail, s.frames_sent)
        )

    def _node_diagnostics(self, key: str, payload: bytes) -> None:
        """The worst status a node reports (e.g. the recorder's disk full) shows in `exolink status`."""
        name = _node_of(key)
        node = self.nodes.get(name)
        if node is None:
            return
        try:
            statuses = cdr.diagnostic_statuses(payload)
        except ValueError as exc:  # anyone may put on the key: checked, never trusted
            self._bad_sample(f"nodes/{name}/diagnostics", exc)
            return
        node.note_diagnostics(statuses)  # a bus reader's receive losses (rx_*) for status
        worst = max(statuses, key=lambda st: st.level, default=None)
        if worst is not None:
            level = {0: "ok", 1: "warn", 2: "error"}.get(int(worst.level), "stale")
            node.health = f"{level}: {worst.message}" if level != "ok" else "ok"

    def _on_node_api(self, sample: Any) -> None:
        """A node's refusals of requests (messaging.API_TOPIC), for `exolink status`."""
        name = _node_of(str(sample.key_expr))
        if name not in self.nodes:
            return
        try:
            counts = json.loads(cdr.string_of(sample.payload.to_bytes()))
            if not (
                isinstance(counts, dict)
                and set(counts) <= set(messaging.Admission.REASONS)
                and all(isinstance(n, int) and n >= 0 for n in counts.values())
            ):
                raise ValueError("not a node's refusal counts")
        except ValueError as exc:  # anyone may put on the key: checked, never trusted
            self._bad_sample(f"nodes/{name}/api", exc)
            return
        self.node_api[name] = counts

    def _bad_sample(self, topic: str, exc: ValueError) -> None:
        """A sample the supervisor cannot read, counted by topic and error and logged rarely
        (``logs.rarely``), as malformed CAN frames are. The error may quote what was sent and
        the topic holds a node name from the key: both are cut, and past BAD_SAMPLE_KINDS
        kinds the rest are counted under one."""
        key = messaging.clip(f"{topic}: {exc}", BAD_SAMPLE_CHARS)
        if key not in self.bad_samples and len(self.bad_samples) >= BAD_SAMPLE_KINDS:
            key = BAD_SAMPLE_OTHER
        n = self.bad_samples[key] = self.bad_samples.get(key, 0) + 1
        if logs.rarely(n):
            self.log.warning("bad_sample", kind=key, count=n)

    def _publish_diagnostics(self) -> None:
        wd = self.watchdog.snapshot()
        values: dict[str, Any] = {
            "watchdog": wd.state,
            "reason": wd.reason,
            "trips": wd.trips,
            "trigger_count": self.trigger_count,
        }
        if self.health is not None:
            values |= {
                "bus_state": self.health.state,
                "txerr": self.health.txerr,
                "rxerr": self.health.rxerr,
            }
        now = time.time_ns()
        level = "error" if wd.state == "tripped" else "ok"
        self.pub_diag.put(
            cdr.diagnostics(
                now, "supervisor", messaging.LEVELS[level], wd.state, self.cfg.device, values
            ),
            now,
        )


def _node_of(key: str) -> str:
    """The node a ``.../nodes/<name>/...`` key is about ("" for none): only a name the
    supervisor configured is ever acted on."""
    parts = key.split("/")
    return parts[parts.index("nodes") + 1] if "nodes" in parts else ""
