"""Shared fixtures: isolated multicast groups and Zenoh ports, configs written to tmp files,
and helpers to run exolink processes for real (no mocks of buses or sessions)."""

from __future__ import annotations

import json
import os
import queue
import random
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest
import yaml
from exolink import messaging
from exolink.config import bundled, load

EXOLINK = [sys.executable, "-m", "exolink.cli.main"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def group() -> str:
    """A multicast group of its own per test, so concurrent or leftover traffic never mixes."""
    return f"239.74.{random.randint(1, 254)}.{random.randint(1, 254)}"


@pytest.fixture
def write_config(tmp_path: Path, group: str) -> Callable[..., Path]:
    """Write the bundled sim config with overrides onto this test's own group and port."""

    def write(nodes: list[dict] | None = None, **overrides: object) -> Path:
        data = yaml.safe_load(bundled("sim").read_text())
        data["can"]["channel"] = group
        data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
        if nodes is not None:
            data["nodes"] = nodes
        for key, value in overrides.items():
            if isinstance(value, dict) and isinstance(data.get(key), dict):
                data[key].update(value)
            else:
                data[key] = value
        path = tmp_path / "appliance.yaml"
        path.write_text(yaml.safe_dump(data))
        return path

    return write


class DrainedBus:
    """A python-can bus read continuously by a thread into a queue.

    At 600 frames/s a UDP socket left unread while a test waits on a CLI call overflows its
    kernel buffer and silently drops the newest frames: exactly the ones a test looks for.
    """

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.q: queue.Queue[can.Message] = queue.Queue()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._drain, daemon=True)
        self._t.start()

    def _drain(self) -> None:
        while not self._stop.is_set():
            m = self.bus.recv(timeout=0.05)
            if m is not None:
                self.q.put(m)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        try:
            return self.q.get(timeout=timeout)
        except queue.Empty:
            return None

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)

    def shutdown(self) -> None:
        self._stop.set()
        self._t.join(1)
        self.bus.shutdown()


@pytest.fixture
def mbus(group: str) -> Iterator[DrainedBus]:
    """An independent listener on the test's udp_multicast bus."""
    bus = DrainedBus(can.Bus(interface="udp_multicast", channel=group, receive_own_messages=False))
    yield bus
    bus.shutdown()


def collect(
    bus: can.BusABC | DrainedBus, seconds: float, ids: set[int] | None = None
) -> list[can.Message]:
    out = []
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        m = bus.recv(timeout=left)
        if m is not None and (ids is None or m.arbitration_id in ids):
            out.append(m)
    return out


def wait_for(pred: Callable[[], object], timeout: float = 10.0, step: float = 0.02) -> object:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(step)
    raise AssertionError(f"condition not met within {timeout} s")


class Proc:
    """A real exolink process whose stderr is kept for the failure message."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.log = log
        self._f = log.open("wb")
        env = {**os.environ, "EXOLINK_LOG_JSON": "1", "PYTHONUNBUFFERED": "1"}
        self.p = subprocess.Popen(
            [*EXOLINK, *args], stdout=self._f, stderr=subprocess.STDOUT, env=env
        )

    def stop(self, timeout: float = 10.0) -> int:
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self._f.close()
        return self.p.returncode

    def output(self) -> str:
        return self.log.read_text(errors="replace")


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Callable[..., Proc]]:
    procs: list[Proc] = []

    def start(*args: str, name: str = "proc") -> Proc:
        p = Proc(list(args), tmp_path / f"{name}-{len(procs)}.log")
        procs.append(p)
        return p

    yield start
    for p in reversed(procs):
        p.stop()


class Appliance:
    def __init__(self, cfg_path, spawn) -> None:  # type: ignore[no-untyped-def]
        self.cfg = load(cfg_path)
        self.at = messaging.local_endpoint(self.cfg.zenoh)
        self.proc = spawn("up", "-c", str(cfg_path), name="up")
        self.session = None
        wait_for(lambda: self.cli("status").returncode == 0, timeout=20)
        wait_for(
            lambda: all(n["heartbeat_age_s"] is not None for n in self.status()["nodes"]),
            timeout=20,
        )

    def cli(self, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*EXOLINK, *args, "--at", self.at, "--timeout", "3"],
            capture_output=True,
            text=True,
            timeout=30,
        )

    def status(self) -> dict:
        r = self.cli("status", "--json")
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    def node(self, name: str) -> dict:
        return next(n for n in self.status()["nodes"] if n["name"] == name)

    def arm(self) -> None:
        r = wait_for(lambda: (x := self.cli("arm")).returncode == 0 and x, timeout=10)
        assert "armed" in r.stdout  # type: ignore[union-attr]
