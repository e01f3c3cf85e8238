"""Unit costs of a machine, the ones the appliance's CPU is made of: a Python loop, a system call,
a wake-up, a CAN frame received (on a vcan: the guest), and a Zenoh sample through the board's
router. Self-contained (stdlib + zenoh):
bench-board runs it in the guest and natively; on a real BeagleBone with exolink installed,
``/opt/exolink/bin/python units.py`` gives the figures to scale a proxy run by.

Why: the proxy (qemu TCG) is a slow CPU but not a uniformly slow one. Measured there against this
x86 VM, a pure-Python loop is ~27x slower, a sleep-and-wake ~10-50x, and one 100 Hz Zenoh topic
from a publisher through a router to a subscriber took 88 % of a CPU (three processes). Which
unit dominates decides what to optimise, and a real A8's ratios may differ from TCG's.

Everything runs pinned to one CPU (the appliance's CPU 0 on the board) and reports CPU time
(user + system, all threads), not wall time. Prints ``UNITS_RESULT {json}``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
import time
from typing import Any

PORT = 17931
KEY = "exolink-units/sample"
LOOPS = 200_000


def _cpu_s(pid: int | str = "self") -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def python_loop_ms() -> float:
    """The probe's calibration loop (benchmarks/board/probe.py): CPU ms."""
    t0 = time.thread_time()
    acc = 0
    for i in range(LOOPS):
        acc += i * i % 7
    return round((time.thread_time() - t0) * 1e3, 2)


def syscall_us(call: str) -> float:
    """CPU us per system call that does next to nothing in the kernel: ``getppid``, and
    ``thread_time`` (clock_gettime of the thread's CPU clock, which no vDSO serves), the call
    the phase clock and the controller manager's budget make per controller update. TCG
    emulates the kernel's entry, exit and page-table work instruction by instruction, so the
    proxy may charge a call far more, relative to Python, than an A8 does (a few us there)."""
    fn = {"getppid": os.getppid, "thread_time": time.thread_time}[call]
    n = LOOPS // 10
    t0 = time.thread_time()
    for _ in range(n):
        fn()
    return round((time.thread_time() - t0) * 1e6 / n, 2)


def beat_us() -> dict[str, float] | None:
    """CPU us of each of a node's beat's two system calls (exolink.liveness): a 9-byte record
    into the supervisor's pipe (drained between rounds, outside the count) and the deadline
    timer set 50 ms ahead. None where os.timerfd_* is missing (Python < 3.13)."""
    if not hasattr(os, "timerfd_create"):
        return None
    r, w = os.pipe()
    fd = os.timerfd_create(time.CLOCK_MONOTONIC, flags=os.TFD_NONBLOCK)
    record, rounds, per_round = b"\0" * 9, 20, 500
    try:
        spent = 0.0
        for _ in range(rounds):
            t0 = time.thread_time()
            for _ in range(per_round):
                os.write(w, record)
            spent += time.thread_time() - t0
            os.read(r, 65536)
        t0 = time.thread_time()
        for _ in range(rounds * per_round):
            os.timerfd_settime(fd, flags=os.TFD_TIMER_ABSTIME, initial=time.monotonic() + 0.05)
        armed = time.thread_time() - t0
    finally:
        for x in (r, w, fd):
            os.close(x)
    n = rounds * per_round
    return {"pipe_write": round(spent * 1e6 / n, 2), "timerfd_rearm": round(armed * 1e6 / n, 2)}


def wake_us(seconds: float) -> float:
    """CPU us per iteration of a loop that sleeps to a 10 ms deadline and does nothing else."""
    c0, t = time.thread_time(), time.monotonic()
    n, end = 0, t + seconds
    while t < end:
        t += 0.01
        time.sleep(max(0.0, t - time.monotonic()))
        n += 1
    return round((time.thread_time() - c0) * 1e6 / n, 1)


def _session(mode: str, endpoint: str):  # type: ignore[no-untyped-def]
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/delay", "0")
    c.insert_json5("transport/shared_memory/enabled", "false")
    where = "listen/endpoints" if mode == "router" else "connect/endpoints"
    c.insert_json5(where, json.dumps([endpoint]))
    return zenoh.open(c)


def _subscribe(s, seconds: float, channel: bool) -> int:  # type: ignore[no-untyped-def]
    """Take each sample's payload, key and attachment as the recorder does: in a callback on
    Zenoh's thread, or (``channel``) from a ring channel drained every 50 ms by the caller's
    thread, so Zenoh's thread never takes the GIL per sample."""
    import zenoh

    got = [0]

    def take(smp) -> None:  # type: ignore[no-untyped-def]
        smp.payload.to_bytes(), str(smp.key_expr), smp.attachment
        got[0] += 1

    if not channel:
        s.declare_subscriber(f"{KEY}/**", take)
        time.sleep(seconds)
        return got[0]
    sub = s.declare_subscriber(f"{KEY}/**", zenoh.handlers.RingChannel(50_000))
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.05)
        while (smp := sub.try_recv()) is not None:
            take(smp)
    return got[0]


def _role(role: str, endpoint: str, seconds: float, burst: int, topics: int, channel: bool) -> None:
    s = _session("router" if role == "router" else "client", endpoint)
    if role == "sub":
        sys.stdout.write(f"{_subscribe(s, seconds, channel)}\n")
    elif role == "pub":
        pubs = [s.declare_publisher(f"{KEY}/{i}") for i in range(topics)]
        payload = bytes(120)  # a JointState's CDR is ~200 bytes, a foot-switch message ~40
        time.sleep(1.0)  # the subscriber's interest reaches us
        sys.stdout.write("go\n")
        sys.stdout.flush()
        t = time.monotonic()
        end = t + seconds
        while t < end:
            t += 0.01 * burst
            time.sleep(max(0.0, t - time.monotonic()))
            for _ in range(burst):
                for pub in pubs:
                    pub.put(payload)
    else:
        time.sleep(seconds)
    s.close()


def zenoh_hop(
    seconds: float, burst: int, topics: int = 1, channel: bool = False, unix: bool = False
) -> dict[str, float]:
    """``topics`` x 100 samples/s (each topic's ``burst`` puts every ``burst`` x 10 ms) from a
    client publisher through a router to a client subscriber: each process's CPU per sample, in
    us. ``burst=4, topics=5`` is the nominal load's shape (a reader waking every 4th cycle);
    ``channel``: the subscriber drains a ring channel instead of a callback per sample;
    ``unix``: the links are unix stream sockets, not TCP on loopback (the kernel's share)."""
    endpoint = f"tcp/127.0.0.1:{PORT + burst * topics + channel}"
    if unix:
        endpoint = f"unixsock-stream/{tempfile.gettempdir()}/exolink-units-{os.getpid()}.sock"
    me = [sys.executable, os.path.abspath(__file__), "--role"]

    def start(role: str, secs: float) -> subprocess.Popen[str]:
        cmd = [*me, role, "--endpoint", endpoint, "--seconds", str(secs), "--burst", str(burst)]
        cmd += ["--topics", str(topics)] + (["--channel"] if channel else [])
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)

    router = start("router", seconds + 60)
    time.sleep(2.0)
    sub = start("sub", seconds + 40)
    time.sleep(2.0)
    pub = start("pub", seconds)
    try:
        assert pub.stdout is not None
        if pub.stdout.readline().strip() != "go":
            raise RuntimeError("the publisher did not start")
        procs = {"publisher": pub, "router": router, "subscriber": sub}
        c0 = {k: _cpu_s(p.pid) for k, p in procs.items()}
        t0 = time.monotonic()
        time.sleep(seconds * 0.9)
        c1 = {k: _cpu_s(p.pid) for k, p in procs.items()}
        samples = 100 * topics * (time.monotonic() - t0)
    finally:
        pub.wait(seconds + 60)
        for p in (sub, router):
            p.terminate()
            p.wait(30)
    return {k: round((c1[k] - c0[k]) * 1e6 / samples) for k in c0}


CAN_UNIT_ID = 0x7F0  # no node of the appliance reads it
SO_TIMESTAMPNS = 35  # asm-generic/socket.h; Python does not export it
CAN_RATE = 1000  # frames/s, sent in bursts of 100 every 100 ms


def _can_socket(channel: str) -> socket.socket:
    s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    s.bind((channel,))
    return s


def _can_send(channel: str, seconds: float) -> None:
    """The other CPU's sender (as the simulator is on the board proxy): CAN_RATE frames/s."""
    with contextlib.suppress(OSError):
        os.sched_setaffinity(0, {1})
    s = _can_socket(channel)
    s.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, b"")  # receives nothing
    frame = struct.pack("=IB3x8s", CAN_UNIT_ID, 8, bytes(range(8)))
    t = time.monotonic()
    end = t + seconds
    while t < end:
        t += 0.1
        time.sleep(max(0.0, t - time.monotonic()))
        for _ in range(CAN_RATE // 10):
            with contextlib.suppress(OSError):  # a full transmit queue: that frame is lost
                s.send(frame)


def _can_receive(channel: str, seconds: float, drop: bool) -> None:
    """A reader of CAN_UNIT_ID on this CPU that takes its frames every 100 ms, one ``recv``
    each (``drop``: the same socket with a content filter that drops them all in the kernel,
    exolink.canbus.filters): prints its frames and CPU seconds over ``seconds``."""
    s = _can_socket(channel)
    s.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, struct.pack("=II", CAN_UNIT_ID, 0x7FF))
    s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)  # as the appliance's readers
    if drop:
        from exolink.canbus import filters as canfilter

        canfilter.attach(s, [canfilter.Drop(CAN_UNIT_ID, 8)])
    s.setblocking(False)
    n, c0 = 0, time.process_time()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.1)
        with contextlib.suppress(BlockingIOError):
            while True:
                s.recvmsg(16, 64)
                n += 1
    sys.stdout.write(f"{n} {time.process_time() - c0}\n")


def can_receive_us(seconds: float, channel: str = "vcan0") -> dict[str, Any] | None:
    """CPU of one reader per CAN frame it is sent, on this CPU, frames sent from the other:
    ``read`` takes them (kernel queue, receive, timestamp, Python), ``kernel_dropped`` has
    them dropped by a content filter before they queue (what canfilter saves a reader per
    frame it never needed). None without a vcan (natively)."""
    if not os.path.exists(f"/sys/class/net/{channel}") or os.cpu_count() == 1:
        return None
    me = [sys.executable, os.path.abspath(__file__), "--endpoint", channel]
    out: dict[str, Any] = {"frames_per_s": CAN_RATE}
    for case in ("read", "kernel_dropped"):
        role = "can-drop" if case == "kernel_dropped" else "can-read"
        sender = subprocess.Popen([*me, "--role", "can-send", "--seconds", str(seconds + 2)])
        try:
            r = subprocess.run(
                [*me, "--role", role, "--seconds", str(seconds)],
                capture_output=True,
                text=True,
                timeout=seconds + 60,
            )
        finally:
            sender.wait(seconds + 60)
        try:
            got, cpu = r.stdout.split()
        except ValueError:  # e.g. an installed exolink without canfilter
            out[case] = {"error": r.stderr.strip().splitlines()[-1:] or f"rc {r.returncode}"}
            continue
        out[case] = {
            "received": int(got),
            "cpu_us_per_frame_sent": round(float(cpu) * 1e6 / (CAN_RATE * seconds), 1),
        }
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--cpu", type=int, default=0, help="the CPU everything runs on")
    p.add_argument(
        "--role",
        choices=["router", "sub", "pub", "can-send", "can-read", "can-drop"],
        help=argparse.SUPPRESS,
    )
    p.add_argument("--endpoint", help=argparse.SUPPRESS)
    p.add_argument("--burst", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--topics", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--channel", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.role in ("can-send", "can-read", "can-drop"):
        if args.role == "can-send":
            _can_send(args.endpoint, args.seconds)
        else:
            _can_receive(args.endpoint, args.seconds, drop=args.role == "can-drop")
        return 0
    if args.role:
        _role(args.role, args.endpoint, args.seconds, args.burst, args.topics, args.channel)
        return 0
    os.sched_setaffinity(0, {args.cpu})  # children inherit it
    out = {
        "cpu": args.cpu,
        "python_loop_ms": python_loop_ms(),
        "syscall_getppid_us": syscall_us("getppid"),
        "syscall_thread_time_us": syscall_us("thread_time"),
        "wake_us": wake_us(args.seconds),
        "beat_us": beat_us(),
        "can_receive_us": can_receive_us(args.seconds),
        "zenoh_us_per_sample": zenoh_hop(args.seconds, 1),
        "zenoh_us_per_sample_burst4": zenoh_hop(args.seconds, 4),
        "zenoh_us_per_sample_burst4x5": zenoh_hop(args.seconds, 4, 5),
        "zenoh_us_per_sample_burst4x5_channel": zenoh_hop(args.seconds, 4, 5, channel=True),
        "zenoh_us_per_sample_burst4x5_unix": zenoh_hop(args.seconds, 4, 5, unix=True),
    }
    sys.stdout.write("UNITS_RESULT " + json.dumps(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
