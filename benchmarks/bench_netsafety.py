"""E-stop latency whatever the network does: e-stop -> first disable frame on the bus, idle and
beside three kinds of hostile client (benchmarks/estop.py: a 100 KB query in flight, three
clients that stop reading, a query flood), on a simulated appliance with the shipped sim
config; and the supervisor's resident memory across it (floods must leave it bounded)."""

from __future__ import annotations

import argparse
import time
from typing import Any

from benchmarks import estop
from benchmarks.harness import Appliance
from exolink import messaging, roles

TRIM_WAIT_S = 12.0


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024, 1)
    return 0.0


def run(quick: bool) -> dict[str, Any]:
    trials = 5 if quick else 30
    app = Appliance.sim()  # the shipped sim config: every node, zenoh.threads 1
    out: dict[str, Any] = {"trials": trials, "goal_p99_ms": 100}
    try:
        assert app.proc is not None
        time.sleep(1)
        out["supervisor_rss_mb_start"] = _rss_mb(app.proc.pid)
        for case in estop.CASES:
            args = argparse.Namespace(
                at=app.at,
                device="sim",
                zenoh_config=None,
                hostile_at=None,
                hostile_config=None,
                bus=f"udp_multicast:{app.group}",
                case=case,
                trials=trials,
            )
            t = time.monotonic()
            out[case] = estop.measure(args)
            out[case]["wall_s"] = round(time.monotonic() - t, 1)
            out[case]["supervisor_rss_mb_after"] = _rss_mb(app.proc.pid)
        # as an observer: in the sim config every client is admin, the floods too, and their
        # queued queries are refused for a while after they end (the login's rate)
        time.sleep(TRIM_WAIT_S)  # the supervisor's MemoryTrim looks every 10 s
        status = messaging.request(app.session, "exolink/sim/status", {}, 5, roles.OBSERVER)
        out["supervisor_rss_mb_end"] = _rss_mb(app.proc.pid)
        out["watchdog_state"] = status.get("watchdog", {}).get("state")
        out["api"] = status.get("api")  # what the supervisor handled and refused
        out["memory"] = status.get("memory")
    finally:
        app.close()
    return out
