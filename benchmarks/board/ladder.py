"""Each node's own cost on CPU 0 while CPU 0 has room: the ladder (``--ladder``).

The nominal load saturates CPU 0 on the proxy, and a saturated CPU's split says what the
scheduler gave each process, not what each would use. Here the load is built up on the running
appliance instead: a base (the supervisor, the H2 reader, the simulator on CPU 1 and one laptop
subscriber to joint_states), then each other configured node alone on top of it (started,
measured, stopped), disabled ones included (the controller manager, the Foxglove bridge, the
dashboard), and last every enabled node together. Nothing is armed, so no pattern runs: motion
needs every critical node, and the base stops some. A node's row is its own process; what it
adds to the supervisor (routing its samples) shows in the supervisor's column.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import structlog

from benchmarks.board import scenario
from exolink import messaging

log = structlog.get_logger("bench-board")

BASE = ("simulator", "h2_reader")
START_TIMEOUT_S = 180.0  # a node's imports under TCG take seconds; the recorder's took ~60 s
SETTLE_S = 5.0

# The probe over a window of ``seconds`` for the named running nodes: its parsed result.
Probe = Callable[[list[str], float], dict[str, Any]]


def run(
    admin: scenario.Laptop,
    cfg: dict[str, Any],
    probe: Probe,
    seconds: float,
    only: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Steps in order, each ``{"running": [...], "probe": {...}, "joint_states": {...}}``;
    ``only``: step through these nodes (default: every configured one)."""
    names = [n["name"] for n in cfg["nodes"]]
    enabled = scenario.enabled_nodes(cfg)
    steps: dict[str, Any] = {}
    _base_only(admin, names)
    steps["base"] = _step(admin, [*BASE], probe, seconds)
    for n in names:
        if n in BASE or (only and n not in only):
            continue
        if not _control(admin, n, "start") or not _wait_beating(admin, {n}):
            steps[f"+{n}"] = {"error": f"{n} did not start beating in {START_TIMEOUT_S:g} s"}
        else:
            steps[f"+{n}"] = _step(admin, [*BASE, n], probe, seconds)
        _control(admin, n, "stop")
    for n in sorted(enabled - set(BASE)):
        _control(admin, n, "start")
    if _wait_beating(admin, enabled):
        steps["all enabled"] = _step(admin, sorted(enabled), probe, seconds)
    else:
        steps["all enabled"] = {"error": f"not all enabled nodes beating in {START_TIMEOUT_S:g} s"}
    _base_only(admin, names)  # once more: how far the CPU's speed drifted during the run
    steps["base again"] = _step(admin, [*BASE], probe, seconds)
    return steps


def _base_only(admin: scenario.Laptop, names: list[str]) -> None:
    for n in names:
        if n not in BASE:
            _control(admin, n, "stop")


def _control(admin: scenario.Laptop, node: str, action: str) -> bool:
    try:
        reply = admin.call("control", body={"node": node, "action": action}, timeout=30)
    except messaging.Unreachable as exc:
        log.warning("ladder: control failed", node=node, action=action, error=str(exc))
        return False
    ok = bool(reply.get("ok"))
    if not ok:
        log.warning("ladder: control refused", node=node, action=action, reply=reply)
    return ok


def _wait_beating(admin: scenario.Laptop, nodes: set[str]) -> bool:
    status, ok = admin.wait_beating(START_TIMEOUT_S, nodes)
    return ok and status is not None


def _step(
    admin: scenario.Laptop, running: list[str], probe: Probe, seconds: float
) -> dict[str, Any]:
    log.info("ladder step", running=running)
    time.sleep(SETTLE_S)
    admin.joint_states.reset()
    admin.joint_states.counting = True
    t0 = time.monotonic()
    result = probe(running, seconds)
    admin.joint_states.counting = False
    return {
        "running": running,
        "probe": result,
        "joint_states": admin.joint_states.summary(t0, seconds),
    }


def table(steps: dict[str, Any]) -> list[str]:
    """One row per step: the added node's CPU share and PSS, the supervisor's and the H2
    reader's, CPU 0 idle, joint_states on the laptop, and the probe's calibration (CPU ms for a
    fixed Python loop: a higher figure is a slower CPU at that moment)."""
    lines = [
        "ladder (not armed; each node alone on top of the base):",
        f"{'step':22} {'node %cpu':>9} {'node PSS':>9} {'superv.':>8} {'h2_reader':>9} "
        f"{'CPU0 idle':>9} {'js Hz':>7} {'calib ms':>8}",
    ]
    for step, s in steps.items():
        if "error" in s:
            lines.append(f"{step:22} {s['error']}")
            continue
        procs = s.get("probe", {}).get("processes", {})
        node = step[1:] if step.startswith("+") else None
        if step == "all enabled":
            added = [p for k, p in procs.items() if k not in ("supervisor", "simulator")]
            cpu = sum(p.get("cpu_pct", 0) for p in added)
            pss = sum(p.get("pss_mb") or 0 for p in added)
        else:
            p = procs.get(node or "", {})
            cpu, pss = p.get("cpu_pct"), p.get("pss_mb")

        def num(v: Any, unit: str = "") -> str:
            return "n/a" if v is None else f"{v:.1f}{unit}"

        idle = s.get("probe", {}).get("idle_pct", {}).get("cpu0")
        lines.append(
            f"{step:22} {num(cpu) if node or step == 'all enabled' else '':>9} "
            f"{num(pss, ' MB') if node or step == 'all enabled' else '':>9} "
            f"{num(procs.get('supervisor', {}).get('cpu_pct')):>8} "
            f"{num(procs.get('h2_reader', {}).get('cpu_pct')):>9} {num(idle):>9} "
            f"{num(s.get('joint_states', {}).get('rate_hz')):>7} "
            f"{num(s.get('probe', {}).get('calibration_ms')):>8}"
        )
    return lines
