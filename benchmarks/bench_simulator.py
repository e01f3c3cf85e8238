"""Simulator timing across processes: period error of id 110 as a udp_multicast listener sees it."""

from __future__ import annotations

import subprocess
import time
from typing import Any

import numpy as np
from exolink.protocol import h2

from benchmarks.harness import EXOLINK, Drained, group, pct


def run(quick: bool) -> dict[str, Any]:
    seconds = 5 if quick else 20
    g = group()
    proc = subprocess.Popen(
        [*EXOLINK, "sim", "-i", "udp_multicast", "--channel", g],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    bus = Drained(g)
    try:
        time.sleep(1.5)
        bus.bus.send(h2.encode_stream(True))
        bus.wait_for(lambda m: m.arbitration_id == 110, 5)
        stamps = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            m = bus.wait_for(lambda m: m.arbitration_id == 110, 1)
            if m is not None:
                stamps.append(m.timestamp)
    finally:
        bus.close()
        proc.terminate()
        proc.wait(5)
    err = np.abs(np.diff(stamps) - h2.PERIOD_S)
    return {"seconds": seconds, "periods": len(stamps) - 1, "period_error_ms": pct(err, 1e3)}
