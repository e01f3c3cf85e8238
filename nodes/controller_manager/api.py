"""What the controller manager serves: the controllers, the H2's commands (``exolink send``), the
MACCEPA boards' commands (``exolink maccepa``) and the operator's presence (``exolink hold``).

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
import structlog
from exolink.nodes.controller_manager.frames import SAFE_MODES
from exolink.nodes.controller_manager.intent import OperatorLimits, Presence
from exolink.nodes.controller_manager.manager import Manager
from exolink.nodes.controller_manager.slots import Switch

from exolink import roles
from exolink.control import requests
from exolink.limits.maccepa import GAINS, target
from exolink.messaging import Caller, Refused, Unlogged
from exolink.node import NodeContext
from exolink.plugins import controller_types
from exolink.protocol import ProtocolError, h2, maccepa
from exolink.wire import cdr, management
from exolink.wire.requests import action_of, with_default

R = TypeVar("R")

SWITCH_WAIT_S = 1.0
OPERATOR = "operator"  # prefix of the controllers that hold what `exolink send` asked
OPERATOR_MODES = ("position", "stiffness", "torque")
DRIVE = ("setpoint", "duty")  # a board runs one of these at a time (closed / open loop)
READS = ("list", "types", "state")  # what an observer may ask of the controllers
PRESENCE = ("hold", "release")  # answered at once, never behind a switch
JOINT_COMMAND = "exolink_msgs/msg/JointCommand"


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


def _frames(frames: list[can.Message]) -> list[str]:
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
    def status(self) -> dict[str, Any]: ...
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
        self.pub_commands = self.node.own(m.publisher("joint_commands", JOINT_COMMAND, raw=True))
        self.node.own(m.serve("controllers", self.on_controllers, _controllers_needs, _presence))
        self.node.own(m.serve(("h2", "command"), self.on_h2, roles.OPERATOR))
        self.node.own(m.serve("maccepa", self.on_maccepa, roles.OPERATOR))

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

    def _controllers(self, req: dict[str, Any], caller: Caller) -> dict[str, Any]:
        req = with_default(req, "list")
        cmd = requests.decode(req, requests.Controllers, "controllers action")
        manager = self.node.manager
        match cmd:
            case requests.ControllersList():
                return self.node.status()
            case requests.ControllerState():
                return manager.state_of(cmd.name)
            case requests.ControllerTypes():
                return {"types": controller_types()}
            case requests.Hold():
                return self._hold(cmd, caller)
            case requests.Release():
                return self._release(cmd)
            case requests.Load():
                return self._load(cmd)
            case requests.Unload():
                manager.unload(cmd.name)
                return {}
            case requests.ControllerCommand():
                if cmd.name in manager.active():  # it moves a joint now
                    self.may_move()
                # the rest is the controller's own command, which its type checks
                body = {k: v for k, v in req.items() if k not in ("action", "name")}
                return manager.command(cmd.name, body)
            case requests.Activate():
                return self._switch(Switch(list(cmd.names), []))
            case requests.Deactivate():
                return self._switch(Switch([], list(cmd.names)))
            case requests.SwitchControllers():
                return self._switch(Switch(list(cmd.activate), list(cmd.deactivate)))
        raise AssertionError(f"a decoded controllers request without a handler: {cmd!r}")

    def _hold(self, req: requests.Hold, caller: Caller) -> dict[str, Any]:
        out = self.node.presence.hold(req.holder, caller.login, req.what, req.take_over)
        reply = {
            **out,
            "driving": self.node.manager.active(),
            "presence_lost_after_s": self.node.presence.lost_s,
        }
        return Unlogged(reply) if out["renewed"] else reply  # renewals: twice a second

    def _release(self, req: requests.Release) -> dict[str, Any]:
        """A holder lets go: what it held stops (the safe action), without a trip."""
        released = self.node.presence.release(req.holder)
        if released and self.node.manager.active():
            self.node.stop_all("its holder released motion")
        return {"released": released}

    def _load(self, req: requests.Load) -> dict[str, Any]:
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
            self._switch(Switch([], [name]))
        old = self.node.manager.add(slot, replace=replace)
        if not activate:
            return slot.status()
        try:
            active = self._switch(Switch([name], []), until)
        except Refused:
            self.node.manager.put_back(slot, old)  # nothing half-done: as before the request
            raise
        return {**slot.status(), **active}

    def _switch(self, sw: Switch, until: float | None = None) -> dict[str, Any]:
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
        return {"active": self.node.manager.active()}

    # --- the H2's commands --------------------------------------------------------------------

    def on_h2(self, req: dict[str, Any], caller: Caller) -> Any:
        """``exolink send``: joint control (motion held by the joint's operator controller;
        disable and stop at once, always allowed), the accepted angles (the operator's limits),
        the data stream. Nothing is sent unless the whole command is valid."""
        cmd = requests.decode(req, requests.H2Command, "command kind")
        try:
            if isinstance(cmd, requests.Joint):
                return self._joint(cmd, caller)
            if isinstance(cmd, requests.Limits):
                return self._limits(cmd, caller)
            frames = [h2.encode_stream(cmd.on)]
            self.node.send_now(frames)
            return {"frames": _frames(frames)}
        except ProtocolError as exc:
            raise Refused(str(exc)) from None

    def _joint(self, cmd: requests.Joint, caller: Caller) -> dict[str, Any]:
        joint = cmd.joint
        mode = h2.mode_id(cmd.mode)
        if mode in SAFE_MODES:  # can only make things safer: always, and at once
            motors = range(1, 7) if joint == "all" else [h2.motor_id(joint)]
            commands = [h2.joint_control(m, mode) for m in motors]
            what = f"{'all joints' if joint == 'all' else joint} {h2.MODE_NAMES[mode]}"
            frames = self.node.stop_joints(
                {m - 1 for m in motors}, mode, f"{what} by {caller.login}"
            )
            for jc in commands:
                self._record(jc, caller)
            return {"frames": _frames(frames)}
        if joint == "all":
            raise Refused("'all' joints is only for disabled or stopped")
        jc = h2.joint_control(joint, mode, cmd.setpoint or 0, cmd.stiffness or 0)
        i = jc.motor - 1
        lim = self.node.limits.in_force
        by = self.node.limits.set_by
        where = f" (set by {by.login})" if by is not None else " (the config's limits:)"
        if why := lim.violation(i, mode, jc.setpoint, jc.stiffness, where=where):
            raise Refused(why)
        self.may_move()
        reply = self._operator(h2.JOINTS[i], h2.MODE_NAMES[mode], jc.setpoint, jc.stiffness)
        self._record(jc, caller)
        return reply

    def _operator(self, joint: str, mode: str, setpoint: int, stiffness: int) -> dict[str, Any]:
        """Held by that joint's own operator controller, made on first use. A joint another
        controller drives is refused with that controller named; a joint the operator drove in
        another mode changes mode at one cycle boundary."""
        name, mine = f"{OPERATOR}.{joint}.{mode}", f"{OPERATOR}.{joint}."
        for key, owner in self.node.manager.owners_of(joint).items():
            if not owner.startswith(mine):
                raise Refused(
                    f"{joint} is driven by controller {owner} ({key}): "
                    f"`exolink controllers deactivate {owner}` first"
                )
        if name not in self.node.manager.names():
            self.node.manager.load(name, "operator", {"joint": joint, "mode": mode})
        reply = self.node.manager.command(name, {"setpoint": setpoint, "stiffness": stiffness})
        if name not in self.node.manager.active():
            before = [n for n in self.node.manager.active() if n.startswith(mine)]
            self._switch(Switch([name], before))
        return {"controller": name, "frames": [], **reply}

    def _limits(self, cmd: requests.Limits, caller: Caller) -> Any:
        """The operator's accepted angles: only narrower than the config's, kept before they
        take effect (they survive a restart), then in force for every way in and sent to the
        H2. ``reset``: back to the config's."""
        if cmd.reset:
            lo = hi = None
        else:
            got = {k: v for k, v in (("min", cmd.min), ("max", cmd.max)) if v is not None}
            if not got:
                raise Refused("limits needs 'min' and/or 'max' (six angles in degrees), or 'reset'")
            checked = {k: h2.decode(h2.encode_accepted_angles(k, v)) for k, v in got.items()}
            lo = [int(a) for a in checked["min"]] if "min" in checked else None
            hi = [int(a) for a in checked["max"]] if "max" in checked else None
        new = self.node.limits.set(lo, hi, caller.login)
        self.node.manager.set_limits(new)
        frames = self.node.limit_frames()
        self.node.send_now(frames)
        return {"frames": _frames(frames), "limits": self.node.limits.describe()}

    def _record(self, jc: h2.JointControl, caller: Caller) -> None:
        """An accepted command on ``joint_commands``, with the login that sent it."""
        now = time.time_ns()
        joint = h2.JOINTS[jc.motor - 1]
        payload = cdr.joint_command(now, joint, jc.mode, jc.setpoint, jc.stiffness, caller.login)
        self.pub_commands.put(payload, now)

    # --- the MACCEPA boards' commands ---------------------------------------------------------

    def on_maccepa(self, req: dict[str, Any], caller: Caller) -> Any:
        """``exolink maccepa N ...``: set-point, duty and gains held by that board's operator
        controller for the kind (``operator.maccepa0.setpoint``); stop control at once."""
        cmd = requests.decode(req, requests.MaccepaCommand, "MACCEPA command")
        board = cmd.board
        if board not in self.node.board_ids:
            configured = ", ".join(str(b) for b in sorted(self.node.board_ids)) or "none"
            raise Refused(
                f"MACCEPA board {board!r} is not driven by the controller manager "
                f"(params.maccepa: {configured})"
            )
        try:
            if isinstance(cmd, requests.Stop):
                frames = self.node.stop_boards(
                    {board}, f"{target(board)} stopped by {caller.login}"
                )
                return {"frames": _frames(frames)}
            self._check_maccepa(cmd)
            self.may_move()
            return self._maccepa(cmd)
        except ProtocolError as exc:
            raise Refused(str(exc)) from None

    def _check_maccepa(self, cmd: requests.Gains | requests.Setpoint | requests.Duty) -> None:
        """The codec's checks (ProtocolError names what is wrong); the board's limits are the
        controller's and the manager's."""
        board = cmd.board
        lim = self.node.manager.boards[board]
        asked = getattr(cmd, "controller", None)  # duty has none: the board's own
        ctl = lim.controller if asked is None else asked
        if ctl not in (lim.controller, maccepa.CONTROLLERS[lim.controller]):
            raise Refused(
                f"{target(board)} runs its {lim.controller} controller under the controller "
                f"manager (params.maccepa), not {ctl!r}"
            )
        if isinstance(cmd, requests.Gains):
            gains = [(g, v) for g in GAINS if (v := getattr(cmd, g)) is not None]
            if not gains:
                raise Refused("gains needs at least one of kp, ki, kd")
            for g, v in gains:
                maccepa.encode_gain(board, g, v, lim.controller)
        elif isinstance(cmd, requests.Setpoint):
            maccepa.encode_setpoint(board, cmd.value, lim.controller)
        else:
            maccepa.encode_duty(board, cmd.value)

    def _maccepa(self, cmd: requests.Gains | requests.Setpoint | requests.Duty) -> dict[str, Any]:
        """Set-point and duty drive the board and replace each other at one cycle boundary;
        gains are their own interface (tuning while something else drives the board). An
        interface another controller owns is refused with that controller named."""
        board, kind = cmd.board, requests.kind_of(cmd)
        group = DRIVE if kind in DRIVE else ("gains",)
        name, mine = f"{OPERATOR}.{target(board)}.{kind}", f"{OPERATOR}.{target(board)}."
        for key, owner in self.node.manager.owners_of(target(board)).items():
            if key.split("/")[1] in group and not owner.startswith(mine):
                raise Refused(
                    f"{target(board)} is driven by controller {owner} ({key}): "
                    f"`exolink controllers deactivate {owner}` first"
                )
        if name not in self.node.manager.names():
            self.node.manager.load(name, "maccepa_operator", {"board": board, "kind": kind})
        body = (
            {g: getattr(cmd, g) for g in GAINS}
            if isinstance(cmd, requests.Gains)
            else {"value": cmd.value}
        )
        reply = self.node.manager.command(name, body)
        if name not in self.node.manager.active():
            before = [
                n
                for n in self.node.manager.active()
                if n.startswith(mine) and n.rpartition(".")[2] in group
            ]
            self._switch(Switch([name], before))
        return {"controller": name, "frames": [], **reply}

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
