"""The DCAN1 overlay applied with fdtoverlay onto the real am335x-boneblack.dtb shipped in Debian's
armhf kernel package (fetched by tests/image/fetch-dtb.sh through the machine's Debian mirror)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.image
REPO = Path(__file__).resolve().parents[2]
DCAN1 = "/ocp/interconnect@48000000/segment@100000/target-module@d0000/can@0"
PINMUX = "/ocp/interconnect@44c00000/segment@200000/target-module@10000/scm@0/pinmux@800"
GPIO0 = "/ocp/interconnect@44c00000/segment@200000/target-module@7000/gpio@0"


def _unavailable(why: str) -> None:
    if os.environ.get("EXOLINK_REQUIRE_IMAGE"):
        pytest.fail(why)
    pytest.skip(f"{why}; run `make test-image`")


@pytest.fixture(scope="module")
def merged(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not shutil.which("dtc") or not shutil.which("fdtoverlay"):
        _unavailable("device-tree-compiler (dtc, fdtoverlay) is not installed")
    r = subprocess.run(
        ["bash", str(REPO / "tests/image/fetch-dtb.sh")], capture_output=True, text=True
    )
    if r.returncode != 0:
        _unavailable(f"cannot fetch Debian's armhf dtb: {r.stderr.strip()[-300:]}")
    base = Path(r.stdout.strip())
    d = tmp_path_factory.mktemp("dt")
    dtbo = d / "exolink-dcan1.dtbo"
    subprocess.run(
        [
            "dtc",
            "-@",
            "-q",
            "-I",
            "dts",
            "-O",
            "dtb",
            "-o",
            str(dtbo),
            str(REPO / "overlays/exolink-dcan1.dts"),
        ],
        check=True,
    )
    out = d / "am335x-boneblack.dtb"
    subprocess.run(["fdtoverlay", "-i", str(base), "-o", str(out), str(dtbo)], check=True)
    assert get(base, DCAN1, "status") == "disabled"  # the base really lacks it
    return out


def get(dtb: Path, node: str, prop: str, kind: str = "s") -> str:
    return subprocess.run(
        ["fdtget", "-t", kind, str(dtb), node, prop], capture_output=True, text=True, check=True
    ).stdout.strip()


def test_dcan1_enabled_with_its_pins(merged: Path) -> None:
    assert get(merged, DCAN1, "status") == "okay"
    assert (
        get(merged, f"{PINMUX}/exolink-dcan1-pins", "pinctrl-single,pins", "x") == "180 12 184 32"
    )
    assert get(merged, DCAN1, "pinctrl-0", "x") == get(
        merged, f"{PINMUX}/exolink-dcan1-pins", "phandle", "x"
    )


def test_trigger_pins_claimed_by_gpio0(merged: Path) -> None:
    assert (
        get(merged, f"{PINMUX}/exolink-trigger-pins", "pinctrl-single,pins", "x") == "164 27 1a0 2f"
    )
    assert get(merged, GPIO0, "pinctrl-0", "x") == get(
        merged, f"{PINMUX}/exolink-trigger-pins", "phandle", "x"
    )
