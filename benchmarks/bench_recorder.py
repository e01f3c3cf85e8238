"""Recorder: raw write throughput, bytes per joint-state message, loss over a long run at
nominal rates on the simulated appliance, and what checking a file's CRCs costs an export."""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from exolink.nodes.recorder import McapFile, RecorderParams
from mcap.reader import make_reader

from benchmarks.harness import Appliance, board_cycles_per_read
from exolink import messaging
from exolink.recordings import readback as recording
from exolink.recordings.readback import info

JS = "sensor_msgs/msg/JointState"


def joint_states() -> list[tuple[int, bytes]]:
    """1000 joint states (stamp, CDR) with plausible angles and torques."""
    cls = messaging.msg_class(JS)
    payloads = []
    rng = np.random.default_rng(0)
    for i in range(1000):
        ns = 1_700_000_000_000_000_000 + i * 10_000_000
        angles = np.round(rng.normal(0, 20, 6)) * np.pi / 180
        payloads.append(
            (
                ns,
                messaging.serialize(
                    cls(
                        header=messaging.header(ns),
                        name=["r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"],
                        position=angles,
                        velocity=np.empty(0),
                        effort=np.round(rng.normal(0, 3, 6)),
                    ),
                    JS,
                ),
            )
        )
    return payloads


def write(path: Path, payloads: list[tuple[int, bytes]], n: int, compression: str) -> float:
    """``n`` joint states into a file as the recorder writes them; the seconds it took."""
    f = McapFile(path, RecorderParams(compression=compression), {})  # type: ignore[arg-type]
    cid = f.channel("h2/joint_states", JS)
    t = time.perf_counter()
    for i in range(n):
        ns, data = payloads[i % 1000]
        f.w.add_message(cid, log_time=ns + i, data=data, publish_time=ns, sequence=i)
    f.close({})
    return time.perf_counter() - t


def throughput(n: int, compression: str) -> dict[str, Any]:
    payloads = joint_states()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.mcap"
        dt = write(path, payloads, n, compression)
        size = path.stat().st_size
    return {
        "messages_per_s": round(n / dt),
        "bytes_per_joint_state": round(size / n, 1),
        "cdr_payload_bytes": len(payloads[0][1]),
    }


def long_run(seconds: float, cycles_per_read: int = 1) -> dict[str, Any]:
    """``cycles_per_read``: the readers' cadence; above 1 (the board's) their 100 Hz topics
    reach the recorder as one bundle per read (messaging.bundle_key)."""
    d = tempfile.mkdtemp(prefix="exolink-rec-")
    every = {"cycles_per_read": cycles_per_read}
    nodes = [
        {"name": "simulator", "plugin": "simulator", "params": {"maccepa_boards": [0]}},
        {"name": "h2_reader", "plugin": "h2_reader", "params": every},
        {
            "name": "maccepa_bridge",
            "plugin": "maccepa_bridge",
            "params": {"boards": [0], **every},
        },
        {"name": "recorder", "plugin": "recorder", "params": {"directory": d}},
    ]
    app = Appliance.sim(nodes=nodes)
    try:
        app.call("record", {"action": "start"})
        cpu0 = app.node("recorder").get("cpu_s") or 0.0
        time.sleep(seconds)
        s = app.call("record", {"action": "stop"})
        rss = app.node("recorder").get("rss_mb")
        cpu = app.node("recorder").get("cpu_s")
    finally:
        app.close()
    files = sorted(Path(d).glob("*.mcap"))
    i = info(files[0])
    return {
        "seconds": seconds,
        "received": s["received"],
        "written": s["written"],
        "dropped": s["dropped"],
        "messages_per_s": round(s["written"] / seconds),
        "file_mb": round(files[0].stat().st_size / 2**20, 2),
        "joint_states": i.topics["/h2/joint_states"]["count"],
        "recorder_rss_mb": rss,
        "recorder_cpu_s": cpu,
        # the recording alone (not the node's start): what each recorded message costs
        "recorder_cpu_us_per_message": round((cpu - cpu0) * 1e6 / max(1, s["written"]), 1)
        if cpu is not None
        else None,
    }


def export_cost(n: int, rounds: int = 5) -> dict[str, Any]:
    """CSV export of a recorder-written file (zstd) with every CRC checked (`exolink export`:
    the whole file first, each chunk again as it is read) against the same writing fed by
    the mcap reader with no check at all. CPU seconds of this process (the export is all
    here), not wall time: on a shared machine the others' load moved wall time by +-15 %;
    best of ``rounds`` each, alternated."""
    with tempfile.TemporaryDirectory() as d:
        path, out = Path(d) / "t.mcap", Path(d) / "csv"
        write(path, joint_states(), n, "zstd")
        best = {"checked": float("inf"), "unchecked": float("inf"), "check_only": float("inf")}
        for _ in range(rounds):
            for kind in best:
                shutil.rmtree(out, ignore_errors=True)
                t = time.process_time()
                if kind == "checked":
                    recording.export_csv(path, out)
                elif kind == "check_only":
                    recording.verify(path)
                else:
                    with path.open("rb") as f:
                        recording.write_csv(make_reader(f).iter_messages(), [], out)
                best[kind] = min(best[kind], time.process_time() - t)
        size = path.stat().st_size
    return {
        "messages": n,
        "file_mb": round(size / 2**20, 2),
        "export_cpu_s_checked": round(best["checked"], 3),
        "export_cpu_s_unchecked": round(best["unchecked"], 3),
        "checked_over_unchecked": round(best["checked"] / best["unchecked"], 3),
        "check_alone_cpu_s": round(best["check_only"], 3),  # `exolink info`'s check of the file
    }


def run(quick: bool) -> dict[str, Any]:
    n = 20_000 if quick else 200_000
    return {
        "write_zstd": throughput(n, "zstd"),
        "write_lz4": throughput(n, "lz4"),
        "write_none": throughput(n, "none"),
        "export_crc": export_cost(20_000 if quick else 100_000),
        "long_run": long_run(10 if quick else 120),
        "long_run_board_cadence": long_run(
            10 if quick else 120, cycles_per_read=board_cycles_per_read()
        ),
    }
