"""Laptop commands for the pattern player, the MACCEPA boards and the timing monitor."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

from exolink import messaging
from exolink.cli.errors import EXIT_REFUSED, EXIT_UNREACHABLE, fail
from exolink.cli.options import Leaves, common, decimal, frame_id, guard, integer, number
from exolink.cli.remote import done_line, hold
from exolink.cli.stopping import stop_on_signals
from exolink.client import remote
from exolink.config import ZenohConfig
from exolink.control import replies, requests
from exolink.control.holder import Holder, HoldRefused, describe
from exolink.wire import management
from exolink.wire.replies import TimingStats
from exolink.wire.requests import classes

# --- pattern ----------------------------------------------------------------------------------


def _show(raw: dict[str, Any]) -> str:
    s = replies.read(raw, replies.PatternInfo)
    why = f" ({s.reason})" if s.reason else ""
    return (
        f"{s.state}{why}  point {s.index}/{s.length}  speed {s.speed} ({s.period_ms} ms)  "
        f"joints {','.join(s.selected) or '-'}  sent {s.sent}"
    )


def pattern_body(args: argparse.Namespace) -> dict[str, Any]:
    """The pattern player request of a parsed `exolink pattern ...` (also the dashboard's)."""
    action = args.action
    req: requests.Pattern
    if action == "speed":
        req = requests.PatternSpeed(args.level)
    elif action in ("select", "disable"):
        req = classes(requests.Pattern)[action](list(args.joints))
    elif action == "load":  # a file on this laptop is uploaded; a bare name is the board's
        local = Path(args.file)
        if local.is_file():
            text = local.read_text(encoding="utf-8", errors="replace")
            req = requests.PatternLoad(content=text, name=local.name)
        else:
            req = requests.PatternLoad(file=args.file)
    else:
        req = classes(requests.Pattern)[action]()  # start, stop, pause, restart, status
    return requests.body(req)


# `pattern start` waits for the player, which waits up to 5 s for the controller manager to
# start the gait (pattern_player.ENGAGE_WAIT_S): a CLI that gave up first would leave a
# pattern running with its holder gone (the manager then stops it and trips the watchdog).
START_TIMEOUT_S = 8.0


@guard
def cmd_pattern(args: argparse.Namespace) -> int:
    action, body = args.action, pattern_body(args)
    if action == "start":
        args.timeout = max(args.timeout, START_TIMEOUT_S)
    with remote(args) as r:
        if action != "start" or args.detach:  # detached: whoever holds motion watches it
            sys.stdout.write(_show(r.call("pattern", body=body)) + "\n")
            return 0
        with stop_on_signals():
            return _attached(r, body, args.take_over)


def _attached(r: Any, body: dict[str, Any], take_over: bool) -> int:
    """Hold motion, start, and stay: this process's renewals are the operator's presence.

    If this laptop freezes or vanishes, the manager stops the pattern and trips the watchdog
    after operator_lost_ms. Ctrl-C stops the pattern and lets go.
    """
    ended = threading.Event()
    holder = _holder(r, "exolink pattern start", ended)
    try:
        holder.acquire(take_over)
    except HoldRefused as exc:
        return fail(
            f"refused: {exc} (a pattern started with --detach is watched by that holder)",
            EXIT_REFUSED,
        )
    try:
        sys.stdout.write(_show(r.call("pattern", body=body)) + "\n")
        sys.stdout.write("holding the pattern; Ctrl-C stops it\n")

        def on_state(msg: Any, _m: messaging.Meta) -> None:
            if msg.state != "running":
                sys.stdout.write(
                    f"pattern {msg.state}{' (' + msg.reason + ')' if msg.reason else ''}\n"
                )
                ended.set()

        m = messaging.Messaging(r.session, _FakeCfg(r))
        sub = m.subscribe("pattern_state", "exolink_msgs/msg/PatternState", on_state)
        try:
            while not ended.wait(1.0):
                s = r.call("pattern", body=requests.body(requests.PatternStatus()))
                sys.stdout.write("\r" + _show(s) + "   ")
                sys.stdout.flush()
            if holder.ended:
                sys.stdout.write(f"\nno longer holding motion: {holder.ended}\n")
        except KeyboardInterrupt:
            sys.stdout.write(
                "\n" + _show(r.call("pattern", body=requests.body(requests.PatternStop()))) + "\n"
            )
        finally:
            sub.undeclare()
    finally:
        holder.release()
    return 0


def _holder(r: Any, what: str, ended: threading.Event) -> Holder:
    def told(why: str) -> None:
        sys.stdout.write(f"\nno longer holding motion: {why}\n")
        sys.stdout.flush()
        ended.set()

    return Holder(lambda b: r.ask("controllers", body=b), describe(what), told)


@guard
def cmd_hold(args: argparse.Namespace) -> int:
    """Hold motion until Ctrl-C (or another client takes over): what an operator keeps running
    while motion is commanded from other terminals, the dashboard or ROS 2."""
    ended = threading.Event()
    with remote(args) as r, stop_on_signals():
        holder = _holder(r, "exolink hold", ended)
        try:
            reply = holder.acquire(args.take_over)
        except HoldRefused as exc:
            return fail(f"refused: {exc}", EXIT_REFUSED)
        sys.stdout.write(
            f"holding motion (it stops if this laptop is silent for {holder.lost_after_s:g} s);"
            f" driving now: {', '.join(reply.driving) or '-'}; Ctrl-C lets go\n"
        )
        sys.stdout.flush()
        try:
            while not ended.wait(0.2):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            holder.release()
        if not holder.ended:
            sys.stdout.write("\nreleased: whatever it held has stopped\n")
    return 0 if not holder.ended else EXIT_REFUSED


class _FakeCfg:
    """The three fields Messaging needs, from the CLI's options (no appliance config on a laptop)."""

    def __init__(self, r: Any) -> None:
        self.zenoh = ZenohConfig(domain_id=r.domain, namespace=r.ns)
        self.device = r.device


# --- MACCEPA ----------------------------------------------------------------------------------


def maccepa_body(args: argparse.Namespace) -> dict[str, Any]:
    """The controller manager's MACCEPA request of a parsed `exolink maccepa ...` (also the dashboard's)."""
    cmd: requests.MaccepaCommand
    if args.kind == "gains":
        cmd = requests.Gains(args.board, args.kp, args.ki, args.kd, args.controller)
    elif args.kind == "setpoint":
        cmd = requests.Setpoint(args.board, args.value, args.controller)
    elif args.kind == "duty":
        cmd = requests.Duty(args.board, args.value)
    elif args.kind == "stop":
        cmd = requests.Stop(args.board)
    else:
        raise ValueError(f"{args.kind} is not a request to the board")
    return requests.body(cmd)


@guard
def cmd_maccepa(args: argparse.Namespace) -> int:
    if args.kind == "watch":
        return _watch(args)
    with remote(args) as r:
        sys.stdout.write(done_line(r.call("maccepa", body=maccepa_body(args))))
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
    ask = management.Timing(
        args.id, args.seconds, args.motor, args.dlc, args.expected_ms, past=args.past
    )
    return requests.body(ask)


@guard
def cmd_timing(args: argparse.Namespace) -> int:
    body = timing_body(args)
    args.timeout = max(args.timeout, 5 if args.past else args.seconds + 5)
    with remote(args) as r:
        raw = r.call("timing", body=body)
    raw.pop("ok", None)
    s = replies.read(raw, TimingStats)
    if not s.n:
        return fail(f"no timing for id {args.id}: {s.error or 'no frames'}", EXIT_UNREACHABLE)
    if args.json:
        sys.stdout.write(json.dumps(raw) + "\n")
        return 0
    motor = f" motor {args.motor}" if args.motor is not None else ""
    sys.stdout.write(
        f"id {args.id}{motor}: n={s.n} period {s.mean_period_ms} ms (expected {s.expected_ms})"
        f"  deviation mean {s.mean_dev_ms} p99 {s.p99_dev_ms} max {s.max_dev_ms} ms\n"
    )
    for k, v in s.histogram.items():
        sys.stdout.write(f"  {k:>12} {v}\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    parent = common()
    p = sub.add_parser("pattern", help="gait pattern player")
    s = Leaves(p.add_subparsers(dest="action", required=True), parent)
    q = s.add_parser(
        "start",
        help="start, holding motion (stays attached: Ctrl-C stops); --detach: leave it to "
        "whoever holds motion (`exolink hold`)",
    )
    q.add_argument("--detach", action="store_true")
    q.add_argument("--take-over", action="store_true", help="take motion from its holder")
    for name in ("stop", "pause", "restart", "status"):
        s.add_parser(name)
    q = s.add_parser("speed", help="speed LEVEL (1..10; 10 = a set-point every 20 ms)")
    q.add_argument("level", type=integer)
    for name in ("select", "disable"):
        q = s.add_parser(name, help=f"{name} JOINT...")
        q.add_argument("joints", nargs="+")
    q = s.add_parser(
        "load",
        help="load FILE: a CSV on this laptop (uploaded) or a name in the board's patterns_dir",
    )
    q.add_argument("file")
    p.set_defaults(func=cmd_pattern)

    p = sub.add_parser(
        "hold",
        parents=[parent],
        help="hold motion until Ctrl-C: nothing moves a joint without a holder",
    )
    p.add_argument("--take-over", action="store_true", help="take motion from its holder")
    p.set_defaults(func=cmd_hold)

    p = sub.add_parser("maccepa", help="MACCEPA actuator boards")
    p.add_argument("board", type=integer)
    s = Leaves(p.add_subparsers(dest="kind", required=True), parent)
    q = s.add_parser("gains", help="gains --kp X --ki Y --kd Z [--controller position|velocity]")
    for g in ("--kp", "--ki", "--kd"):
        q.add_argument(g, type=number)
    q.add_argument("--controller", choices=["position", "velocity"], default="position")
    q = s.add_parser("setpoint", help="setpoint VALUE [--controller ...]")
    q.add_argument("value", type=number)
    q.add_argument("--controller", choices=["position", "velocity"], default="position")
    q = s.add_parser("duty", help="duty PERCENT (0..100)")
    q.add_argument("value", type=number)
    s.add_parser("stop", help="stop control")
    q = s.add_parser("watch", help="live link-2 vs lever-arm plot (the tuning view)")
    q.add_argument("--rate", type=decimal, default=10.0, help="lines per second")
    q.add_argument("--seconds", type=decimal, default=0, help="stop after N seconds")
    p.set_defaults(func=cmd_maccepa)

    p = sub.add_parser(
        "timing", parents=[parent], help="period deviation of a CAN id (timing monitor)"
    )
    p.add_argument("id", type=frame_id)
    p.add_argument(
        "--motor", type=integer, help="only frames whose first byte is this (id 70: motor id)"
    )
    p.add_argument("--seconds", type=decimal, default=10.0)
    p.add_argument(
        "--dlc",
        type=integer,
        help="only frames of this length (id 70 is also MACCEPA board 0's, 8 bytes)",
    )
    p.add_argument("--expected-ms", type=decimal)
    p.add_argument(
        "--past",
        action="store_true",
        help="the --seconds before now, answered at once (default: the next --seconds)",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_timing)
