"""CPU per frame of the H2 codec against a cantools decode of the same DBC."""

from __future__ import annotations

import time
from typing import Any

import can
import cantools
from exolink.protocol import dbc, h2


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
    }
