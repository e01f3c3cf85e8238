"""The supervisor's management API: what a laptop's CLI, the dashboard, ROS 2 services and the
appliance's own nodes ask the supervisor (status, node control and logs, the watchdog, the
trigger, the board's clock, software updates), each route with the role it needs
(exolink.roles). Handlers read the supervisor's state; only the watchdog and node control act.
"""

from __future__ import annotations

import functools
import os
import threading
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as installed_version
from typing import Any, Protocol

from exolink import messaging, roles
from exolink.board import update
from exolink.board.clock import BoardClock
from exolink.config import ApplianceConfig
from exolink.messaging import Refused
from exolink.supervisor import canlink, trigger
from exolink.supervisor.forking import Zygote
from exolink.supervisor.memory import MemoryTrim, rss_mb
from exolink.supervisor.processes import NodeProcess
from exolink.supervisor.wakeup import Wakeup
from exolink.supervisor.watchdog import Watchdog
from exolink.wire import management, replies
from exolink.wire.requests import action_of, decode, tag_of

Route = tuple[Any, messaging.Needs]


class Supervised(Protocol):
    """What the API reads and acts on of the supervisor (supervisor.core.Supervisor)."""

    cfg: ApplianceConfig
    log: Any
    msg: messaging.Messaging
    wake: Wakeup
    nodes: dict[str, NodeProcess]
    watchdog: Watchdog
    zygote: Zygote | None
    health: canlink.LinkHealth | None
    clock: BoardClock
    update: update.Receiver
    memory: MemoryTrim
    bad_samples: dict[str, int]
    trigger_count: int
    last_trigger_ns: int | None
    trigger_src: Any
    trigger_out: Any

    def take_beats(self) -> None: ...
    def described(self, node: NodeProcess) -> replies.NodeInfo: ...
    def arm_blockers(self) -> list[str]: ...


class ManagementApi:
    """The routes under the supervisor's management key, and the e-stop's race with arming."""

    def __init__(self, sup: Supervised) -> None:
        self.sup = sup
        self._arming = threading.Lock()  # an arm's last check and the e-stops' count
        self._estops = 0

    def routes(self) -> dict[str, Route]:
        """path -> (handler, the role it needs: a role, or a function of the request)."""
        return {
            "status": (self.status, roles.OBSERVER),
            "nodes": (self.nodes, roles.OBSERVER),
            "control": (self.control, roles.ADMIN),
            "logs": (self.logs, roles.ADMIN),
            "watchdog": (self.watchdog, _watchdog_needs),
            "trigger": (self.trigger, roles.status_or(roles.OPERATOR)),
            "clock": (self.clock, roles.status_or(roles.OPERATOR)),
            "update": (self.update, roles.status_or(roles.ADMIN)),
        }

    def serve(self, msg: messaging.Messaging) -> list[Any]:
        """Every route declared on ``msg``'s session (an e-stop on its own, urgent, thread)."""
        return [
            msg.serve(path, handler, needs, _is_estop if path == "watchdog" else None)
            for path, (handler, needs) in self.routes().items()
        ]

    def nodes(self, _req: dict[str, Any]) -> replies.Nodes:
        sup = self.sup
        sup.take_beats()
        return replies.Nodes(nodes=[sup.described(n) for n in list(sup.nodes.values())])

    def status(self, _req: dict[str, Any]) -> replies.Status:
        sup = self.sup
        sup.take_beats()  # heartbeat ages as of now
        wd = sup.watchdog.snapshot()
        silent = sup.watchdog.silent_for()
        return replies.Status(
            device=sup.cfg.device,
            pid=os.getpid(),
            zygote_pid=sup.zygote.proc.pid if sup.zygote is not None else None,
            watchdog=replies.WatchdogStatus(**vars(wd)),
            bus=replies.Bus(
                interface=sup.cfg.can.interface,
                channel=sup.cfg.can.channel,
                **(vars(sup.health) if sup.health else {}),
                # the device's pulse (exolink.hardware: "h2 data"), and how long it is silent
                pulse=sup.watchdog.device.pulse,
                pulse_silent_s=None if silent is None else round(silent, 3),
            ),
            clock=sup.clock.status(),
            software=sup.update.status(version()),
            trigger=replies.TriggerStatus(
                source=sup.cfg.trigger.source,
                count=sup.trigger_count,
                last_ns=sup.last_trigger_ns,
            ),
            # a copy taken at once (under the GIL): the API answers while start() still adds
            # nodes, and iterating the dict itself then failed ("changed size during iteration")
            nodes=[sup.described(n) for n in list(sup.nodes.values())],
            # requests the supervisor's API handled and refused (messaging.Admission), samples
            # it could not read, and what it gave back to the kernel (memory.MemoryTrim)
            api=sup.msg.admission.counters(),
            bad_samples=dict(sup.bad_samples),
            memory=replies.Memory(rss_mb=round(rss_mb(), 1), trims=sup.memory.trims),
        )

    def _node(self, name: str) -> NodeProcess:
        nodes = self.sup.nodes
        if name not in nodes:
            raise Refused(f"unknown node {_shown(name)} (configured: {', '.join(nodes)})")
        return nodes[name]

    def control(self, req: dict[str, Any]) -> replies.NodeReply:
        cmd = decode(req, management.NodeControl, "node action")
        node, action = self._node(cmd.node), tag_of(cmd)
        if action != "start" and node.cfg.critical:
            # Before the process goes, whatever the order its exit is reported in: a critical
            # node down is a trip (and arming waits for it to beat again).
            why = "stopped" if action == "stop" else "restarted"
            self.sup.watchdog.trip(f"critical node {why} by operator", node.name)
        if action != "start":
            node.stop()
        if action != "stop":
            with node.lock:
                node.restart_times.clear()
                node.start()
        self.sup.wake.set()  # a started node is looked at for its first beat at once
        return replies.NodeReply(node=self.sup.described(node))

    def logs(self, req: dict[str, Any]) -> replies.LogLines:
        ask = management.convert(req, management.Logs, "logs")
        return replies.LogLines(lines=list(self._node(ask.node).logs)[-ask.lines :])

    def watchdog(self, req: dict[str, Any], caller: messaging.Caller) -> replies.Watchdog:
        """``caller``: the login Zenoh proved, which the e-stop's detail names (a ``by`` in the
        request is the client's own text and is not used)."""
        wd = self.sup.watchdog
        # An e-stop first, as it came: nothing else in the request is looked at.
        action, cmd = ("estop" if _is_estop(req) else None), None
        if action is None and not management.status_asked(req):
            cmd = decode(req, management.Watchdog, "watchdog action")
            action = tag_of(cmd)
        if action == "arm":
            estops = self._estops
            blockers = self.sup.arm_blockers()  # reads every node's pipe: not under the lock
            with self._arming:
                if self._estops != estops:
                    raise Refused("not armed: an e-stop came in while arming")
                wd.arm(blockers)  # ArmRefused is a refusal: its text is the reply's error
        elif action == "disarm":
            wd.disarm()
        elif action == "estop":
            # On its own thread (urgent), beside an arm on the API's: counted first, so that
            # an arm under way either finished before (and is tripped now) or sees the count
            # and refuses; it never arms after this e-stop.
            with self._arming:
                self._estops += 1
            wd.trip("operator e-stop", f"by {caller.login}")
        elif isinstance(cmd, management.Trip):  # the appliance's own nodes (the holder lost)
            wd.trip(cmd.reason[:80] or "node request", cmd.detail[:300])
        s = wd.snapshot()
        return replies.Watchdog(state=s.state, reason=s.reason, detail=s.detail)

    def trigger(self, req: dict[str, Any]) -> replies.Fired | replies.TriggerStatus:
        sup = self.sup
        if not management.status_asked(req):
            decode(req, management.Trigger, "trigger action")  # fire is the one there is
            if sup.trigger_out is not None:
                return replies.Fired(fired_ns=sup.trigger_out.fire())
            if isinstance(sup.trigger_src, trigger.SimulatedTrigger):
                sup.trigger_src.fire()
                return replies.Fired(fired_ns=sup.last_trigger_ns)
            raise Refused("no trigger output configured (trigger.output in the config)")
        return replies.TriggerStatus(count=sup.trigger_count, last_ns=sup.last_trigger_ns)

    def clock(self, req: dict[str, Any], caller: messaging.Caller) -> replies.ClockStatus:
        """The board's clock (any role: a laptop measures its offset from ``now``), or a step
        to an operator laptop's time (exolink.board.clock: refused while armed or synchronised)."""
        clock = self.sup.clock
        if not management.status_asked(req):
            ask = decode(req, management.Clock, "clock action")
            step = clock.step(ask.offset_s, ask.error_s, caller.login, self.sup.watchdog.armed)
            self.sup.log.warning(
                "clock_stepped", by=step.by, at=step.at, step_s=step.step_s, error_ms=step.error_ms
            )
        return clock.status()

    def update(
        self, req: dict[str, Any], caller: messaging.Caller
    ) -> replies.Software | replies.UploadAt | replies.Committed:
        """A new root file system from an admin laptop, in chunks (exolink.board.update; the
        requests: exolink.wire.management's ``Update``); no action is the software status (any
        role). Refused while armed: installing ends in a reboot, never under a walking patient;
        once committed, arming is refused until the reboot."""
        rx = self.sup.update
        if management.status_asked(req):
            return rx.status(version())
        ask = decode(req, management.Update, "update action")
        if isinstance(ask, management.Abort):
            rx.abort()
            return rx.status(version())
        if isinstance(ask, management.Begin | management.Commit) and self.sup.watchdog.armed:
            raise update.UpdateRefused(
                "the exoskeleton is armed: an update ends in a reboot, never under a walking "
                "patient. Disarm first (exolink watchdog disarm)"
            )
        if isinstance(ask, management.Begin):
            return rx.begin(ask, caller.login)
        if isinstance(ask, management.Chunk):
            return rx.chunk(ask)
        return rx.commit(caller.login)


@functools.cache
def version() -> str:
    """The installed exolink's version (the software status names it)."""

    try:
        return installed_version("exolink")
    except PackageNotFoundError:
        return "unknown"


def _is_estop(req: dict[str, Any]) -> bool:
    """An e-stop is acted on at once, whatever the rate of its login or the queue before it,
    and whatever else its request holds."""
    return action_of(req) == "estop"


def _shown(value: Any) -> str:
    """A client's value in an error: its repr, cut (it may be a megabyte)."""
    return messaging.clip(repr(value), 60)


def _watchdog_needs(req: dict[str, Any]) -> str:
    """E-stop is every login's; arming and disarming are the operator's; a trip with a reason
    of its own only the appliance's nodes'."""
    action = action_of(req)
    if action == "trip":
        return roles.APPLIANCE_USER
    return roles.OPERATOR if action in ("arm", "disarm") else roles.OBSERVER
