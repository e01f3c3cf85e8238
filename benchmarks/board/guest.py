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
- Each ssh login (key exchange, PAM session, logind) stalled CPU 0 although sshd runs on CPU 1;
  commands sent over one connection opened after boot did not: every ssh here shares it
  (OpenSSH connection multiplexing).
"""

from __future__ import annotations

import contextlib
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
    def __init__(self, card: Card, work: Path, ssh_key: Path, journal_console: bool) -> None:
        self.card, self.work, self.ssh_key = card, work, ssh_key
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
        log.info("qemu started", zenoh_port=self.zenoh_port, ssh_port=self.ssh_port)
        return self.console

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
