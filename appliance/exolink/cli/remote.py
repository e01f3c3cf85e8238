"""Laptop-side commands that act: ``send`` (the H2's commands, through the controller manager)
and the supervisor's management (start, stop, logs, arm, disarm, estop, params, trigger). Data
commands are exolink.cli.data, the status exolink.cli.status."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from exolink import messaging
from exolink.cli import clock
from exolink.cli.errors import EXIT_REFUSED, fail
from exolink.cli.options import Leaves, common, guard, integer, number, print_json
from exolink.client import remote
from exolink.control import requests
from exolink.control.replies import Commanded, Frames
from exolink.wire import management, replies
from exolink.wire.replies import NodeParams, ParamSet
from exolink.wire.requests import classes


def _angles(text: str) -> list[float]:
    parts = [p for p in text.replace(" ", "").split(",") if p]
    if len(parts) != 6:
        raise argparse.ArgumentTypeError(f"need six comma-separated angles, got {len(parts)}")
    return [number(p) for p in parts]


def done_line(raw: dict[str, Any]) -> str:
    """What a motion command did: held by an operator controller (the manager writes it each
    cycle, ``Commanded``) or frames sent at once (``Frames``)."""
    if "controller" in raw:
        return f"ok held by controller {replies.read(raw, Commanded).controller}\n"
    return "ok " + " ".join(replies.read(raw, Frames).frames) + "\n"


def _h2_command(args: argparse.Namespace, body: dict[str, Any]) -> int:
    with remote(args) as r:
        sys.stdout.write(done_line(r.call("h2", "command", body=body)))
    return 0


def h2_body(args: argparse.Namespace) -> dict[str, Any]:
    """The H2 command of a parsed `exolink send ...` (also what the dashboard sends)."""
    what = args.what
    cmd: requests.H2Command
    if what in ("joint", "position", "stiffness"):
        mode = args.mode if what == "joint" else what
        cmd = requests.Joint(args.joint, mode, args.value, args.stiffness)
    elif what == "torque":
        cmd = requests.Joint(args.joint, "torque", args.value)
    elif what in ("disable", "stop"):
        cmd = requests.Joint(args.joint, "disabled" if what == "disable" else "stopped")
    elif what == "limits":
        cmd = requests.Limits(args.min, args.max, bool(args.reset))
    else:
        cmd = requests.Stream(args.state == "on")
    return requests.body(cmd)


@guard
def cmd_send(args: argparse.Namespace) -> int:
    return _h2_command(args, h2_body(args))


# --- registration ----------------------------------------------------------------------------


def register(sub: argparse._SubParsersAction) -> None:
    parent = common()

    p = sub.add_parser("send", help="send a validated command to the H2")
    s = Leaves(p.add_subparsers(dest="what", required=True), parent)
    q = s.add_parser("joint", help="joint JOINT MODE VALUE (e.g. joint r_knee position 30)")
    q.add_argument("joint")
    q.add_argument("mode", choices=["position", "stiffness", "torque", "disabled", "stopped"])
    q.add_argument("value", type=number, nargs="?", default=0)
    q.add_argument("--stiffness", type=number, default=0)
    q = s.add_parser("position", help="position JOINT DEG")
    q.add_argument("joint")
    q.add_argument("value", type=number)
    q.set_defaults(stiffness=0)
    q = s.add_parser("stiffness", help="stiffness JOINT DEG PERCENT")
    q.add_argument("joint")
    q.add_argument("value", type=number)
    q.add_argument("stiffness", type=number)
    q = s.add_parser("torque", help="torque JOINT COUNTS")
    q.add_argument("joint")
    q.add_argument("value", type=number)
    for name in ("disable", "stop"):
        q = s.add_parser(name, help=f"{name} JOINT|all")
        q.add_argument("joint")
    q = s.add_parser(
        "limits",
        help="limits --min a,b,c,d,e,f --max a,b,c,d,e,f (deg; only inside the config's); "
        "--reset: the config's",
    )
    q.add_argument("--min", type=_angles)
    q.add_argument("--max", type=_angles)
    q.add_argument("--reset", action="store_true", help="back to the config's limits")
    q = s.add_parser("stream", help="stream on|off")
    q.add_argument("state", choices=["on", "off"])
    p.set_defaults(func=cmd_send)


# --- management (supervisor) -----------------------------------------------------------------


def control_body(action: str, node: str) -> dict[str, Any]:
    """A node's start, stop or restart (exolink.wire.management)."""
    return requests.body(classes(management.NodeControl)[action](node))


def watchdog_body(action: str) -> dict[str, Any]:
    """arm, disarm or estop (exolink.wire.management)."""
    return requests.body(classes(management.Watchdog)[action]())


def trigger_body(fire: bool) -> dict[str, Any]:
    """A pulse on the trigger output, or (False) the trigger's status."""
    return requests.body(management.Fire()) if fire else {}


@guard
def cmd_control(args: argparse.Namespace) -> int:
    with remote(args) as r:
        n = replies.read(
            r.call("control", body=control_body(args.command, args.node)), replies.NodeReply
        )
    sys.stdout.write(f"{n.node.name}: {n.node.state} pid={n.node.pid}\n")
    return 0


def hold(seconds: float = 0) -> None:
    """Keep a subscription open for ``seconds`` (0: until Ctrl-C); Ctrl-C is a normal end."""
    end = time.monotonic() + (seconds or float("inf"))
    try:
        while time.monotonic() < end:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass


@guard
def cmd_logs(args: argparse.Namespace) -> int:
    with remote(args) as r:
        ask = requests.body(management.Logs(args.node, args.lines))
        for line in replies.read(r.call("logs", body=ask), replies.LogLines).lines:
            sys.stdout.write(line + "\n")
        if not args.follow:
            return 0
        sys.stdout.flush()
        sub = r.session.declare_subscriber(
            messaging.mgmt_key(r.device, "log", args.node),
            lambda s: (
                sys.stdout.write(s.payload.to_bytes().decode(errors="replace") + "\n"),
                sys.stdout.flush(),
            ),
        )
        try:
            hold()
        finally:
            sub.undeclare()
    return 0


@guard
def cmd_watchdog(args: argparse.Namespace) -> int:
    body = watchdog_body(args.command)  # the e-stop's detail names this session's login
    with remote(args) as r:
        if args.command == "arm":  # a board with no time server takes this laptop's first
            sys.stdout.write(clock.sync_at_arm(r))
        s = r.call("watchdog", body=body)
    detail = f": {s['detail']}" if s.get("detail") else ""
    sys.stdout.write(f"watchdog {s['state']} ({s['reason']}{detail})\n")
    return 0


def params_body(args: argparse.Namespace) -> dict[str, Any]:
    """The params request of a parsed `exolink params NODE [--set KEY VALUE]`: a VALUE that
    is JSON is taken as such (3, true, [1, 2]), anything else as text."""
    if not args.set:
        return {}
    key, raw = args.set
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return requests.body(management.Params(management.SetParam(key, value)))


@guard
def cmd_params(args: argparse.Namespace) -> int:
    with remote(args) as r:
        names = [n.name for n in r.nodes()]
        if args.node not in names:
            return fail(f"no node {args.node} (nodes: {', '.join(names)})", EXIT_REFUSED)
        if args.set:
            done = replies.read(
                r.call("nodes", args.node, "params", body=params_body(args)), ParamSet
            )
            sys.stdout.write(f"{args.node}.{done.key} = {json.dumps(done.value)}\n")
        else:
            print_json(replies.read(r.call("nodes", args.node, "params"), NodeParams).params)
    return 0


@guard
def cmd_trigger(args: argparse.Namespace) -> int:
    with remote(args) as r:
        reply = r.call("trigger", body=trigger_body(args.action == "fire"))
    sys.stdout.write(json.dumps({k: v for k, v in reply.items() if k != "ok"}) + "\n")
    return 0


def register_management(sub: argparse._SubParsersAction) -> None:
    parent = common()
    for name in ("start", "stop", "restart"):
        p = sub.add_parser(name, parents=[parent], help=f"{name} a node")
        p.add_argument("node")
        p.set_defaults(func=cmd_control)
    p = sub.add_parser("logs", parents=[parent], help="a node's recent output")
    p.add_argument("node")
    p.add_argument("--lines", "-n", type=integer, default=50)
    p.add_argument("--follow", "-f", action="store_true")
    p.set_defaults(func=cmd_logs)
    for name, text in (
        ("arm", "allow motion (refused while a failure persists)"),
        ("disarm", "disable the motors and refuse motion"),
        ("estop", "trip the watchdog now: motors disabled, latched"),
    ):
        p = sub.add_parser(name, parents=[parent], help=text)
        p.set_defaults(func=cmd_watchdog)
    p = sub.add_parser("params", parents=[parent], help="show or set a node's params")
    p.add_argument("node")
    p.add_argument("--set", nargs=2, metavar=("KEY", "VALUE"))
    p.set_defaults(func=cmd_params)
    p = sub.add_parser(
        "trigger", parents=[parent], help="trigger count, or fire the trigger output"
    )
    p.add_argument("action", nargs="?", choices=["fire"])
    p.set_defaults(func=cmd_trigger)
