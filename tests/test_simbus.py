"""The simulated bus as python-can's interface ``exolink_sim``: opened by ``can.Bus`` in another
process and by python-can's own tools, talking to the appliance's reader, on python-can's
udp_multicast wire format."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import can
import pytest
from can.interfaces.udp_multicast.utils import pack_message

from exolink.canbus import open_bus, open_reader
from exolink.canbus.simbus import SIM_PORT, SimBus, sim_source
from exolink.config import CanConfig

PEER = r"""
import json, sys, time
import can

group = sys.argv[1]
bus = can.Bus(interface="exolink_sim", channel=group,
              can_filters=[{"can_id": 70, "can_mask": 0x7FF, "extended": False}])
time.sleep(0.3)  # the appliance's reader is open before this process starts
for i in (110, 120, 130):
    bus.send(can.Message(arbitration_id=i, data=bytes([i & 0xFF, 1]), is_extended_id=False))
got = []
end = time.monotonic() + 5
while time.monotonic() < end and len(got) < 2:
    m = bus.recv(0.2)
    if m is not None:
        got.append([m.arbitration_id, bytes(m.data).hex()])
print(json.dumps({"cls": f"{type(bus).__module__}.{type(bus).__name__}", "got": got,
                  "valid": "exolink_sim" in can.interfaces.VALID_INTERFACES}))
bus.shutdown()
"""


@pytest.mark.parametrize("name", ["exolink_sim", "udp_multicast"])
def test_can_bus_in_another_process_talks_to_the_appliance_reader(group: str, name: str) -> None:
    """A process that knows only python-can opens the sim bus by its interface name, sends
    to the appliance's batched reader and receives what the appliance sends; the appliance's
    config names the bus either way (``udp_multicast`` is the same bus)."""
    cfg = CanConfig(interface=name, channel=group)  # type: ignore[arg-type]
    reader = open_reader(cfg, [110, 130])
    tx = open_bus(cfg, filters=[])
    try:
        peer = subprocess.Popen(
            [sys.executable, "-c", PEER, group], stdout=subprocess.PIPE, text=True
        )
        got = []
        end = time.monotonic() + 10
        while time.monotonic() < end and len(got) < 2:
            got += reader.read(0.2)
        for i in (70, 71, 70):
            tx.send(can.Message(arbitration_id=i, data=bytes([i, 2]), is_extended_id=False))
            time.sleep(0.05)
        out, _ = peer.communicate(timeout=15)
        assert peer.returncode == 0
        res = json.loads(out.strip().splitlines()[-1])
        assert res == {
            "cls": "exolink.canbus.simbus.SimBus",
            "got": [[70, "4602"], [70, "4602"]],
            "valid": True,
        }
        assert [(f.arbitration_id, f.data) for f in got] == [(110, b"\x6e\x01"), (130, b"\x82\x01")]
        assert reader.dropped == 0 and reader.malformed == 0
        assert reader.counters()["filtered"] == 0  # 120 never reached it: kernel membership
    finally:
        reader.close()
        tx.shutdown()


def test_python_can_logger_reads_the_sim_bus(group: str) -> None:
    """python-can's own tool, given only the interface name and the group, logs our frames."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "can.logger", "-i", "exolink_sim", "-c", group],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    tx = open_bus(CanConfig(interface="exolink_sim", channel=group), filters=[])
    try:
        time.sleep(1.5)  # python-can's import and the logger's start
        for _ in range(3):
            tx.send(can.Message(arbitration_id=0x6E, data=b"\xca\xfe", is_extended_id=False))
            time.sleep(0.2)
    finally:
        tx.shutdown()
        proc.terminate()
    out, _ = proc.communicate(timeout=10)
    assert "Connected to SimBus" in out
    lines = [ln for ln in out.splitlines() if "ID:" in ln]
    assert lines and all("06e" in ln and "ca fe" in ln for ln in lines), out


def test_the_datagram_is_python_cans_from_the_ids_source(group: str) -> None:
    """The wire: python-can's udp_multicast msgpack, to the group's port, from the loopback
    source that encodes the id (what a filtered reader joins)."""
    lo = socket.if_nametoindex("lo")
    plain = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    plain.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    plain.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    plain.bind((group, SIM_PORT))
    mreq = socket.inet_aton(group) + socket.inet_aton("127.0.0.1") + lo.to_bytes(4, sys.byteorder)
    plain.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
    plain.settimeout(2)
    bus = can.Bus(interface="exolink_sim", channel=group)
    try:
        assert isinstance(bus, SimBus) and bus.fileno() == bus.socket.fileno()
        msg = can.Message(arbitration_id=0x123, data=b"\x01\x02\x03", is_extended_id=False)
        bus.send(msg)
        data, (src, port) = plain.recvfrom(4096)
        assert data == pack_message(msg)
        assert (src, port) == (sim_source(0x123), SIM_PORT)
        assert bus.socket.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
    finally:
        bus.shutdown()
        plain.close()
