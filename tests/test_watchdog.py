"""The watchdog's own bus checks, in-process on a real python-can virtual bus.

What cannot be made on demand here is a scheduler stall of the supervisor's reader thread: a gate
in front of ``recv`` stands in for it (frames keep queueing in the real bus meanwhile, as they do in
a SocketCAN socket while the reader waits for the CPU). Everything else is the real Watchdog.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import can
import pytest

from benchmarks.harness import FrameStream, wait_for
from exolink import hardware
from exolink.canbus import FrameReader, open_bus, open_reader
from exolink.config import CanConfig, WatchdogConfig
from exolink.protocol import h2, maccepa
from exolink.supervisor.watchdog import Watchdog, WatchdogState
from exolink.wire import cdr

H2 = hardware.load("h2")  # the device the watchdog guards here

ANGLES = h2.encode(h2.JointAngles(76, 94, 0, 76, 93, 11))


class StalledReader(can.BusABC):
    """A real virtual bus whose reader can be held, like a thread that gets no CPU."""

    def __init__(self, channel: str) -> None:
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.running, self.parked = threading.Event(), threading.Event()
        self.running.set()
        super().__init__(channel=channel)

    def hold(self) -> None:
        """Returns once the reader is held (not inside a recv that could still read)."""
        self.running.clear()
        assert self.parked.wait(2), "the watchdog's reader never came back to recv"

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self.running.is_set():
            self.parked.set()
            self.running.wait()
            self.parked.clear()
        return self.inner.recv(timeout), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


def h2_board(channel: str, bus: can.BusABC | None = None, *also: can.Message) -> FrameStream:
    """Joint angles (and any other frames) at 100 Hz from another thread, pausable."""
    bus = bus if bus is not None else can.Bus(interface="virtual", channel=channel)
    return FrameStream(bus, [ANGLES, *also])


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[Watchdog, StalledReader, FrameStream]]:
    channel = f"wd-{request.node.name}"
    board = h2_board(channel)
    reader = StalledReader(channel)
    states: list[WatchdogState] = []
    frames = FrameReader(
        reader, CanConfig(interface="virtual"), [h2.JOINT_ANGLES, h2.JOINT_CONTROL]
    )
    wd = Watchdog(WatchdogConfig(pulse_silence_ms=100), frames, states.append, H2)
    wd.start()
    try:
        end = time.monotonic() + 5
        while wd.silent_for() is None and time.monotonic() < end:
            time.sleep(0.01)
        wd.arm([])
        yield wd, reader, board
    finally:
        wd.close()
        reader.shutdown()
        board.close()


def settle(wd: Watchdog, seconds: float) -> None:
    """Let the reader catch up, running the supervisor's periodic check meanwhile."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        wd.check()
        time.sleep(0.01)


def test_a_late_reader_is_not_h2_silence(rig) -> None:  # type: ignore[no-untyped-def]
    wd, reader, _board = rig
    reader.hold()  # the supervisor busy for 300 ms; the board keeps sending
    time.sleep(0.3)
    reader.running.set()
    settle(wd, 0.3)
    assert wd.snapshot().state == "armed", wd.snapshot()


def test_a_real_gap_trips_even_when_read_late(rig) -> None:  # type: ignore[no-untyped-def]
    wd, reader, board = rig
    reader.hold()
    board.sending.clear()  # the board is silent for 250 ms while nobody reads
    time.sleep(0.25)
    board.sending.set()
    time.sleep(0.1)
    reader.running.set()  # only queued frames, the newest fresh, show the gap
    settle(wd, 0.3)
    s = wd.snapshot()
    assert (s.state, s.reason) == ("tripped", "h2 data silent"), s
    gap_ms = int(s.detail.split("for ")[1].split(" ms")[0])
    assert 150 < gap_ms < 1000, s.detail


def test_silence_trips_with_the_reader_running(rig) -> None:  # type: ignore[no-untyped-def]
    wd, _reader, board = rig
    board.sending.clear()
    settle(wd, 0.5)
    s = wd.snapshot()
    assert (s.state, s.reason) == ("tripped", "h2 data silent") and "limit 100 ms" in s.detail


def test_a_stalled_reader_trips_the_backstop(rig) -> None:  # type: ignore[no-untyped-def]
    wd, reader, _board = rig
    reader.hold()  # the reader never comes back: silence it cannot rule out
    try:
        settle(wd, 1.0)
        s = wd.snapshot()
        assert (s.state, s.reason) == ("tripped", "h2 data silent"), s
        assert "watchdog bus reader stalled" in s.detail
    finally:
        reader.running.set()


def test_motion_frame_on_the_bus_before_the_trip_is_no_violation(rig) -> None:  # type: ignore[no-untyped-def]
    wd, reader, board = rig
    reader.hold()
    board.bus.send(h2.encode_joint_control("r_knee", "position", 20))  # while armed
    time.sleep(0.02)
    wd.trip("operator e-stop")
    reader.running.set()
    settle(wd, 0.2)
    assert wd.snapshot().violations == 0
    board.bus.send(h2.encode_joint_control("r_knee", "position", 20))  # after the trip: rogue
    settle(wd, 0.2)
    assert wd.snapshot().violations == 1


def test_malformed_angle_frames_do_not_mask_h2_silence(rig) -> None:  # type: ignore[no-untyped-def]
    """Issue 19 (2): junk id-110 frames of DLC 2 at 100 Hz while the H2 is silent held the watchdog
    ARMED (it checked the id, not the frame's shape). They are counted and not H2 data."""
    wd, _reader, board = rig
    board.sending.clear()
    junk = can.Message(arbitration_id=h2.JOINT_ANGLES, data=b"\x01\x02", is_extended_id=False)
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        board.bus.send(junk)
        wd.check()
        time.sleep(0.01)
    s = wd.snapshot()
    assert (s.state, s.reason) == ("tripped", "h2 data silent"), s
    assert s.malformed.get(f"{h2.JOINT_ANGLES} bad length", 0) >= 10, s.malformed


def test_maccepa_traffic_on_id_70_is_neither_malformed_nor_answered(rig) -> None:  # type: ignore[no-untyped-def]
    """MACCEPA board 0's controller frame shares id 70 (8 bytes): answering it with the safe action
    (which includes "stop control" to board 0) fed back into itself on the sim bus."""
    wd, _reader, board = rig
    wd.trip("operator e-stop")
    settle(wd, 0.3)  # the trip's own repeats are done
    sent = wd.snapshot().frames_sent
    controller_b0 = can.Message(arbitration_id=70, data=bytes(8), is_extended_id=False)
    assert isinstance(maccepa.decode(controller_b0), maccepa.Controller)
    board.bus.send(controller_b0)
    board.bus.send(can.Message(arbitration_id=h2.JOINT_CONTROL, data=b"\x01", is_extended_id=False))
    settle(wd, 0.3)
    s = wd.snapshot()
    assert s.frames_sent == sent and s.malformed == {f"{h2.JOINT_CONTROL} bad length": 1}, s


def test_on_sockets_angle_frames_never_wake_the_watchdog_yet_silence_and_motion_are_caught(
    group: str,
) -> None:
    """Issue 18: the supervisor's watchdog woke for every id-110 and id-70 frame (about 200 a
    second, most of its CPU on the board proxy). Armed, it now sleeps to the silence deadline
    (reads per frame << 1); the silence still trips; disarmed, a motion frame is answered."""
    cfg = CanConfig(interface="udp_multicast", channel=group)
    maccepa_b0 = can.Message(arbitration_id=70, data=bytes(8), is_extended_id=False)
    board = h2_board(group, open_bus(cfg), maccepa_b0)  # real sockets, as on the board
    reader = open_reader(cfg, [h2.JOINT_ANGLES, h2.JOINT_CONTROL], wake_on=[h2.JOINT_CONTROL])
    wd = Watchdog(WatchdogConfig(pulse_silence_ms=100), reader, lambda _s: None, H2)
    wd.start()
    try:
        assert wait_for(lambda: wd.silent_for() is not None)
        wd.arm([])
        before = reader.counters()
        time.sleep(1.0)
        after = reader.counters()
        frames = after["frames"] - before["frames"]
        reads = after["batches"] - before["batches"]
        assert frames >= 100 and reads <= frames / 4, (frames, reads)
        assert wd.snapshot().state == "armed"
        board.sending.clear()
        assert wait_for(lambda: wd.snapshot().state == "tripped", timeout=2)
        assert wd.snapshot().reason == "h2 data silent"
        board.sending.set()
        wd.disarm()
        time.sleep(0.2)
        assert wd.snapshot().violations == 0  # MACCEPA board 0's id-70 frames are not motion
        board.bus.send(h2.encode_joint_control("r_knee", "position", 20))
        assert wait_for(lambda: wd.snapshot().violations == 1, timeout=2)
    finally:
        wd.close()
        reader.close()
        board.close()


def test_a_nodes_view_of_the_watchdog_counts_its_words_and_the_longest_wait() -> None:
    """What `pattern status` and `controllers list` show as watchdog_word: a stale view (no word
    for 3 s) is told apart from a tripped watchdog by these. The transport is a stand-in: only
    the bookkeeping is under test (the word's way over Zenoh is in test_motion)."""
    from exolink.control.arming import ArmingState

    class Msg:
        def subscribe_raw(self, *_a: object, **_k: object) -> None:
            return None

        def request(self, *_a: object) -> dict[str, object]:
            return {"ok": True, "state": "armed", "reason": "operator"}

    a = ArmingState(Msg())  # type: ignore[arg-type]
    assert a.check() is None and a.counters()["received"] == 1
    time.sleep(0.05)
    a._update("armed", "operator")
    c = a.counters()
    assert c["received"] == 2 and 0.05 <= c["max_gap_s"] < 1 and c["age_s"] < 1  # type: ignore[operator]
    # Words come with the time the supervisor put them: one put 2 s after the last, and one
    # that took 4 s on the way, are told apart (the supervisor late, or the delivery). The
    # message's own stamp is when the state began, not when it was put.
    now = time.time_ns()
    word = cdr.watchdog_event_msg(now - 100_000_000_000, "armed", "operator", "", 0)
    a._on_event(word, now - 4_000_000_000)
    a._on_event(word, now - 2_000_000_000)
    a._on_event(word, now - 1_500_000_000)
    c = a.counters()
    assert c["received"] == 5 and c["stamp_gap_max_s"] == 2.0, c
    assert 4.0 <= c["delivery_max_s"] < 5.0, c  # type: ignore[operator]
    a._on_event(b"\x00\x01\x00\x00garbage", now)  # not a WatchdogEvent: not taken
    assert a.counters()["received"] == 5
