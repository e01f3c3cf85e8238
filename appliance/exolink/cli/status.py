"""Laptop-side ``status`` and ``nodes``: the supervisor's status as an operator reads it."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from exolink import messaging
from exolink.cli import clock
from exolink.cli.controllers import show
from exolink.cli.options import common, guard, print_json
from exolink.cli.update import describe
from exolink.client import Refused, remote
from exolink.control.replies import ManagerStatus
from exolink.wire.replies import UNSET, NodeInfo, Nodes, Status, read


def _receive(rx: dict[str, Any] | None) -> str:
    """A bus reader's receive losses and backlog, after its health."""
    if not rx:
        return ""
    dropped = "n/a" if rx.get("dropped") is None else rx["dropped"]
    return (
        f"  rx dropped {dropped} late {rx.get('late')} lag max {rx.get('lag_max_ms')} ms"
        f" batch max {rx.get('batch_max')}"
    )


def node_health(n: NodeInfo) -> str:
    """What the health column says for a node: never blank."""
    if not n.enabled:
        return "disabled"
    state = n.state or "unknown"
    if state == "running":
        if n.heartbeat_age_s is None:
            return "starting"  # spawned, no heartbeat yet
        return n.health or "ok"  # its own diagnostics, if it publishes any
    return {"backoff": "restarting"}.get(state, state)


def _starved(n: NodeInfo) -> str:
    """Silences past its deadline while it waited for the CPU: the core is full, not the node
    hung (exolink.supervisor.starving)."""
    return f" (starved {n.starved}x)" if n.starved else ""


def _or(value: Any, absent: str = "-") -> Any:
    return absent if value is UNSET else value


# (title, right-aligned, cell); the last column is not padded.
_COLUMNS: list[tuple[str, bool, Any]] = [
    ("node", False, lambda n: n.name + ("*" if n.critical else "")),
    ("state", False, lambda n: n.state if n.enabled else "disabled"),
    ("pid", True, lambda n: n.pid or "-"),
    ("uptime", True, lambda n: n.uptime_s),
    ("restarts", True, lambda n: n.restarts),
    ("cpu_s", True, lambda n: _or(n.cpu_s)),
    ("rss_mb", True, lambda n: _or(n.rss_mb)),
    ("last exit", False, lambda n: n.last_exit or "-"),
    ("health", False, lambda n: node_health(n) + _starved(n) + _receive(_or(n.receive, ""))),
]


def _node_table(nodes: list[NodeInfo]) -> str:
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


def _api_lines(s: Status) -> str:
    """What the management API did with requests: the supervisor's counts, then each node's
    refusals (too large, over its login's rate, queue full, ...), and unreadable samples."""
    api = s.api
    if not api:  # an older supervisor
        return ""
    refused = {k: v for k, v in api.items() if not k.startswith(("handled", "urgent")) and v}
    text = f"api      handled {api.get('handled', 0)}  urgent {api.get('urgent', 0)}"
    if api.get("urgent_unlogged"):
        text += f" ({api['urgent_unlogged']} not in the command log)"
    text += "  refused " + (", ".join(f"{k} {v}" for k, v in refused.items()) or "0") + "\n"
    for n in s.nodes:
        if n.api_refused:
            counts = ", ".join(f"{k} {v}" for k, v in n.api_refused.items())
            text += f"         {n.name} refused {counts}\n"
    if bad := s.bad_samples:
        text += f"samples  unreadable {sum(bad.values())} ({len(bad)} kinds)\n"
    return text


def _bytes(n: float) -> str:
    """A size as people read a card's: GiB from 1 GiB up, else MiB."""
    return f"{n / 2**30:.2f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def _card_line(nodes: list[NodeInfo]) -> str:
    """The recordings card, as the recorder last reported it: free space and the hours of
    recording that leaves at the current rate (above the reserve the recorder keeps)."""
    card = next((n.card for n in nodes if isinstance(n.card, dict)), None)
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
        raw = r.call("status")  # printed whole with --json: a newer board's fields too
        s = read(raw, Status)
        manager = any(n.plugin == "controller_manager" and n.state == "running" for n in s.nodes)
        ctrl: dict[str, Any] | None = None
        if manager:  # a manager starting (or failing to) must not take the whole status away
            try:
                ctrl = r.call("controllers")
            except (messaging.Unreachable, Refused) as exc:
                ctrl = {"error": f"controller manager: {exc}"}
        off = clock.offset(r) if "clock" in raw else None  # (an older supervisor has none)
    if args.json:
        if off is not None:  # the board's clock minus this laptop's
            raw["clock"].update(offset_ms=off.offset_s * 1e3, offset_error_ms=off.error_s * 1e3)
        print_json(raw if ctrl is None else {**raw, "controllers": ctrl})
        return 0
    wd, bus, trig = s.watchdog, s.bus, s.trigger
    why = f" ({wd.reason}{': ' + wd.detail if wd.detail else ''})" if wd.state != "armed" else ""
    sys.stdout.write(
        f"device   {s.device}\nwatchdog {wd.state.upper()}{why}  trips={wd.trips}"
        f"  read lag max {wd.read_lag_max_ms} ms"
        f"  malformed {sum(wd.malformed.values())}"
        f"  socket drops {'n/a' if wd.socket_dropped is None else wd.socket_dropped}\n"
        f"bus      {bus.interface}:{bus.channel} {bus.state} "
        f"{bus.pulse} silent {bus.pulse_silent_s} s\n"
        f"trigger  {_or(trig.source, '')} count={trig.count}\n"
        + (clock.describe(s.clock, off) if off is not None and s.clock is not None else "")
        + describe(s.software)
        + _card_line(s.nodes)
        + _api_lines(s)
        + _node_table(s.nodes)
    )
    if ctrl is not None and "error" in ctrl:
        sys.stdout.write(f"controllers  unavailable: {ctrl['error']}\n")
    elif ctrl is not None:
        sys.stdout.write("controllers  " + show(read(ctrl, ManagerStatus)) + "\n")
    return 0


@guard
def cmd_nodes(args: argparse.Namespace) -> int:
    with remote(args) as r:
        raw = r.call("nodes")  # printed whole with --json, as ``status`` does
    if args.json:
        print_json(raw["nodes"])
    else:
        sys.stdout.write(_node_table(read(raw, Nodes).nodes))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    parent = common()
    p = sub.add_parser("status", parents=[parent], help="watchdog, bus, trigger and every node")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("nodes", parents=[parent], help="node table")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_nodes)
