"""``exolink controllers ...``: the controller manager from a laptop (list, types, load, unload,
activate, deactivate, switch, command). Reading needs the observer role, the rest operator."""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from typing import Any

from exolink.cli.options import Leaves, common, decimal, guard
from exolink.client import remote
from exolink.control import replies, requests
from exolink.wire.requests import classes


def _limits(lim: replies.LimitsInfo) -> list[str]:
    """The limits in force, one line per joint, and who set them."""
    who = f"set by {lim.set_by} at {_time(lim.set_at_ns)}" if lim.set_by else "the config's"
    lines = [f"limits   {who}; step {lim.max_step_deg} deg per 10 ms"]
    if lim.unreadable:
        lines.append(f"         UNREADABLE (motion refused): {lim.unreadable}")
    for j, v in lim.joints.items():
        lines.append(
            f"  {j:<8} {v.min:>4}..{v.max:<4} deg  torque {v.torque} "
            f"(+-{v.torque_step} per 10 ms)  stiffness {v.stiffness} %"
        )
    return lines


def _presence(p: replies.PresenceInfo) -> str:
    h = p.holder
    lost = f"lost after {p.lost_after_s:g} s, {p.losses} lost so far"
    if h is None:
        return f"motion   held by nobody (motion refused; `exolink hold`); {lost}"
    return (
        f"motion   held by {h.login} ({h.what}) since {_time(h.since_ns)}, "
        f"renewed {h.renewed_s_ago} s ago; {lost}"
    )


def _time(ns: int | None) -> str:

    if not ns:
        return "-"
    return datetime.datetime.fromtimestamp(ns / 1e9).strftime("%Y-%m-%d %H:%M:%S")


def show(s: replies.ManagerStatus) -> str:
    lines = [_presence(s.presence), *_limits(s.limits)]
    lines.append(f"cycles {s.cycles}  written {s.written}  safe-action frames {s.safe}")
    if s.maccepa:  # boards the manager drives: who owns what, what it last wrote
        lines.append(
            f"maccepa frames written {s.maccepa_written}  "
            f"stop-control frames {s.maccepa_safe}  "
            f"malformed {sum(s.malformed.values())}"
        )
        for name, b in sorted(s.maccepa.items()):
            held = {k.split("/")[1]: v for k, v in s.owners.items() if k.split("/")[0] == name}
            gains = "-" if b.gains is None else ",".join(f"{g:g}" for g in b.gains)
            sp = "-" if b.setpoint is None else f"{b.setpoint:g}"
            lines.append(
                f"{name:<16} {b.controller} controller  set-point {sp}  gains {gains}  "
                + (", ".join(f"{k} by {v}" for k, v in sorted(held.items())) or "not claimed")
            )
    for c in s.controllers:
        why = f" ({c.error})" if c.error else ""
        mean = c.update_ms_mean
        lines.append(
            f"{c.name:<16} {c.type:<18} {c.state}{why}\n"
            f"  claims {', '.join(c.claims)}\n"
            f"  update ms mean {mean if mean is not None else '-'} max {c.update_ms_max} "
            f"(budget {c.budget_ms})  overruns {c.overruns}  limited {c.limited}"
        )
    return "\n".join(lines)


def _value(text: str) -> tuple[str, float]:
    joint, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"{text!r}: give JOINT=VALUE, e.g. r_knee=30")
    try:
        return joint, decimal(value)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc}") from None


def _params(text: str) -> dict[str, Any]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"--params is not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise argparse.ArgumentTypeError("--params must be a JSON object")
    return data


def controllers_body(args: argparse.Namespace) -> dict[str, Any]:
    """The controllers request of a parsed `exolink controllers ...`
    (exolink.control.requests.Controllers)."""
    a = args.action
    req: requests.Controllers
    if a == "load":
        req = requests.Load(
            args.name,
            args.type,
            args.params,
            activate=args.activate,
            replace=args.replace,
            budget_ms=args.budget_ms,
        )
    elif a == "unload":
        req = requests.Unload(args.name)
    elif a in ("activate", "deactivate"):
        req = classes(requests.Controllers)[a](list(args.names))
    elif a == "switch":
        req = requests.SwitchControllers(list(args.activate), list(args.deactivate))
    elif a == "command":  # the controller's own command: its values by joint
        return {**requests.body(requests.ControllerCommand(args.name)), "values": dict(args.values)}
    else:  # list, types
        req = classes(requests.Controllers)[a]()
    return requests.body(req)


@guard
def cmd_controllers(args: argparse.Namespace) -> int:
    a = args.action
    body = controllers_body(args)
    with remote(args) as r:
        reply = r.call("controllers", body=body)
    reply.pop("ok", None)
    if getattr(args, "json", False):
        sys.stdout.write(json.dumps(reply) + "\n")
    elif a == "list":
        sys.stdout.write(show(replies.read(reply, replies.ManagerStatus)) + "\n")
    elif a == "types":
        for name, where in sorted(replies.read(reply, replies.Types).types.items()):
            sys.stdout.write(f"{name:<20} {where}\n")
    elif a in ("activate", "deactivate", "switch"):
        active = replies.read(reply, replies.Active).active
        sys.stdout.write(f"active: {', '.join(active) or '-'}\n")
    else:
        sys.stdout.write("ok " + json.dumps(reply) + "\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    parent = common()
    p = sub.add_parser("controllers", help="controller manager: list, load, activate, switch")
    s = Leaves(p.add_subparsers(dest="action", required=True), parent)
    q = s.add_parser("list", help="loaded controllers, their state, claims and update times")
    q.add_argument("--json", action="store_true")
    s.add_parser("types", help="installed controller types (entry points exolink.controllers)")
    q = s.add_parser(
        "load", help="load NAME TYPE [--params JSON]: validated, then inactive (or --activate)"
    )
    q.add_argument("name")
    q.add_argument("type")
    q.add_argument("--params", type=_params, default={})
    q.add_argument("--budget-ms", type=decimal, help="CPU per update before it is deactivated")
    q.add_argument("--replace", action="store_true", help="unload a controller of that name first")
    q.add_argument("--activate", action="store_true", help="and activate it at the next cycle")
    q = s.add_parser("unload", help="unload NAME (inactive only)")
    q.add_argument("name")
    for name in ("activate", "deactivate"):
        q = s.add_parser(name, help=f"{name} NAME... at the next H2 cycle")
        q.add_argument("names", nargs="+")
    q = s.add_parser("switch", help="deactivate some and activate others at one H2 cycle")
    q.add_argument("--activate", nargs="+", default=[], metavar="NAME")
    q.add_argument("--deactivate", nargs="+", default=[], metavar="NAME")
    q = s.add_parser(
        "command",
        help="command NAME JOINT=VALUE... (forward_command, pid; maccepa_setpoint: maccepa0=30)",
    )
    q.add_argument("name")
    q.add_argument("values", nargs="+", type=_value)
    p.set_defaults(func=cmd_controllers)
