"""The bench copy of the card booted under qemu-system-arm (TCG): console, ports, ssh.

Same machine as tests/image/test_built_image.py: ``-M virt -cpu cortex-a15 -smp 2 -m 512``,
the card's own armmp kernel and initrd, the card as a virtio disk; user networking forwards the
Zenoh port and ssh to 127.0.0.1. This runs on the host (the guest gets the wheel, probe.py and
estop.py), so its ports come from the harness's ``free_port``.

Two artifacts of the emulator, not of a board, stalled the guest's CPU 0 for 50-250 ms and tripped
the stock 50 ms deadline (seen with QEMU 7.2, ftrace in the guest and ``info jit``):
- TCG's translated-code buffer (1 GiB by default) holds ~0.96 GiB at the window's start (the boot's
  wheel install and nine Python processes' code) and filled minutes later (6 min after boot in a
  guest with ssh logins, ~40 MB each); its flush stops every vCPU while the hot
  code is translated again: ``TB_SIZE_MB`` holds a whole run, and the monitor's flush count is
  read before the load and after it (``jit``; never during: it stalls the guest too).
- Time the vCPU that is the board's CPU 0 does not run is charged by the guest to the task it
  was running, and under a 50 % quota the cgroup then owes it: every node at zero CPU over an
  idle core for twice as long (H67: 37 of 37 periods throttled with 0 usage). ``CoreSampler``
  follows the vCPU's host scheduling every 50 ms; a stretch the guest counts as busy while the
  host neither ran the vCPU nor had it waiting for a core is a stall inside qemu: the
  monitor's ``info jit`` (C67: 0.45 s at 0-13 % run; H67: 0.8 s), so the cap is set after
  the first read and the second comes once the service is stopped. Host cores taken by the
  laptop show as the vCPU waiting (1-3 % over a run). ``own_core`` gives that vCPU host CPU 0
  at nice -20 (``board_core``): tried once (A66), the calibration was 14 % slower and the
  window tripped anyway, so it is an option, not the default.
- Each ssh login (key exchange, PAM session, logind) stalled CPU 0 although sshd runs on CPU 1;
  commands sent over one connection opened after boot did not: every ssh here shares it
  (OpenSSH connection multiplexing).
"""

from __future__ import annotations

import bisect
import contextlib
import itertools
import os
import re
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import structlog

from benchmarks.board.card import Card
from benchmarks.harness import free_port

log = structlog.get_logger("bench-board")

ROOT_PARTUUID = "45786f6c-02"
# TCG's largest on an x86-64 host (it caps more to 2 GiB): mapped, touched as used; ~0.96 GiB at
# the window's start, ~7-18 MB a minute during it
TB_SIZE_MB = 2048


class Console:
    """qemu's serial console, read in a thread, each line with seconds since qemu started."""

    def __init__(self, proc: subprocess.Popen[bytes], t0: float, path: Path) -> None:
        self.proc, self.t0, self.path = proc, t0, path
        self.lines: list[tuple[float, str]] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        """Also written as it comes, so a boot can be followed (tail -f) while the bench runs."""
        assert self.proc.stdout is not None
        with open(self.path, "w") as f:
            for raw in self.proc.stdout:
                t, line = time.monotonic() - self.t0, raw.decode(errors="replace").rstrip()
                self.lines.append((t, line))
                f.write(f"{t:7.1f} {line}\n")
                f.flush()

    def first(self, pattern: str) -> float | None:
        rx = re.compile(pattern)
        return next((t for t, line in list(self.lines) if rx.search(line)), None)

    def grep(self, pattern: str) -> list[str]:
        rx = re.compile(pattern)
        return [f"{t:7.1f} {line}" for t, line in list(self.lines) if rx.search(line)]


class Guest:
    def __init__(
        self, card: Card, work: Path, ssh_key: Path, journal_console: bool, own_core: bool = False
    ) -> None:
        self.card, self.work, self.ssh_key = card, work, ssh_key
        self.own_core = own_core
        self.core: dict[str, Any] = {"own": False}  # what board_core found and did
        self.zenoh_port, self.ssh_port = free_port(), free_port()
        # short paths: a unix socket's is limited to 107 bytes, and the work dir may be deep
        self._sockets = Path(tempfile.mkdtemp(prefix="exo-bench-"))
        self.monitor = self._sockets / "monitor"
        for name in ("vmlinuz", "initrd.img"):  # slot A's (A/B cards), else the FAT's (older)
            try:
                card.root_dump(f"/boot/exolink/{name}", work / name)
            except (subprocess.CalledProcessError, RuntimeError):
                (work / name).write_bytes(card.fat_read(name))
        append = (
            f"root=PARTUUID={ROOT_PARTUUID} rootwait console=ttyAMA0 systemd.show_status=1 "
            "rauc.slot=A"
        )
        fwd = (
            f"hostfwd=tcp:127.0.0.1:{self.zenoh_port}-:7447,"
            f"hostfwd=tcp:127.0.0.1:{self.ssh_port}-:22"
        )
        self.cmd = [
            "qemu-system-arm",
            "-name",
            "exolink-board,debug-threads=on",  # threads named: "CPU 0/TCG" is the board's core
            "-M",
            "virt",
            "-accel",
            f"tcg,tb-size={TB_SIZE_MB}",
            "-cpu",
            "cortex-a15",
            "-smp",
            "2",
            "-m",
            "512",
            "-nographic",
            "-no-reboot",
            "-kernel",
            str(work / "vmlinuz"),
            "-initrd",
            str(work / "initrd.img"),
            "-append",
            append,
            "-drive",
            f"file={card.img},format=raw,if=none,id=card",
            "-device",
            "virtio-blk-device,drive=card",
            "-netdev",
            f"user,id=net,{fwd}",
            "-device",
            "virtio-net-device,netdev=net",
            "-monitor",
            f"unix:{self.monitor},server,nowait",
        ]
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def at(self) -> str:
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    def start(self) -> Console:
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(
            self.cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
        )
        self.console = Console(self.proc, self.t0, self.work / "console.log")
        self.core = board_core(self.proc.pid, self.own_core)
        log.info("qemu started", zenoh_port=self.zenoh_port, ssh_port=self.ssh_port, **self.core)
        return self.console

    def core_cpu_s(self) -> float | None:
        """The host CPU time the board's vCPU thread has had (s): against the guest's own
        count of CPU 0's busy time, what the host took from the board."""
        tid = self.core.get("tid")
        if tid is None or self.proc is None:
            return None
        return thread_cpu_s(self.proc.pid, tid)

    def core_sampler(self) -> CoreSampler | None:
        """The vCPU's host scheduling sampled from now on (CoreSampler), if it was found."""
        tid = self.core.get("tid")
        if tid is None or self.proc is None:
            return None
        return CoreSampler(self.proc.pid, tid, self.work / "vcpu0-schedstat.txt").start()

    def clock_ahead_s(self) -> float | None:
        """How far the guest's wall clock is ahead of the host's (s, +- half an ssh round
        trip): to put the guest journal's times beside CoreSampler's."""
        t0 = time.time()
        r = self.ssh("date +%s.%N")
        t1 = time.time()
        try:
            return round(float(r.stdout.strip()) - (t0 + t1) / 2, 3)
        except ValueError:
            return None

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def ssh_cmd(self, remote: str) -> list[str]:
        return [*self._ssh_options(), "root@127.0.0.1", remote]

    def _ssh_options(self) -> list[str]:
        return [
            "ssh",
            "-i",
            str(self.ssh_key),
            "-p",
            str(self.ssh_port),
            "-o",
            "StrictHostKeyChecking=no",
            "-o",
            "UserKnownHostsFile=/dev/null",
            "-o",
            "LogLevel=ERROR",
            "-o",
            "BatchMode=yes",
            "-o",
            "ConnectTimeout=60",
            "-o",
            "ControlMaster=auto",  # the first connection stays open; later ones ride on it
            "-o",
            f"ControlPath={self._sockets}/ssh",
            "-o",
            "ControlPersist=yes",
        ]

    def ssh(self, remote: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
        return subprocess.run(self.ssh_cmd(remote), capture_output=True, text=True, timeout=timeout)

    def upload(self, local: Path, remote: str) -> None:
        """Copy a file to the guest (the probe and unit scripts, a recording to fetch)."""
        with open(local, "rb") as f:
            subprocess.run(self.ssh_cmd(f"cat > {remote}"), stdin=f, check=True, timeout=600)

    def jit(self) -> dict[str, Any]:
        """TCG's translation counters from the monitor's ``info jit`` (``flushes``: times the
        code buffer was emptied, each a stall of the whole guest), or ``error``."""
        text = ""
        try:
            with socket.socket(socket.AF_UNIX) as s:
                s.settimeout(5)
                s.connect(str(self.monitor))
                s.sendall(b"info jit\n")
                while not re.search(r"TB flush count\s+\d+\s*\n", text):
                    if not (chunk := s.recv(65536)):
                        break
                    text += chunk.decode(errors="replace")
        except OSError as exc:
            return {"error": f"qemu monitor: {exc}"}
        out: dict[str, Any] = {}
        for key, rx in (
            ("code_bytes", r"gen code size\s+(\d+)/(\d+)"),
            ("tbs", r"TB count\s+(\d+)"),
            ("flushes", r"TB flush count\s+(\d+)"),
        ):
            if m := re.search(rx, text):
                out[key] = int(m.group(1))
                if key == "code_bytes":
                    out["buffer_bytes"] = int(m.group(2))
        return out or {"error": "qemu monitor: no 'info jit' answer"}

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(OSError, subprocess.SubprocessError):
                subprocess.run(
                    [*self._ssh_options(), "-O", "exit", "root@127.0.0.1"],
                    capture_output=True,
                    timeout=10,
                )
            self.proc.kill()
            self.proc.wait()
        shutil.rmtree(self._sockets, ignore_errors=True)


VCPU0 = "CPU 0/TCG"  # qemu's name for the board's core's thread (-name debug-threads=on)
HOST_CORE = 0


def board_core(pid: int, own: bool, wait_s: float = 10.0) -> dict[str, Any]:
    """The board's vCPU thread found; ``own``: on host CPU ``HOST_CORE`` at nice -20, so the
    laptop and qemu's other threads use that core only while the board's CPU 0 idles (a halted
    vCPU sleeps). Everything else keeps both host cores."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        for task in Path(f"/proc/{pid}/task").glob("*"):
            with contextlib.suppress(OSError):
                if (task / "comm").read_text().strip() == VCPU0:
                    tid = int(task.name)
                    if not own:
                        return {"own": False, "tid": tid}
                    os.sched_setaffinity(tid, {HOST_CORE})
                    os.setpriority(os.PRIO_PROCESS, tid, -20)
                    return {"own": True, "tid": tid, "host_cpu": HOST_CORE, "nice": -20}
        time.sleep(0.05)
    log.warning("the board's vCPU thread not found: it shares the host's cores", name=VCPU0)
    return {"own": False, "error": f"no thread named {VCPU0!r} in qemu {pid}"}


def thread_cpu_s(pid: int, tid: int) -> float | None:
    """utime + stime of one thread (/proc/<pid>/task/<tid>/stat, in clock ticks)."""
    try:
        stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class CoreSampler:
    """The board's vCPU as the host scheduled it, every ``every_s`` into ``path`` (host wall
    time, then the thread's run and runqueue-wait ns from its schedstat, then the run ns of
    qemu's main thread: its main loop, where the guest's network (user networking) and its
    timers' host side are served).

    Why: the guest charges CPU 0's busy time to whatever it ran, so a stretch in which the host
    did not run the vCPU (a laptop CLI's start, qemu's network thread) looks to the watchdog like
    a node that stopped. F66's and K66's stops tripped on the h2 reader with CPU 0 ~0.4 s busy
    and no thread holding the time; this says whether the host had the vCPU waiting then."""

    def __init__(self, pid: int, tid: int, path: Path, every_s: float = 0.05) -> None:
        self.file = Path(f"/proc/{pid}/task/{tid}/schedstat")
        self.main = Path(f"/proc/{pid}/task/{pid}/schedstat")
        self.path, self.every_s = path, every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="vcpu0-sampler")

    def start(self) -> CoreSampler:
        self._thread.start()
        return self

    def _run(self) -> None:
        with open(self.path, "w", buffering=1) as out:  # lines readable as written (points)
            while not self._stop.wait(self.every_s):
                try:
                    run_ns, wait_ns, _ = self.file.read_text().split()
                    main_ns = self.main.read_text().split()[0]
                except (OSError, ValueError, IndexError):
                    return
                out.write(f"{time.time():.3f} {run_ns} {wait_ns} {main_ns}\n")

    def points(self) -> list[tuple[float, int, int, int]]:
        """The samples so far: (host wall time, run ns, runqueue-wait ns, main loop run ns)."""
        rows = (ln.split() for ln in self.path.read_text().splitlines())
        return [(float(t), int(r), int(w), int(m)) for t, r, w, m in rows]

    def stop(self, worst: int = 8, span_s: float = 0.5) -> dict[str, Any]:
        """Totals, and the ``worst`` stretches of ``span_s`` by the share the vCPU waited."""
        self._stop.set()
        self._thread.join(2)
        pts = self.points()
        if len(pts) < 2:
            return {"error": "no samples"}
        a, b = pts[0], pts[-1]
        out: dict[str, Any] = {
            "samples": str(self.path),
            "run_pct": _share(a, b, RUN),
            "waited_pct": _share(a, b, WAITED),
            "qemu_main_pct": _share(a, b, MAIN),
        }
        step = max(1, round(span_s / self.every_s))
        spans = [
            (
                _share(a, b, WAITED),
                _share(a, b, RUN),
                time.strftime("%H:%M:%S", time.gmtime(a[0])) + f"{a[0] % 1:.2f}"[1:],
            )
            for a, b in itertools.pairwise(pts[::step])
        ]
        out["worst"] = [
            {"at_utc": at, "waited_pct": w, "ran_pct": r} for w, r, at in sorted(spans)[-worst:]
        ]
        return out


RUN, WAITED, MAIN = 1, 2, 3  # CoreSampler's columns after the wall time


def _share(a: tuple[float, ...], b: tuple[float, ...], column: int) -> float:
    """A column's ns between two samples as % of the wall time between them."""
    return round((b[column] - a[column]) / 1e7 / (b[0] - a[0]), 1)


def ran_pct(
    points: list[tuple[float, int, int, int]], t0: float, t1: float, column: int = RUN
) -> float | None:
    """The share of host wall time ``t0``..``t1`` the vCPU ran (CoreSampler's ``points``;
    ``column`` MAIN: qemu's main loop; None without two samples in it). Beside the guest's own
    count of CPU 0 busy, a stretch the guest calls busy that the host did not run is the
    host's (qemu's lock, say)."""
    i, j = bisect.bisect_left(points, (t0,)), bisect.bisect_right(points, (t1, 1 << 62))
    if j - i < 2 or points[j - 1][0] <= points[i][0]:
        return None
    return _share(points[i], points[j - 1], column)
