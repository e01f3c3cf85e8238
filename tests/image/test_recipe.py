"""The image recipe's own consistency, on the host in `make test` (the build itself is
`make image`; its result is checked by test_built_image.py)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# exolink's runtime dependencies that the image takes from Debian, not PyPI.
FROM_DEBIAN = {
    "gpiod": "python3-libgpiod",
    "pyyaml": "python3-yaml",
    "zstandard": "python3-zstandard",
}


def pins(path: Path) -> dict[str, str]:
    lines = path.read_text().splitlines()
    found = (re.match(r"^([A-Za-z0-9_.-]+)==(\S+)", line) for line in lines)
    return {m.group(1).lower().replace("_", "-"): m.group(2) for m in found if m}


def test_image_python_pins_match_the_lock() -> None:
    lock = pins(REPO / "requirements.lock")
    image = pins(REPO / "image/python-requirements.txt")
    assert image, "no pins read"
    assert {name: v for name, v in image.items() if lock.get(name) != v} == {}


def test_every_runtime_dependency_has_a_source_in_the_image() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    deps = {re.split(r"[\[<>=~ ]", d, maxsplit=1)[0].lower() for d in project["dependencies"]}
    debian = (REPO / "image/debian-packages.txt").read_text().split()
    image = pins(REPO / "image/python-requirements.txt")
    missing = [d for d in deps if d not in image and FROM_DEBIAN.get(d, "?") not in debian]
    assert missing == []


def test_debian_lock_pins_what_the_image_keeps(debian_lock: dict[str, str]) -> None:
    """Every package the recipe asks for and keeps has a locked version (the build-only ones are
    purged before the manifest is taken), and the pinned Python GPIO binding is libgpiod v2."""
    lock = debian_lock
    customize = (REPO / "image/hooks/customize.sh").read_text()
    [purge] = re.findall(r"apt-get purge -y -qq ([^>]+)>", customize)
    wanted = set(re.sub(r"#.*", "", (REPO / "image/debian-packages.txt").read_text()).split())
    assert sorted(wanted - set(purge.split()) - lock.keys()) == []
    assert lock["python3-libgpiod"].split(".")[0] == "2"
    assert "linux-image-armmp" in lock and "u-boot-omap" in lock


def test_units_install_where_systemd_reads_them() -> None:
    etc = REPO / "services/etc"
    assert (etc / "systemd/system/exolink.service").exists()
    unit = (etc / "systemd/system/exolink.service").read_text()
    assert "Type=notify" in unit and "WatchdogSec=" in unit and "Restart=always" in unit
    assert "/etc/exolink/appliance.yaml" in unit
    assert (
        "RuntimeWatchdogSec=" in (etc / "systemd/system.conf.d/exolink-watchdog.conf").read_text()
    )


def test_unit_retries_missing_hardware_but_not_a_bad_config() -> None:
    """A bad config never fixes itself: restarting it would hit the start limit and reboot the
    board every few minutes. The codes are the CLI's own (tests/test_supervisor.py runs them)."""
    from exolink.cli.errors import EXIT_CONFIG, EXIT_HARDWARE

    unit = (REPO / "services/etc/systemd/system/exolink.service").read_text()
    [line] = [x for x in unit.splitlines() if x.startswith("RestartPreventExitStatus=")]
    prevented = {int(c) for c in line.split("=", 1)[1].split()}
    assert EXIT_CONFIG in prevented and EXIT_HARDWARE not in prevented
    assert "ExecStartPre" not in unit  # its exit status would not count as the main process's


def test_unit_lets_the_supervisor_read_and_set_the_clock() -> None:
    """exolink.board.clock reads adjtimex on every status and steps the clock for a laptop: both are
    in systemd's @clock set, which @system-service leaves out and ProtectClock forbids. A
    supervisor without them was killed by the kernel (SIGSYS) at its first status on the proxy."""
    unit = (REPO / "services/etc/systemd/system/exolink.service").read_text()
    keys = [line.split("=", 1) for line in unit.splitlines() if "=" in line and line[0] != "#"]
    filters = {v for k, v in keys if k == "SystemCallFilter"}
    assert "@clock" in filters
    assert not any(k == "ProtectClock" and v == "yes" for k, v in keys)
    for key in ("AmbientCapabilities", "CapabilityBoundingSet"):
        [value] = [v for k, v in keys if k == key]
        assert "CAP_SYS_TIME" in value.split()


def _conf() -> dict[str, str]:
    return dict(re.findall(r"(?m)^([A-Z_]+)=([^\s$]+)$", (REPO / "image/image.conf").read_text()))


def test_a_b_layout_fits_and_each_partition_has_its_partuuid() -> None:
    """Four MBR partitions: FAT, root A, root B, data; PARTUUIDs <disk id>-0N as the boot script
    (part uuid) and RAUC's system.conf find them; U-Boot raw below the FAT."""
    c = _conf()
    disk = c["DISK_ID"].removeprefix("0x")
    for n, key in enumerate(("BOOT", "ROOT_A", "ROOT_B", "DATA"), start=1):
        assert c[f"{key}_PARTUUID"] == f"{disk}-0{n}"
    assert int(c["BOOT_START_MIB"]) * 1024 * 1024 > 384 * 1024 + 1024 * 1024  # u-boot.img < 1 MiB
    assert int(c["ROOT_SLOT_MIB"]) >= 1024 and int(c["BOOT_TRIES"]) == 3
    conf = (REPO / "image/rauc/system.conf.in").read_text()
    assert "bootloader=custom" in conf and "bundle-formats=verity" in conf
    assert "device=/dev/disk/by-partuuid/@ROOT_A_PARTUUID@" in conf and "bootname=A" in conf
    assert "device=/dev/disk/by-partuuid/@ROOT_B_PARTUUID@" in conf and "bootname=B" in conf
    assert "data-directory=/data/" in conf  # on the shared data partition, not in a slot


def test_boot_script_uses_raucs_u_boot_names_and_no_setexpr() -> None:
    """The BeagleBone's U-Boot (Debian's am335x_boneblack) has no setexpr: the counter goes down
    by a table; the names are RAUC's (BOOT_ORDER, BOOT_<slot>_LEFT)."""
    cmd = (REPO / "image/boot.cmd").read_text()
    code = "\n".join(line for line in cmd.splitlines() if not line.lstrip().startswith("#"))
    assert "setexpr" not in code
    for name in ("BOOT_ORDER", "BOOT_A_LEFT", "BOOT_B_LEFT", "fatwrite", "env import -t"):
        assert name in code
    assert "rauc.slot=${exo_slot}" in code
    assert "/boot/exolink/vmlinuz" in code  # the kernel comes with its slot


def test_update_units_are_enabled_and_run_the_agent_as_root() -> None:
    system = REPO / "services/etc/systemd/system"
    customize = (REPO / "image/hooks/customize.sh").read_text()
    for unit in ("exolink-boot-check.service", "exolink-update.path", "exolink-mark-good.path"):
        assert unit in customize and (system / unit).exists()
    for unit, action in (
        ("exolink-update.service", "install"),
        ("exolink-mark-good.service", "mark-good"),
        ("exolink-boot-check.service", "boot-check"),
    ):
        text = (system / unit).read_text()
        assert f"exolink update-agent {action}" in text and "User=" not in text
    # The supervisor writes its requests where the path units look (exolink.board.update.UPDATE_DIR).
    from exolink.board import update

    for unit in ("exolink-update.path", "exolink-mark-good.path"):
        [path] = re.findall(r"PathExists=(\S+)", (system / unit).read_text())
        assert Path(path).parent == update.UPDATE_DIR
    # A path unit starts before basic.target (paths.target): ordering it after a normal service
    # is a cycle, which systemd broke at boot by skipping the path unit (seen under qemu: the
    # new slot was never marked good).
    for unit in ("exolink-update.path", "exolink-mark-good.path"):
        text = (system / unit).read_text()
        assert not re.search(r"(?m)^(After|Requires|Wants)=.*\.service", text), unit
    check = (system / "exolink-boot-check.service").read_text()
    assert not re.search(r"(?m)^Before=.*\.path", check)
    fstab = re.search(r"cat > \"\$R/etc/fstab\" <<FSTAB\n(.*?)FSTAB", customize, re.S)
    assert fstab and "/data/exolink             /var/lib/exolink" in fstab.group(1)


def test_no_private_key_is_committed() -> None:
    import subprocess

    tracked = subprocess.run(
        ["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.split()
    for name in tracked:
        if name.endswith((".pem", ".key")):
            assert "PRIVATE KEY" not in (REPO / name).read_text(errors="replace"), name
