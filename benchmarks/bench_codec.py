"""CPU per frame of the H2 codec against a cantools decode of the same DBC, and what preparing
the ROS 2 types costs a node cold."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import Any

import can
import cantools

from exolink.protocol import dbc, h2

COLD_PREPARE = """
import json, time
t = time.perf_counter()
from exolink import messaging
messaging.typestore()
out = {"typestore_build_ms": (time.perf_counter() - t) * 1e3}
for name in ("sensor_msgs/msg/JointState", "diagnostic_msgs/msg/DiagnosticArray",
             "exolink_msgs/msg/Heartbeat"):
    t = time.perf_counter()
    messaging.prepare(name)
    out[name.split("/")[-1]] = (time.perf_counter() - t) * 1e3
print(json.dumps(out))
"""


def cold_prepare_ms() -> dict[str, float]:
    """What a node pays in configure (messaging.prepare) so its loop never does: rosbags builds
    the store and generates each type's CDR code on first use. A fresh interpreter: cold."""
    r = subprocess.run([sys.executable, "-c", COLD_PREPARE], capture_output=True, text=True)
    r.check_returncode()
    return {k: round(v, 1) for k, v in json.loads(r.stdout).items()}


def run(quick: bool) -> dict[str, Any]:
    n = 20_000 if quick else 200_000
    msg = can.Message(arbitration_id=110, data=bytes.fromhex("4C5E004C5D0B"), is_extended_id=False)
    t = time.perf_counter()
    for _ in range(n):
        h2.decode(msg)
    ours = (time.perf_counter() - t) / n
    db = cantools.database.load_file(str(dbc.bundled("h2")))
    data = bytes(msg.data)
    m = n // 10
    t = time.perf_counter()
    for _ in range(m):
        db.decode_message(110, data)
    theirs = (time.perf_counter() - t) / m
    t = time.perf_counter()
    for _ in range(n):
        h2.encode_joint_control(2, 1, 30)
    enc = (time.perf_counter() - t) / n
    return {
        "h2_decode_us": round(ours * 1e6, 3),
        "cantools_decode_us": round(theirs * 1e6, 3),
        "speedup_vs_cantools": round(theirs / ours, 1),
        "joint_control_encode_us": round(enc * 1e6, 3),
        "cold_type_prepare_ms": cold_prepare_ms(),
    }
