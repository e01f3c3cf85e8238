"""Shared fixtures: isolated multicast groups and Zenoh ports, configs written to tmp files,
and exolink processes run for real (no mocks of buses or sessions). The appliance, the bus
listener and the processes are the harness's (benchmarks/harness.py, shared with the
benchmarks); the fixtures here only give each test its own and end them after it."""

from __future__ import annotations

import contextlib
import os
import re
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from benchmarks import harness
from benchmarks.harness import DrainedBus, Spawner, connect, wait_for
from exolink.canbus import FrameReader
from exolink.supervisor import canlink

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session", autouse=True)
def kernel_timestamps_on() -> Iterator[None]:
    """Keep the kernel's receive timestamping on for the whole session. Linux enables it
    asynchronously (a work item) when the first SO_TIMESTAMP socket opens and disables it when
    the last closes, so a frame arriving in between carries the read's time instead: two
    full-suite runs this stop saw it (a test's first socket after another test closed all of its own)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, 35, 1)  # SO_TIMESTAMPNS
    time.sleep(0.05)  # the work item runs
    yield
    s.close()


@pytest.fixture
def lab_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Callable[..., Path]:
    """A lab's package installed the way pip would (a dist-info with its entry points) in a
    folder on the PYTHONPATH of the processes the test starts: ``lab_package("lab_rig",
    "[exolink.hardware]\nrig = lab_rig:Rig\n", {"lab_rig.py": code})``."""

    def install(name: str, entry_points: str, files: dict[str, str]) -> Path:
        site = tmp_path / f"{name}-site"
        info = site / f"{name}-0.1.dist-info"
        info.mkdir(parents=True)
        dist = name.replace("_", "-")
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
        (info / "entry_points.txt").write_text(entry_points)
        for filename, text in files.items():
            (site / filename).parent.mkdir(parents=True, exist_ok=True)
            (site / filename).write_text(text)
        path = os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))
        monkeypatch.setenv("PYTHONPATH", path)
        return site

    return install


@pytest.fixture
def group() -> str:
    """A multicast group of its own per test, so concurrent or leftover traffic never mixes."""
    return harness.group(harness.TEST_GROUPS)


@pytest.fixture
def write_config(tmp_path: Path, group: str) -> Callable[..., Path]:
    """Write the bundled sim config with overrides onto this test's own group and port."""

    def write(nodes: list[dict] | None = None, **overrides: object) -> Path:
        return harness.sim_config(tmp_path / "appliance.yaml", group, nodes, **overrides)

    return write


@pytest.fixture
def in_node(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Callable[[str, str], None]:
    """Run code at interpreter start in the processes whose argv names a node (a sitecustomize
    on PYTHONPATH, inherited by the supervisor and its nodes): how the tests make a node slow
    to start or its disk slow, which cannot be made for real here."""

    def install(node: str, code: str) -> None:
        site = tmp_path / "site"
        site.mkdir(exist_ok=True)
        body = "".join(f"    {line}\n" for line in code.strip().splitlines())
        (site / "sitecustomize.py").write_text(f"import sys\nif {node!r} in sys.argv:\n{body}")
        path = os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))
        monkeypatch.setenv("PYTHONPATH", path)
        monkeypatch.setenv("EXOLINK_SPAWN", "exec")  # hooks run at interpreter start: no fork

    return install


@pytest.fixture
def mbus(group: str) -> Iterator[DrainedBus]:
    """An independent listener on the test's udp_multicast bus."""
    bus = DrainedBus(group)
    yield bus
    bus.close()


def bus_sockets(pid: int) -> int:
    """The sim-bus sockets (bound to its UDP port) a process holds, from /proc."""
    from exolink.canbus.simbus import SIM_PORT

    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        with contextlib.suppress(OSError):
            if (target := os.readlink(fd)).startswith("socket:["):
                inodes.add(target[8:-1])
    port = f":{SIM_PORT:04X}"
    rows = Path("/proc/net/udp").read_text().splitlines()[1:]
    return sum(1 for r in rows if r.split()[1].endswith(port) and r.split()[9] in inodes)


def read_cycle(tx: can.BusABC, reader: FrameReader, ids: list[int]) -> list[int]:
    """Send one frame of each of ``ids`` (the last one wakes ``reader``) and read until it
    comes back: the ids the reader returned for that cycle, in order."""
    for fid in ids:
        tx.send(can.Message(arbitration_id=fid, data=bytes(6), is_extended_id=False))
    got: list[int] = []
    end = time.monotonic() + 5
    while ids[-1] not in got and time.monotonic() < end:
        got += [f.arbitration_id for f in reader.read(0.5)]
    return got


def wait_alive(endpoint: str, names: list[str], timeout: float = 30.0) -> None:
    """Until every named node has declared its liveliness token (it does so after configure())."""
    s = connect(endpoint, timeout)
    try:

        def alive() -> bool:
            replies = s.liveliness().get("exolink/*/nodes/*/alive", timeout=1)
            seen = {str(r.ok.key_expr).split("/")[3] for r in replies if r.ok is not None}
            return set(names) <= seen

        wait_for(alive, timeout=timeout)
    finally:
        s.close()


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Spawner]:
    """exolink processes (``spawn("up", "-c", cfg, name="up")``) logging into the test's tmp
    folder, all ended after the test, its ``cleanups`` (holders, sessions) first."""
    spawner = Spawner(tmp_path)
    yield spawner
    spawner.close()


# --- kernel-level fixtures (tests/kernel): real vcan0 and vfat card (UML guest), gpio-sim (qemu) ---
# On a kernel without them (the plain host) those tests skip with the reason; `make test-kernel`
# runs them inside the guests (tests/kernel/vmtest.sh), where a missing feature fails instead.

GPIO_SIM = Path("/sys/kernel/config/gpio-sim")
REQUIRED = os.environ.get("EXOLINK_REQUIRE_KERNEL", "")  # set inside the guests: fail, never skip


def _missing(feature: str, why: str) -> None:
    if feature in REQUIRED:
        pytest.fail(f"inside the test guest: {why}")
    pytest.skip(why)


def _vcan_possible() -> str | None:
    from pyroute2 import IPRoute
    from pyroute2.netlink.exceptions import NetlinkError

    try:
        with IPRoute() as ip:
            if ip.link_lookup(ifname="vcan0"):
                ip.link("del", index=ip.link_lookup(ifname="vcan0")[0])
            ip.link("add", ifname="vcan0", kind="vcan")
    except NetlinkError as exc:
        return f"this kernel has no SocketCAN vcan ({exc}); run `make test-kernel`"
    return None


@pytest.fixture
def vcan0() -> Iterator[str]:
    """vcan0 created through netlink and brought up by the supervisor's own bring-up code."""
    why = _vcan_possible()
    if why:
        _missing("can", why)
    from exolink.config import CanConfig

    canlink.bring_up(CanConfig(interface="socketcan", channel="vcan0"))
    yield "vcan0"
    from pyroute2 import IPRoute

    with IPRoute() as ip:
        idx = ip.link_lookup(ifname="vcan0")
        if idx:
            ip.link("del", index=idx[0])


@pytest.fixture
def own_clock() -> Iterator[None]:
    """A kernel whose wall clock a test may step: only a throwaway guest's (`make test-kernel`
    sets EXOLINK_REQUIRE_KERNEL=clock in the UML guest); the host's clock is never stepped. The
    clock is put back (to within the test's run time) afterwards."""
    if "clock" not in REQUIRED:
        pytest.skip("stepping the wall clock needs a throwaway kernel; run `make test-kernel`")
    wall, mono = time.time(), time.monotonic()
    yield
    time.clock_settime(time.CLOCK_REALTIME, wall + time.monotonic() - mono)


class SimChip:
    """A gpio-sim chip made through configfs; lines are driven through their `pull` attribute."""

    def __init__(self, name: str, lines: int = 8) -> None:
        self.dir = GPIO_SIM / name
        (self.dir / "bank0").mkdir(parents=True)
        (self.dir / "bank0" / "num_lines").write_text(str(lines))
        (self.dir / "live").write_text("1")
        self.chip = "/dev/" + (self.dir / "bank0" / "chip_name").read_text().strip()
        dev = (self.dir / "dev_name").read_text().strip()
        self.sysfs = Path("/sys/devices/platform") / dev / Path(self.chip).name

    def pull(self, line: int, up: bool) -> None:
        (self.sysfs / f"sim_gpio{line}" / "pull").write_text("pull-up" if up else "pull-down")

    def value(self, line: int) -> int:
        return int((self.sysfs / f"sim_gpio{line}" / "value").read_text())

    def close(self) -> None:
        (self.dir / "live").write_text("0")
        (self.dir / "bank0").rmdir()
        self.dir.rmdir()


@pytest.fixture
def gpio_sim() -> Iterator[SimChip]:
    if not GPIO_SIM.is_dir():
        _missing("gpio", "this kernel has no gpio-sim (configfs gpio-sim); run `make test-kernel`")
    chip = SimChip(f"exo{os.getpid()}{int(time.time() * 1000) % 100000}")
    yield chip
    chip.close()


@pytest.fixture
def fat_boot(tmp_path: Path) -> Iterator[Path]:
    """A fresh vfat on /dev/ubdb (UML guest; its backing file is $EXOLINK_FAT_CARD), mounted like
    the board's /boot/firmware, with periodic writeback off so only explicit syncs reach it."""
    if not os.environ.get("EXOLINK_FAT_CARD") or not Path("/dev/ubdb").exists():
        _missing("fat", "no FAT card disk (/dev/ubdb); run `make test-kernel`")
    subprocess.run(["mkfs.vfat", "-n", "EXOLINK", "/dev/ubdb"], check=True, capture_output=True)
    mnt = tmp_path / "boot"
    mnt.mkdir()
    subprocess.run(
        ["mount", "-t", "vfat", "-o", "fmask=0177,dmask=0077", "/dev/ubdb", str(mnt)], check=True
    )
    vm = Path("/proc/sys/vm")
    saved = {
        k: (vm / k).read_text() for k in ("dirty_writeback_centisecs", "dirty_expire_centisecs")
    }
    (vm / "dirty_writeback_centisecs").write_text("0")
    (vm / "dirty_expire_centisecs").write_text("360000")
    try:
        yield mnt
    finally:
        for k, v in saved.items():
            (vm / k).write_text(v)
        subprocess.run(["umount", str(mnt)], check=True)


# --- image fixtures (tests/image): the recipe checks on the host and the built-image checks ---


@pytest.fixture
def debian_lock() -> dict[str, str]:
    """image/debian.lock as package -> version; a malformed line fails here, not as a wrong pin."""
    lines = (REPO / "image/debian.lock").read_text().splitlines()
    bad = [line for line in lines if not re.fullmatch(r"[a-z0-9][a-z0-9+.-]*=\S+", line)]
    assert bad == [], "not name=version"
    return dict(line.split("=", 1) for line in lines)


# --- foot switches streamed to an h2 reader (tests/test_data_path.py, tests/kernel) -----------

FEET_A, FEET_B, FEET_C = (1, 0, 0, 1), (0, 1, 1, 0), (0, 0, 0, 0)
# cycles: 40 of A, 30 of B, 2 of C, 28 of A again, then A with another battery count
FEET_STATES = (
    [(FEET_A, 200)] * 40
    + [(FEET_B, 200)] * 30
    + [(FEET_C, 200)] * 2
    + [(FEET_A, 200)] * 28
    + [(FEET_A, 199)] * 5
)
# its transitions, as a subscriber sees them (switches as booleans)
FEET_RUNS = [
    (tuple(bool(x) for x in sw), bat)
    for sw, bat in [(FEET_A, 200), (FEET_B, 200), (FEET_C, 200), (FEET_A, 200), (FEET_A, 199)]
]
FeetSample = tuple[int, tuple[bool, ...], int]  # stamp (ns), switches, battery count


def stream_feet(bus: can.BusABC) -> None:
    """FEET_STATES as the H2 sends them: angles, torques, foot switches every 10 ms."""
    from exolink.protocol import h2

    t = time.monotonic()
    for sw, battery in FEET_STATES:
        for frame in (
            h2.JointAngles(10, 20, 0, 10, 20, 0),
            h2.JointTorques(0, 0, 0, 0, 0, 0),
            h2.FootSwitches(*sw, battery),
        ):
            bus.send(h2.encode(frame))
        t += 0.01
        time.sleep(max(0.0, t - time.monotonic()))


def feet_subscriber(hub: Any) -> tuple[Any, list[FeetSample]]:
    """A subscriber of ``foot_switches`` on ``hub`` and the samples it got, in order."""
    from exolink import messaging

    key = messaging.topic_key(0, "h2", "foot_switches", "exolink_msgs/msg/FootSwitches")
    got: list[FeetSample] = []

    def on(sample: Any) -> None:
        m = messaging.deserialize(sample.payload.to_bytes(), "exolink_msgs/msg/FootSwitches")
        sw = (m.r_heel, m.r_toe, m.l_heel, m.l_toe)
        got.append((messaging.stamp_ns(m.header.stamp), sw, m.battery_raw))

    return hub.declare_subscriber(key, on), got


def feet_runs(got: list[FeetSample]) -> list[tuple[tuple[bool, ...], int]]:
    """The transitions in what a subscriber got (a refresh repeats a state: not one)."""
    return [
        (sw, bat) for i, (_t, sw, bat) in enumerate(got) if i == 0 or got[i - 1][1:] != (sw, bat)
    ]


def reader_stats(hub: Any, timeout_s: float = 3) -> dict[str, Any] | None:
    """The sim config's h2 reader's stats, or None while its queryable is not declared yet."""
    from exolink import messaging

    try:
        return messaging.request(hub, "exolink/sim/nodes/h2_reader/stats", timeout_s=timeout_s)
    except messaging.Unreachable:
        return None
