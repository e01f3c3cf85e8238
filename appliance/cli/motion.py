"""Laptop commands for the pattern player, the MACCEPA boards and the timing monitor."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from exolink import messaging
from exolink.cli.errors import EXIT_UNREACHABLE, fail
from exolink.cli.remote import (
    _decimal,
    _frame_id,
    _guard,
    _integer,
    _Leaves,
    _number,
    common,
    hold,
    remote,
)

# --- pattern ----------------------------------------------------------------------------------


def _show(s: dict[str, Any]) -> str:
    why = f" ({s['reason']})" if s.get("reason") else ""
    return (
        f"{s['state']}{why}  point {s['index']}/{s['length']}  speed {s['speed']} ({s['period_ms']} ms)  "
        f"joints {','.join(s['selected']) or '-'}  timing {s['timing']}  sent {s['sent']}"
    )


def pattern_body(args: argparse.Namespace) -> dict[str, Any]:
    """The pattern player request of a parsed `exolink pattern ...` (also the dashboard's)."""
    action = args.action
    body: dict[str, Any] = {"action": action}
    if action == "speed":
        body["speed"] = args.level
    elif action in ("select", "disable"):
        body["joints"] = args.joints
    elif action == "load":  # a file on this laptop is uploaded; a bare name is the board's
        local = Path(args.file)
        if local.is_file():
            body["content"] = local.read_text(encoding="utf-8", errors="replace")
            body["name"] = local.name
        else:
            body["file"] = args.file
    return body


# `pattern start` waits for the player, which waits up to 5 s for the controller manager to
# start the gait (pattern_player.ENGAGE_WAIT_S): a CLI that gave up first would leave a
# pattern running with nobody holding it (the watchdog then trips for the lost operator).
START_TIMEOUT_S = 8.0


@_guard
def cmd_pattern(args: argparse.Namespace) -> int:
    action, body = args.action, pattern_body(args)
    if action == "start":
        args.timeout = max(args.timeout, START_TIMEOUT_S)
    with remote(args) as r:
        if action != "start" or args.detach:
            sys.stdout.write(_show(r.call("pattern", body=body)) + "\n")
            return 0
        return _hold(r, body)


def _hold(r: Any, body: dict[str, Any]) -> int:
    """Start and stay attached: this session's liveliness token is the operator's presence.

    If this laptop vanishes (Wi-Fi drop, closed lid), the watchdog trips after operator_lost_ms.
    Ctrl-C stops the pattern.
    """
    operator = uuid.uuid4().hex[:12]
    token = r.session.liveliness().declare_token(
        messaging.mgmt_key(r.device, "operators", operator)
    )
    try:
        sys.stdout.write(_show(r.call("pattern", body={**body, "operator": operator})) + "\n")
        sys.stdout.write("holding the pattern; Ctrl-C stops it\n")
        done = threading.Event()

        def on_state(msg: Any, _m: messaging.Meta) -> None:
            if msg.state != "running":
                sys.stdout.write(
                    f"pattern {msg.state}{' (' + msg.reason + ')' if msg.reason else ''}\n"
                )
                done.set()

        m = messaging.Messaging(r.session, _FakeCfg(r))
        sub = m.subscribe("pattern_state", "exolink_msgs/msg/PatternState", on_state)
        try:
            while not done.wait(1.0):
                s = r.call("pattern", body={"action": "status"})
                sys.stdout.write("\r" + _show(s) + "   ")
                sys.stdout.flush()
        except KeyboardInterrupt:
            sys.stdout.write("\n" + _show(r.call("pattern", body={"action": "stop"})) + "\n")
        finally:
            sub.undeclare()
    finally:
        token.undeclare()
    return 0


class _FakeCfg:
    """The three fields Messaging needs, from the CLI's options (no appliance config on a laptop)."""

    def __init__(self, r: Any) -> None:
        from exolink.config import ZenohConfig

        self.zenoh = ZenohConfig(domain_id=r.domain, namespace=r.ns)
        self.device = r.device


# --- MACCEPA ----------------------------------------------------------------------------------


def maccepa_body(args: argparse.Namespace) -> dict[str, Any]:
    """The MACCEPA bridge request of a parsed `exolink maccepa ...` (also the dashboard's)."""
    body: dict[str, Any] = {"board": args.board, "kind": args.kind}
    if args.kind == "gains":
        body |= {"kp": args.kp, "ki": args.ki, "kd": args.kd, "controller": args.controller}
    elif args.kind == "setpoint":
        body |= {"value": args.value, "controller": args.controller}
    elif args.kind == "duty":
        body["value"] = args.value
    return body


@_guard
def cmd_maccepa(args: argparse.Namespace) -> int:
    if args.kind == "watch":
        return _watch(args)
    with remote(args) as r:
        reply = r.call("maccepa", body=maccepa_body(args))
    if reply.get("controller"):  # the bridge handed it to the controller manager
        sys.stdout.write(f"ok held by controller {reply['controller']}\n")
    else:
        sys.stdout.write("ok " + " ".join(reply["frames"]) + "\n")
    return 0


def strip(link: float, lever: float, lo: float = -120, hi: float = 120, width: int = 61) -> str:
    """One line of the tuning plot: L = link 2, A = lever arm, * where they coincide."""
    line = [" "] * width
    line[round((0 - lo) / (hi - lo) * (width - 1))] = "|"

    def col(v: float) -> int:
        return max(0, min(width - 1, round((v - lo) / (hi - lo) * (width - 1))))

    a, b = col(lever), col(link)
    line[a] = "A"
    line[b] = "*" if a == b else "L"
    return "".join(line)


def _watch(args: argparse.Namespace) -> int:
    """The thesis' tuning plot in a terminal: link-2 against lever-arm position, scrolling."""
    last = [0.0]

    def on(msg: Any, _m: messaging.Meta) -> None:
        now = time.monotonic()
        if now - last[0] < 1 / args.rate:
            return
        last[0] = now
        sys.stdout.write(
            f"{strip(msg.link_deg, msg.lever_deg)}  link {msg.link_deg:5d}  lever {msg.lever_deg:5d}\n"
        )
        sys.stdout.flush()

    with remote(args) as r:
        m = messaging.Messaging(r.session, _FakeCfg(r))
        sub = m.subscribe(f"maccepa/b{args.board}/state", "exolink_msgs/msg/MaccepaState", on)
        try:
            hold(args.seconds)
        finally:
            sub.undeclare()
    return 0


# --- timing -----------------------------------------------------------------------------------


def timing_body(args: argparse.Namespace) -> dict[str, Any]:
    """The timing monitor request of a parsed `exolink timing ...` (also the dashboard's)."""
    body: dict[str, Any] = {
        "id": args.id,
        "seconds": args.seconds,
        "byte0": args.motor,
        "dlc": args.dlc,
    }
    if args.expected_ms is not None:
        body["expected_ms"] = args.expected_ms
    return body


@_guard
def cmd_timing(args: argparse.Namespace) -> int:
    body = timing_body(args)
    args.timeout = max(args.timeout, args.seconds + 5)
    with remote(args) as r:
        s = r.call("timing", body=body)
    s.pop("ok", None)
    if not s.get("n"):
        return fail(f"no timing for id {args.id}: {s.get('error', 'no frames')}", EXIT_UNREACHABLE)
    if args.json:
        sys.stdout.write(json.dumps(s) + "\n")
        return 0
    sys.stdout.write(
        f"id {args.id}{f' motor {args.motor}' if args.motor is not None else ''}: n={s['n']} period {s['mean_period_ms']} ms "
        f"(expected {s['expected_ms']})  deviation mean {s['mean_dev_ms']} p99 {s['p99_dev_ms']} max {s['max_dev_ms']} ms\n"
    )
    for k, v in s["histogram"].items():
        sys.stdout.write(f"  {k:>12} {v}\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parent = common()
    p = sub.add_parser("pattern", help="gait pattern player")
    s = _Leaves(p.add_subparsers(dest="action", required=True), parent)
    q = s.add_parser("start", help="start (stays attached: Ctrl-C stops; --detach returns at once)")
    q.add_argument("--detach", action="store_true")
    for name in ("stop", "pause", "restart", "status"):
        s.add_parser(name)
    q = s.add_parser("speed", help="speed LEVEL (1..10; 10 = a set-point every 20 ms)")
    q.add_argument("level", type=_integer)
    for name in ("select", "disable"):
        q = s.add_parser(name, help=f"{name} JOINT...")
        q.add_argument("joints", nargs="+")
    q = s.add_parser(
        "load",
        help="load FILE: a CSV on this laptop (uploaded) or a name in the board's patterns_dir",
    )
    q.add_argument("file")
    p.set_defaults(func=cmd_pattern)

    p = sub.add_parser("maccepa", help="MACCEPA actuator boards")
    p.add_argument("board", type=_integer)
    s = _Leaves(p.add_subparsers(dest="kind", required=True), parent)
    q = s.add_parser("gains", help="gains --kp X --ki Y --kd Z [--controller position|velocity]")
    for g in ("--kp", "--ki", "--kd"):
        q.add_argument(g, type=_number)
    q.add_argument("--controller", choices=["position", "velocity"], default="position")
    q = s.add_parser("setpoint", help="setpoint VALUE [--controller ...]")
    q.add_argument("value", type=_number)
    q.add_argument("--controller", choices=["position", "velocity"], default="position")
    q = s.add_parser("duty", help="duty PERCENT (0..100)")
    q.add_argument("value", type=_number)
    s.add_parser("stop", help="stop control")
    q = s.add_parser("watch", help="live link-2 vs lever-arm plot (the tuning view)")
    q.add_argument("--rate", type=_decimal, default=10.0, help="lines per second")
    q.add_argument("--seconds", type=_decimal, default=0, help="stop after N seconds")
    p.set_defaults(func=cmd_maccepa)

    p = sub.add_parser(
        "timing", parents=[parent], help="period deviation of a CAN id (timing monitor)"
    )
    p.add_argument("id", type=_frame_id)
    p.add_argument(
        "--motor", type=_integer, help="only frames whose first byte is this (id 70: motor id)"
    )
    p.add_argument("--seconds", type=_decimal, default=10.0)
    p.add_argument(
        "--dlc",
        type=_integer,
        help="only frames of this length (id 70 is also MACCEPA board 0's, 8 bytes)",
    )
    p.add_argument("--expected-ms", type=_decimal)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_timing)
