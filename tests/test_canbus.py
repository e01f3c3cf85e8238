"""The batched frame reader and the simulated bus (udp_multicast on loopback) on real sockets."""

from __future__ import annotations

import socket
import struct
import threading
import time
from pathlib import Path

import can
import pytest
from conftest import read_cycle

from exolink.canbus import SO_TIMESTAMPNS, BatchReceiver, open_bus, open_reader
from exolink.canbus.simbus import sim_source
from exolink.config import CanConfig


def _raw_to_group(group: str, data: bytes, source: str) -> None:
    """A datagram onto the sim bus from ``source`` (through loopback), not python-can's."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((source, 0))
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        s.sendto(data, (group, 43113))
    finally:
        s.close()


def test_a_reader_with_every_s_takes_frames_arriving_meanwhile_as_one_batch(group: str) -> None:
    """Why the timing monitor uses ``every_s``: one wake for the frames of a period, none
    counted late for the wait."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, [110], every_s=0.5)
    tx = open_bus(cfg)
    msg = can.Message(arbitration_id=110, data=b"\x01" * 6, is_extended_id=False)
    try:
        tx.send(msg)
        assert len(reader.read(1.0)) == 1  # the first frame after a quiet bus: at once
        for _ in range(3):  # arrive while the reader waits out its 500 ms
            tx.send(msg)
            time.sleep(0.005)
        frames = reader.read(1.0)
        assert len(frames) == 3
        # Their timestamps are not checked here: right after the first timestamping socket
        # opens, the kernel turns timestamps on asynchronously, and a frame that arrives before
        # that carries the read's time (seen twice in full-suite runs). The kernel-time test
        # is test_reader_batches_frames_with_kernel_timestamps.
        c = reader.counters()
        assert c["frames"] == 4 and c["batch_max"] == 3
        assert c["late"] == 0 and c["dropped"] == 0
    finally:
        reader.bus.shutdown()
        tx.shutdown()


def test_sim_kernel_filter_keeps_only_the_ids_asked_for(group: str) -> None:
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, [5, 110, 1100])
    plain = open_bus(cfg)  # no filter: hears everything (proves the frames were on the bus)
    tx = open_bus(cfg)
    try:
        ids = [0, 5, 70, 110, 120, 200, 1100, 1101, 0x7FF]
        for i in ids:
            tx.send(can.Message(arbitration_id=i, data=bytes([i & 0xFF]), is_extended_id=False))
        tx.send(can.Message(arbitration_id=110, data=b"x", is_extended_id=True))
        time.sleep(0.2)
        got = [f.arbitration_id for f in reader.read(0.5)]
        heard = []
        while (m := plain.recv(0.2)) is not None:
            heard.append(m.arbitration_id)
        assert got == [5, 110, 1100] and sorted(heard) == sorted([*ids, 110])
        assert reader.malformed == 0
        # Filtered in the kernel: frames of other ids were never queued, so never counted as
        # drops (a socket filter counted every frame it rejected as dropped).
        assert reader.dropped == 0
        # A datagram in no python-can layout, from an accepted id's source, is counted, not
        # fatal; from any other source it never reaches the filtered reader.
        _raw_to_group(group, b"garbage", source="127.0.0.1")
        _raw_to_group(group, b"garbage", source=sim_source(110))
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
        c = reader.counters()
        assert c["frames"] == 20 and c["batch_max"] == 20 and c["dropped"] == 0
        assert c["late"] == 20  # read 200 ms after they arrived: all later than one H2 period
    finally:
        reader.bus.shutdown()
        tx.shutdown()


def test_batch_receiver_reads_a_batch_per_call_with_kernel_times_where_asked() -> None:
    """One recvmmsg per call, up to the batch limit, each datagram whole and in order; a socket
    that asked for no kernel timestamps gives None (the reader then uses the read time); a
    closed socket raises OSError, as recvmsg would."""
    rx_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx_sock.bind(("127.0.0.1", 0))
    stamped = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stamped.bind(("127.0.0.1", 0))
    stamped.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        plain, timed = BatchReceiver(rx_sock), BatchReceiver(stamped)
        assert plain.receive() == []  # nothing queued: no wait, no error
        t0 = time.time()
        for i in range(70):
            tx.sendto(bytes([i]) * (1 + i), rx_sock.getsockname())
            tx.sendto(bytes([i]) * 3, stamped.getsockname())
        time.sleep(0.1)
        first, rest = plain.receive(), plain.receive()
        assert [d for d, _ts in first + rest] == [bytes([i]) * (1 + i) for i in range(70)]
        assert len(first) == 64 and {ts for _d, ts in first + rest} == {None}
        got = timed.receive() + timed.receive()
        assert len(got) == 70
        assert all(t0 - 0.01 < ts < time.time() for _d, ts in got)  # type: ignore[operator]
        rx_sock.close()
        with pytest.raises(OSError):
            plain.receive()
    finally:
        for s in (rx_sock, stamped, tx):
            s.close()


def test_fixed_size_batch_parses_stamps_and_flags_truncated_datagrams() -> None:
    """SocketCAN's batch path (receive_fixed: one struct call per batch for the headers and the
    kernel times) on real kernel datagrams of a can_frame's 16 bytes: every one whole and
    stamped, in order; a longer one (a CAN FD frame's 72 bytes) arrives truncated and says so;
    a socket without timestamps gives None. Checked against the per-datagram path."""
    rx_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx_sock.bind(("127.0.0.1", 0))
    rx_sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    plain = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    plain.bind(("127.0.0.1", 0))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    frame = struct.Struct("=IB3x8s")
    try:
        fixed, other = BatchReceiver(rx_sock, frame.size), BatchReceiver(plain, frame.size)
        assert fixed.receive_fixed()[0] == 0
        t0 = time.time()
        sent = [frame.pack(100 + i, i % 9, bytes(range(i, i + 8))) for i in range(70)]
        sent[5] = bytes(72)  # too long for the buffer
        for d in sent:
            tx.sendto(d, rx_sock.getsockname())
        tx.sendto(sent[0], plain.getsockname())
        time.sleep(0.1)
        n, data, whole, stamps = fixed.receive_fixed()
        assert n == 64 and len(data) == 64 * frame.size
        assert whole == [i != 5 for i in range(64)]
        assert all(t0 - 0.01 < ts < time.time() for ts in stamps)  # type: ignore[operator]
        got = [bytes(data[i * 16 : (i + 1) * 16]) for i in range(64)]
        assert got[:5] == sent[:5] and got[6:] == sent[6:64]
        n, data, whole, stamps = fixed.receive_fixed()
        assert n == 6 and bytes(data) == b"".join(sent[64:]) and all(whole)
        assert other.receive_fixed()[3] == [None]
    finally:
        for s in (rx_sock, plain, tx):
            s.close()


def test_stalled_sim_reader_counts_every_frame_it_lost(group: str) -> None:
    """frames of its ids sent = received + dropped, exactly, on the simulated bus; frames of
    other ids on the same bus (as many again) are neither received nor counted."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, [110], rcvbuf=1 << 16)  # a small queue: the stall overflows it
    tx = open_bus(cfg)
    sent = 2000
    try:
        for i in range(sent):  # nobody reads meanwhile: the reader is stalled
            tx.send(
                can.Message(arbitration_id=110, data=i.to_bytes(2, "little"), is_extended_id=False)
            )
            tx.send(
                can.Message(arbitration_id=120, data=i.to_bytes(2, "little"), is_extended_id=False)
            )
        received = []
        while frames := reader.read(0.3):
            received += frames
        dropped = reader.dropped
        assert dropped is not None and dropped > 0
        assert len(received) + dropped == sent
        assert {f.arbitration_id for f in received} == {110}
        assert reader.counters()["batches_full"] > 0  # the backlog it came back to
    finally:
        reader.bus.shutdown()
        tx.shutdown()


def test_receive_buffer_is_what_the_kernel_granted(group: str) -> None:
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, [110], rcvbuf=1 << 16)
    try:
        sock = reader.bus.socket  # type: ignore[attr-defined]
        assert reader.rcvbuf == sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        assert reader.rcvbuf == 2 * (1 << 16)  # below any rmem_max: granted (doubled) as asked
    finally:
        reader.bus.shutdown()


def test_more_ids_than_the_kernel_filter_takes(group: str) -> None:
    """Past net.ipv4.igmp_max_msf sources the reader joins for every source and filters in
    Python: same frames, and the others are counted as filtered."""
    limit = int(Path("/proc/sys/net/ipv4/igmp_max_msf").read_text())
    ids = list(range(200, 200 + limit + 1))
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, ids)
    tx = open_bus(cfg)
    try:
        for i in (ids[0], 70, ids[-1], 120):
            tx.send(can.Message(arbitration_id=i, data=b"\x01", is_extended_id=False))
        time.sleep(0.2)
        assert [f.arbitration_id for f in reader.read(0.5)] == [ids[0], ids[-1]]
        c = reader.counters()
        assert c["filtered"] == 2 and c["dropped"] == 0
    finally:
        reader.bus.shutdown()
        tx.shutdown()


def test_a_bus_that_only_sends_is_sent_nothing(group: str) -> None:
    """filters=[] (the h2 sender's bus): no membership, so no frame is queued for it."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    quiet = open_bus(cfg, filters=[])
    tx = open_bus(cfg)
    try:
        for _ in range(5):
            tx.send(can.Message(arbitration_id=110, data=b"\x01", is_extended_id=False))
        time.sleep(0.1)
        sock = quiet.socket  # type: ignore[attr-defined]
        sock.setblocking(False)
        with pytest.raises(BlockingIOError):
            sock.recv(256)
    finally:
        quiet.shutdown()
        tx.shutdown()


def _send(bus: can.BusABC, *ids: int) -> None:
    for i in ids:
        bus.send(can.Message(arbitration_id=i, data=bytes([i & 0xFF]) * 6, is_extended_id=False))


def test_only_the_waking_id_wakes_a_reader_and_the_cycle_comes_in_order(group: str) -> None:
    """The h2 reader's one wake-up per H2 cycle: 110 and 120 wait, quietly, for the 130 that
    ends the cycle; a cycle without its 130 is read when the timeout ends."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    tx = open_bus(cfg)
    with open_reader(cfg, [110, 120, 130], wake_on=[130]) as reader:
        _send(tx, 110, 120)
        start = time.monotonic()
        got = reader.read(0.4)
        assert time.monotonic() - start >= 0.4  # nothing woke it
        assert [f.arbitration_id for f in got] == [110, 120]
        for _ in range(3):
            _send(tx, 110, 120, 130)
            start = time.monotonic()
            got = reader.read(5.0)
            assert time.monotonic() - start < 4.0  # the 130 woke it, not the timeout
            while len(got) < 3:  # the three datagrams may land a moment apart
                got += reader.read(0.2)
            assert [f.arbitration_id for f in got] == [110, 120, 130]
            assert got == sorted(got, key=lambda f: f.timestamp)
        c = reader.counters()
        assert c["frames"] == 11 and c["dropped"] == 0
    tx.shutdown()


def test_a_deadline_reader_sleeps_through_frames_and_a_wake_fd_ends_the_wait(group: str) -> None:
    """The watchdog's armed mode: no frame ends the wait (frames_wake=False); a byte on a wake
    descriptor does (arming changed), and the frames queued meanwhile come with it."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    tx = open_bus(cfg)
    r, w = socket.socketpair()
    try:
        with open_reader(cfg, [70, 110], wake_on=[70]) as reader:
            _send(tx, 110, 70)
            time.sleep(0.05)
            start = time.monotonic()
            got = reader.read(0.3, wake_fds=[r.fileno()], frames_wake=False)
            assert time.monotonic() - start >= 0.3
            assert sorted(f.arbitration_id for f in got) == [70, 110] and reader.complete
            _send(tx, 110)
            threading.Timer(0.1, lambda: w.send(b"!")).start()
            start = time.monotonic()
            got = reader.read(5.0, wake_fds=[r.fileno()], frames_wake=False)
            assert time.monotonic() - start < 4.0
            assert [f.arbitration_id for f in got] == [110]
    finally:
        r.close()
        w.close()
        tx.shutdown()


def test_wake_on_must_name_some_but_not_all_ids(group: str) -> None:
    cfg = CanConfig(interface="udp_multicast", channel=group)
    for wake in ([200], [110, 120]):
        with pytest.raises(ValueError, match="wake_on"):
            open_reader(cfg, [110, 120], wake_on=wake)


def test_a_reader_that_fell_behind_skips_stale_frames_and_counts_them(group: str) -> None:
    """On the board proxy the h2 reader fell 79 s behind and never caught up (a FIFO as long
    as its buffer): with stale_s it skips what is older, counted, and reads the news."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    tx = open_bus(cfg)
    with open_reader(cfg, [110, 120], wake_on=[120], stale_s=0.2) as reader:
        for _ in range(5):
            _send(tx, 110, 120)
        time.sleep(0.4)  # the reader "busy": these ten frames go stale
        _send(tx, 110, 120)
        got = []
        end = time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < end:
            got += reader.read(0.5)
        c = reader.counters()
        assert [f.arbitration_id for f in got] == [110, 120]
        assert c["stale"] == 10 and c["frames"] == 12 and c["dropped"] == 0
    tx.shutdown()


def test_a_reader_behind_by_more_than_a_batch_reads_its_two_sockets_in_step(group: str) -> None:
    """On the board proxy the h2 reader, behind by seconds, took 64 frames of each socket per
    read: 64 cycles of the waking 130 but only 32 of the quiet 110/120, so the quiet socket fell
    ever further behind, its frames went stale and overflowed, and no joint_states came out at
    all (published 0, 130 only). Each read must end where the socket that stopped at its batch
    ended: frames come out in kernel-time order, every one of them, across reads."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    tx = open_bus(cfg)
    cycles = 150  # 450 frames: several batches of each socket
    with open_reader(cfg, [110, 120, 130], wake_on=[130]) as reader:
        for _ in range(cycles):
            _send(tx, 110, 120, 130)
        time.sleep(0.3)  # all queued: the reader "was busy"
        got = reader.read(0.2)
        assert not reader.complete and reader.behind_s > 0.25, reader.behind_s  # says it is behind
        end = time.monotonic() + 10
        while len(got) < 3 * cycles and time.monotonic() < end:
            batch = reader.read(0.2)
            if got and batch:
                assert batch[0].timestamp >= got[-1].timestamp, "a read went back in time"
            got += batch
        ids = [f.arbitration_id for f in got]
        assert ids == [110, 120, 130] * cycles, ids[:12]
        assert reader.read(0.05) == [] and reader.behind_s == 0.0
        assert reader.counters()["dropped"] == 0
    tx.shutdown()


def test_set_ids_changes_what_a_two_socket_reader_returns_without_reopening(group: str) -> None:
    """The controller manager drops torque and foot-switch frames when no loaded controller
    reads them, and takes them back, on the reader it has open: nothing queued is lost."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    with (
        open_bus(cfg) as tx,
        open_reader(cfg, [70, 110, 120, 130], wake_on=[110]) as reader,
    ):

        def cycle() -> list[int]:
            return read_cycle(tx, reader, [70, 120, 130, 110])

        assert cycle() == [70, 120, 130, 110]
        reader.set_ids([70, 110])
        assert cycle() == [70, 110]
        with pytest.raises(ValueError, match="must keep the waking ids"):
            reader.set_ids([70, 120])
        reader.set_ids([70, 110, 130])
        assert cycle() == [70, 130, 110]
        reader.set_ids([70, 110, 120, 130])
        assert cycle() == [70, 120, 130, 110]


def test_a_reader_asks_for_a_batch_that_holds_its_wake(group: str) -> None:
    """The h2 reader with a MACCEPA board wakes once per 10 cycles for ~66 frames: a batch of
    the default 64 stopped short and a second read (a whole loop iteration more, beat and
    publish included) followed every wake (board proxy, docs/performance.md); so did a quarter
    of the wakes with a batch of 72 when the core was busy. The batch is twice the wake's
    cycles and two more; one read then takes them all."""
    from exolink.canbus import Cadence

    assert Cadence(0.01, 10).batch(6) == 132 and Cadence(0.01, 1).batch(3) == 64
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
        pytest.raises(ValueError, match=r"1\.\.1024"),
    ):
        BatchReceiver(sock, 16, 0)
    cfg = CanConfig(interface="udp_multicast", channel=group)
    tx = open_bus(cfg)
    with open_reader(cfg, [110, 120, 130, 50, 60, 70], batch=72) as reader:
        for _ in range(11):
            _send(tx, 110, 120, 130, 50, 60, 70)
        time.sleep(0.3)
        got = reader.read(1.0)
        c = reader.counters()
    tx.shutdown()
    assert len(got) == 66 and c["batches"] == 1 and c["batches_full"] == 0, c


def test_a_reader_keeps_its_cadence_whatever_its_caller_spends_on_a_read() -> None:
    """The next read is due ``every_s`` after the last was due, not after the caller's work
    ended; one far behind starts afresh instead of reading twice in a row."""
    from exolink.canbus.reader import next_read

    assert next_read(10.0, 10.017, 0.1) == pytest.approx(10.1)  # 17 ms on the frames: no drift
    assert next_read(10.0, 10.09, 0.1) == pytest.approx(10.19)  # late by most of a period
    assert next_read(10.0, 10.3, 0.1) == pytest.approx(10.4)  # far behind: a period from now
    assert next_read(0.0, 5000.0, 0.1) == pytest.approx(5000.1)  # the first read
