"""Laptop-side data commands: ``topics``, ``echo``, ``hz`` (Zenoh subscriptions, never a hang)."""

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
from exolink.cli.errors import EXIT_UNREACHABLE, fail
from exolink.cli.options import common, decimal, guard, integer
from exolink.cli.units import degrees, unit
from exolink.client import remote


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
        # Closed on every way out, the reader gone (stdout's EPIPE interrupts this thread) and
        # Ctrl-C included: a subscriber left to the interpreter's exit is dropped while its
        # callbacks may run (test_management_commands once waited 10 s for an `echo | head -1`).
        try:
            start = time.monotonic()
            while not done.wait(0.1):
                if count[0] == 0 and time.monotonic() - start > args.timeout:
                    return fail(
                        f"no messages on {args.topic} within {args.timeout:g} s "
                        f"(appliance at {args.at}; see `exolink topics`)",
                        EXIT_UNREACHABLE,
                    )
        finally:
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
