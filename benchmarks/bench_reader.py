"""The data path: CAN timestamp -> subscriber in another process, reader CPU, memory, import
time, and the highest frame rate the reader follows with zero loss."""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from typing import Any

import yaml

from benchmarks.harness import (
    Appliance,
    board_cycles_per_read,
    cpu_s,
    free_port,
    group,
    pct,
    pss_mb,
)
from exolink import messaging
from exolink.canbus import open_bus
from exolink.config import CanConfig, bundled
from exolink.protocol import h2

RUNTIME = [sys.executable, "-m", "exolink.runtime"]
LATENCY_SUBSCRIBER = r"""
import sys, time
from exolink import messaging
s = messaging.open_client_session(sys.argv[1])
key = messaging.topic_key(0, "h2", "joint_states", "sensor_msgs/msg/JointState")
lat = []
def on(sample):
    now = time.time_ns()
    _, ts, _ = messaging.decode_attachment(sample.attachment.to_bytes())
    lat.append(now - ts)
sub = s.declare_subscriber(key, on)
time.sleep(float(sys.argv[2]))
sub.undeclare(); s.close()
print(" ".join(map(str, lat)))
"""


def latency_and_cpu(
    seconds: float, cycles_per_read: int = 1, zenoh_own_threads: bool = False
) -> dict[str, Any]:
    """The sim config's appliance; ``cycles_per_read``: the h2 reader's (4: a quarter of the
    wake-ups and Zenoh bursts, every sample up to 30 ms later; the board config's, below);
    ``zenoh_own_threads``: Zenoh's own runtimes instead of the configs' ``zenoh.threads: 1``."""
    nodes = None
    if cycles_per_read != 1:
        nodes = yaml.safe_load(bundled("sim").read_text())["nodes"]
        for n in nodes:
            if n["plugin"] == "h2_reader":
                n.setdefault("params", {})["cycles_per_read"] = cycles_per_read
    app = Appliance.sim(nodes=nodes, zenoh={"threads": None} if zenoh_own_threads else {})
    try:
        time.sleep(1)
        pid = app.node("h2_reader")["pid"]
        before = cpu_s(pid)
        out = subprocess.run(
            [sys.executable, "-c", LATENCY_SUBSCRIBER, app.at, str(seconds)],
            capture_output=True,
            text=True,
            timeout=seconds + 30,
        )
        cpu = cpu_s(pid) - before
        lat = [int(x) for x in out.stdout.split()]
        frames = 300 * seconds
        nodes = app.call("status")["nodes"]
        return {
            "e2e_latency_ms": pct(lat, 1e-6),
            "joint_states_received": len(lat),
            "reader_cpu_per_frame_us": round(cpu / frames * 1e6, 1),
            "reader_cpu_percent_at_100hz": round(cpu / seconds * 100, 1),
            "rss_mb": {n["name"]: n.get("rss_mb") for n in nodes},
            "pss_mb": {n["name"]: pss_mb(n["pid"]) for n in nodes if n.get("pid")},
        }
    finally:
        app.close()


def import_time() -> dict[str, float]:
    def t(code: str) -> float:
        runs = []
        for _ in range(5):
            s = time.perf_counter()
            subprocess.run([sys.executable, "-c", code], check=True)
            runs.append(time.perf_counter() - s)
        return statistics.median(runs)

    base = t("pass")
    return {
        "python_startup_ms": round(base * 1e3, 1),
        "reader_import_ms": round((t("import exolink.nodes.h2_reader") - base) * 1e3, 1),
        "cli_help_ms": round((t("import exolink.cli.main as m; m.build_parser()") - base) * 1e3, 1),
    }


def max_rate(quick: bool) -> dict[str, Any]:
    """Cycles of 110/120/130 at rising rates into a reader process; zero loss = every cycle published."""
    g, port = group(), free_port()
    import yaml

    from exolink.config import bundled

    data = yaml.safe_load(bundled("sim").read_text())
    data["can"]["channel"] = g
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["nodes"] = [
        {"name": "h2_reader", "plugin": "h2_reader", "params": {"start_stream": False}}
    ]
    import tempfile

    path = tempfile.mktemp(suffix=".yaml")
    with open(path, "w") as f:
        yaml.safe_dump(data, f)
    proc = subprocess.Popen(
        [*RUNTIME, "h2_reader", "-c", path, "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    bus = open_bus(CanConfig(interface="udp_multicast", channel=g))
    results = []
    try:
        time.sleep(2)
        s = messaging.open_client_session(f"tcp/127.0.0.1:{port}")
        frames = [
            h2.encode(h2.JointAngles(1, 2, 3, 4, 5, 6)),
            h2.encode(h2.JointTorques(1, 2, 3, 4, 5, 6)),
            h2.encode(h2.FootSwitches(1, 0, 1, 0, 200)),
        ]
        for rate in [100, 1000, 2000] if quick else [100, 500, 1000, 1500, 2000, 3000, 4000]:
            before = messaging.request(s, "exolink/sim/nodes/h2_reader/stats")[
                "published_joint_states"
            ]
            cpu0 = cpu_s(proc.pid)
            n = int(rate * 2)
            period = 1.0 / rate
            start = time.perf_counter()
            for i in range(n):
                target = start + i * period
                while time.perf_counter() < target:
                    pass
                for f in frames:
                    bus.send(f)
            time.sleep(0.5)
            after = messaging.request(s, "exolink/sim/nodes/h2_reader/stats")[
                "published_joint_states"
            ]
            results.append(
                {
                    "cycles_per_s": rate,
                    "frames_per_s": rate * 3,
                    "sent": n,
                    "published": after - before,
                    # the reader alone (its own process, no other node): CPU per CAN frame
                    "cpu_per_frame_us": round((cpu_s(proc.pid) - cpu0) / (n * 3) * 1e6, 1),
                }
            )
        s.close()
    finally:
        bus.shutdown()
        proc.terminate()
        proc.wait(5)
    ok = [r["frames_per_s"] for r in results if r["published"] == r["sent"]]
    return {
        "steps": results,
        "alone_cpu_per_frame_us_at_100hz": results[0]["cpu_per_frame_us"],
        "max_zero_loss_frames_per_s": max(ok) if ok else 0,
        "note": "udp_multicast itself drops frames near 10k/s; vcan figures come with the kernel tests",
    }


def run(quick: bool) -> dict[str, Any]:
    secs = 5 if quick else 20
    board_n = board_cycles_per_read()
    cadenced = {n: latency_and_cpu(secs, cycles_per_read=n) for n in sorted({4, board_n})}

    def trim(r: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in r.items() if k not in ("rss_mb", "pss_mb")}

    return {
        **latency_and_cpu(secs),
        "board_cadence_4": trim(cadenced[4]),
        "board_config": {"cycles_per_read": board_n, **trim(cadenced[board_n])},
        "zenoh_own_threads": latency_and_cpu(5 if quick else 20, zenoh_own_threads=True),
        "import": import_time(),
        "max_rate": max_rate(quick),
    }
