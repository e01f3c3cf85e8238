"""E-stop -> first disable frame on the bus, against any appliance endpoint and bus, with hostile
clients beside it. Stdlib and exolink only (no numpy), so it runs wherever exolink is installed:
on this machine against ``make sim`` or a benchmark's appliance, or inside the board proxy's
guest (``/opt/exolink/bin/python -m benchmarks.estop measure --bus socketcan:vcan0 ...``).

Subcommands:
- ``measure``: e-stops from one client session, each timed from the query's send to the kernel
  receive stamp of the first "joint disabled" frame an independent listener reads; percentiles
  as JSON on stdout. ``--case`` puts a load beside it (``idle``, ``big_query``: a 100 KB query
  to a node sent just before each e-stop, ``stalled``: three client processes that queue
  thousands of status queries and are then SIGSTOPped, ``flood``: three processes that keep
  queries in flight to status / logs / control).
- ``stall`` and ``flood``: one hostile client process each (what ``measure`` starts).

The sender and the listener must share a clock: on the board proxy both would run in the guest
(this file uploaded and run by /opt/exolink/bin/python, ``--bus socketcan:vcan0``, a login file
from the card's FAT partition) and the hostile clients on the host, through the forwarded Zenoh
port: ``stall`` / ``flood`` started (and SIGSTOPped) there around ``measure --case idle``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import can
import zenoh

from exolink import messaging
from exolink.canbus import open_bus
from exolink.config import CanConfig
from exolink.protocol import h2

BIG_QUERY_BYTES = 100 * 1024
STALLED_CLIENTS = 3
STALL_QUERIES = 3000
FLOOD_CLIENTS = 3
FLOOD_IN_FLIGHT = 1000
TRIAL_TIMEOUT_S = 20.0
SETTLE_S = 0.4  # after a trip the watchdog repeats the safe action at +50 and +250 ms
CASES = ("idle", "big_query", "stalled", "flood")


def is_disable(m: can.Message) -> bool:
    f = h2.decode(m)
    return isinstance(f, h2.JointControl) and f.mode == h2.MODES["disabled"]


class Listener:
    """The bus read by a thread: every frame with its kernel receive stamp (wall clock)."""

    def __init__(self, bus: str) -> None:
        interface, _, channel = bus.partition(":")
        self.bus = open_bus(CanConfig(interface=interface, channel=channel))  # type: ignore[arg-type]
        self.q: queue.Queue[can.Message] = queue.Queue()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._read, daemon=True, name="listener")
        self._t.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            m = self.bus.recv(0.05)
            if m is not None:
                self.q.put(m)

    def clear(self) -> None:
        while not self.q.empty():
            self.q.get_nowait()

    def first_disable_after(self, t0: float, timeout: float) -> float | None:
        """The stamp of the first disable frame received after ``t0``, or None."""
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            try:
                m = self.q.get(timeout=left)
            except queue.Empty:
                return None
            if m.timestamp >= t0 and is_disable(m):
                return float(m.timestamp)
        return None

    def close(self) -> None:
        self._stop.set()
        self._t.join(1)
        self.bus.shutdown()


def percentiles(values: list[float]) -> dict[str, float | int]:
    """ms figures of seconds: n, p50, p99 (nearest rank), max."""
    if not values:
        return {"n": 0}
    ms = sorted(v * 1e3 for v in values)
    rank = min(len(ms) - 1, max(0, round(0.99 * len(ms) + 0.5) - 1))
    return {
        "n": len(ms),
        "p50": round(statistics.median(ms), 1),
        "p99": round(ms[rank], 1),
        "max": round(ms[-1], 1),
    }


def _session(at: str, zenoh_config: str | None) -> tuple[zenoh.Session, str]:
    """A client session, patient with a router that a hostile client has stalled."""
    session = messaging.open_client_session(at, zenoh_config, handshake_s=TRIAL_TIMEOUT_S)
    return session, messaging.client_login(zenoh_config)


def _hostile(mode: str, args: argparse.Namespace, count: int) -> list[subprocess.Popen[str]]:
    # this file as a script: it runs where only exolink is installed (a board's /opt/exolink)
    cmd = [sys.executable, os.path.abspath(__file__), mode, "--at", args.hostile_at or args.at]
    cmd += ["--device", args.device]
    if args.hostile_config:
        cmd += ["--zenoh-config", args.hostile_config]
    return [
        subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)
        for _ in range(count)
    ]


def _kill(procs: list[subprocess.Popen[str]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGCONT)
            p.kill()
        p.wait()


@contextlib.contextmanager
def _flooding(args: argparse.Namespace) -> Iterator[None]:
    procs = _hostile("flood", args, FLOOD_CLIENTS)
    try:
        for p in procs:  # each says when its queries flow
            assert p.stdout is not None
            p.stdout.readline()
        time.sleep(1.0)
        yield
    finally:
        _kill(procs)


def _stalled(args: argparse.Namespace) -> list[subprocess.Popen[str]]:
    """Clients that queued their status queries and stopped reading (SIGSTOP)."""
    procs = _hostile("stall", args, STALLED_CLIENTS)
    for p in procs:
        assert p.stdout is not None
        p.stdout.readline()  # "sent": its queries are on their way
        p.send_signal(signal.SIGSTOP)
    time.sleep(0.3)  # their replies fill what they no longer read
    return procs


def _ask(session: zenoh.Session, key: str, payload: bytes) -> list[float]:
    """Send a query now; the list gets the time its first answer came."""
    replied: list[float] = []

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            replied.append(time.time())

    session.get(key, on_reply, payload=payload, timeout=TRIAL_TIMEOUT_S)
    return replied


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """``args.trials`` e-stops in case ``args.case``; latencies and how many got no frame."""
    session, login = _session(args.at, args.zenoh_config)
    other = messaging.open_client_session(
        args.hostile_at or args.at, args.hostile_config, handshake_s=TRIAL_TIMEOUT_S
    )
    listener = Listener(args.bus)
    key = f"{messaging.mgmt_key(args.device, 'watchdog')}/{login}"
    big_login = messaging.client_login(args.hostile_config)
    big_key = f"{messaging.mgmt_key(args.device, 'controllers')}/{big_login}"
    frames: list[float] = []
    replies: list[float] = []
    lost = 0
    with contextlib.ExitStack() as closing:
        closing.callback(session.close)
        closing.callback(other.close)
        closing.callback(listener.close)
        if args.case == "flood":
            closing.enter_context(_flooding(args))
        for _ in range(args.trials):
            stalled = _stalled(args) if args.case == "stalled" else []
            try:
                if args.case == "big_query":
                    big = json.dumps({"pad": "x" * BIG_QUERY_BYTES}).encode()
                    other.get(big_key, lambda _r: None, payload=big, timeout=10)
                    time.sleep(0.02)  # on its way through the router
                listener.clear()
                t0 = time.time()
                replied = _ask(session, key, b'{"action": "estop"}')
                stamp = listener.first_disable_after(t0, TRIAL_TIMEOUT_S)
                if stamp is None:
                    lost += 1
                else:
                    frames.append(stamp - t0)
                end = time.monotonic() + 2
                while not replied and time.monotonic() < end:
                    time.sleep(0.005)
                if replied:
                    replies.append(replied[0] - t0)
            finally:
                _kill(stalled)
            time.sleep(SETTLE_S)
    return {
        "estop_to_first_disable_frame_ms": percentiles(frames),
        "estop_reply_ms": percentiles(replies),
        "no_frame_within_s": {"s": TRIAL_TIMEOUT_S, "trials": lost},
    }


def stall(args: argparse.Namespace) -> None:
    """Queue STALL_QUERIES status queries and say so; the caller then SIGSTOPs this process."""
    session, login = _session(args.at, args.zenoh_config)
    key = f"{messaging.mgmt_key(args.device, 'status')}/{login}"
    for _ in range(STALL_QUERIES):
        session.get(key, lambda _r: None, payload=b"{}", timeout=60)
    print("sent", flush=True)
    time.sleep(3600)


def flood(args: argparse.Namespace) -> None:
    """Keep FLOOD_IN_FLIGHT queries in flight (status, logs, control in turn) until killed."""
    session, login = _session(args.at, args.zenoh_config)
    bodies = [
        ("status", b"{}"),
        ("logs", json.dumps({"node": "simulator", "lines": 500}).encode()),
        ("control", json.dumps({"node": "no_such_node", "action": "restart"}).encode()),
    ]
    slots = threading.Semaphore(FLOOD_IN_FLIGHT)
    sent = 0
    print("flooding", flush=True)
    while True:
        slots.acquire()
        path, body = bodies[sent % len(bodies)]
        key = f"{messaging.mgmt_key(args.device, path)}/{login}"
        session.get(
            key,
            zenoh.handlers.Callback(lambda _r: None, slots.release),
            payload=body,
            timeout=5,
        )
        sent += 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.estop")
    p.add_argument("mode", choices=["measure", "stall", "flood"])
    p.add_argument("--at", default="tcp/127.0.0.1:7447")
    p.add_argument("--device", default="sim")
    p.add_argument("--zenoh-config", help="the e-stop client's login file")
    p.add_argument("--hostile-at", help="where the hostile clients connect (default --at)")
    p.add_argument(
        "--hostile-config", help="the hostile clients' login file (default: --zenoh-config's)"
    )
    p.add_argument("--bus", default="udp_multicast:239.74.163.2", help="interface:channel")
    p.add_argument("--case", choices=CASES, default="idle")
    p.add_argument("--trials", type=int, default=20)
    args = p.parse_args(argv)
    args.hostile_config = args.hostile_config or args.zenoh_config  # a board has logins
    if args.mode == "measure":
        json.dump(measure(args), sys.stdout)
        sys.stdout.write("\n")
    elif args.mode == "stall":
        stall(args)
    else:
        flood(args)
    return 0


if __name__ == "__main__":
    os.environ.setdefault("EXOLINK_LOG_JSON", "1")
    sys.exit(main())
