"""Operator command latency: a joint command from a laptop's session (what `exolink send
position` and the dashboard send) to its frame on the bus, seen by an independent listener.

The request goes laptop -> router -> the controller manager, which checks it once (limits in
force, armed, a holder, the owner) and holds it in the joint's operator controller: the frame
leaves at the manager's next cycle, so the figure is one Zenoh round trip, the checks and up to
one H2 period (10 ms) of waiting. Set-points alternate by 2 deg, inside one step, so the first
frame after the request carries it. Trials are paced under a login's rate limit (an operator's
commands come far slower): a request refused for it would be asked again after 100 ms by the
harness and measure the limit, not the path (stop 51's harness made p99 ~100 ms so).
"""

from __future__ import annotations

import random
import time
from typing import Any

from benchmarks.harness import Appliance, DrainedBus, motion_nodes, pct
from exolink.control import requests
from exolink.messaging import rpc
from exolink.protocol import h2

# Under rpc.RATE_PER_S with the holder's presence renewals (up to 4 a second) on the same login.
PACE_S = 2.0 / rpc.RATE_PER_S


def run(quick: bool) -> dict[str, Any]:
    n = 50 if quick else 300
    app = Appliance.sim(nodes=motion_nodes())
    bus = DrainedBus(app.group)
    request_ms, frame_ms = [], []
    refused = 0
    phase = random.Random(53)
    try:
        app.arm_and_hold()
        for i in range(n):
            sp = 30 + 2 * (i % 2)
            bus.clear()
            t0 = time.time()
            body = requests.body(requests.Joint("r_knee", "position", sp))
            reply = app.call("h2/command", body)
            t1 = time.time()
            if not reply.get("ok"):
                refused += 1
                continue
            m = bus.wait_for(lambda m, sp=sp: _is(m, sp), 1.0)
            if i == 0 or m is None:  # the first one makes and activates the joint's controller
                continue
            request_ms.append(t1 - t0)
            frame_ms.append(m.timestamp - t0)
            time.sleep(PACE_S + phase.uniform(0, h2.PERIOD_S))  # at any phase of the cycle
    finally:
        bus.close()
        app.close()
    return {
        "trials": len(frame_ms),
        "hops": "laptop -> router -> controller_manager (one)",
        "refused": refused,
        "pace_s": PACE_S,
        "request_round_trip_ms": pct(request_ms, 1e3),
        "to_frame_on_bus_ms": pct(frame_ms, 1e3),
    }


def _is(m: Any, sp: int) -> bool:
    f = h2.decode(m)
    return isinstance(f, h2.JointControl) and f.motor == 2 and f.mode == 1 and f.setpoint == sp
