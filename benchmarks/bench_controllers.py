"""Controller manager: H2 angle frame (id 110) on the bus -> the command frame (id 70) it causes,
with 1 and 3 forward-command controllers active, and the manager's own work per cycle without
the controllers' (``overhead_us``, measured inside the node: read -> frames sent, minus update).

Goal (issue 20): p99 < 1 ms on x86 on the sim bus. Both frames are stamped by the listener's
kernel on the same socket, so the figure is bus to bus, including the udp_multicast path.

``controllers_1_maccepa``: the 1-controller case plus a ``maccepa_setpoint`` controller holding a
simulated MACCEPA board (its status frames read and decoded every 10 ms; the held set-point
re-sent every ``MACCEPA_REFRESH_CYCLES`` cycles): its ``overhead_us`` against ``controllers_1`` is
the MACCEPA interface's cost per cycle inside ``cycle`` and the writes (the status frames' decoding
is outside that figure), ``board_frame_to_setpoint_ms`` the angle frame -> MACCEPA set-point frame
latency of the cycles that write one.

``controllers_1_every_2_cycles``: the 1-controller case at the board's ``cycles_per_update: 2``.

``cpu_us_per_cycle`` / ``cpu_pct``: the manager process's CPU over the window (its reads, decoding,
Zenoh and the loop), per H2 cycle and as % of one core; ``controllers_0_idle`` is the manager
with controllers loaded and none active (off the bus since issue 18's ladder showed it costing
>= 47 % of the proxy's CPU 0 that way).
"""

from __future__ import annotations

import time
from typing import Any

from benchmarks.harness import Appliance, DrainedBus, cpu_s, pct
from exolink.protocol import h2, maccepa

JOINTS3 = ["r_knee", "l_knee", "r_hip"]


def measure(
    n_controllers: int, seconds: float, board: bool = False, cycles_per_update: int = 1
) -> dict[str, Any]:
    """``n_controllers`` 0: one loaded, none activated (the idle manager); ``cycles_per_update``
    2: the board config's manager (an update per two H2 cycles; half the cycles get no command
    by design)."""
    controllers = [
        {"name": f"c{i}", "type": "forward_command", "params": {"joints": [j]}}
        for i, j in enumerate(JOINTS3[: max(n_controllers, 1)])
    ]
    manager: dict[str, Any] = {"controllers": controllers, "cycles_per_update": cycles_per_update}
    if board:
        controllers.append(
            {"name": "m0", "type": "maccepa_setpoint", "params": {"board": 0, "gains": {"kp": 2}}}
        )
        manager["maccepa"] = [{"board": 0}]
    nodes = [
        {
            "name": "simulator",
            "plugin": "simulator",
            "params": {"maccepa_boards": [0] if board else []},
        },
        {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
        {
            "name": "controller_manager",
            "plugin": "controller_manager",
            "critical": True,
            "heartbeat_deadline_ms": 50,
            "priority": {"fifo": 50},
            "params": manager,
        },
    ]
    app = Appliance.sim(nodes=nodes, watchdog={"maccepa_boards": [0]})
    bus = DrainedBus(app.group)
    try:
        app.arm_and_hold()
        names = [c["name"] for c in controllers] if n_controllers else []
        if names:
            reply = app.call("controllers", {"action": "activate", "names": names})
            if not reply.get("ok"):
                raise RuntimeError(f"activate: {reply}")
        if board:
            body = {"action": "command", "name": "m0", "values": {"maccepa0": 20}}
            app.call("controllers", body)
        time.sleep(0.3)
        pid = app.node("controller_manager")["pid"]
        bus.clear()
        c0, t0 = cpu_s(pid), time.monotonic()
        frames = bus.collect(seconds)
        cpu, wall = cpu_s(pid) - c0, time.monotonic() - t0
        status = app.call("controllers", {"action": "list"})
    finally:
        bus.close()
        app.close()
    # first command frame after each angle frame, before the next angle frame
    latency, pending = [], None
    board_latency, board_pending = [], None
    for m in frames:
        if m.arbitration_id == h2.JOINT_ANGLES:
            pending = board_pending = m.timestamp
        elif m.arbitration_id == h2.JOINT_CONTROL and pending is not None and len(m.data) == 6:
            latency.append(m.timestamp - pending)
            pending = None
        elif m.arbitration_id == maccepa.SETPOINT_BASE and board_pending is not None:
            board_latency.append(m.timestamp - board_pending)
            board_pending = None
    cycles = sum(1 for m in frames if m.arbitration_id == h2.JOINT_ANGLES)
    extra = {}
    if board:
        extra = {
            "board_frame_to_setpoint_ms": pct(board_latency, 1e3),
            "setpoint_frames": len(board_latency),
            "maccepa_written": status.get("maccepa_written"),
            "malformed": status.get("malformed"),
        }
    cpu_figures = {
        "cpu_us_per_cycle": round(cpu / max(cycles, 1) * 1e6, 1),
        "cpu_pct": round(cpu / wall * 100, 2),
    }
    if not n_controllers:
        return {**cpu_figures, "reading": status.get("reading"), "cycles": cycles}
    return {
        **extra,
        **cpu_figures,
        "frame_to_command_ms": pct(latency, 1e3),
        "cycles_without_command": cycles - len(latency),
        "overhead_us": status["overhead_us"],
        "update_ms_max": max(c["update_ms_max"] for c in status["controllers"]),
        "still_active": sum(c["state"] == "active" for c in status["controllers"]),
        "stopped_because": sorted({c["error"] for c in status["controllers"] if c["error"]}),
    }


def run(quick: bool) -> dict[str, Any]:
    seconds = 3.0 if quick else 15.0
    out = {"controllers_0_idle": measure(0, seconds)}
    out.update({f"controllers_{n}": measure(n, seconds) for n in (1, 3)})
    out["controllers_1_maccepa"] = measure(1, seconds, board=True)
    out["controllers_1_every_2_cycles"] = measure(1, seconds, cycles_per_update=2)
    return out
