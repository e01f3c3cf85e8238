"""image/boot.cmd, the A/B boot selection, run by a real U-Boot: Debian's qemu_arm build under
qemu-system-arm -M virt (a few seconds a boot), on a small card with the real layout's first three
partitions (FAT with boot.scr and exolink-boot.env; slots A and B holding a stand-in kernel).

The kernel is a stand-in (bootz refuses it, the script says so): what is under test is which
slot the script picks, the root it would hand the kernel and what it writes back to the FAT.
The BeagleBone's U-Boot runs the same script (its commands are checked in test_recipe.py);
tests/image/test_update.py boots the real card through it.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UBOOT = Path("/usr/lib/u-boot/qemu_arm/u-boot.bin")
TOOLS = ("qemu-system-arm", "mkimage", "mkfs.vfat", "mcopy", "mtype", "mkfs.ext4", "sfdisk")
MIB = 1 << 20

pytestmark = pytest.mark.skipif(
    not UBOOT.is_file() or any(shutil.which(t) is None for t in TOOLS),
    reason=f"needs {UBOOT} (u-boot-qemu) and {', '.join(TOOLS)} (qemu-system-arm, u-boot-tools, "
    "dosfstools, mtools, e2fsprogs, fdisk)",
)


@pytest.fixture
def card(tmp_path: Path) -> Path:
    slot = tmp_path / "slot"
    (slot / "boot/exolink").mkdir(parents=True)
    for name in ("vmlinuz", "initrd.img"):
        (slot / "boot/exolink" / name).write_bytes(b"not a kernel\n" * 100)
    subprocess.run(["mkfs.ext4", "-q", "-F", "-d", str(slot), str(tmp_path / "slot.ext4"), "4M"],
                   check=True)  # fmt: skip
    subprocess.run(["mkimage", "-A", "arm", "-O", "linux", "-T", "script", "-C", "none", "-d",
                    str(REPO / "image/boot.cmd"), str(tmp_path / "boot.scr")], check=True,
                   capture_output=True)  # fmt: skip
    subprocess.run(["mkfs.vfat", "-F", "32", "-C", str(tmp_path / "boot.vfat"), str(40 * 1024)],
                   check=True, capture_output=True)  # fmt: skip
    subprocess.run(["mcopy", "-i", str(tmp_path / "boot.vfat"), str(tmp_path / "boot.scr"), "::/"],
                   check=True)  # fmt: skip
    img = tmp_path / "card.img"
    with open(img, "wb") as f:
        f.truncate(56 * MIB)
    table = (
        "label: dos\nlabel-id: 0x45786f6c\nunit: sectors\n"
        "start=2048, size=81920, type=c, bootable\n"
        "start=83968, size=8192, type=83\nstart=92160, size=8192, type=83\n"
    )
    subprocess.run(["sfdisk", "-q", str(img)], input=table, text=True, check=True)
    for src, sector in (("boot.vfat", 2048), ("slot.ext4", 83968), ("slot.ext4", 92160)):
        subprocess.run(["dd", f"if={tmp_path / src}", f"of={img}", "bs=512", f"seek={sector}",
                        "conv=notrunc", "status=none"], check=True)  # fmt: skip
    return img


def fat(img: Path) -> str:
    return f"{img}@@{2048 * 512}"


def set_state(img: Path, text: str, tmp_path: Path) -> None:
    (tmp_path / "exolink-boot.env").write_text(text)
    subprocess.run(["mcopy", "-o", "-i", fat(img), str(tmp_path / "exolink-boot.env"), "::/"],
                   check=True)  # fmt: skip


def state(img: Path) -> dict[str, str]:
    out = subprocess.run(["mtype", "-i", fat(img), "::exolink-boot.env"], capture_output=True,
                         check=True).stdout.decode()  # fmt: skip
    return dict(re.findall(r"(?m)^(BOOT_\w+)=([^\n\0]*)", out))


def boot(img: Path, until: str = r"did not boot", timeout: float = 60) -> str:
    """One power-on: U-Boot's distro boot finds boot.scr and runs it; the console up to ``until``."""
    cmd = ["qemu-system-arm", "-M", "virt", "-cpu", "cortex-a15", "-m", "256", "-nographic",
           "-nic", "none", "-bios", str(UBOOT), "-drive", f"file={img},format=raw,if=none,id=c",
           "-device", "virtio-blk-device,drive=c"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL)  # fmt: skip
    out, deadline = b"", time.monotonic() + timeout
    assert proc.stdout is not None
    try:
        os.set_blocking(proc.stdout.fileno(), False)
        while time.monotonic() < deadline and not re.search(until.encode(), out):
            chunk = proc.stdout.read()
            if chunk:
                out += chunk
            else:
                time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait()
    text = out.decode(errors="replace")
    assert re.search(until, text), text[-2000:]
    return text


def chosen(console: str) -> list[str]:
    return re.findall(r"exolink: booting slot ([AB])", console)


def test_a_fresh_card_boots_a_and_counts_one_attempt(card: Path) -> None:
    out = boot(card)
    assert chosen(out) == ["A"]
    assert state(card) == {"BOOT_ORDER": "A B", "BOOT_A_LEFT": "2", "BOOT_B_LEFT": "3"}


def test_new_slot_gets_three_attempts_then_the_old_one_boots(card: Path, tmp_path: Path) -> None:
    """What RAUC's set-primary leaves (B first, 3 attempts) and a B that never marks itself good:
    B, B, B, then A with nobody touching the board."""
    set_state(card, "BOOT_ORDER=B A\nBOOT_A_LEFT=3\nBOOT_B_LEFT=3\n", tmp_path)
    seen = []
    for _ in range(4):
        seen += chosen(boot(card))
    assert seen == ["B", "B", "B", "A"]
    assert state(card) == {"BOOT_ORDER": "B A", "BOOT_A_LEFT": "2", "BOOT_B_LEFT": "0"}


def test_a_slot_marked_good_keeps_booting(card: Path, tmp_path: Path) -> None:
    set_state(card, "BOOT_ORDER=B A\nBOOT_A_LEFT=3\nBOOT_B_LEFT=1\n", tmp_path)
    assert chosen(boot(card)) == ["B"]
    set_state(card, "BOOT_ORDER=B A\nBOOT_A_LEFT=3\nBOOT_B_LEFT=3\n", tmp_path)  # mark-good
    assert chosen(boot(card)) == ["B"]
    assert state(card)["BOOT_B_LEFT"] == "2"


def test_both_used_up_start_over_instead_of_never_booting(card: Path, tmp_path: Path) -> None:
    set_state(card, "BOOT_ORDER=A B\nBOOT_A_LEFT=0\nBOOT_B_LEFT=0\n", tmp_path)
    out = boot(card, until=r"exolink: booting slot")  # after the reset, in the same power-on
    assert "no slot has attempts left; resetting both to 3" in out
    assert chosen(out) == ["A"]


def test_a_missing_state_file_means_a_first(card: Path) -> None:
    subprocess.run(["mdel", "-i", fat(card), "::exolink-boot.env"], capture_output=True)
    assert chosen(boot(card)) == ["A"]
