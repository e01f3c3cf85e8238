"""Content filters (exolink.canbus.filters): the BPF program the kernel runs on a SocketCAN reader's
socket drops exactly the frames the Python rules drop, and readers on the simulated bus drop the
same frames. The nodes' rules keep what each one acts on.

This kernel has no CAN sockets: the program is run here by the kernel's own BPF on an AF_UNIX
datagram socket fed struct can_frame bytes (the filter sees the same 16 bytes as on CAN_RAW);
tests/kernel/test_socketcan.py runs it on a real vcan in User-Mode Linux."""

from __future__ import annotations

import socket
import time

import can
import pytest
from exolink.nodes.controller_manager import drop_rules, one_socket
from hypothesis import given, settings
from hypothesis import strategies as st

from exolink.canbus import CAN_FRAME, open_bus, open_reader
from exolink.canbus import filters as canfilter
from exolink.canbus.filters import Drop, Predicate
from exolink.config import CanConfig
from exolink.protocol import h2, maccepa

RULES = [Drop(70, 6, byte=1, keep=frozenset({4, 5})), Drop(70, 8), Drop(75, 6)]


def kernel_keeps(rules: list[Drop], frames: list[tuple[int, bytes]]) -> list[bool]:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    with a, b:
        canfilter.attach(b, rules)
        b.setblocking(False)
        out = []
        for can_id, data in frames:
            a.send(CAN_FRAME.pack(can_id, len(data), data))
            try:
                out.append(b.recv(64) == CAN_FRAME.pack(can_id, len(data), data))
            except BlockingIOError:
                out.append(False)
        return out


frames = st.lists(
    st.tuples(
        st.sampled_from([70, 75, 110, 71, 70 | 0x40000000, 70 | 0x80000000]),
        st.binary(min_size=0, max_size=8),
    ),
    min_size=1,
    max_size=40,
)


@settings(max_examples=60, deadline=None)
@given(frames)
def test_the_kernel_drops_what_the_python_rules_drop(batch: list[tuple[int, bytes]]) -> None:
    pred = Predicate(RULES)
    want = [
        bool(cid & 0xE0000000) or not pred.drops(cid, data)  # flagged ids never match a rule
        for cid, data in batch
    ]
    assert kernel_keeps(RULES, batch) == want


def test_the_manager_keeps_disables_and_stops_and_a_configured_board_0() -> None:
    """Of id 70 the manager acts on an H2 disable or stop (from anyone) and on board 0's status
    when it drives board 0; the gait's set-points and an unconfigured board's status are dropped.
    An H2 frame on a driven board's duty id (80: the H2's max angles) is the H2's."""
    jc = h2.JOINT_CONTROL
    position = bytes([1, h2.MODES["position"], 30, 0, 0, 0])
    disable = bytes([2, h2.MODES["disabled"], 0, 0, 0, 0])
    stop = bytes([3, h2.MODES["stopped"], 0, 0, 0, 0])
    status = bytes(maccepa.dlc_of(jc) or 0)
    alone = Predicate(drop_rules(set(), []))
    assert [alone.drops(jc, d) for d in (position, disable, stop, status)] == [
        True,
        False,
        False,
        True,
    ]
    assert not alone.drops(jc, bytes(7))  # malformed: the reader counts it
    ids = [*maccepa.data_ids([0]), maccepa.DUTY_BASE]
    driving = Predicate(drop_rules({0}, ids))
    assert [driving.drops(jc, d) for d in (position, disable, status)] == [True, False, False]
    assert driving.drops(maccepa.DUTY_BASE, bytes(6))  # the H2's max angles on id 80
    assert not driving.drops(maccepa.DUTY_BASE, bytes(8))  # board 0's duty / stop control
    assert not driving.drops(h2.JOINT_ANGLES, bytes(6))


def test_the_manager_reads_one_socket_only_where_the_rest_is_rare_news() -> None:
    """Its filters leave of id 70 only disables and stops (rare): angles and 70 share a socket
    on SocketCAN. Torques, foot switches or a driven board 0's status stream every cycle: they
    go on a second socket that never wakes the loop; the simulated bus filters after the wake."""
    jc, ja = h2.JOINT_CONTROL, h2.JOINT_ANGLES
    assert one_socket("socketcan", [jc, ja], set())
    assert not one_socket("socketcan", [jc, ja, h2.JOINT_TORQUES], set())
    assert not one_socket("socketcan", [jc, ja], {0})  # board 0's status is on 70
    assert not one_socket("udp_multicast", [jc, ja], set())


def test_bad_rules_are_refused_by_name() -> None:
    for rule, words in [
        (Drop(0x800, 6), "standard 11-bit"),
        (Drop(70, 9), "dlc must be 0..8"),
        (Drop(70, 6, byte=6), "inside the frame's 6 bytes"),
        (Drop(70, 6, keep=frozenset({1})), "keep values need a byte"),
        (Drop(70, 6, byte=1, keep=frozenset({256})), "bytes (0..255)"),
    ]:
        with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
            canfilter.check([rule])
    with pytest.raises(ValueError, match="two drop rules for id 70 with 6 bytes"):
        canfilter.check([Drop(70, 6), Drop(70, 6, byte=0, keep=frozenset({1}))])


def test_a_sim_bus_reader_drops_the_same_frames_and_counts_them(group: str) -> None:
    """On the simulated bus the kernel cannot read python-can's datagrams: the reader applies
    the rules itself and counts what it left out in ``filtered``; the waking id still wakes."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    reader = open_reader(cfg, [70, 110], wake_on=[110], drop=RULES)
    tx = open_bus(cfg)
    try:
        sent = [
            (70, bytes([1, 1, 30, 0, 0, 0])),
            (70, bytes(8)),
            (70, bytes([2, 4, 0, 0, 0, 0])),
            (110, bytes(6)),
        ]
        for fid, data in sent:
            tx.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        got, deadline = [], time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < deadline:
            got += reader.read(1.0)
        assert [(f.arbitration_id, f.data) for f in got] == [sent[2], sent[3]]
        assert reader.filtered == 2
    finally:
        reader.close()
        tx.shutdown()
