"""Shared fixtures: isolated multicast groups and Zenoh ports, configs written to tmp files,
and helpers to run exolink processes for real (no mocks of buses or sessions)."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import random
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest
import yaml
import zenoh
from exolink import messaging
from exolink.canbus import Frame, FrameReader, open_reader
from exolink.config import CanConfig, bundled, load
from exolink.holder import Holder
from exolink.supervisor import canlink

EXOLINK = [sys.executable, "-m", "exolink.cli.main"]
REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
def group() -> str:
    """A multicast group of its own per test, so concurrent or leftover traffic never mixes."""
    return f"239.74.{random.randint(1, 254)}.{random.randint(1, 254)}"


def motion_nodes(deadline_ms: int = 300, h2_timeout_ms: int | None = 300) -> list[dict]:
    """The simulated H2, its reader and the controller manager (the one writer of motion).
    ``deadline_ms``: the manager's heartbeat deadline (300: above a loaded test machine's
    stalls, where the deadline is not under test; 50 as shipped)."""
    manager: dict = {
        "name": "controller_manager",
        "plugin": "controller_manager",
        "critical": True,
        "heartbeat_deadline_ms": deadline_ms,
    }
    if h2_timeout_ms is not None:
        manager["params"] = {"h2_timeout_ms": h2_timeout_ms}
    return [
        {"name": "simulator", "plugin": "simulator"},
        {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
        manager,
    ]


@pytest.fixture
def write_config(tmp_path: Path, group: str) -> Callable[..., Path]:
    """Write the bundled sim config with overrides onto this test's own group and port."""

    def write(nodes: list[dict] | None = None, **overrides: object) -> Path:
        data = yaml.safe_load(bundled("sim").read_text())
        data["can"]["channel"] = group
        data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
        if nodes is not None:
            data["nodes"] = nodes
        for key, value in overrides.items():
            if isinstance(value, dict) and isinstance(data.get(key), dict):
                data[key].update(value)
            else:
                data[key] = value
        path = tmp_path / "appliance.yaml"
        path.write_text(yaml.safe_dump(data))
        return path

    return write


class DrainedBus:
    """A bus listener read continuously by a thread into a queue, with an exact loss count.

    At 600 frames/s a socket left unread while a test waits on a CLI call overflows its kernel
    buffer and silently drops the newest frames: exactly the ones a test looks for. The thread
    reads through the appliance's own FrameReader (its large receive queue), and ``dropped``
    is the kernel's count of what this listener lost, so a test can tell "not on the bus"
    from "not seen"."""

    def __init__(self, reader: FrameReader) -> None:
        self.reader = reader
        self.q: queue.Queue[Frame] = queue.Queue()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._drain, daemon=True)
        self._t.start()

    def _drain(self) -> None:
        while not self._stop.is_set():
            for m in self.reader.read(0.05):
                self.q.put(m)

    @property
    def dropped(self) -> int:
        return self.reader.dropped or 0

    def recv(self, timeout: float | None = None) -> Frame | None:
        try:
            return self.q.get(timeout=timeout)
        except queue.Empty:
            return None

    def send(self, msg: can.Message) -> None:
        self.reader.bus.send(msg)

    def shutdown(self) -> None:
        self._stop.set()
        self._t.join(1)
        self.reader.close()


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
    bus = DrainedBus(open_reader(CanConfig(interface="udp_multicast", channel=group)))
    yield bus
    bus.shutdown()


def collect(
    bus: can.BusABC | DrainedBus, seconds: float, ids: set[int] | None = None
) -> list[can.Message]:
    out = []
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        m = bus.recv(timeout=left)
        if m is not None and (ids is None or m.arbitration_id in ids):
            out.append(m)
    return out


def bus_sockets(pid: int) -> int:
    """The sim-bus sockets (bound to its UDP port) a process holds, from /proc."""
    from exolink.simbus import SIM_PORT

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


def wait_for(pred: Callable[[], object], timeout: float = 10.0, step: float = 0.02) -> object:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(step)
    raise AssertionError(f"condition not met within {timeout} s")


def connect(endpoint: str, timeout: float = 30.0) -> zenoh.Session:
    """A client session to a process just spawned: it listens once its imports are done, which
    took longer than one connect attempt (3 s) on a host busy with other test runs."""
    end = time.monotonic() + timeout
    while True:
        try:
            return messaging.open_client_session(endpoint)
        except messaging.Unreachable:
            if time.monotonic() > end:
                raise


def connect_as(endpoint: str, login: Path | None, timeout: float = 30.0) -> zenoh.Session:
    """``connect`` with a laptop login file (a board with logins), or none."""
    end = time.monotonic() + timeout
    while True:
        try:
            return messaging.open_client_session(endpoint, str(login) if login else None)
        except messaging.Unreachable:
            if time.monotonic() > end:
                raise


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


class Proc:
    """A real exolink process whose stderr is kept for the failure message."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.log = log
        self._f = log.open("wb")
        env = {**os.environ, "EXOLINK_LOG_JSON": "1", "PYTHONUNBUFFERED": "1"}
        self.p = subprocess.Popen(
            [*EXOLINK, *args], stdout=self._f, stderr=subprocess.STDOUT, env=env
        )

    def stop(self, timeout: float = 10.0) -> int:
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self._f.close()
        return self.p.returncode

    def output(self) -> str:
        return self.log.read_text(errors="replace")


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Callable[..., Proc]]:
    procs: list[Proc] = []
    cleanups: list[Callable[[], None]] = []  # run before the processes stop (holders, sessions)

    def start(*args: str, name: str = "proc") -> Proc:
        p = Proc(list(args), tmp_path / f"{name}-{len(procs)}.log")
        procs.append(p)
        return p

    start.cleanups = cleanups  # type: ignore[attr-defined]
    yield start
    for c in reversed(cleanups):
        with contextlib.suppress(Exception):
            c()
    for p in reversed(procs):
        p.stop()


class Appliance:
    def __init__(
        self, cfg_path, spawn, *, wait_nodes: bool = True, login: Path | None = None
    ) -> None:  # type: ignore[no-untyped-def]
        self.cfg = load(cfg_path)
        self.at = messaging.local_endpoint(self.cfg.zenoh)
        self.login = login  # the laptop login file the CLI uses (a board with logins)
        self.proc = spawn("up", "-c", str(cfg_path), name="up")
        self._cleanups: list[Callable[[], None]] = getattr(spawn, "cleanups", [])
        self.session = None
        wait_for(lambda: self.cli("status").returncode == 0, timeout=20)
        if wait_nodes:
            wait_for(
                lambda: all(n["heartbeat_age_s"] is not None for n in self.status()["nodes"]),
                timeout=20,
            )

    def cli(self, *args: str, login: Path | None = None) -> subprocess.CompletedProcess[str]:
        who = login or self.login
        opts = ["--zenoh-config", str(who)] if who else []
        return subprocess.run(
            # 10 s, not the CLI's 3: the connect waits that long too (a --timeout above 3 s
            # does), and on this 2-core host with chromium and an appliance running, one
            # connect of the dashboard test timed out at 3 s twice in ~8 full-suite runs
            [*EXOLINK, *args, "--at", self.at, "--timeout", "10", *opts],
            capture_output=True,
            text=True,
            timeout=30,
        )

    def status(self) -> dict:
        r = self.cli("status", "--json")
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    def node(self, name: str) -> dict:
        return next(n for n in self.status()["nodes"] if n["name"] == name)

    def arm(self) -> None:
        self.arm_as(None)

    def arm_as(self, login: Path | None) -> None:
        r = wait_for(lambda: (x := self.cli("arm", login=login)).returncode == 0 and x, timeout=10)
        assert "armed" in r.stdout  # type: ignore[union-attr]

    def hold(self, login: Path | None = None, take_over: bool = False) -> Holder:
        """Motion held from this test, as `exolink hold` holds it (renewed from a thread until
        the test ends): nothing moves a joint without a holder. Held once per appliance."""
        held = getattr(self, "_holder", None)
        if held is not None and held.holding and not take_over:
            return held
        who = login or self.login
        session = connect_as(self.at, who)
        user = messaging.client_login(str(who) if who else None)
        key = messaging.mgmt_key(self.cfg.device, "controllers")

        def call(body: dict) -> dict:
            return messaging.request(session, key, body, 10.0, user)

        holder = Holder(call, "test")
        holder.acquire(take_over)
        self._cleanups += [session.close, holder.release]
        self._holder = holder
        return holder

    def arm_and_hold(self) -> Holder:
        self.arm()
        return self.hold()


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
