"""CPU per thread over time in the appliance's cgroup, for the seconds a window's averages hide.

Why: under a CPU cap the watchdog trips at the load's start (arm, the pattern's start, the
laptop's sessions), never in a steady window, and the probe's 60 s averages cannot say who took
the core then. Runs in the guest like the probe (stdlib only, on CPU 1): every ``--every``
seconds it writes one JSON line with each thread's cumulative CPU ticks (utime + stime), its
nice, and the cgroup's throttling counters, until killed. The host turns the lines into
per-second shares with :func:`summarize`.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from typing import Any

CLK = os.sysconf("SC_CLK_TCK")


def _read(path: str) -> str:
    with open(path) as f:
        return f.read()


def _stat(path: str) -> tuple[str, int, int] | None:
    """(comm, utime + stime ticks, nice) of a /proc/.../stat; None when it is gone."""
    try:
        stat = _read(path)
    except OSError:
        return None
    f = stat.rsplit(")", 1)[1].split()
    return stat[stat.index("(") + 1 : stat.rindex(")")], int(f[11]) + int(f[12]), int(f[16])


def _add(out: dict[str, list[int]], key: str, ticks: int, nice: int) -> None:
    """Ticks of the same name summed (threads of one name, processes of one comm)."""
    old = out.get(key)
    out[key] = [ticks + (old[0] if old else 0), nice]


def _procs(cgroup: str) -> list[str]:
    try:
        return _read(f"{cgroup}/cgroup.procs").split()
    except OSError:
        return []


def _threads(pids: list[str]) -> dict[str, list[int]]:
    """``"proc/thread": [ticks, nice]`` for every thread of these processes (the cgroup's); a
    thread's name is its comm (Zenoh's rx-0, app-0, ...; the node's own thread is the process's)."""
    out: dict[str, list[int]] = {}
    for pid in pids:
        try:
            proc = _read(f"/proc/{pid}/comm").strip()
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            continue
        for tid in tids:
            if (st := _stat(f"/proc/{pid}/task/{tid}/stat")) is not None:
                comm, ticks, nice = st
                _add(out, f"{proc}/{comm}" if comm != proc else proc, ticks, nice)
    return out


def _throttling(cgroup: str) -> dict[str, int]:
    try:
        text = _read(f"{cgroup}/cpu.stat")
    except OSError:
        return {}
    keep = ("usage_usec", "nr_periods", "nr_throttled", "throttled_usec")
    return {k: int(v) for k, v in (ln.split() for ln in text.splitlines()) if k in keep}


Procs = dict[str, tuple[str, int, int]]  # pid -> (comm, ticks, nice): a walk of /proc


def walk() -> Procs:
    """Every process's stat (a walk of all /proc: at every 0.25 s sample it took 35-100 % of
    CPU 1 under TCG, where the simulator runs; E63)."""
    out: Procs = {}
    for pid in os.listdir("/proc"):
        if pid.isdigit() and (st := _stat(f"/proc/{pid}/stat")):
            out[pid] = st
    return out


def _name(comm: str) -> str:
    """A kworker's comm without its work suffix (the work varies), any other as it is."""
    return comm.split("-")[0] if comm.startswith("kworker") else comm


def _others(procs: Procs, inside: set[str]) -> dict[str, list[int]]:
    """Every process but ``inside`` (the cgroup's) by comm, summed (ksoftirqd/0, systemd,
    sshd, ...): CPU 0 busy while the appliance is throttled below its quota is theirs or the
    kernel's."""
    out: dict[str, list[int]] = {}
    for pid, (comm, ticks, nice) in procs.items():
        if pid not in inside:
            _add(out, "~" + _name(comm), ticks, nice)
    return out


# Kernel threads and system daemons read at every sample (found at each walk), named ``^comm``:
# the stop's stalls had CPU 0 busy with system time that no appliance thread held (F66, J67,
# D68, H68), and a walk every 2 s is too coarse to say whose it was.
WATCH = ("ksoftirqd/0", "kworker/0", "kworker/u", "rcu", "migration/0", "systemd-journal", "jbd2")


def watched(procs: Procs) -> list[str]:
    """The pids of a walk to read at every sample (``WATCH``)."""
    return [pid for pid, (comm, _, _) in procs.items() if comm.startswith(WATCH)]


def _kernel(pids: list[str]) -> dict[str, list[int]]:
    """``"^comm": [ticks, nice]`` of the watched pids."""
    out: dict[str, list[int]] = {}
    for pid in pids:
        if (st := _stat(f"/proc/{pid}/stat")) is not None:
            comm, ticks, nice = st
            _add(out, "^" + _name(comm), ticks, nice)
    return out


def _cpu0() -> list[int]:
    """CPU 0's ticks: user nice system idle iowait irq softirq (/proc/stat)."""
    for line in _read("/proc/stat").splitlines():
        if line.startswith("cpu0 "):
            return [int(x) for x in line.split()[1:8]]
    return []


def _irqs0() -> dict[str, int]:
    """CPU 0's interrupt counts by source (/proc/interrupts: its first count column), those
    taken at all: which device's interrupts the board's core handled between two samples
    (kernel time over the idle task shows in no thread's counters)."""
    out: dict[str, int] = {}
    for line in _read("/proc/interrupts").splitlines()[1:]:
        parts = line.split()
        if len(parts) > 2 and parts[1].isdigit() and int(parts[1]):
            name = parts[0].rstrip(":")
            out[f"{name} {parts[-1]}" if not name.isalpha() else name] = int(parts[1])
    return out


def sample(
    cgroup: str, procs: Procs | None = None, watch: list[str] | None = None
) -> dict[str, Any]:
    """``procs``: a ``walk`` to add the processes outside the cgroup from; ``watch``: pids read
    at every sample (``watched``)."""
    pids = _procs(cgroup)
    return {
        "wall": time.time(),
        "mono": time.monotonic(),
        "threads": _threads(pids)
        | (_others(procs, set(pids)) if procs is not None else {})
        | _kernel(watch or []),
        "cpu_stat": _throttling(cgroup),
        "cpu0": _cpu0(),
        "irqs0": _irqs0(),
    }


def summarize(lines: list[str], top: int = 6) -> list[dict[str, Any]]:
    """Per interval between samples: the cgroup's CPU share and throttled periods, CPU 0's
    idle / irq / softirq, and the ``top`` threads by CPU share (% of one CPU), largest first;
    processes outside the cgroup are named ``~comm`` (all their threads summed; they run on
    either CPU), over the span since the last sample that walked them; the watched kernel
    threads and daemons ``^comm``, per interval (not in the cgroup's share). Threads that appear
    between samples (a node restarted) count from zero."""
    samples = [json.loads(ln) for ln in lines if ln.startswith("{")]
    out = []
    walked = samples[0] if samples else None  # the last sample with the processes outside
    for a, b in itertools.pairwise(samples):
        dt = b["mono"] - a["mono"]
        if dt <= 0:
            continue
        shares = {
            k: 100.0 * (v[0] - a["threads"].get(k, [0])[0]) / CLK / dt
            for k, v in b["threads"].items()
            if k[0] != "~"
        }
        if walked is not None and any(k[0] == "~" for k in b["threads"]):
            span = b["mono"] - walked["mono"]
            shares |= {
                k: 100.0 * (v[0] - walked["threads"].get(k, v)[0]) / CLK / span
                for k, v in b["threads"].items()
                if k[0] == "~"
            }
            walked = b
        best = sorted(((s, k) for k, s in shares.items() if s > 0), reverse=True)[:top]
        sa, sb = a["cpu_stat"], b["cpu_stat"]
        row: dict[str, Any] = {
            "wall": round(b["wall"], 2),
            "cpu_pct": round(sum(s for k, s in shares.items() if s > 0 and k[0] not in "~^"), 1),
            "top": [[k, round(s, 1)] for s, k in best],
        }
        if a.get("cpu0") and b.get("cpu0"):  # CPU 0's idle, irq and softirq shares
            d = [y - x for x, y in zip(a["cpu0"], b["cpu0"], strict=True)]
            row["cpu0"] = {
                k: round(100.0 * d[i] / CLK / dt, 1)
                for k, i in (("idle", 3), ("irq", 5), ("si", 6))
            }
        if "nr_periods" in sa and "nr_periods" in sb:  # a quota's counters, once it is set
            row["usage_pct"] = round((sb["usage_usec"] - sa["usage_usec"]) / 1e4 / dt, 1)
            periods = sb["nr_periods"] - sa["nr_periods"]
            row["throttled"] = f"{sb['nr_throttled'] - sa['nr_throttled']}/{periods}"
        out.append(row)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cgroup", default="/sys/fs/cgroup/system.slice/exolink.service")
    ap.add_argument("--every", type=float, default=0.25)
    ap.add_argument("--others-every", type=int, default=8, help="walk all /proc every N samples")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    watch: list[str] = []
    with open(args.out, "a") as f:
        for n in itertools.count():
            procs = walk() if n % args.others_every == 0 else None
            if procs is not None:
                watch = watched(procs)
            line = sample(args.cgroup, procs, watch)
            f.write(json.dumps(line, separators=(",", ":")) + "\n")
            f.flush()
            time.sleep(args.every)


if __name__ == "__main__":
    sys.exit(main())
