"""Simulator across processes: period error of id 110 as a udp_multicast listener sees it, and the
simulator's CPU (H2 and one MACCEPA board) while it takes the pattern's commands (four joint
controls and a board set-point every 10 ms). On udp_multicast Python sends every frame and spins
before each deadline; on SocketCAN (the board proxy) the kernel sends them and Python does not
spin, so this CPU is an upper bound of what the proxy's CPU 1 carries per cycle."""

from __future__ import annotations

import subprocess
import time
from typing import Any

import numpy as np

from benchmarks.harness import EXOLINK, DrainedBus, cpu_s, group, pct
from exolink.protocol import h2, maccepa


def run(quick: bool) -> dict[str, Any]:
    seconds = 5 if quick else 20
    g = group()
    proc = subprocess.Popen(
        [*EXOLINK, "sim", "-i", "udp_multicast", "--channel", g, "--maccepa", "0"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    bus = DrainedBus(g)
    try:
        time.sleep(1.5)
        bus.send(h2.encode_stream(True))
        bus.wait_for(lambda m: m.arbitration_id == 110, 5)
        commands = [h2.encode_joint_control(j, "position", 20) for j in (1, 2, 4, 5)]
        commands.append(maccepa.encode_setpoint(0, 10.0, "position"))
        stamps = []
        c0, t0 = cpu_s(proc.pid), time.monotonic()
        end = t0 + seconds
        while time.monotonic() < end:
            m = bus.wait_for(lambda m: m.arbitration_id == 110, 1)
            if m is not None:
                stamps.append(m.timestamp)
                for c in commands:  # the pattern's load, once per H2 cycle
                    bus.send(c)
        cpu = cpu_s(proc.pid) - c0
        wall = time.monotonic() - t0
    finally:
        bus.close()
        proc.terminate()
        proc.wait(5)
    err = np.abs(np.diff(stamps) - h2.PERIOD_S)
    return {
        "seconds": seconds,
        "periods": len(stamps) - 1,
        "period_error_ms": pct(err, 1e3),
        "cpu_pct_with_commands": round(100 * cpu / wall, 2),
        "cpu_us_per_cycle": round(cpu / max(1, len(stamps)) * 1e6, 1),
    }
