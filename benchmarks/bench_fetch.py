"""Fetching a recording over the network (exolink record fetch): throughput, and what it costs
the appliance while the simulator streams and the recorder records: the CPU of the supervisor
(its process holds the Zenoh router every chunk passes through) and of the recorder (which
reads, encodes and answers each chunk), against the same interval without a fetch."""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from exolink.nodes.recorder import RecorderParams

from benchmarks.bench_recorder import joint_states, write
from benchmarks.harness import Appliance, board_cycles_per_read, cpu_s
from exolink import messaging
from exolink.recordings import fetching


def _nodes(directory: Path, fetch_mb_s: float) -> list[dict[str, Any]]:
    every = {"cycles_per_read": board_cycles_per_read()}  # 100 Hz topics come bundled
    return [
        {"name": "simulator", "plugin": "simulator", "params": {"maccepa_boards": [0]}},
        {"name": "h2_reader", "plugin": "h2_reader", "params": every},
        {
            "name": "maccepa_bridge",
            "plugin": "maccepa_bridge",
            "params": {"boards": [0], **every},
        },
        {
            "name": "recorder",
            "plugin": "recorder",
            "params": {"directory": str(directory), "fetch_mb_s": fetch_mb_s},
        },
    ]


def _cpu(pids: dict[str, int]) -> dict[str, float]:
    return {k: cpu_s(p) for k, p in pids.items()}


def _share(before: dict[str, float], after: dict[str, float], seconds: float) -> dict[str, float]:
    """% of one CPU each process used over ``seconds``."""
    return {k: round(100 * (after[k] - before[k]) / seconds, 1) for k in before}


def fetch_cost(file_mb: int, chunk: int, fetch_mb_s: float) -> dict[str, Any]:
    """One fetch of a ``file_mb`` recording in ``chunk`` bytes, the recorder serving at most
    ``fetch_mb_s`` (0: as fast as it can)."""
    d = Path(tempfile.mkdtemp(prefix="exolink-fetch-"))
    laptop = Path(tempfile.mkdtemp(prefix="exolink-laptop-"))
    # A closed recording as the recorder writes them (uncompressed: its size is the transfer's)
    n = file_mb * 2**20 // 180
    write(d / "sim_big_000.mcap", joint_states(), n, "none")
    size = (d / "sim_big_000.mcap").stat().st_size
    app = Appliance.sim(nodes=_nodes(d, fetch_mb_s))
    try:
        app.call("record", {"action": "start"})  # live data flows and is written meanwhile
        rec = app.node("recorder")
        pids = {"supervisor": app.proc.pid, "recorder": int(rec["pid"])}
        key = messaging.mgmt_key("sim", "recordings")

        ask = fetching.Patient(lambda body: messaging.request(app.session, key, body, 5))

        # The board's sha256, once (what the first `stat` of a fetch starts).
        t = time.monotonic()
        st = ask({"action": "stat", "name": "sim_big_000.mcap"})
        while st["sha256"] is None:
            time.sleep(0.05)
            st = ask({"action": "stat", "name": "sim_big_000.mcap"})
        hash_s = time.monotonic() - t
        time.sleep(2)
        dropped0 = app.call("record")["dropped"]
        # Baseline: the same appliance, recording, no fetch.
        c0, t0 = _cpu(pids), time.monotonic()
        time.sleep(5)
        idle = _share(c0, _cpu(pids), time.monotonic() - t0)
        c1, t1 = _cpu(pids), time.monotonic()
        f = fetching.fetch(ask, "sim_big_000.mcap", laptop, chunk)
        dt = time.monotonic() - t1
        during = _share(c1, _cpu(pids), dt)
        s = app.call("record")
    finally:
        app.close()
        shutil.rmtree(d, ignore_errors=True)
        shutil.rmtree(laptop, ignore_errors=True)
    return {
        "file_mb": round(size / 2**20, 1),
        "chunk_kib": chunk >> 10,
        "recorder_fetch_mb_s": fetch_mb_s,
        "fetch_s": round(dt, 2),
        "throughput_mb_s": round(size / 1e6 / dt, 1),
        "board_sha256_s": round(hash_s, 2),
        "cpu_pct_recording_no_fetch": idle,
        "cpu_pct_recording_and_fetch": during,
        "recorder_dropped_during_fetch": s["dropped"] - dropped0,
        "recorder_written": s["written"],
        "sha256_equal": f.sha256 == st["sha256"],
        "retried_rate_limited": ask.retried_rate,
        "retried_reply_lost": ask.retried_lost,
    }


def run(quick: bool) -> dict[str, Any]:
    mb = 16 if quick else 128
    return {
        "paced_default": fetch_cost(mb, 1 << 20, RecorderParams().fetch_mb_s),
        "paced_4mb_s": fetch_cost(mb, 1 << 20, 4.0),
        "unpaced_1mib": fetch_cost(mb, 1 << 20, 0),
        "unpaced_256kib": fetch_cost(mb, 256 << 10, 0),
    }
