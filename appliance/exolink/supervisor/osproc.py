"""What the kernel says and does about the node processes: priorities (nice, SCHED_FIFO,
affinity) per thread, /proc reads (state, usage, children), and the sweep of stray node
processes. No psutil on a 512 MB board: /proc is read directly."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Callable

import structlog

from exolink.config import NodeConfig


def plain_priority(pid: int) -> None:
    """A node imports and configures at plain priority; its configured one comes with its first
    heartbeat. Under emulation a SCHED_FIFO node importing for seconds starved the supervisor
    until systemd's watchdog killed it; on the board's single core that would be the same."""
    with contextlib.suppress(OSError):  # already lower (a niced supervisor): leave it
        os.setpriority(os.PRIO_PROCESS, pid, max(0, os.getpriority(os.PRIO_PROCESS, 0)))


def _threads(pid: int) -> list[int]:
    """Scheduling is per thread in Linux; a running node has Zenoh's threads besides its own."""
    try:
        return sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return [pid]


def apply_priority(cfg: NodeConfig, pid: int) -> None:
    """Nice / SCHED_FIFO / affinity as configured, on every thread of the node; a clear warning
    where not permitted."""
    log = structlog.get_logger().bind(node=cfg.name)
    pr = cfg.priority
    tids = _threads(pid)
    try:
        for tid in tids:
            with contextlib.suppress(ProcessLookupError):  # ended meanwhile: skip it, not the rest
                if pr.fifo is not None:
                    os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(pr.fifo))
                elif pr.nice is not None:
                    os.setpriority(os.PRIO_PROCESS, tid, pr.nice)
    except PermissionError:
        log.warning(
            "priority_not_permitted",
            fifo=pr.fifo,
            nice=pr.nice,
            fix="run the supervisor with CAP_SYS_NICE (the systemd unit grants it)",
        )
    except OSError as exc:
        log.warning("priority_failed", error=str(exc))
    if pr.cpus:
        try:
            for tid in tids:
                with contextlib.suppress(ProcessLookupError):
                    os.sched_setaffinity(tid, pr.cpus)
        except OSError as exc:
            log.warning("affinity_failed", cpus=pr.cpus, error=str(exc))


_CLK = os.sysconf("SC_CLK_TCK")
_PAGE = os.sysconf("SC_PAGE_SIZE")


def proc_state(pid: int) -> str:
    """The kernel's word on a process (``State:`` and ``wchan``), for a stop that hangs."""
    try:
        with open(f"/proc/{pid}/status") as f:
            state = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("State:")), "?")
        with open(f"/proc/{pid}/wchan") as f:
            return f"{state}, wchan {f.read().strip() or '-'}"
    except OSError as exc:
        return f"gone ({exc.strerror})"


def thread_state(pid: int, tid: int | None = None) -> str:
    """A thread's state letter (R: runnable; S, D, T: not) from its ``stat``, by raw system
    calls (read at each late look at a node); OSError: gone."""
    fd = os.open(
        f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat", os.O_RDONLY
    )
    try:
        return os.read(fd, 1024).rpartition(b")")[2].split()[0].decode()
    finally:
        os.close(fd)


def runnable_others(pid: int) -> tuple[int, int]:
    """How many of a process's other threads are runnable, of how many: a loop asleep in a
    futex while one is says it waits for that thread (the GIL), not that it hung."""
    runnable = total = 0
    with contextlib.suppress(OSError):
        for tid in os.listdir(f"/proc/{pid}/task"):
            if tid == str(pid):
                continue
            with contextlib.suppress(OSError, IndexError):
                runnable += thread_state(pid, int(tid)) == "R"
                total += 1
    return runnable, total


def children(pid: int, leader_only: bool = False) -> dict[int, tuple[str, str]]:
    """Every child of ``pid`` -> (state letter, comm), from each of its threads' list: a
    subreaper's orphans are re-parented to one of its threads. ``leader_only``: the main
    thread's list alone, where the kernel re-parents them while it lives (its first live
    thread): one read instead of one per thread (~50 in the supervisor)."""
    out: dict[int, tuple[str, str]] = {}
    try:
        tasks = [str(pid)] if leader_only else os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                kids = [int(c) for c in f.read().split()]
        except OSError:
            continue
        for kid in kids:
            try:
                with open(f"/proc/{kid}/stat") as f:
                    head, _, rest = f.read().rpartition(")")
                out[kid] = (rest.split()[0], head.partition("(")[2])
            except (OSError, IndexError):
                continue  # gone meanwhile
    return out


NODE_COMM = "exo-"  # a forked node's process name (exolink.zygote.set_comm)


def kill_strays(known: Callable[[], set[int]], leader_only: bool = False) -> list[tuple[int, str]]:
    """Node processes among this process' children that no node counts as its own (and the
    zombies of such), killed and reaped: a node process the supervisor does not watch must not
    run. ``known`` is asked after the children are listed, so a node forked meanwhile is
    either not listed yet or already known. ``leader_only``: see ``children``."""
    kids = children(os.getpid(), leader_only)
    mine = known()
    strays = []
    for pid, (state, name) in kids.items():
        if pid in mine or not name.startswith(NODE_COMM):
            continue
        if state not in ("Z", "X"):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
            strays.append((pid, name))
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)
    return strays


def proc_usage(pid: int) -> dict[str, float]:
    """CPU seconds and resident memory from /proc (no psutil on a 512 MB board)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        with open(f"/proc/{pid}/statm") as f:
            rss_pages = int(f.read().split()[1])
    except (OSError, IndexError, ValueError):
        return {}
    cpu = (int(fields[11]) + int(fields[12])) / _CLK
    return {"cpu_s": round(cpu, 2), "rss_mb": round(rss_pages * _PAGE / 2**20, 1)}
