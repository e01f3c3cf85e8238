"""Laptop-side commands: talk to an appliance over Zenoh, never hang, say why on failure."""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import sys
import threading
import time
from typing import Any

from exolink import messaging
from exolink.cli import clock
from exolink.cli.controllers import show
from exolink.cli.errors import EXIT_REFUSED, EXIT_UNREACHABLE, fail
from exolink.cli.options import Leaves, common, decimal, guard, integer, number
from exolink.cli.units import degrees, unit
from exolink.cli.update import describe
from exolink.client import Refused, remote
from exolink.control import requests
from exolink.wire import management
from exolink.wire.requests import classes


def to_builtin(obj: Any) -> Any:
    """rosbags message -> plain data for printing (numpy arrays become lists)."""
    if hasattr(obj, "__dataclass_fields__"):
        return {k: to_builtin(getattr(obj, k)) for k in obj.__dataclass_fields__}
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, list | tuple):
        return [to_builtin(x) for x in obj]
    if isinstance(obj, bytes):
        return obj.hex()
    return obj


# --- data topics ------------------------------------------------------------------------------


@guard
def cmd_topics(args: argparse.Namespace) -> int:
    seen: dict[tuple[str, str], int] = {}
    lock = threading.Lock()

    def on(sample: Any) -> None:
        try:
            key = messaging.parse_key(str(sample.key_expr))
        except ValueError:
            return
        with lock:
            seen[key] = seen.get(key, 0) + 1

    with remote(args) as r:
        sub = r.session.declare_subscriber(f"{args.domain}/**", on)
        time.sleep(args.listen)
        sub.undeclare()
    if not seen:
        return fail(f"no topics seen at {args.at} within {args.listen:g} s", EXIT_UNREACHABLE)
    for (topic, typename), n in sorted(seen.items()):
        sys.stdout.write(f"/{topic:40} {typename:40} {n / args.listen:7.1f} Hz\n")
    return 0


@guard
def cmd_echo(args: argparse.Namespace) -> int:
    done = threading.Event()
    count = [0]

    def on(key: str, _seq: int, _ns: int, payload: bytes) -> None:
        if done.is_set():
            return
        _topic, typename = messaging.parse_key(key)
        data = to_builtin(messaging.deserialize(payload, typename))
        line = json.dumps(data) if args.json else _pretty(data, typename=typename)
        try:
            sys.stdout.write(line + ("\n" if args.json else "\n---\n"))
            sys.stdout.flush()
        except BrokenPipeError:  # `exolink echo ... | head -1`: the reader is gone, so are we
            done.set()
            _quiet_stdout()
            return
        count[0] += 1
        if args.count and count[0] >= args.count:
            done.set()

    with remote(args) as r:
        # A bundled topic (joint_states on the board) as its bundles: the board then puts
        # nothing one by one for this laptop (messaging.MessageSubscription).
        sub = messaging.MessageSubscription(
            r.session, r.device, r.selector(args.topic), on, ask_s=min(args.timeout, 3.0)
        )
        start = time.monotonic()
        while not done.wait(0.1):
            if count[0] == 0 and time.monotonic() - start > args.timeout:
                sub.close()
                return fail(
                    f"no messages on {args.topic} within {args.timeout:g} s "
                    f"(appliance at {args.at}; see `exolink topics`)",
                    EXIT_UNREACHABLE,
                )
        sub.close()
    return 0


def _quiet_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not raise again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


def _pretty(data: Any, indent: int = 0, typename: str = "") -> str:
    """YAML-like text; a top-level field of a known unit (exolink.cli.units) shows it."""
    pad = "  " * indent
    if isinstance(data, dict):
        lines = []
        for k, v in data.items():
            if isinstance(v, dict):
                lines.append(f"{pad}{k}:\n{_pretty(v, indent + 1)}")
                continue
            u = unit(typename, k, data) if typename else None
            text = f"{pad}{k}: {_fmt(v)}"
            if u and v != []:
                text += f" {u}"
                if u == "rad":
                    text += f"  ({_fmt(degrees(v))} deg)"
            lines.append(text)
        return "\n".join(lines)
    return pad + _fmt(data)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


@guard
def cmd_hz(args: argparse.Namespace) -> int:
    stamps: list[float] = []
    lock = threading.Lock()

    def on(_sample: Any) -> None:
        with lock:
            stamps.append(time.monotonic())

    with remote(args) as r:
        sub = r.session.declare_subscriber(r.selector(args.topic), on)
        start = time.monotonic()
        reports = 0
        while args.count == 0 or reports < args.count:
            time.sleep(args.window)
            with lock:
                window = [t for t in stamps if t > time.monotonic() - args.window]
                del stamps[: max(0, len(stamps) - 10_000)]
            if len(window) < 2:
                if time.monotonic() - start > args.timeout and not stamps:
                    sub.undeclare()
                    return fail(
                        f"no messages on {args.topic} within {args.timeout:g} s", EXIT_UNREACHABLE
                    )
                continue
            periods = [b - a for a, b in itertools.pairwise(window)]
            rate = (len(window) - 1) / (window[-1] - window[0])
            sys.stdout.write(
                f"rate {rate:8.2f} Hz  min {min(periods) * 1e3:6.2f} ms  "
                f"max {max(periods) * 1e3:6.2f} ms  std {statistics.pstdev(periods) * 1e3:6.2f} ms"
                f"  n={len(window)}\n"
            )
            sys.stdout.flush()
            reports += 1
        sub.undeclare()
    return 0


# --- commands to the H2 (the controller manager) ---------------------------------------------


def _angles(text: str) -> list[float]:
    parts = [p for p in text.replace(" ", "").split(",") if p]
    if len(parts) != 6:
        raise argparse.ArgumentTypeError(f"need six comma-separated angles, got {len(parts)}")
    return [number(p) for p in parts]


def _h2_command(args: argparse.Namespace, body: dict[str, Any]) -> int:
    with remote(args) as r:
        reply = r.call("h2", "command", body=body)
    if reply.get("controller"):  # motion through the controller manager: it writes each cycle
        sys.stdout.write(f"ok held by controller {reply['controller']}\n")
    else:
        sys.stdout.write("ok " + " ".join(reply.get("frames", [])) + "\n")
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

    p = sub.add_parser("topics", parents=[parent], help="list data topics with type and rate")
    p.add_argument("--listen", type=decimal, default=2.0, help="seconds to listen")
    p.set_defaults(func=cmd_topics)

    p = sub.add_parser("echo", parents=[parent], help="print messages of a topic")
    p.add_argument("topic")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--count", "-n", type=integer, default=0, help="stop after N messages")
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("hz", parents=[parent], help="measure a topic's publishing rate")
    p.add_argument("topic")
    p.add_argument("--window", type=decimal, default=1.0)
    p.add_argument("--count", "-n", type=integer, default=0, help="stop after N reports")
    p.set_defaults(func=cmd_hz)

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


def _print_json(data: Any) -> None:
    sys.stdout.write(json.dumps(data, indent=2) + "\n")


def _receive(rx: dict[str, Any] | None) -> str:
    """A bus reader's receive losses and backlog, after its health."""
    if not rx:
        return ""
    dropped = "n/a" if rx.get("dropped") is None else rx["dropped"]
    return (
        f"  rx dropped {dropped} late {rx.get('late')} lag max {rx.get('lag_max_ms')} ms"
        f" batch max {rx.get('batch_max')}"
    )


def node_health(n: dict[str, Any]) -> str:
    """What the health column says for a node: never blank."""
    if not n.get("enabled", True):
        return "disabled"
    state = str(n.get("state") or "unknown")
    if state == "running":
        if n.get("heartbeat_age_s") is None:
            return "starting"  # spawned, no heartbeat yet
        return str(n.get("health") or "ok")  # its own diagnostics, if it publishes any
    return {"backoff": "restarting"}.get(state, state)


# (title, right-aligned, cell); the last column is not padded.
_COLUMNS: list[tuple[str, bool, Any]] = [
    ("node", False, lambda n: n["name"] + ("*" if n.get("critical") else "")),
    ("state", False, lambda n: n["state"] if n.get("enabled", True) else "disabled"),
    ("pid", True, lambda n: n.get("pid") or "-"),
    ("uptime", True, lambda n: n.get("uptime_s", 0)),
    ("restarts", True, lambda n: n.get("restarts", 0)),
    ("cpu_s", True, lambda n: n.get("cpu_s", "-")),
    ("rss_mb", True, lambda n: n.get("rss_mb", "-")),
    ("last exit", False, lambda n: n.get("last_exit") or "-"),
    ("health", False, lambda n: node_health(n) + _receive(n.get("receive"))),
]


def _node_table(nodes: list[dict[str, Any]]) -> str:
    """One row per node; every column as wide as its widest cell, so long names keep it aligned."""
    cells = [[title for title, _r, _f in _COLUMNS]]
    cells += [[str(f(n)) for _t, _r, f in _COLUMNS] for n in nodes]
    widths = [max(len(row[i]) for row in cells) for i in range(len(_COLUMNS))]
    lines = []
    for row in cells:
        parts = [
            c.rjust(w) if right else c.ljust(w)
            for c, w, (_t, right, _f) in zip(row, widths, _COLUMNS, strict=True)
        ]
        lines.append("  ".join([*parts[:-1], row[-1]]).rstrip())
    return "\n".join(lines) + "\n(* critical)\n"


def _api_lines(s: dict[str, Any]) -> str:
    """What the management API did with requests: the supervisor's counts, then each node's
    refusals (too large, over its login's rate, queue full, ...), and unreadable samples."""
    api = s.get("api")
    if api is None:  # an older supervisor
        return ""
    refused = {k: v for k, v in api.items() if not k.startswith(("handled", "urgent")) and v}
    text = f"api      handled {api.get('handled', 0)}  urgent {api.get('urgent', 0)}"
    if api.get("urgent_unlogged"):
        text += f" ({api['urgent_unlogged']} not in the command log)"
    text += "  refused " + (", ".join(f"{k} {v}" for k, v in refused.items()) or "0") + "\n"
    for n in s["nodes"]:
        if n.get("api_refused"):
            counts = ", ".join(f"{k} {v}" for k, v in n["api_refused"].items())
            text += f"         {n['name']} refused {counts}\n"
    if bad := s.get("bad_samples"):
        text += f"samples  unreadable {sum(bad.values())} ({len(bad)} kinds)\n"
    return text


def _bytes(n: float) -> str:
    """A size as people read a card's: GiB from 1 GiB up, else MiB."""
    return f"{n / 2**30:.2f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def _card_line(nodes: list[dict[str, Any]]) -> str:
    """The recordings card, as the recorder last reported it: free space and the hours of
    recording that leaves at the current rate (above the reserve the recorder keeps)."""
    card = next((n["card"] for n in nodes if isinstance(n.get("card"), dict)), None)
    if not card:
        return ""

    def num(key: str) -> float | None:
        v = card.get(key)
        return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None

    free, total, reserve = num("free"), num("total"), num("reserve")
    if free is None or total is None:
        return ""
    text = f"card     {_bytes(free)} free of {_bytes(total)}"
    hours, rate = num("hours_left"), num("rate_bps")
    if hours is not None and rate:
        text += f"  {hours:.1f} h of recording left at {rate / 1e3:.1f} kB/s"
    else:
        text += "  hours left: n/a (no recording rate measured yet)"
    if reserve is not None:
        text += f" (the recorder stops {reserve / 2**20:g} MiB before full)"
    return text + "\n"


@guard
def cmd_status(args: argparse.Namespace) -> int:
    with remote(args) as r:
        s = r.call("status")
        manager = any(
            n.get("plugin") == "controller_manager" and n["state"] == "running" for n in s["nodes"]
        )
        ctrl: dict[str, Any] | None = None
        if manager:  # a manager starting (or failing to) must not take the whole status away
            try:
                ctrl = r.call("controllers")
            except (messaging.Unreachable, Refused) as exc:
                ctrl = {"error": f"controller manager: {exc}"}
        off = clock.offset(r) if "clock" in s else None  # (an older supervisor has none)
    if args.json:
        if off is not None:  # the board's clock minus this laptop's
            s["clock"].update(offset_ms=off.offset_s * 1e3, offset_error_ms=off.error_s * 1e3)
        _print_json(s if ctrl is None else {**s, "controllers": ctrl})
        return 0
    wd, bus, trig = s["watchdog"], s["bus"], s["trigger"]
    why = (
        f" ({wd['reason']}{': ' + wd['detail'] if wd['detail'] else ''})"
        if wd["state"] != "armed"
        else ""
    )
    sys.stdout.write(
        f"device   {s['device']}\nwatchdog {wd['state'].upper()}{why}  trips={wd['trips']}"
        f"  read lag max {wd.get('read_lag_max_ms', '?')} ms"
        f"  malformed {sum(wd.get('malformed', {}).values())}"
        f"  socket drops {'n/a' if wd.get('socket_dropped') is None else wd['socket_dropped']}\n"
        f"bus      {bus['interface']}:{bus['channel']} {bus.get('state', 'n/a')} "
        f"{bus.get('pulse', 'pulse')} silent {bus.get('pulse_silent_s')} s\n"
        f"trigger  {trig['source']} count={trig['count']}\n"
        + (clock.describe(s["clock"], off) if off is not None else "")
        + update_line(s.get("software"))
        + _card_line(s["nodes"])
        + _api_lines(s)
        + _node_table(s["nodes"])
    )
    if ctrl is not None and "error" in ctrl:
        sys.stdout.write(f"controllers  unavailable: {ctrl['error']}\n")
    elif ctrl is not None:
        sys.stdout.write("controllers  " + show(ctrl) + "\n")
    return 0


def update_line(sw: dict[str, Any] | None) -> str:
    return describe(sw)


@guard
def cmd_nodes(args: argparse.Namespace) -> int:
    with remote(args) as r:
        nodes = r.call("nodes")["nodes"]
    sys.stdout.write(json.dumps(nodes, indent=2) + "\n" if args.json else _node_table(nodes))
    return 0


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
        n = r.call("control", body=control_body(args.command, args.node))["node"]
    sys.stdout.write(f"{n['name']}: {n['state']} pid={n.get('pid')}\n")
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
        for line in r.call("logs", body=ask)["lines"]:
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
        names = [n["name"] for n in r.call("status")["nodes"]]
        if args.node not in names:
            return fail(f"no node {args.node} (nodes: {', '.join(names)})", EXIT_REFUSED)
        if args.set:
            reply = r.call("nodes", args.node, "params", body=params_body(args))
            sys.stdout.write(f"{args.node}.{reply['key']} = {json.dumps(reply['value'])}\n")
        else:
            _print_json(r.call("nodes", args.node, "params")["params"])
    return 0


@guard
def cmd_trigger(args: argparse.Namespace) -> int:
    with remote(args) as r:
        reply = r.call("trigger", body=trigger_body(args.action == "fire"))
    sys.stdout.write(json.dumps({k: v for k, v in reply.items() if k != "ok"}) + "\n")
    return 0


def register_management(sub: argparse._SubParsersAction) -> None:
    parent = common()
    p = sub.add_parser("status", parents=[parent], help="watchdog, bus, trigger and every node")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("nodes", parents=[parent], help="node table")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_nodes)
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
