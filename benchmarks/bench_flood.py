"""The sim bus flooded at the highest rate one sender reaches, read by h2_reader-style
FrameReaders in processes of their own: per reader, frames of its ids sent, received, and the
drops its socket counted (sent == received + dropped must hold, exactly); then a 100 ms reader
stall at that rate (the receive queue is sized for it: ``canbus.RCVBUF_BYTES``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from typing import Any

import can

from benchmarks.harness import group
from exolink.canbus import open_bus
from exolink.config import CanConfig
from exolink.protocol import h2

# A reader as h2_reader runs it: batches from a FrameReader, each frame decoded. On SIGTERM it
# reads what is still queued, then reports.
READER = r"""
import json, signal, sys
from exolink.canbus import open_reader
from exolink.config import CanConfig
from exolink.protocol import h2
ids = None if sys.argv[2] == "all" else [int(i) for i in sys.argv[2].split(",")]
r = open_reader(CanConfig(interface="udp_multicast", channel=sys.argv[1]), ids)
stop = []
signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
print("ready", flush=True)
received = 0
while not stop:
    for f in r.read(0.05):
        h2.decode(f)
        received += 1
while frames := r.read(0):
    received += len(frames)
print(json.dumps({"received": received, **r.counters()}), flush=True)
"""

# 110/120/130 are the h2 reader's ids, 70 is not: frames of other ids on the bus are neither
# received nor counted by a filtered reader.
FLOOD_IDS = [h2.JOINT_ANGLES, h2.JOINT_TORQUES, h2.FOOT_SWITCHES, h2.JOINT_CONTROL]
READERS = {"h2_reader_a": "110,120,130", "h2_reader_b": "110,120,130", "angles_only": "110"}


def _frames(n: int) -> list[can.Message]:
    return [
        can.Message(
            arbitration_id=FLOOD_IDS[i % len(FLOOD_IDS)], data=bytes(8), is_extended_id=False
        )
        for i in range(n)
    ]


def _start_readers(g: str) -> dict[str, subprocess.Popen[str]]:
    procs = {
        name: subprocess.Popen(
            [sys.executable, "-c", READER, g, ids], stdout=subprocess.PIPE, text=True
        )
        for name, ids in READERS.items()
    }
    for p in procs.values():
        assert p.stdout is not None and p.stdout.readline().strip() == "ready"
    return procs


def _reports(procs: dict[str, subprocess.Popen[str]]) -> dict[str, dict[str, Any]]:
    out = {}
    for name, p in procs.items():
        p.send_signal(signal.SIGTERM)
        stdout, _ = p.communicate(timeout=30)
        out[name] = json.loads(stdout.strip().splitlines()[-1])
    return out


def _sent_to(ids: str, frames: list[can.Message]) -> int:
    wanted = {int(i) for i in ids.split(",")}
    return sum(1 for f in frames if f.arbitration_id in wanted)


def flood(n: int) -> dict[str, Any]:
    """``n`` frames as fast as one sender goes, readers reading as they can."""
    g = group()
    procs = _start_readers(g)
    tx = open_bus(CanConfig(interface="udp_multicast", channel=g))
    frames = _frames(n)
    try:
        t0 = time.perf_counter()
        for f in frames:
            tx.send(f)
        dt = time.perf_counter() - t0
        time.sleep(0.5)
        reports = _reports(procs)
    finally:
        tx.shutdown()
        for p in procs.values():
            p.kill()
    readers = {}
    for name, r in reports.items():
        sent = _sent_to(READERS[name], frames)
        readers[name] = {
            "ids": READERS[name],
            "sent": sent,
            "received": r["received"],
            "dropped": r["dropped"],
            "sent_eq_received_plus_dropped": sent == r["received"] + r["dropped"],
            "lost_percent": round(100 * r["dropped"] / sent, 1),
            "lag_max_ms": r["lag_max_ms"],
            "batch_max": r["batch_max"],
            "rcvbuf_bytes": r["rcvbuf"],
        }
    return {
        "frames_sent": n,
        "send_rate_frames_per_s": round(n / dt),
        "readers": readers,
        "all_exact": all(r["sent_eq_received_plus_dropped"] for r in readers.values()),
    }


def stall(frames: int) -> dict[str, Any]:
    """Readers stopped (SIGSTOP) while ``frames`` go out as fast as one sender goes: at the
    flood rate, 100 ms of it is what a 100 ms stall of a reader puts in its receive queue."""
    g = group()
    procs = _start_readers(g)
    tx = open_bus(CanConfig(interface="udp_multicast", channel=g))
    sent = _frames(frames)
    try:
        for p in procs.values():
            os.kill(p.pid, signal.SIGSTOP)
        t0 = time.perf_counter()
        for f in sent:
            tx.send(f)
        dt = time.perf_counter() - t0
        for p in procs.values():
            os.kill(p.pid, signal.SIGCONT)
        time.sleep(0.5)
        reports = _reports(procs)
    finally:
        tx.shutdown()
        for p in procs.values():
            p.kill()
    return {
        "frames_sent_while_stopped": frames,
        "send_ms": round(dt * 1e3, 1),
        "dropped": {name: r["dropped"] for name, r in reports.items()},
        "exact": all(
            _sent_to(READERS[name], sent) == r["received"] + r["dropped"]
            for name, r in reports.items()
        ),
    }


def run(quick: bool) -> dict[str, Any]:
    result = flood(5_000 if quick else 20_000)
    return {
        "flood": result,
        "stall_100ms_at_flood_rate": stall(round(result["send_rate_frames_per_s"] * 0.1)),
        "note": "per reader: frames of its ids only; 70 is on the bus for none of them",
    }
