"""The bench's copy of the built SD card: the checkout's wheel, vcan0, CPU pinning, a login.

Nothing here touches the built image: it is copied (sparse) and only the copy is edited, the FAT
partition with mtools and the ext4 root with debugfs at its byte offset (no loop devices, as in
tests/image/test_built_image.py). The copy gets, and a flashed card never has:

- ``bench/`` on the FAT partition: the checkout's pure-Python wheel; ``install.sh``, which an
  ``exolink-setup.service`` drop-in runs before the card's settings are applied (``pip install
  --no-deps --force-reinstall`` into /opt/exolink's venv); ``prep.sh``, which
  ``exolink-bench.service`` runs before the supervisor: vcan0 (modprobe vcan can-bcm);
- the checkout's ``exolink.service`` (its rights and system-call filter go with its code) and a
  drop-in: requires that unit and sets ``CPUAffinity=0``;
- ``/etc/exolink/appliance.yaml``: the bench config (scenario.bench_config);
- root's authorized_keys for the bench's throwaway ssh key, and a known Zenoh password.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog
import yaml

from exolink import config

log = structlog.get_logger("bench-board")

MIB = 1 << 20
IMAGE_ZENOH_CONFIG = "/etc/exolink/zenoh.json5"  # written by exolink-setup from the card
# bring_up: the supervisor sets vcan0 up through netlink (canlink.bring_up accepts vcan) as it
# does can0 on the board: that imports pyroute2 inside start(), before READY=1. With
# bring_up: false the first import happens in the watchdog-pinged loop instead (_check_bus), and
# under TCG the supervisor missed systemd's 5 s WatchdogSec right after READY on every start.
GUEST_CAN = {
    "interface": "socketcan",
    "channel": "vcan0",
    "bring_up": True,
    "require_overlay": False,
}

INSTALL_SH = """\
#!/bin/sh
# exolink bench (a copy of the card only, never a flashed card): the checkout's exolink, run by
# exolink-setup.service before it applies the card's settings, so that the checkout's boardsetup
# reads them (the image's older one refused a settings file of a newer schema and the board kept
# its old login). Early boot: no /tmp yet.
set -eu
export TMPDIR=/run
out=/run/exolink-bench-installed
: > "$out"
# Pinned dependencies the checkout has and the image predates (armv7 wheels fetched by the host).
if ls /boot/firmware/bench/deps/*.whl >/dev/null 2>&1; then
  /opt/exolink/bin/pip install -q --no-deps --no-index --no-cache-dir /boot/firmware/bench/deps/*.whl
  ls /boot/firmware/bench/deps >> "$out"
fi
for w in /boot/firmware/bench/*.whl; do
  /opt/exolink/bin/pip install -q --no-deps --no-index --no-cache-dir --force-reinstall "$w"
  sha256sum "$w" >> "$out"
done
/opt/exolink/bin/python -c 'import exolink, importlib.metadata as m
print("exolink", m.version("exolink"), exolink.__file__)' >> "$out"
cat "$out"
"""

PREP_SH = """\
#!/bin/sh
# exolink bench (a copy of the card only, never a flashed card): the bench's CAN bus, before
# exolink.service starts.
set -eu
modprobe vcan
modprobe can_raw
modprobe can_bcm
ip link show vcan0 >/dev/null 2>&1 || ip link add vcan0 type vcan
ip link set vcan0 up
cat /run/exolink-bench-installed
echo "exolink-bench: ready"
"""

SETUP_DROP_IN = """\
# exolink bench (a copy of the card only): the checkout's wheel before the card's settings.
[Service]
ExecStartPre=/bin/sh /boot/firmware/bench/install.sh
TimeoutStartSec=20min
"""

BENCH_UNIT = """\
[Unit]
Description=exolink bench: vcan0 (bench copy of the card only; the wheel: exolink-setup)
After=exolink-setup.service local-fs.target
RequiresMountsFor=/boot/firmware

[Service]
Type=oneshot
RemainAfterExit=yes
ExecStart=/bin/sh /boot/firmware/bench/prep.sh
StandardOutput=journal+console
StandardError=journal+console
TimeoutStartSec=20min
"""

DROP_IN = """\
# exolink bench (a copy of the card only): the checkout's wheel and vcan0 first; the supervisor
# and every node it starts on CPU 0 (the simulator node moves itself to CPU 1: priority.cpus).
# No reboot after repeated failures: the bench reports them and the guest stays up to look at.
[Unit]
Requires=exolink-bench.service
After=exolink-bench.service
StartLimitAction=none

[Service]
CPUAffinity=0
"""
# (appended by prepare() for --timings relaxed: WatchdogSec=)

SSH_DROP_IN = """\
# exolink bench (a copy of the card only): the bench's own commands (scp of the probe, ps,
# journalctl) on CPU 1 with the simulator and the probe, not on the measured CPU 0, and below
# the simulator there: on CPU 1 at nice 0 the journal fetch starved the simulator (H2 silent
# for 100 ms). (The manager's deadline misses after the window stayed: not the bench's ssh.)
[Service]
CPUAffinity=1
Nice=19
IOSchedulingClass=idle
"""


def git(repo: Path, *args: str) -> str:
    r = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True)
    return r.stdout.strip()


def checkout_info(repo: Path) -> dict[str, Any]:
    dirty = [line for line in git(repo, "status", "--porcelain").splitlines() if line]
    return {
        "commit": git(repo, "rev-parse", "HEAD"),
        "describe": git(repo, "describe", "--always", "--dirty"),
        "branch": git(repo, "rev-parse", "--abbrev-ref", "HEAD"),
        "uncommitted_files": dirty,
    }


def find_image(repo: Path, given: str | None) -> Path:
    if given:
        return Path(given)
    found = sorted(
        (repo / "build/image").glob("exolink-bbb-*.img"), key=lambda p: p.stat().st_mtime
    )
    if not found:
        raise SystemExit(
            "no built image in build/image (build/image/exolink-bbb-<version>.img): build it with "
            "`sudo make image` (root, ~20 min from nothing, ~8 min with build/image/cache), "
            "or pass --image PATH"
        )
    return found[-1]


def build_wheel(repo: Path, out: Path) -> Path:
    """The checkout's pure-Python wheel (what ran is what is in the tree, committed or not)."""
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("exolink-*.whl"):
        old.unlink()
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out), str(repo)],
        capture_output=True,
        text=True,
    )
    if r.returncode != 0:
        raise RuntimeError(f"pip wheel failed:\n{r.stdout}{r.stderr}")
    (wheel,) = out.glob("exolink-*.whl")
    return wheel


def _partitions(img: Path) -> list[dict[str, Any]]:
    out = subprocess.run(["sfdisk", "--json", str(img)], capture_output=True, text=True, check=True)
    return list(json.loads(out.stdout)["partitiontable"]["partitions"])


@dataclass
class Card:
    """An image file with its FAT partition (mtools spec) and ext4 root (debugfs spec)."""

    img: Path

    def __post_init__(self) -> None:
        boot, root = _partitions(self.img)[:2]
        self.fat = f"{self.img}@@{boot['start'] * 512}"
        self.root = f"{self.img}?offset={root['start'] * 512}"

    def fat_read(self, name: str) -> bytes:
        r = subprocess.run(["mtype", "-i", self.fat, f"::{name}"], capture_output=True, check=True)
        return r.stdout

    def fat_write(self, local: Path, dest_dir: str = "/") -> None:
        subprocess.run(["mcopy", "-o", "-i", self.fat, str(local), f"::{dest_dir}"], check=True)

    def fat_mkdir(self, name: str) -> None:
        subprocess.run(["mmd", "-D", "s", "-i", self.fat, f"::{name}"], capture_output=True)

    def root_dump(self, path: str, local: Path) -> None:
        """A binary file of the root slot (A) to ``local``."""
        subprocess.run(["debugfs", "-R", f"dump {path} {local}", self.root], capture_output=True,
                       check=True)  # fmt: skip
        if not local.exists() or not local.stat().st_size:
            raise RuntimeError(f"{path} not found in the card's root")

    def root_read(self, path: str) -> str:
        r = subprocess.run(
            ["debugfs", "-R", f"cat {path}", self.root], capture_output=True, text=True, check=True
        )
        return r.stdout

    def root_edit(self, commands: list[str]) -> None:
        """debugfs -w requests; a missing file to remove or an existing dir is not an error."""
        subprocess.run(
            ["debugfs", "-w", "-f", "-", self.root],
            input="\n".join(commands) + "\n",
            text=True,
            check=True,
            capture_output=True,
        )

    def root_names(self, path: str) -> list[str]:
        r = subprocess.run(
            ["debugfs", "-R", f"ls -p {path}", self.root], capture_output=True, text=True
        )
        return [f.split("/")[5] for f in r.stdout.splitlines() if f.count("/") >= 6]

    def group_id(self, name: str) -> int:
        for line in self.root_read("/etc/group").splitlines():
            parts = line.split(":")
            if parts[0] == name:
                return int(parts[2])
        raise KeyError(f"no group {name} in the image")


def copy_card(image: Path, dest: Path) -> Card:
    dest.unlink(missing_ok=True)
    subprocess.run(["cp", "--sparse=always", str(image), str(dest)], check=True)
    # A "bigger card": the first boot grows the data partition, as on a card, enough for the
    # recorder's reserve (256 MiB free) and then some (with less the nominal load's recorder
    # stopped at once, "card full", and recorded nothing).
    with open(dest, "r+b") as f:
        f.truncate(dest.stat().st_size + 1024 * MIB)
    return Card(dest)


def _norm(name: str) -> str:
    return name.lower().replace("-", "_").replace(".", "_")


def missing_pins(card: Card, repo: Path) -> list[str]:
    """Lines of the checkout's image/python-requirements.txt that the card's venv lacks at that
    version: what the wheel under test needs and an older image does not have."""
    (lib,) = [n for n in card.root_names("/opt/exolink/lib") if n.startswith("python3.")] or [
        "python3"
    ]
    have = {}
    for n in card.root_names(f"/opt/exolink/lib/{lib}/site-packages"):
        if n.endswith(".dist-info"):
            name, _, version = n[: -len(".dist-info")].partition("-")
            have[_norm(name)] = version
    out = []
    for line in (repo / "image/python-requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = line.split("==")
            if have.get(_norm(name)) != version:
                out.append(line)
    return out


def download_pins(pins: list[str], dest: Path, python: str = "3.13") -> list[Path]:
    """armv7l / pure-Python wheels of ``pins`` for the card's CPython (as image/build.sh)."""
    dest.mkdir(parents=True, exist_ok=True)
    for old in dest.glob("*.whl"):
        old.unlink()
    if not pins:
        return []
    cp = "cp" + python.replace(".", "")
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:"]
    cmd += ["--python-version", python, "--implementation", "cp", "--abi", cp, "--abi", "abi3"]
    cmd += ["--abi", "none", "--platform", "manylinux_2_17_armv7l"]
    cmd += ["--platform", "manylinux2014_armv7l", "--platform", "any", "-d", str(dest), *pins]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"pip download of {pins} for armv7 failed:\n{r.stderr[-2000:]}")
    return sorted(dest.glob("*.whl"))


def _write_file(card: Card, local: Path, path: str, mode: int, uid: int, gid: int) -> list[str]:
    return [
        f"rm {path}",
        f"write {local} {path}",
        f"sif {path} mode 0{0o100000 | mode:o}",
        f"sif {path} uid {uid}",
        f"sif {path} gid {gid}",
    ]


def admin_password(operator_password: str) -> str:
    return operator_password + "A"


def prepare(
    image: Path,
    work: Path,
    wheel: Path,
    ssh_pubkey: str,
    zenoh_password: str,
    start_grace_ms: int,
    timings: str,
    extra_wheels: tuple[Path, ...] = (),
    env: tuple[str, ...] = (),
    without: tuple[str, ...] = (),
    cpu_quota: int | None = None,
) -> tuple[Card, dict[str, Any]]:
    """The bench copy of ``image`` in ``work``; returns it and the appliance config it runs.
    ``extra_wheels`` (an armv7 py-spy, say) are installed beside exolink, without dependencies.
    ``cpu_quota``: the appliance's service (supervisor, zygote, every node but the simulator's
    CPU 1 work, all in its cgroup) capped at this % of one CPU, enforced every 10 ms
    (CPUQuotaPeriodSec): a budget proven as a hard limit, not read off a share, and no
    throttle lasts longer than 10 ms minus the quota, well inside the 50 ms deadline."""
    work.mkdir(parents=True, exist_ok=True)
    card = copy_card(image, work / "card.img")
    log.info("card copied", image=str(image), copy=str(card.img))

    settings = yaml.safe_load(card.fat_read("exolink-settings.yaml").decode("utf-8-sig"))
    # admin: the ladder starts and stops nodes (benchmarks/board/ladder.py)
    settings["zenoh"] = {
        "logins": ["operator", "admin"],
        "passwords": {"operator": zenoh_password, "admin": admin_password(zenoh_password)},
    }
    settings["ssh"] = {"authorized_keys": [ssh_pubkey], "password": ""}
    settings["simulate"] = False  # --sim would put the bus on udp_multicast: the bench uses vcan0
    (work / "exolink-settings.yaml").write_text(yaml.safe_dump(settings, sort_keys=False))
    card.fat_write(work / "exolink-settings.yaml")
    card.fat_mkdir("bench")
    for name, text in (("prep.sh", PREP_SH), ("install.sh", INSTALL_SH)):
        (work / name).write_text(text)
        card.fat_write(work / name, "/bench/")
    for w in (wheel, *extra_wheels):
        card.fat_write(w, "/bench/")
    pins = missing_pins(card, Path(__file__).resolve().parents[2])
    deps = download_pins(pins, work / "deps")
    if deps:
        card.fat_mkdir("bench/deps")
        for w in deps:
            card.fat_write(w, "/bench/deps/")
    log.info("dependencies the image lacks", pins=pins, wheels=[w.name for w in deps])

    from benchmarks.board.scenario import TIMINGS, bench_config

    # The checkout's board.yaml, not the one baked into the image: the wheel under test ships it
    # (a per-node deadline, say), and the native run uses the same file.
    base = yaml.safe_load(config.bundled("board").read_text())
    # ... with the logins the image enables (image/hooks/customize.sh uncomments this line of
    # board.yaml): without it the guest's router ran open and every laptop login failed
    # Zenoh's handshake ("UsrPwd extension - Recv InitSyn. Decoding error"), which the last
    # stops' runs took for a router too starved to answer.
    base["zenoh"]["config_file"] = IMAGE_ZENOH_CONFIG
    cfg = bench_config(base, GUEST_CAN, start_grace_ms, timings, without)
    text = yaml.safe_dump(cfg, sort_keys=False)
    config.parse(text, "bench appliance.yaml")  # the board would refuse a bad one
    (work / "appliance.yaml").write_text(text)
    (work / "exolink-bench.service").write_text(BENCH_UNIT)
    wd_s = TIMINGS[timings]["systemd_watchdog_s"]
    environment = "".join(f'Environment="{e}"\n' for e in env)  # --guest-env: experiments
    quota = f"CPUQuota={cpu_quota}%\nCPUQuotaPeriodSec=10ms\n" if cpu_quota else ""
    (work / "bench.conf").write_text(
        DROP_IN + (f"WatchdogSec={wd_s}s\n" if wd_s else "") + environment + quota
    )
    (work / "setup-bench.conf").write_text(SETUP_DROP_IN)
    (work / "ssh-bench.conf").write_text(SSH_DROP_IN)
    (work / "authorized_keys").write_text(ssh_pubkey + "\n")
    gid = card.group_id("exolink")
    unit = Path(__file__).parents[2] / "services/etc/systemd/system/exolink.service"
    cmds = [
        # the checkout's unit with its wheel: the rights and system calls the code needs
        *_write_file(card, unit, "/etc/systemd/system/exolink.service", 0o644, 0, 0),
        *_write_file(card, work / "appliance.yaml", "/etc/exolink/appliance.yaml", 0o640, 0, gid),
        *_write_file(
            card,
            work / "exolink-bench.service",
            "/etc/systemd/system/exolink-bench.service",
            0o644,
            0,
            0,
        ),
        "mkdir /etc/systemd/system/exolink-setup.service.d",
        *_write_file(
            card,
            work / "setup-bench.conf",
            "/etc/systemd/system/exolink-setup.service.d/bench.conf",
            0o644,
            0,
            0,
        ),
        "mkdir /etc/systemd/system/exolink.service.d",
        *_write_file(
            card,
            work / "bench.conf",
            "/etc/systemd/system/exolink.service.d/bench.conf",
            0o644,
            0,
            0,
        ),
        "mkdir /etc/systemd/system/ssh.service.d",
        *_write_file(
            card,
            work / "ssh-bench.conf",
            "/etc/systemd/system/ssh.service.d/bench.conf",
            0o644,
            0,
            0,
        ),
        "mkdir /root/.ssh",
        "sif /root/.ssh mode 040700",
        *_write_file(card, work / "authorized_keys", "/root/.ssh/authorized_keys", 0o600, 0, 0),
    ]
    card.root_edit(cmds)
    back = card.root_read("/etc/exolink/appliance.yaml")
    if back != text:
        raise RuntimeError("debugfs did not write appliance.yaml on the card copy")
    if not re.search(
        r"CPUAffinity=0", card.root_read("/etc/systemd/system/exolink.service.d/bench.conf")
    ):
        raise RuntimeError("debugfs did not write the exolink.service drop-in")
    return card, cfg
