"""What the set-points on the bus carried, from the probe's frames (``probe.FrameTap``): each
motor's steps between consecutive position set-points and its range, against the limits.

Why: the bench counted the gait's frames and timed them, and a renewal bug that sent slots
a ring old (the gait jumping back 180 ms) lived for several stops because nothing read what
the frames said. Decoded here, on the host, by the one H2 decoder (exolink.protocol.h2).
"""

from __future__ import annotations

from typing import Any

import can

from exolink.canbus.frames import CAN_FRAME
from exolink.limits.joints import POSITION
from exolink.protocol import h2

CYCLE_MS = round(h2.PERIOD_S * 1000)  # the limits' step is per H2 cycle


def steps(raw: bytes, limits: dict[str, Any] | None = None, slot_ms: int = 20) -> dict[str, Any]:
    """Per motor (1..6): position set-points, the largest step between two in a row, and the
    lowest and highest; with ``limits`` (the config's ``limits``) the steps over the step
    limit for a slot of ``slot_ms`` and the set-points outside the joint's range, counted."""
    last: dict[int, int] = {}
    per: dict[int, dict[str, Any]] = {}
    other = 0
    limit = int(limits.get("max_step_deg", 5)) * slot_ms // CYCLE_MS if limits else None
    for cid, dlc, data in CAN_FRAME.iter_unpack(raw[: len(raw) - len(raw) % CAN_FRAME.size]):
        msg = can.Message(arbitration_id=cid & 0x7FF, data=data[:dlc], is_extended_id=False)
        d = h2.decode(msg)
        if not isinstance(d, h2.JointControl) or d.mode != POSITION:
            other += 1  # MACCEPA board 0's status shares the id; other modes step from nothing
            continue
        m = per.setdefault(
            d.motor, {"n": 0, "max_step": 0, "over": 0, "min": d.setpoint, "max": d.setpoint}
        )
        m["n"] += 1
        if d.motor in last:
            step = abs(d.setpoint - last[d.motor])
            m["max_step"] = max(m["max_step"], step)
            m["over"] += limit is not None and step > limit
        m["min"], m["max"] = min(m["min"], d.setpoint), max(m["max"], d.setpoint)
        last[d.motor] = d.setpoint
    out: dict[str, Any] = {"frames": len(raw) // CAN_FRAME.size, "not_position": other}
    out["motors"] = {str(k): per[k] for k in sorted(per)}
    if limits is not None:
        out["step_limit_deg"] = limit
        out["over_step_limit"] = sum(m["over"] for m in per.values())  # steps, all motors
        joints = limits.get("joints", {})
        out["out_of_range"] = [
            k
            for k, m in per.items()
            if 1 <= k <= len(h2.JOINTS)
            and (j := joints.get(h2.JOINTS[k - 1]))
            and not j["min"] <= m["min"] <= m["max"] <= j["max"]
        ]
    return out
