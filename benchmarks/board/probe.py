"""Per-process CPU and memory of a running appliance, from /proc (stdlib only).

Runs where the appliance runs: inside the qemu guest (sent over ssh as ``python3 - ARGS``, so it
must not import anything outside the standard library) and on the host for the native figures.
It finds the supervisor and its node processes, takes a snapshot, prints ``PROBE_T0`` (the host
starts its own counters on that line), sleeps the window, takes a second snapshot and prints one
JSON document: CPU share per process (utime+stime delta / wall), PSS, the CPUs each process is
allowed on, per-CPU idle, CAN link counters and kernel CAN stats.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import os
import socket
import struct
import subprocess
import sys
import time
from typing import Any

CLK = os.sysconf("SC_CLK_TCK")


def _read(path: str) -> str:
    with open(path) as f:
        return f.read()


def find_appliance(supervisor: int, nodes: list[str] | None = None) -> dict[str, int]:
    """``{"supervisor": pid, "zygote": pid, "<node>": pid, ...}``: the node processes are its
    children. A node started by exec has ``exolink.runtime NAME`` (or the CLI's ``node run
    NAME``) in its argv; one forked by the zygote
    keeps the zygote's argv and is named ``exo-NAME`` (15 characters at most: ``nodes``, the
    configured names, complete it)."""
    found = {"supervisor": supervisor}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = _read(f"/proc/{entry}/stat")
            argv = _read(f"/proc/{entry}/cmdline").split("\0")
            comm = _read(f"/proc/{entry}/comm").strip()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid != supervisor:
            continue
        if "exolink.runtime" in argv and argv.index("exolink.runtime") + 1 < len(argv):
            found[argv[argv.index("exolink.runtime") + 1]] = int(entry)  # started by exec
        elif "node" in argv and "run" in argv:
            found[argv[argv.index("run") + 1]] = int(entry)
        elif comm.startswith("exo-"):
            short = comm[4:]
            full = [n for n in nodes or [] if n.startswith(short)]
            found[full[0] if len(full) == 1 else short] = int(entry)
        elif any(a.endswith("exolink.zygote") for a in argv):
            found["zygote"] = int(entry)
    return found


def _cpus_allowed(pid: int) -> list[str]:
    """The distinct Cpus_allowed_list values over the process's threads."""
    lists = set()
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    for tid in tids:
        try:
            for line in _read(f"/proc/{pid}/task/{tid}/status").splitlines():
                if line.startswith("Cpus_allowed_list:"):
                    lists.add(line.split(":", 1)[1].strip())
        except OSError:
            continue
    return sorted(lists)


def _kb(text: str, key: str) -> int | None:
    for line in text.splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return None


def _threads(pid: int) -> tuple[dict[str, int], int]:
    """CPU ticks per thread name (digits dropped, so Zenoh's ``rx-0``..``rx-3`` add up) and the
    context switches of all threads: whether a process's CPU is Python's or Zenoh's runtime's,
    and how often it wakes."""
    ticks: dict[str, int] = {}
    switches = 0
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return ticks, switches
    for tid in tids:
        try:
            f = _read(f"/proc/{pid}/task/{tid}/stat").rsplit(")", 1)[1].split()
            comm = _read(f"/proc/{pid}/task/{tid}/comm").strip()
            status = _read(f"/proc/{pid}/task/{tid}/status")
        except OSError:
            continue
        name = "main" if tid == str(pid) else comm.rstrip("0123456789").rstrip("-_") or comm
        ticks[name] = ticks.get(name, 0) + int(f[11]) + int(f[12])
        switches += (_kb(status, "voluntary_ctxt_switches") or 0) + (
            _kb(status, "nonvoluntary_ctxt_switches") or 0
        )
    return ticks, switches


def process(pid: int, pss: bool = True) -> dict[str, Any] | None:
    """``pss``: read smaps_rollup too (a walk of the process's page tables under its mmap lock:
    slow on the proxy, so only the window's end snapshot, which reports memory, reads it)."""
    try:
        fields = _read(f"/proc/{pid}/stat").rsplit(")", 1)[1].split()
        status = _read(f"/proc/{pid}/status")
    except OSError:
        return None
    rollup = ""
    if pss:
        with contextlib.suppress(OSError):
            rollup = _read(f"/proc/{pid}/smaps_rollup")
    thread_ticks, switches = _threads(pid)
    return {
        "pid": pid,
        "thread_ticks": thread_ticks,
        "switches": switches,
        "cpu_ticks": int(fields[11]) + int(fields[12]),
        "start_ticks": int(fields[19]),
        "nice": int(fields[16]),
        "policy": int(fields[38]),
        "last_cpu": int(fields[36]),
        "threads": int(fields[17]),
        "pss_kb": _kb(rollup, "Pss"),
        "rss_kb": _kb(status, "VmRSS"),
        "cpus_allowed": _cpus_allowed(pid),
        "autogroup": _autogroup(pid),
    }


def _autogroup(pid: int) -> str | None:
    """The kernel's scheduling group of the process's session (CONFIG_SCHED_AUTOGROUP): groups
    share the CPU equally and nice orders threads only within one, so the appliance's
    processes must share one for board.yaml's priorities to mean anything."""
    try:
        return _read(f"/proc/{pid}/autogroup").split()[0]
    except (OSError, IndexError):
        return None


def cpu_times() -> dict[str, list[int]]:
    out = {}
    for line in _read("/proc/stat").splitlines():
        if line.startswith("cpu"):
            name, *vals = line.split()
            out[name] = [int(v) for v in vals]
    return out


def idle_pct(a: list[int], b: list[int]) -> float:
    d = [y - x for x, y in zip(a, b, strict=False)]
    total = sum(d[:8])  # user nice system idle iowait irq softirq steal (guest time is in user)
    return round(100.0 * (d[3] + d[4]) / total, 1) if total else float("nan")


def link(channel: str) -> dict[str, Any]:
    if not channel:
        return {}
    r = subprocess.run(
        ["ip", "-s", "-s", "-j", "link", "show", channel], capture_output=True, text=True
    )
    if r.returncode != 0:
        return {"error": r.stderr.strip()}
    data = json.loads(r.stdout)[0]
    return {"stats64": data.get("stats64"), "txqlen": data.get("txqlen")}


def can_stats() -> str | None:
    try:
        return _read("/proc/net/can/stats")
    except OSError:
        return None


FRAMES_RCVBUF = 4 << 20  # a second of any id's frames, many times over
FRAMES_EVERY_S = 0.5  # read in batches: no wake per frame on CPU 1, where the simulator runs


class FrameTap:
    """One id's frames on the bus during the window, as the kernel's ``struct can_frame``s
    (16 bytes each), for the host to decode (benchmarks/board/setpoints.py): what the
    set-points carried, read by a reader of its own, not only how many there were."""

    def __init__(self, channel: str, can_id: int) -> None:
        self.sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        self.sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, b"")  # none until ``watch``
        with contextlib.suppress(OSError):  # SO_RCVBUFFORCE (root): past rmem_max
            self.sock.setsockopt(socket.SOL_SOCKET, 33, FRAMES_RCVBUF)
        self.sock.bind((channel,))
        self.sock.setblocking(False)
        self.can_id, self.got = can_id, bytearray()

    def drain(self) -> None:
        with contextlib.suppress(BlockingIOError):
            while True:
                self.got += self.sock.recv(16)

    def watch(self, seconds: float) -> None:
        """Sleep the window, reading what queued every FRAMES_EVERY_S (standard data frames
        of the id, from now: nothing queued before to read at the window's edge)."""
        rule = struct.pack("=II", self.can_id, 0x7FF | 3 << 30)  # | CAN_EFF_FLAG | CAN_RTR_FLAG
        self.sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, rule)
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            time.sleep(min(left, FRAMES_EVERY_S))
            self.drain()

    def result(self) -> dict[str, Any]:
        self.drain()
        self.sock.close()
        return {
            "id": self.can_id,
            "n": len(self.got) // 16,
            "b64": base64.b64encode(self.got).decode(),
        }


CALIBRATION_LOOPS = 200_000


def calibrate() -> float:
    """CPU ms this interpreter takes for a fixed pure-Python loop: how fast this CPU runs Python
    right now. Runs of the same code on the proxy differed by ~30 % from one boot to the next
    (the host's speed drifts); dividing by this puts them on one scale. CPU time, not wall:
    a loop sharing its CPU with the simulator takes as much CPU either way."""
    t0 = time.thread_time()
    acc = 0
    for i in range(CALIBRATION_LOOPS):
        acc += i * i % 7
    return round((time.thread_time() - t0) * 1e3, 2)


def snapshot(pids: dict[str, int], channel: str, pss: bool = True) -> dict[str, Any]:
    return {
        "t": time.monotonic(),
        "procs": {name: process(pid, pss) for name, pid in pids.items()},
        "cpu": cpu_times(),
        "link": link(channel),
        "can_stats": can_stats(),
    }


def _delta64(a: dict[str, Any], b: dict[str, Any]) -> dict[str, int]:
    out: dict[str, int] = {}
    for side in ("rx", "tx"):
        x, y = (a.get("stats64") or {}).get(side, {}), (b.get("stats64") or {}).get(side, {})
        for k, v in y.items():
            if isinstance(v, int) and isinstance(x.get(k), int):
                out[f"{side}_{k}"] = v - x[k]
    return out


def compare(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    wall = b["t"] - a["t"]
    procs = {}
    for name, p0 in a["procs"].items():
        p1 = b["procs"].get(name)
        if p0 is None or p1 is None or p0["start_ticks"] != p1["start_ticks"]:
            procs[name] = {"pid": (p0 or p1 or {}).get("pid"), "error": "restarted or gone"}
            continue
        procs[name] = {
            "pid": p1["pid"],
            "cpu_pct": round(100.0 * (p1["cpu_ticks"] - p0["cpu_ticks"]) / CLK / wall, 2),
            "pss_mb": None if p1["pss_kb"] is None else round(p1["pss_kb"] / 1024, 1),
            "rss_mb": None if p1["rss_kb"] is None else round(p1["rss_kb"] / 1024, 1),
            "threads": p1["threads"],
            "thread_cpu_pct": {
                t: round(100.0 * (v - p0["thread_ticks"].get(t, 0)) / CLK / wall, 2)
                for t, v in sorted(p1["thread_ticks"].items())
                if v - p0["thread_ticks"].get(t, 0) > 0
            },
            "switches_per_s": round((p1["switches"] - p0["switches"]) / wall),
            "nice": p1["nice"],
            "policy": {0: "other", 1: "fifo", 2: "rr", 3: "batch", 5: "idle"}.get(
                p1["policy"], p1["policy"]
            ),
            "cpus_allowed": sorted(set(p0["cpus_allowed"]) | set(p1["cpus_allowed"])),
            "autogroup": p1.get("autogroup"),
        }
    cpus = {
        name: idle_pct(vals, b["cpu"][name]) for name, vals in a["cpu"].items() if name in b["cpu"]
    }
    return {
        "wall_s": round(wall, 2),
        "t0_monotonic": a["t"],
        "t1_monotonic": b["t"],
        "processes": procs,
        "idle_pct": cpus,
        "link_delta": _delta64(a["link"], b["link"]),
        "link_end": b["link"],
        "can_stats_start": a["can_stats"],
        "can_stats_end": b["can_stats"],
    }


def _systemd_main_pid(unit: str) -> int:
    r = subprocess.run(
        ["systemctl", "show", "-p", "MainPID", "--value", unit], capture_output=True, text=True
    )
    return int(r.stdout.strip() or 0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--pid", type=int, help="the supervisor's pid")
    who.add_argument("--unit", help="the systemd unit whose main process is the supervisor")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--channel", default="", help="CAN link to count frames on (vcan0)")
    p.add_argument("--nodes", default="", help="configured node names, comma-separated")
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        metavar="ID",
        help="keep this id's frames on --channel during the window (in the result, base64)",
    )
    p.add_argument(
        "--go",
        action="store_true",
        help="print PROBE_READY once started and calibrated, and begin the window only when a "
        "line comes on stdin: the interpreter's start and the calibration (seconds of CPU 1 "
        "on the proxy) then happen before the load, not at the window's edge",
    )
    args = p.parse_args()
    sup = args.pid if args.pid else _systemd_main_pid(args.unit)
    if not sup:
        sys.stdout.write(json.dumps({"error": f"no main pid for {args.unit}"}) + "\n")
        return 1
    nodes = [n for n in args.nodes.split(",") if n]
    calibration_ms = calibrate()
    tap = FrameTap(args.channel, args.frames) if args.frames is not None and args.channel else None
    if args.go:
        sys.stdout.write("PROBE_READY\n")
        sys.stdout.flush()
        sys.stdin.readline()
    # At the window's start: a node restarted between the probe's start and the word (a
    # hung-kill at the arm) is then measured, not lost from the table.
    pids = find_appliance(sup, nodes)
    first = snapshot(pids, args.channel, pss=False)
    sys.stdout.write(f"PROBE_T0 {json.dumps(sorted(pids))}\n")
    sys.stdout.flush()
    if tap is not None:
        tap.watch(args.seconds)
    else:
        time.sleep(args.seconds)
    second = snapshot(pids, args.channel)
    out = compare(first, second)
    if tap is not None:
        out["frames"] = tap.result()
    out["pids"] = pids
    out["calibration_ms"] = calibration_ms
    out["nodes_now"] = sorted(find_appliance(sup, nodes))
    sys.stdout.write("PROBE_RESULT " + json.dumps(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
