"""The simulated bus stays on this machine: joined on and sent through loopback whatever the
routes say, needing no route at all, and `exolink up` says what is missing when loopback is.

Each test runs in a network namespace of its own (``unshare``: a user namespace maps this user
to root there, so no privilege is needed on the host), where routes and interfaces are ours."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.harness import EXOLINK

ROUND_TRIPS = r"""
import json, socket, subprocess, sys, time
import can
from exolink.canbus import open_bus, open_reader
from exolink.config import CanConfig

group = sys.argv[1]
def sh(cmd):
    subprocess.run(cmd, shell=True, check=True, capture_output=True)

def sniffer(dev):  # every packet leaving or entering dev
    s = socket.socket(socket.AF_PACKET, socket.SOCK_DGRAM, socket.htons(0x0003))
    s.bind((dev, 0))
    s.setblocking(False)
    return s

def to_group(s):
    n = 0
    while True:
        try:
            pkt = s.recv(2048)
        except BlockingIOError:
            return n
        n += len(pkt) >= 20 and pkt[16:20] == socket.inet_aton(group)

sh("ip link set lo up")
for dev, net in (("e0", "10.9.0"), ("f0", "10.8.0")):
    sh(f"ip link add {dev} type veth peer name {dev}p && ip link set {dev}p up && "
       f"ip link set {dev} up && ip addr add {net}.2/24 dev {dev}")
sniff = {dev: sniffer(dev) for dev in ("e0", "f0")}
cfg = CanConfig(interface="udp_multicast", channel=group)
out = {}
try:
    reader, tx = open_reader(cfg, [110]), open_bus(cfg)
except Exception as exc:
    print(json.dumps({"open_error": str(exc)}))
    sys.exit(0)

def trial(name):
    for _ in range(10):
        tx.send(can.Message(arbitration_id=110, data=b"\x01" * 6, is_extended_id=False))
    time.sleep(0.1)
    got = []
    while frames := reader.read(0.2):
        got += frames
    out[name] = len(got)

trial("no_route")
sh("ip route add default via 10.9.0.1 dev e0")
trial("default_via_e0")
sh("ip route replace default via 10.8.0.1 dev f0")
trial("default_via_f0")
out["left_on"] = {dev: to_group(s) for dev, s in sniff.items()}
reader.bus.shutdown()
tx.shutdown()
print(json.dumps(out))
"""


def in_netns(*cmd: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    if not shutil.which("unshare"):
        pytest.skip("no unshare(1) for a private network namespace")
    probe = subprocess.run(["unshare", "-rn", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no private network namespace here: {probe.stderr.decode().strip()}")
    return subprocess.run(["unshare", "-rn", *cmd], capture_output=True, text=True, timeout=timeout)


def test_sim_bus_stays_on_loopback_whatever_the_routes(group: str) -> None:
    """No route at all, then a default route, then the default route moved to another
    interface mid-run: every frame arrives, and none leaves by either interface. (python-can's
    own bus needed a route, went out on the default route's interface, and went silent when
    the route moved: its members stayed joined on the old interface.)"""
    r = in_netns(sys.executable, "-c", ROUND_TRIPS, group)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {
        "no_route": 10,
        "default_via_e0": 10,
        "default_via_f0": 10,
        "left_on": {"e0": 0, "f0": 0},
    }


def test_up_without_loopback_says_so_in_one_line(write_config) -> None:  # type: ignore[no-untyped-def]
    """Loopback down (a fresh namespace): `exolink up --sim` exits non-zero with one line that
    names what is missing and the command that fixes it."""
    cfg: Path = write_config()
    r = in_netns(*EXOLINK, "up", "--sim", "-c", str(cfg))
    assert r.returncode != 0
    errors = [line for line in r.stderr.splitlines() if line.startswith("exolink:")]
    assert len(errors) == 1, r.stderr
    assert "loopback" in errors[0] and "`ip link set lo up`" in errors[0]
    assert "Traceback" not in r.stderr + r.stdout


def test_sim_bus_datagrams_leave_with_ttl_zero(group: str) -> None:
    """Belt and braces: were a frame ever routed off loopback, TTL 0 keeps it on the host."""
    from exolink.canbus import open_bus
    from exolink.config import CanConfig

    bus = open_bus(CanConfig(interface="udp_multicast", channel=group))
    try:
        sock = bus.socket  # type: ignore[attr-defined]
        assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
    finally:
        bus.shutdown()
