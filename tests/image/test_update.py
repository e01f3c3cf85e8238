"""A/B updates of the built card under qemu, booting through U-Boot (`make image bundle`, then
`make test-update`; ~40 min here, TCG):

- A -> B kept: `exolink update` sends the bundle from `make bundle` to a board on slot A; RAUC
  checks its signature and installs it into slot B; the board reboots through U-Boot's boot script
  (image/boot.cmd) into B and marks it good once every critical node beats.
- B whose supervisor cannot start -> back on A with no hand on the board: systemd's start limit
  reboots it, U-Boot counts B's attempts down and boots A again.
- A bundle with a bad signature is refused and the board stays as it was.

Real parts: Debian's qemu_arm U-Boot (-M virt) running the card's boot.scr from its FAT, the
card's kernel, systemd, RAUC 1.13 and supervisor, the laptop's `exolink update` over Zenoh, bundles
signed with build/rauc's development key. What cannot exist here: the BeagleBone (its U-Boot runs the
same script; MLO, mmc and the board's dtb are not exercised), real sensors (the card is set to
simulate). Two edits of every card and bundle root, each said where it is made: the watchdog's
timings widened for TCG (tests/image/test_built_image.py), and in the broken bundle a drop-in that
makes the supervisor's ExecStart fail. Timings go to build/image/update-report.json.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from test_built_image import (
    CONF,
    MIB,
    REPO,
    Console,
    _beating,
    _free_port,
    _relaxed_for_tcg,
    mcat,
    partition_table,
)

pytestmark = [pytest.mark.image, pytest.mark.slow]
UBOOT = Path("/usr/lib/u-boot/qemu_arm/u-boot.bin")
KEYS = REPO / "build/rauc"
REPORT = REPO / "build/image/update-report.json"


def _unavailable(why: str) -> None:
    if os.environ.get("EXOLINK_REQUIRE_IMAGE"):
        pytest.fail(why)
    pytest.skip(f"{why}; run `make image bundle test-update`")


@pytest.fixture(scope="module")
def built() -> dict[str, Path]:
    if not (os.environ.get("EXOLINK_IMAGE") or os.environ.get("EXOLINK_REQUIRE_IMAGE")):
        pytest.skip("the update round trip runs with `make test-update` (built image and bundle)")
    out = REPO / "build/image"
    images = sorted(out.glob("exolink-bbb-*.img"), key=lambda p: p.stat().st_mtime)
    bundles = sorted(out.glob("exolink-bbb-*.raucb"), key=lambda p: p.stat().st_mtime)
    if not images:
        _unavailable("no built image in build/image (make image)")
    if not bundles:
        _unavailable("no bundle in build/image (make bundle)")
    for tool in ("qemu-system-arm", "sfdisk", "mcopy", "debugfs", "rauc", "mksquashfs"):
        if not shutil.which(tool):
            _unavailable(f"{tool} is not installed")
    if not UBOOT.is_file():
        _unavailable(f"{UBOOT} missing (Debian's u-boot-qemu)")
    if not (KEYS / "dev.key.pem").is_file():
        _unavailable("no development signing key in build/rauc (made by make image)")
    return {"image": images[-1], "bundle": bundles[-1]}


def _slot_offset(img: Path, n: int) -> int:
    return int(partition_table(img)["partitions"][n - 1]["start"]) * 512


def _debugfs_write(spec: str, local: Path, path: str, mode: str = "0100644") -> None:
    cmds = f"rm {path}\nwrite {local} {path}\nsif {path} mode {mode}\n"
    subprocess.run(["debugfs", "-w", "-f", "-", spec], input=cmds, text=True, check=True,
                   capture_output=True)  # fmt: skip
    got = subprocess.run(["debugfs", "-R", f"cat {path}", spec], capture_output=True, text=True)
    assert got.stdout == local.read_text(), path


def _relax_root(spec: str, d: Path) -> None:
    """The TCG edit of appliance.yaml (as test_built_image makes it) in a root at ``spec``."""
    path = "/etc/exolink/appliance.yaml"
    r = subprocess.run(["debugfs", "-R", f"cat {path}", spec], capture_output=True, text=True)
    local = d / "appliance.yaml"
    local.write_text(yaml.safe_dump(_relaxed_for_tcg(yaml.safe_load(r.stdout)), sort_keys=False))
    _debugfs_write(spec, local, path, "0100640")


def _card(image: Path, d: Path) -> Path:
    """A copy of the card: simulate, an admin login, slot A's appliance.yaml relaxed for TCG."""
    img = d / "card.img"
    subprocess.run(["cp", "--sparse=always", str(image), str(img)], check=True)
    # A bigger card: the first boot grows p4, which then holds a bundle (258 MB) on its way in.
    os.truncate(img, img.stat().st_size + 1024 * MIB)
    fat = f"{img}@@{int(CONF['BOOT_START_MIB']) * MIB}"
    text = mcat(fat, "exolink-settings.yaml").decode()
    text = text.replace("simulate: false", "simulate: true")
    text = re.sub(r"logins: \[operator, observer\]", "logins: [operator, observer, admin]", text)
    assert "admin]" in text
    (d / "exolink-settings.yaml").write_text(text)
    subprocess.run(["mcopy", "-o", "-i", fat, str(d / "exolink-settings.yaml"), "::/"], check=True)
    _relax_root(f"{img}?offset={_slot_offset(img, 2)}", d)
    return img


def _rebundle(bundle: Path, d: Path, name: str, version: str, broken: bool) -> Path:
    """The bundle's root, relaxed for TCG (and with a supervisor that cannot start when
    ``broken``), signed again with the development key."""
    work = d / f"rebundle-{name}"
    shutil.rmtree(work, ignore_errors=True)
    subprocess.run(["rauc", "extract", f"--keyring={KEYS / 'dev.cert.pem'}", str(bundle),
                    str(work)], check=True, capture_output=True)  # fmt: skip
    root = work / "rootfs.ext4"
    _relax_root(str(root), d)
    if broken:
        dropin = d / "broken.conf"
        dropin.write_text(
            "# test_update: a supervisor that cannot start (exits 1 at once, every time)\n"
            "[Service]\nExecStart=\nExecStart=/bin/sh -c 'echo exolink: supervisor cannot start;"
            " exit 1'\n"
        )
        subprocess.run(["debugfs", "-w", "-R", "mkdir /etc/systemd/system/exolink.service.d",
                        str(root)], check=True, capture_output=True)  # fmt: skip
        _debugfs_write(str(root), dropin, "/etc/systemd/system/exolink.service.d/broken.conf")
    manifest = work / "manifest.raucm"
    text = re.sub(r"(?m)^version=.*$", f"version={version}", manifest.read_text())
    text = re.sub(r"(?m)^(sha256|size)=.*\n", "", text)  # the image changed: rauc bundle recounts
    manifest.write_text(re.sub(r"(?m)^\[bundle\]\n(?:[a-z-]+=.*\n)*", "[bundle]\nformat=verity\n",
                               text))  # fmt: skip
    for f in work.iterdir():  # rauc extract leaves the verity hash alongside: a new one is made
        if f.name not in ("manifest.raucm", "rootfs.ext4"):
            f.unlink()
    out = d / f"{name}.raucb"
    subprocess.run(["rauc", "bundle", f"--cert={KEYS / 'dev.cert.pem'}",
                    f"--key={KEYS / 'dev.key.pem'}", str(work), str(out)], check=True,
                   capture_output=True)  # fmt: skip
    shutil.rmtree(work)
    return out


def _tampered(d: Path) -> Path:
    """A small bundle signed with the development key, then one byte of its signature flipped."""
    work = d / "tiny"
    (d / "tiny-root").mkdir()
    (d / "tiny-root/noise").write_bytes(os.urandom(256 << 10))  # squashfs must exceed 4 KiB
    work.mkdir()
    subprocess.run(["mkfs.ext4", "-q", "-F", "-d", str(d / "tiny-root"),
                    str(work / "rootfs.ext4"), "8M"], check=True)  # fmt: skip
    (work / "manifest.raucm").write_text(
        f"[update]\ncompatible={CONF['RAUC_COMPATIBLE']}\nversion=tampered\n\n"
        "[bundle]\nformat=verity\n\n[image.rootfs]\nfilename=rootfs.ext4\n"
    )
    out = d / "tampered.raucb"
    subprocess.run(["rauc", "bundle", f"--cert={KEYS / 'dev.cert.pem'}",
                    f"--key={KEYS / 'dev.key.pem'}", str(work), str(out)], check=True,
                   capture_output=True)  # fmt: skip
    data = bytearray(out.read_bytes())
    # [squashfs][CMS signature][its size, 8 bytes]: the CMS ends with the RSA signature value.
    assert int.from_bytes(data[-8:], "big") > 512
    data[-8 - 20] ^= 0x01
    out.write_bytes(bytes(data))
    r = subprocess.run(["rauc", "info", f"--keyring={KEYS / 'dev.cert.pem'}", str(out)],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode != 0, "the host's rauc accepted the tampered bundle"
    return out


class Board:
    """The card under qemu -M virt, started by Debian's U-Boot (reboots stay in the same qemu)."""

    def __init__(self, img: Path, d: Path, log: str) -> None:
        self.port, self.d, self.log = _free_port(), d, log
        cmd = [
            "qemu-system-arm", "-M", "virt", "-cpu", "cortex-a15", "-smp", "2", "-m", "512",
            "-nographic", "-bios", str(UBOOT),
            "-drive", f"file={img},format=raw,if=none,id=card",
            "-device", "virtio-blk-device,drive=card",
            "-netdev", f"user,id=net,hostfwd=tcp:127.0.0.1:{self.port}-:7447",
            "-device", "virtio-net-device,netdev=net",
        ]  # fmt: skip
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL)  # fmt: skip
        self.console = Console(self.proc)
        fat = f"{img}@@{int(CONF['BOOT_START_MIB']) * MIB}"
        self.login = d / "exolink-admin.json5"
        self.fat = fat

    def cli(self, *args: str, timeout: float = 3600) -> subprocess.CompletedProcess[str]:
        if not self.login.exists():
            try:  # written by exolink-setup on the first boot
                self.login.write_bytes(mcat(self.fat, "exolink-admin.json5"))
            except subprocess.CalledProcessError:
                return subprocess.CompletedProcess([], 4, "", "no admin login on the card yet")
        cmd = [sys.executable, "-m", "exolink.cli.main", *args, "--timeout", "20", "--at",
               f"tcp/127.0.0.1:{self.port}", "--zenoh-config", str(self.login)]  # fmt: skip
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)

    def status(self) -> dict | None:
        r = self.cli("status", "--json", timeout=120)
        return json.loads(r.stdout) if r.returncode == 0 else None

    def wait_up(self, timeout: float, slot: str, result: str | None = None) -> dict:
        """Every node beating on ``slot`` (and the update's ``result``, when given)."""
        deadline, last = time.monotonic() + timeout, None
        while time.monotonic() < deadline:
            with contextlib.suppress(subprocess.TimeoutExpired, ValueError):
                last = self.status()
            sw = (last or {}).get("software", {})
            if (
                last is not None
                and all(_beating(n) for n in last["nodes"])
                and sw.get("slot") == slot
                and (result is None or sw.get("result") == result)
            ):
                return last
            time.sleep(5)
        tail = "\n".join(s for _, s in self.console.lines[-40:])
        raise AssertionError(f"not up on slot {slot} ({result}): {last and last.get('software')}"
                             f"\n{tail}")  # fmt: skip

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()
        (REPO / "build/image" / self.log).write_text(
            "\n".join(f"{t:7.1f} {s}" for t, s in self.console.lines) + "\n"
        )


@contextlib.contextmanager
def _board(img: Path, d: Path, log: str) -> Iterator[Board]:
    b = Board(img, d, log)
    try:
        yield b
    finally:
        b.close()


def _report(key: str, value: dict) -> None:
    data = json.loads(REPORT.read_text()) if REPORT.exists() else {}
    data[key] = value
    REPORT.write_text(json.dumps(data, indent=2) + "\n")
    sys.stderr.write(f"update report {key}: {json.dumps(value)}\n")


def _boots(c: Console, since: int = 0) -> list[str]:
    return [s for _, s in c.lines[since:] if "exolink: booting slot" in s]


@pytest.mark.timeout(4800)
def test_a_to_b_is_kept_and_a_bad_signature_is_refused(
    built: dict[str, Path], tmp_path: Path
) -> None:
    img = _card(built["image"], tmp_path)
    good = _rebundle(built["bundle"], tmp_path, "good", "test-b", broken=False)
    tampered = _tampered(tmp_path)
    rep: dict = {"bundle_mib": round(good.stat().st_size / MIB, 1)}
    with _board(img, tmp_path, "update-console-good.log") as b:
        c = b.console
        c.wait_for(r"exolink: booting slot A", 300)
        st = b.wait_up(1500, "A")
        rep["first_boot_up_s"] = round(time.monotonic() - c.t0, 1)
        assert st["software"]["version"]
        c.wait_for(r"update_marked_good|marked good", 300)

        # The tampered bundle: refused by RAUC's signature check, nothing installed.
        t0 = time.monotonic()
        r = b.cli("update", str(tampered))
        assert r.returncode == 5, r.stdout + r.stderr
        assert "refused" in r.stderr and "signature" in r.stderr.lower(), r.stderr
        rep["tampered_refused_s"] = round(time.monotonic() - t0, 1)
        sw = b.status()["software"]  # type: ignore[index]
        assert sw["slot"] == "A" and sw["result"] == "refused" and not sw["installing"]

        # The good one: A -> B, kept once every node beats.
        n = len(c.lines)
        t0 = time.monotonic()
        r = b.cli("update", str(good))
        total = time.monotonic() - t0
        assert r.returncode == 0, r.stdout + r.stderr
        sent = re.search(r"sent in (\d+) s", r.stdout)
        rep.update(
            upload_s=int(sent.group(1)) if sent else None,
            round_trip_s=round(total, 1),
            cli_output=r.stdout.splitlines()[-3:],
        )
        assert _boots(c, n)[-1].startswith("exolink: booting slot B"), _boots(c, n)
        st = b.wait_up(600, "B", "good")
        assert st["software"]["bundle_version"] == "test-b"
        # What must survive an update: the card's settings (device name), the logins (this
        # admin login still works), the state on the data partition.
        assert st["device"] == "exo-01"
        out = b.cli("status")
        assert "on slot B" in out.stdout and "last update: good" in out.stdout, out.stdout
        # The count reset by mark-good: U-Boot's next boot is B with 3 attempts.
        env = mcat(b.fat, "exolink-boot.env").decode()
        assert "BOOT_ORDER=B A" in env and "BOOT_B_LEFT=3" in env, env
    _report("a_to_b_good", rep)


@pytest.mark.timeout(4800)
def test_b_whose_supervisor_cannot_start_falls_back_to_a(
    built: dict[str, Path], tmp_path: Path
) -> None:
    img = _card(built["image"], tmp_path)
    broken = _rebundle(built["bundle"], tmp_path, "broken", "test-broken", broken=True)
    rep: dict = {}
    with _board(img, tmp_path, "update-console-fallback.log") as b:
        c = b.console
        b.wait_up(1500, "A")
        c.wait_for(r"update_marked_good|marked good", 300)
        n = len(c.lines)
        t0 = time.monotonic()
        r = b.cli("update", str(broken))
        took = time.monotonic() - t0
        assert r.returncode == 1, r.stdout + r.stderr
        assert "rolled back" in r.stderr, r.stderr
        boots = _boots(c, n)
        # B three times (its attempts), then A: nobody touched the board.
        assert [s.split()[3] for s in boots] == ["B", "B", "B", "A"], boots
        # Each B boot ended in a reboot nobody asked for (systemd's start limit on a supervisor
        # that exits at once; its own words are in B's journal, not on the console), and no
        # boot of B was marked good.
        on_a = next(i for i in range(len(c.lines) - 1, n, -1) if "booting slot A" in c.lines[i][1])
        reboots = [s for _, s in c.lines[n:on_a] if "reboot: Restarting system" in s]
        assert len(reboots) == 4, reboots  # after the install, then after each B boot
        assert not any("update_marked_good" in s for _, s in c.lines[n:on_a])
        st = b.wait_up(600, "A", "rolled back")
        assert "did not come up" in st["software"]["detail"]
        rep.update(round_trip_s=round(took, 1), boots=boots)
    _report("b_broken_falls_back", rep)
