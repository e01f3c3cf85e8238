"""Files the board writes to the card's FAT boot partition survive pulling the power right after
the write returns (UML guest: a real vfat on a ubd disk whose backing file is the "card").

Power is cut by reading the backing file instead of the mounted filesystem: what is in that
file is what a card pulled at that instant would hold. Periodic writeback is switched off in the
guest, so only the writer's own syncs put anything there.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from exolink.board import setup as boardsetup

pytestmark = pytest.mark.kernel

CARD = os.environ.get("EXOLINK_FAT_CARD", "")  # the backing file of /dev/ubdb (tests/kernel/run.sh)


def _card_after_power_cut(tmp_path: Path) -> Path:
    """A copy of the card as it is now; clean page cache dropped so hostfs reads the host file."""
    Path("/proc/sys/vm/drop_caches").write_text("1")
    copy = tmp_path / "pulled.img"
    copy.write_bytes(Path(CARD).read_bytes())
    return copy


def _mtype(card: Path, name: str) -> str:
    r = subprocess.run(["mtype", "-i", str(card), f"::{name}"], capture_output=True, text=True)
    return r.stdout if r.returncode == 0 else f"<{r.stderr.strip()}>"


def _names(card: Path) -> list[str]:
    r = subprocess.run(["mdir", "-b", "-a", "-i", str(card), "::"], capture_output=True, text=True)
    return sorted(line.removeprefix("::/") for line in r.stdout.split())


def test_a_new_boot_file_is_on_the_card_when_write_returns(fat_boot: Path, tmp_path: Path) -> None:
    text = "// Zenoh login for exo-01\n" + "x" * 3000 + "\n"
    boardsetup._write(fat_boot, boardsetup.laptop_file("operator"), text, 0o600)
    card = _card_after_power_cut(tmp_path)
    assert _mtype(card, boardsetup.laptop_file("operator")) == text
    assert _names(card) == [
        boardsetup.laptop_file("operator")
    ]  # no stray temp entry sharing its clusters
    check = subprocess.run(["fsck.vfat", "-n", str(card)], capture_output=True, text=True)
    assert "cross-linked" not in check.stdout and "Orphaned" not in check.stdout, check.stdout


def test_a_rewritten_boot_file_is_the_new_one_when_write_returns(
    fat_boot: Path, tmp_path: Path
) -> None:
    boardsetup._write(fat_boot, boardsetup.laptop_file("operator"), "old\n", 0o600)
    boardsetup._write(fat_boot, boardsetup.laptop_file("operator"), "new login\n", 0o600)
    card = _card_after_power_cut(tmp_path)
    assert _mtype(card, boardsetup.laptop_file("operator")) == "new login\n"
    assert _names(card) == [boardsetup.laptop_file("operator")]
