"""The batched frame reader and the simulated bus' kernel filter, on real udp_multicast sockets
(the simulated bus runs on loopback: a datagram from elsewhere goes through lo)."""

from __future__ import annotations

import socket
import time

import can
from exolink.canbus import open_bus, open_reader
from exolink.config import CanConfig


def test_udp_kernel_filter_keeps_only_the_ids_asked_for(group: str) -> None:
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, [5, 110, 1100])
    plain = open_bus(cfg)  # no filter: hears everything (proves the frames were on the bus)
    tx = open_bus(cfg)
    try:
        ids = [5, 70, 110, 120, 200, 1100, 1101, 0x7FF]
        for i in ids:
            tx.send(can.Message(arbitration_id=i, data=bytes([i & 0xFF]), is_extended_id=False))
        time.sleep(0.2)
        got = [f.arbitration_id for f in reader.read(0.5)]
        heard = []
        while (m := plain.recv(0.2)) is not None:
            heard.append(m.arbitration_id)
        assert got == [5, 110, 1100] and sorted(heard) == sorted(ids)
        assert reader.malformed == 0
        # A datagram in no python-can layout passes the kernel filter and is counted, not fatal.
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        s.sendto(b"garbage", (group, plain._multicast._socket.getsockname()[1]))  # type: ignore[attr-defined]
        s.close()
        time.sleep(0.1)
        assert reader.read(0.2) == [] and reader.malformed == 1
    finally:
        for b in (reader.bus, plain, tx):
            b.shutdown()


def test_reader_batches_frames_with_kernel_timestamps(group: str) -> None:
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, [110])
    tx = open_bus(cfg)
    try:
        t0 = time.time()
        for _ in range(20):
            tx.send(can.Message(arbitration_id=110, data=b"\x01" * 6, is_extended_id=False))
        time.sleep(0.2)
        frames = reader.read(0.5)
        assert len(frames) == 20  # one wake-up, one batch
        assert all(t0 - 0.01 < f.timestamp < time.time() for f in frames)
        assert frames[0].data == b"\x01" * 6
        assert reader.dropped is None  # filtered datagrams count as drops on UDP: not reported
    finally:
        reader.bus.shutdown()
        tx.shutdown()
