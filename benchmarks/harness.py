"""Shared pieces of the benchmark suite: statistics, a simulated appliance, a drained bus."""

from __future__ import annotations

import json
import os
import queue
import random
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
import yaml
from exolink import messaging
from exolink.canbus import open_bus
from exolink.config import CanConfig, bundled
from exolink.holder import Holder

EXOLINK = [sys.executable, "-m", "exolink.cli.main"]


def pct(values: list[float] | np.ndarray, scale: float = 1.0, digits: int = 3) -> dict[str, float]:
    """mean/p50/p99/max of values times scale (e.g. 1e3 for ms)."""
    a = np.asarray(values, dtype=float) * scale
    if a.size == 0:
        return {"n": 0}
    return {
        "n": int(a.size),
        "mean": round(float(a.mean()), digits),
        "p50": round(float(np.percentile(a, 50)), digits),
        "p99": round(float(np.percentile(a, 99)), digits),
        "max": round(float(a.max()), digits),
    }


def pss_mb(pid: int) -> float | None:
    """Proportional set size: shared pages split among the processes that map them, so the
    appliance's total is what it really takes of the board's 512 MB."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        return None
    return None


def cpu_s(pid: int) -> float:
    """On-CPU time of every thread, in ns precision (schedstat): tick-sampled utime/stime alias
    with a 100 Hz loop woken at the tick rate and misreport it by a factor of two either way."""
    total = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                total += int(f.read().split()[0])
        except OSError:
            continue
    return total / 1e9


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def group() -> str:
    return f"239.75.{random.randint(1, 254)}.{random.randint(1, 254)}"


class Drained:
    """A listener bus read by a thread, so a busy benchmark loop never overflows its socket."""

    def __init__(self, channel: str) -> None:
        self.bus = open_bus(CanConfig(interface="udp_multicast", channel=channel))
        self.q: queue.Queue[can.Message] = queue.Queue()
        self.stop = threading.Event()
        self.t = threading.Thread(target=self._drain, daemon=True)
        self.t.start()

    def _drain(self) -> None:
        while not self.stop.is_set():
            m = self.bus.recv(0.05)
            if m is not None:
                self.q.put(m)

    def wait_for(self, pred: Callable[[can.Message], bool], timeout: float) -> can.Message | None:
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            try:
                m = self.q.get(timeout=left)
            except queue.Empty:
                return None
            if pred(m):
                return m
        return None

    def collect(self, seconds: float) -> list[can.Message]:
        out, end = [], time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                out.append(self.q.get(timeout=left))
            except queue.Empty:
                break
        return out

    def clear(self) -> None:
        while not self.q.empty():
            self.q.get_nowait()

    def close(self) -> None:
        self.stop.set()
        self.t.join(1)
        self.bus.shutdown()


def motion_nodes(*extra: dict[str, Any]) -> list[dict[str, Any]]:
    """The simulated H2, its reader and the controller manager (the motion node, on the shipped
    50 ms deadline), and ``extra`` nodes."""
    return [
        {"name": "simulator", "plugin": "simulator"},
        {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
        {
            "name": "controller_manager",
            "plugin": "controller_manager",
            "critical": True,
            "heartbeat_deadline_ms": 50,
        },
        *extra,
    ]


class Appliance:
    """``exolink up`` on its own multicast group and port, with overrides of the sim config."""

    def __init__(self, nodes: list[dict[str, Any]] | None = None, **overrides: Any) -> None:
        data = yaml.safe_load(bundled("sim").read_text())
        self.group = group()
        data["can"]["channel"] = self.group
        data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
        if nodes is not None:
            data["nodes"] = nodes
        for k, v in overrides.items():
            data[k] = {**data.get(k, {}), **v} if isinstance(v, dict) else v
        self.dir = Path(tempfile.mkdtemp(prefix="exolink-bench-"))
        self.cfg_path = self.dir / "appliance.yaml"
        self.cfg_path.write_text(yaml.safe_dump(data))
        self.at = data["zenoh"]["listen"][0]
        self.log = (self.dir / "up.log").open("wb")
        env = {**os.environ, "EXOLINK_LOG_JSON": "1"}
        self.proc = subprocess.Popen(
            [*EXOLINK, "up", "-c", str(self.cfg_path)],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        self.session: Any = None
        self.holder: Holder | None = None
        try:
            self.session = messaging.open_client_session(self.at) if self._wait_up() else None
        except BaseException:  # never leave an appliance running behind a failed benchmark
            self.close()
            raise

    def _wait_up(self) -> bool:
        end = time.monotonic() + 30
        while time.monotonic() < end:
            try:
                s = messaging.open_client_session(self.at)
            except messaging.Unreachable:
                time.sleep(0.2)
                continue
            try:
                st = messaging.request(s, "exolink/sim/status", timeout_s=1)
                # not ok, or no nodes: a supervisor still starting
                nodes = st.get("nodes") if st.get("ok") else None
                if nodes and all(
                    n["heartbeat_age_s"] is not None for n in nodes if n["state"] == "running"
                ):
                    return True
            except messaging.Unreachable:
                pass
            finally:
                s.close()
            time.sleep(0.2)
        raise RuntimeError(f"appliance did not come up; see {self.dir}/up.log")

    def call(self, path: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
        assert self.session is not None
        return messaging.request(self.session, f"exolink/sim/{path}", body or {}, timeout_s=3)

    def node(self, name: str) -> dict[str, Any]:
        return next(n for n in self.call("status")["nodes"] if n["name"] == name)

    def arm(self, timeout: float = 10) -> None:
        """Armed, and motion held from here (nothing moves a joint without a holder)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.call("watchdog", {"action": "arm"}).get("ok"):
                self.hold()
                return
            time.sleep(0.1)
        raise RuntimeError("could not arm: " + json.dumps(self.call("watchdog", {"action": "arm"})))

    def hold(self) -> None:
        if self.holder is None or not self.holder.holding:
            self.holder = Holder(lambda b: self.call("controllers", b), "benchmark")
            self.holder.acquire()

    def close(self) -> None:
        if self.holder is not None:
            self.holder.release()
        if self.session is not None:
            self.session.close()
        self.proc.terminate()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.log.close()
