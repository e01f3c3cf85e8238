"""A flood of the simulated bus, read by FrameReaders in processes of their own, one of them
stopped for the whole flood: for every reader, frames of its ids sent = received + dropped
(its socket's kernel count), and the stopped one really lost frames. `make bench` runs the same
at full size (benchmarks/bench_flood.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import can

from exolink.canbus import open_bus
from exolink.config import CanConfig

READER = r"""
import json, signal, sys
from exolink.canbus import open_reader
from exolink.config import CanConfig
ids = [int(i) for i in sys.argv[2].split(",")]
r = open_reader(CanConfig(interface="udp_multicast", channel=sys.argv[1]), ids,
                rcvbuf=int(sys.argv[3]))
stop = []
signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
print("ready", flush=True)
received = 0
while not stop:
    received += len(r.read(0.05))
while frames := r.read(0):
    received += len(frames)
print(json.dumps({"received": received, "dropped": r.dropped}), flush=True)
"""


def test_flood_every_frame_received_or_counted(group: str) -> None:
    readers = {  # name: (ids, receive queue asked for, stopped during the flood)
        "stalled": ("110,120,130", 1 << 16, True),
        "running": ("110,120,130", 1 << 16, False),
        "angles": ("110", 1 << 20, False),
    }
    procs = {
        name: subprocess.Popen(
            [sys.executable, "-c", READER, group, ids, str(rcvbuf)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for name, (ids, rcvbuf, _) in readers.items()
    }
    tx = open_bus(CanConfig(interface="udp_multicast", channel=group))
    ids = [110, 120, 130, 70]  # 70 is none of the readers' ids
    frames = [
        can.Message(arbitration_id=ids[i % 4], data=bytes(8), is_extended_id=False)
        for i in range(4000)
    ]
    reports = {}
    try:
        for p in procs.values():
            assert p.stdout is not None and p.stdout.readline().strip() == "ready"
        os.kill(procs["stalled"].pid, signal.SIGSTOP)
        for f in frames:
            tx.send(f)
        os.kill(procs["stalled"].pid, signal.SIGCONT)
        for name, p in procs.items():
            p.send_signal(signal.SIGTERM)
            out, _ = p.communicate(timeout=30)
            reports[name] = json.loads(out.strip().splitlines()[-1])
    finally:
        tx.shutdown()
        for p in procs.values():
            p.kill()
    for name, (rids, _, _) in readers.items():
        sent = sum(1 for f in frames if str(f.arbitration_id) in rids.split(","))
        r = reports[name]
        assert sent == r["received"] + r["dropped"], (name, sent, r)
    assert reports["stalled"]["dropped"] > 0  # 3000 frames into a queue that holds ~150
