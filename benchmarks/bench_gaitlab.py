"""Gait-lab export (exolink.gaitlab): time and file sizes of a C3D + OpenSim + events export of
a synthetic walking recording written by the recorder's own writer (McapFile, zstd): H2 joint
states at 100 Hz, foot switches on change (1 s refresh), one MACCEPA board at 100 Hz, trigger
edges, labels and stats metadata. ``synthetic`` is also what tests/test_gaitlab.py uses for its
files with known gaps."""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from exolink.nodes.recorder import McapFile, RecorderParams

from exolink import messaging
from exolink.protocol import h2
from exolink.wire import cdr

T0 = 1_700_000_000_000_000_000
GAIT_S = 1.2  # one stride
JS = "sensor_msgs/msg/JointState"
FS = "exolink_msgs/msg/FootSwitches"
MS = "exolink_msgs/msg/MaccepaState"
TRIGGER = "exolink_msgs/msg/TriggerEvent"


def feet_at(t_s: float) -> tuple[bool, bool, bool, bool]:
    """Right heel/toe, left heel/toe of the synthetic gait: stance 60 % of the stride (heel
    0-45 %, toe 10-60 %), the left half a stride behind."""
    out: list[bool] = []
    for shift in (0.0, 0.5):
        phase = (t_s / GAIT_S + shift) % 1.0
        out += [phase < 0.45, 0.10 <= phase < 0.60]
    return out[0], out[1], out[2], out[3]


def angles_at(t_s: float) -> list[float]:
    """Whole degrees, as the H2 sends them: hip, knee, ankle per side."""
    out = []
    for shift in (0.0, 0.5):
        w = 2 * math.pi * (t_s / GAIT_S + shift)
        out += [
            round(15 + 25 * math.cos(w)),
            round(30 - 28 * math.cos(w + 1.2)),
            round(8 * math.sin(w)),
        ]
    return out


def synthetic(
    path: Path,
    seconds: float,
    gaps: Sequence[tuple[float, float]] = (),
    stale_every: int = 0,
    triggers: Sequence[float] = (1.0, 1.1),
    labels: dict[str, str] | None = None,
    dropped: int = 0,
) -> dict[str, int]:
    """A walking recording of ``seconds`` at ``path``: nothing H2 (joints, feet) inside the
    ``gaps`` ((start s, length s)); every ``stale_every``-th MACCEPA cycle marks its sensors
    frame stale. Returns the messages written per kind."""
    f = McapFile(
        path,
        RecorderParams(compression="zstd"),  # type: ignore[call-arg]
        {
            "exolink.labels": labels or {"subject": "S01", "session": "walk1"},
            "exolink": {"device": "sim"},
        },
    )
    js_c, fs_c = cdr.JointStateCdr(h2.JOINTS), cdr.FootSwitchesCdr()
    mc_c = cdr.MaccepaStateCdr()
    cid = {
        "js": f.channel("h2/joint_states", JS),
        "fs": f.channel("h2/foot_switches", FS),
        "mc": f.channel("h2/maccepa/b0/state", MS),
        "tr": f.channel("h2/trigger", TRIGGER),
    }
    trig_cls = messaging.msg_class(TRIGGER)
    counts = dict.fromkeys(cid, 0)
    last_feet: tuple[tuple[bool, ...], float] | None = None
    pending = sorted(triggers)
    n = round(seconds / h2.PERIOD_S)
    for i in range(n):
        t_s = i * h2.PERIOD_S
        ns = T0 + i * 10_000_000 + (i * 7919 % 200_000)  # receive-time jitter up to 0.2 ms
        while pending and pending[0] <= t_s:
            at = T0 + round(pending.pop(0) * 1e9)
            edge = "rising" if counts["tr"] % 2 == 0 else "falling"
            msg = trig_cls(
                stamp=messaging.stamp(at),
                edge=edge,
                chip="sim",
                line=0,
                count=counts["tr"] + 1,
                source="simulated",
            )
            f.w.add_message(cid["tr"], at, messaging.serialize(msg, TRIGGER), at, counts["tr"])
            counts["tr"] += 1
        stale = 1 if stale_every and i % stale_every == 0 else 0
        board = [
            round(500 + 300 * math.sin(t_s)),
            35,
            round(60 * math.cos(t_s)),
            round(100 * math.sin(2 * t_s)),
            *angles_at(t_s)[:2],
            0,
            0,
            10,
            20,
            30,
        ]
        f.w.add_message(cid["mc"], ns, mc_c.encode(ns + 1000, 0, stale, board), ns, counts["mc"])
        counts["mc"] += 1
        if any(a <= t_s < a + d for a, d in gaps):
            continue
        a = angles_at(t_s)
        torques = [round(5 * math.sin(2 * math.pi * t_s / GAIT_S + k)) for k in range(6)]
        f.w.add_message(
            cid["js"],
            ns,
            js_c.encode(ns, [x * math.pi / 180 for x in a], [float(x) for x in torques]),
            ns,
            counts["js"],
        )
        counts["js"] += 1
        feet = feet_at(t_s)
        if last_feet is None or last_feet[0] != feet or t_s - last_feet[1] >= 1.0:
            raw = 225 - int(t_s // 60)
            f.w.add_message(cid["fs"], ns, fs_c.encode(ns, feet, raw, raw * 0.1), ns, counts["fs"])
            counts["fs"] += 1
            last_feet = (feet, t_s)
    total = sum(counts.values())
    f.close({"received": str(total + dropped), "written": str(total), "dropped": str(dropped)})
    return counts


def export_hour(seconds: float) -> dict[str, Any]:
    """Write a ``seconds`` recording, export it to C3D, OpenSim and events CSV; wall and CPU
    time of the export (best of one: it is long), and the sizes."""
    from exolink import gaitlab

    with tempfile.TemporaryDirectory() as d:
        src = Path(d) / "walk.mcap"
        t = time.perf_counter()
        counts = synthetic(src, seconds)
        write_s = time.perf_counter() - t
        wall, cpu = time.perf_counter(), time.process_time()
        trial = gaitlab.build_trial(src, zero="first-trigger")
        build_s = time.perf_counter() - wall
        c3d = gaitlab.write_c3d(trial, Path(d) / "walk.c3d")
        c3d_s = time.perf_counter() - wall - build_s
        files = gaitlab.write_opensim(trial, Path(d) / "opensim")
        events = gaitlab.write_events_csv(trial, Path(d) / "walk_events.csv")
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        mb = {p.name: round(p.stat().st_size / 2**20, 2) for p in (src, c3d, events, *files)}
    return {
        "recording_s": seconds,
        "messages": counts,
        "synthetic_write_s": round(write_s, 1),
        "export_wall_s": round(wall, 2),
        "export_cpu_s": round(cpu, 2),
        "read_and_resample_s": round(build_s, 2),
        "c3d_write_s": round(c3d_s, 2),
        "frames": trial.frames,
        "channels": len(trial.channels),
        "events": len(trial.events),
        "file_mb": mb,
    }


def run(quick: bool) -> dict[str, Any]:
    return {"export_1h" if not quick else "export_5min": export_hour(300 if quick else 3600)}
