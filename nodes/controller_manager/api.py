"""What the controller manager serves: the controllers and the operator's presence (``exolink
hold``); the operator's one-off commands to the H2 and the MACCEPA boards are commands.py's, on
the checks and switches of this one.

Every way motion is asked for (the CLI, the dashboard, ROS 2's ``cmd/joint`` and
``joint_command`` through the supervisor, a controller loaded by hand) reaches these handlers in
one hop from the router and is checked here once, by the one set of rules: the limits in force
(``intent``), the watchdog armed, a holder present, the joint not driven by someone else. The
frames are encoded once, where they are sent (the node's cycle).

Requests run in order on a thread of their key (``messaging.Served``): one that switches
controllers waits there for a cycle boundary, never on Zenoh's callback thread, which also
carries the watchdog's word; the presence keep-alive is answered at once (``urgent``), never
behind a switch.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Protocol, TypeVar

import can
import msgspec
import structlog
from exolink.nodes.controller_manager.intent import OperatorLimits, Presence
from exolink.nodes.controller_manager.manager import Manager
from exolink.nodes.controller_manager.slots import Switch

from exolink import roles
from exolink.control import replies, requests
from exolink.messaging import Caller, Refused, Unlogged
from exolink.node import NodeContext
from exolink.plugins import controller_types
from exolink.wire import management
from exolink.wire.requests import action_of, with_default

R = TypeVar("R")

SWITCH_WAIT_S = 1.0
OPERATOR = "operator"  # prefix of the controllers that hold what `exolink send` asked
READS = ("list", "types", "state")  # what an observer may ask of the controllers
PRESENCE = ("hold", "release")  # answered at once, never behind a switch


def _controllers_needs(request: dict[str, Any]) -> str:
    return roles.OBSERVER if action_of(request, "list") in READS else roles.OPERATOR


def _presence(request: dict[str, Any]) -> bool:
    return action_of(request) in PRESENCE


def _deadline(within: Any) -> float | None:
    """``within_s``: the asker waits this long for the answer, so nothing it asked for may take
    effect after that (it would then say the request failed while the manager drove on)."""
    if within is None:
        return None
    if not isinstance(within, int | float) or isinstance(within, bool) or not 0 < within <= 10:
        raise Refused(f"within_s must be a number of seconds in (0, 10], not {within!r}")
    return time.monotonic() + within


def frame_texts(frames: list[can.Message]) -> list[str]:
    return [f"{f.arbitration_id:03X}#{f.data.hex().upper()}" for f in frames]


class ManagerNode(Protocol):
    """What the requests use of the controller manager's node (``ControllerManagerNode``)."""

    ctx: NodeContext
    log: structlog.typing.FilteringBoundLogger
    manager: Manager
    limits: OperatorLimits
    presence: Presence
    board_ids: set[int]
    wake: threading.Event  # a queued switch: the loop opens the reader now

    def own(self, resource: R) -> R: ...
    def status(self) -> replies.ManagerStatus: ...
    def not_armed(self) -> str | None: ...
    def maybe_tell(self) -> None: ...
    def limit_frames(self) -> list[can.Message]: ...
    def send_now(self, frames: list[can.Message]) -> None: ...
    def stop_joints(self, joints: set[int], mode: int, why: str) -> list[can.Message]: ...
    def stop_boards(self, boards: set[int], why: str) -> list[can.Message]: ...
    def stop_all(self, why: str) -> None: ...


class ManagerApi:
    """The requests of ``ControllerManagerNode``, which makes one of these and serves it (it
    uses the node's manager, intent, presence and bus: ``ManagerNode``)."""

    def __init__(self, node: ManagerNode) -> None:
        self.node = node

    def serve(self) -> None:
        m = self.node.ctx.messaging
        self.node.own(m.serve("controllers", self.on_controllers, _controllers_needs, _presence))

    # --- checks -------------------------------------------------------------------------------

    def may_move(self) -> None:
        """Refused unless motion may start now: armed, a holder present, the limits known."""
        for why in (self.node.not_armed(), self.node.presence.check(), self.node.limits.check()):
            if why:
                raise Refused(why)

    # --- controllers --------------------------------------------------------------------------

    def on_controllers(self, req: dict[str, Any], caller: Caller) -> Any:
        try:
            return self._controllers(req, caller)
        finally:
            self.node.maybe_tell()

    def _controllers(self, req: dict[str, Any], caller: Caller) -> replies.Reply | Unlogged:
        req = with_default(req, "list")
        cmd = requests.decode(req, requests.Controllers, "controllers action")
        manager = self.node.manager
        match cmd:
            case requests.ControllersList():
                return self.node.status()
            case requests.ControllerState():
                return manager.state_of(cmd.name)
            case requests.ControllerTypes():
                return replies.Types(controller_types())
            case requests.Hold():
                return self._hold(cmd, caller)
            case requests.Release():
                return self._release(cmd)
            case requests.Load():
                return self._load(cmd)
            case requests.Unload():
                manager.unload(cmd.name)
                return replies.Done()
            case requests.ControllerCommand():
                if cmd.name in manager.active():  # it moves a joint now
                    self.may_move()
                # the rest is the controller's own command, which its type checks
                body = {k: v for k, v in req.items() if k not in ("action", "name")}
                return replies.Commanded(cmd.name, manager.command(cmd.name, body))
            case requests.Activate():
                return self.switch(Switch(list(cmd.names), []))
            case requests.Deactivate():
                return self.switch(Switch([], list(cmd.names)))
            case requests.SwitchControllers():
                return self.switch(Switch(list(cmd.activate), list(cmd.deactivate)))
        raise AssertionError(f"a decoded controllers request without a handler: {cmd!r}")

    def _hold(self, req: requests.Hold, caller: Caller) -> replies.Held | Unlogged:
        holder, renewed = self.node.presence.hold(req.holder, caller.login, req.what, req.take_over)
        reply = replies.Held(holder, renewed, self.node.manager.active(), self.node.presence.lost_s)
        # renewals (twice a second) stay out of the command log
        return Unlogged(replies.plain(reply)) if renewed else reply

    def _release(self, req: requests.Release) -> replies.Released:
        """A holder lets go: what it held stops (the safe action), without a trip."""
        released = self.node.presence.release(req.holder)
        if released and self.node.manager.active():
            self.node.stop_all("its holder released motion")
        return replies.Released(released)

    def _load(self, req: requests.Load) -> replies.Loaded:
        """``replace``: a controller of that name is deactivated and unloaded first;
        ``activate``: the new one is activated at the next cycle (within ``within_s`` of this
        request, if given). One request instead of four (what the pattern player sends). An
        activation refused (not armed, nobody holding motion, a claim held, no cycle in time)
        leaves the controllers as they were, except that a replaced one that was active is
        now inactive."""
        name, activate, replace = req.name, req.activate, req.replace
        until = _deadline(req.within_s)
        if activate:
            self.may_move()
        slot = self.node.manager.prepare(
            name, req.type, dict(req.params), req.budget_ms, replacing=replace
        )
        if replace and name in self.node.manager.active():
            self.switch(Switch([], [name]))
        old = self.node.manager.add(slot, replace=replace)
        loaded = replies.Loaded(**msgspec.structs.asdict(slot.status()))
        if not activate:
            return loaded
        try:
            active = self.switch(Switch([name], []), until)
        except Refused:
            self.node.manager.put_back(slot, old)  # nothing half-done: as before the request
            raise
        loaded.active = active.active
        return loaded

    def switch(self, sw: Switch, until: float | None = None) -> replies.Active:
        """Applied at one cycle boundary, or refused whole. An activation supersedes the
        operator's one-off holds (``operator.*``) on the joints and boards it claims, in the
        same switch: the operator who starts a pattern means the pattern to drive.
        ``until`` (monotonic): the asker's own limit, waited for instead of SWITCH_WAIT_S, never
        passed."""

        if sw.activate:
            self.may_move()
            held = self.node.manager.superseded(sw.activate, OPERATOR + ".")
            sw.deactivate += [n for n in held if n not in sw.deactivate]
        wait = SWITCH_WAIT_S if until is None else until - time.monotonic()
        if wait <= 0:
            raise Refused("the request's within_s ran out before its switch")
        self.node.manager.request(sw)
        self.node.wake.set()
        if not sw.done.wait(wait) and self.node.manager.withdraw(sw):
            raise Refused(f"no H2 cycle within {wait:.2g} s to switch at (is the H2 streaming?)")
        sw.done.wait()
        if sw.error is not None:
            raise Refused(sw.error)
        return replies.Active(self.node.manager.active())

    # --- presence -----------------------------------------------------------------------------

    def check_presence(self) -> None:
        """A holder whose keep-alive ran out while something drives: everything stops now
        (the safe action) and the watchdog is asked to trip (latched until re-armed)."""
        lost = self.node.presence.lapsed()
        if lost is None:
            return
        detail = (
            f"{lost.login} ({lost.what or 'no description'}) sent no keep-alive for "
            f"{self.node.presence.lost_s:g} s"
        )
        if not self.node.manager.active():
            self.node.log.info("presence_expired", detail=detail)
            return
        self.node.stop_all(f"operator lost: {detail}")
        self.node.log.error("operator_lost", detail=detail)
        if self.node.ctx.config.watchdog.trip_on_operator_lost:
            self._ask_trip("operator lost", detail)

    def _ask_trip(self, reason: str, detail: str) -> None:
        """The supervisor's watchdog trips (its answer is not waited for by the loop)."""

        def ask() -> None:
            try:
                body = requests.body(management.Trip(reason, detail))
                self.node.ctx.messaging.command("watchdog", body=body, timeout_s=2.0)
            except Refused as exc:
                self.node.log.error("trip_request_failed", reason=reason, error=str(exc))

        threading.Thread(target=ask, daemon=True, name="trip").start()
