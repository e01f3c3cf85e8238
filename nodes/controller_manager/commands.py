"""The operator's one-off commands, through the controller manager: the H2's (``exolink send``:
joint control, the accepted angles, the data stream) and the MACCEPA boards' (``exolink maccepa``:
set-point, duty, gains, stop control). Motion is held by an operator controller per joint or
board (``operator.r_knee.position``), switched in at one cycle boundary by the manager's API
(api.py), which checks it as every other way in; disable and stop go out at once.
"""

from __future__ import annotations

import time
from typing import Any

from exolink.nodes.controller_manager.api import OPERATOR, ManagerApi, ManagerNode, frame_texts
from exolink.nodes.controller_manager.frames import SAFE_MODES
from exolink.nodes.controller_manager.slots import Switch

from exolink import roles
from exolink.control import replies, requests
from exolink.limits.maccepa import GAINS, target
from exolink.messaging import Caller, Refused
from exolink.protocol import ProtocolError, h2, maccepa
from exolink.wire import cdr

DRIVE = ("setpoint", "duty")  # a board runs one of these at a time (closed / open loop)
JOINT_COMMAND = "exolink_msgs/msg/JointCommand"


class OperatorCommands:
    """The H2's and the MACCEPA boards' commands of ``ControllerManagerNode`` (which makes one
    of these beside its ``ManagerApi`` and serves it)."""

    def __init__(self, node: ManagerNode, api: ManagerApi) -> None:
        self.node = node
        self.api = api

    def serve(self) -> None:
        m = self.node.ctx.messaging
        self.pub_commands = self.node.own(m.publisher("joint_commands", JOINT_COMMAND, raw=True))
        self.node.own(m.serve(("h2", "command"), self.on_h2, roles.OPERATOR))
        self.node.own(m.serve("maccepa", self.on_maccepa, roles.OPERATOR))

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
            return replies.Frames(frame_texts(frames))
        except ProtocolError as exc:
            raise Refused(str(exc)) from None

    def _joint(self, cmd: requests.Joint, caller: Caller) -> replies.Frames | replies.Commanded:
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
            return replies.Frames(frame_texts(frames))
        if joint == "all":
            raise Refused("'all' joints is only for disabled or stopped")
        jc = h2.joint_control(joint, mode, cmd.setpoint or 0, cmd.stiffness or 0)
        i = jc.motor - 1
        lim = self.node.limits.in_force
        by = self.node.limits.set_by
        where = f" (set by {by.login})" if by is not None else " (the config's limits:)"
        if why := lim.violation(i, mode, jc.setpoint, jc.stiffness, where=where):
            raise Refused(why)
        self.api.may_move()
        reply = self._operator(h2.JOINTS[i], h2.MODE_NAMES[mode], jc.setpoint, jc.stiffness)
        self._record(jc, caller)
        return reply

    def _operator(self, joint: str, mode: str, setpoint: int, stiffness: int) -> replies.Commanded:
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
            self.api.switch(Switch([name], before))
        return replies.Commanded(name, reply)

    def _limits(self, cmd: requests.Limits, caller: Caller) -> replies.LimitsSet:
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
        return replies.LimitsSet(frame_texts(frames), self.node.limits.describe())

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
                return replies.Frames(frame_texts(frames))
            self._check_maccepa(cmd)
            self.api.may_move()
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

    def _maccepa(
        self, cmd: requests.Gains | requests.Setpoint | requests.Duty
    ) -> replies.Commanded:
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
            self.api.switch(Switch([name], before))
        return replies.Commanded(name, reply)
