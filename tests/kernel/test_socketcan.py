"""Real SocketCAN (vcan in the UML guest): kernel filters, netlink bring-up, the appliance on vcan0
with an independent socketcan listener, and the broadcast manager's timing."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import can
import pytest
import yaml
from conftest import (
    FEET_RUNS,
    FEET_STATES,
    feet_runs,
    feet_subscriber,
    read_cycle,
    reader_stats,
    stream_feet,
)
from exolink.nodes.simulator import SimParams, Simulator

from benchmarks.harness import EXOLINK, wait_for
from exolink.canbus import CAN_FRAME, FrameWriter, id_filters, open_bus, open_reader
from exolink.config import CanConfig, bundled
from exolink.protocol import h2
from exolink.supervisor import canlink

pytestmark = pytest.mark.kernel


def listener(channel: str) -> can.BusABC:
    return can.Bus(interface="socketcan", channel=channel, receive_own_messages=False)


def drain(bus: can.BusABC, seconds: float, ids: set[int] | None = None) -> list[can.Message]:
    out, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        m = bus.recv(left)
        if m is not None and (ids is None or m.arbitration_id in ids):
            out.append(m)
    return out


def test_bus_factory_kernel_filters(vcan0: str) -> None:
    bus = open_bus(CanConfig(interface="socketcan", channel=vcan0), filters=id_filters([110]))
    tx = listener(vcan0)
    try:
        for fid in (120, 110, 130, 110):
            tx.send(can.Message(arbitration_id=fid, data=bytes(6), is_extended_id=False))
        got = drain(bus, 0.3)
        assert [m.arbitration_id for m in got] == [110, 110]
        assert bus._is_filtered  # applied in the kernel, not in python-can
        assert abs(got[0].timestamp - time.time()) < 5  # kernel timestamps are wall clock
    finally:
        bus.shutdown()
        tx.shutdown()


def test_a_send_only_bus_receives_nothing(vcan0: str) -> None:
    """``open_bus(filters=[])`` (the h2 sender's, pattern player's, controller manager's and
    watchdog's send buses): python-can takes [] as no filter and the kernel queued every frame
    of the bus on such a socket, never read; it must send and receive nothing."""
    send_only = open_bus(CanConfig(interface="socketcan", channel=vcan0), filters=[])
    other = listener(vcan0)
    try:
        for fid in (70, 110, 120):
            other.send(can.Message(arbitration_id=fid, data=bytes(6), is_extended_id=False))
        send_only.send(can.Message(arbitration_id=85, data=b"\x01", is_extended_id=False))
        assert send_only.recv(0.3) is None
        assert [m.arbitration_id for m in drain(other, 0.3)] == [85]
    finally:
        send_only.shutdown()
        other.shutdown()


def _wire(m: can.Message) -> tuple[int, bool, bool, int, bytes]:
    """What a frame is on the wire (a remote frame carries a length, no data)."""
    data = b"" if m.is_remote_frame else bytes(m.data)
    return m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc, data


def test_frame_writer_sends_a_batch_in_order_and_names_what_failed(vcan0: str) -> None:
    """The controller manager's cycle goes out in one sendmmsg: every frame, in the batch's
    order, with its id kind, length and data as python-can's own send would put them."""
    cfg = CanConfig(interface="socketcan", channel=vcan0)
    bus = open_bus(cfg, filters=[])
    other = listener(vcan0)
    batch = [
        can.Message(arbitration_id=70, data=bytes([m, 1, 0, 30, 0, 0]), is_extended_id=False)
        for m in range(1, 7)
    ]
    batch += [
        can.Message(arbitration_id=0x1ABCDEF0, data=b"\x01\x02", is_extended_id=True),
        can.Message(arbitration_id=85, data=b"", is_extended_id=False),
        can.Message(arbitration_id=0x7FF, is_remote_frame=True, dlc=3, is_extended_id=False),
    ]
    try:
        writer = FrameWriter(bus, cfg)
        assert writer.fd is not None  # the sendmmsg path, not python-can's
        writer.send(batch * 10)  # 90 frames: two system calls of at most 64
        got = drain(other, 0.5)
        assert [_wire(m) for m in got] == [_wire(m) for m in batch * 10]
        bad = FrameWriter(bus, cfg)
        bad.fd = -1  # a socket that is gone: nothing sent, and the error says so
        with pytest.raises(can.CanOperationError, match="sent 0 of 9 frames"):
            bad.send(batch)
    finally:
        bus.shutdown()
        other.shutdown()


def test_netlink_up_down_and_bitrate_refusal(vcan0: str) -> None:
    monitor = canlink.LinkMonitor(vcan0)  # the supervisor's periodic check
    canlink.set_state(vcan0, up=False)
    assert canlink.health(vcan0).state == "down" and monitor.health().state == "down"
    canlink.set_state(vcan0, up=True)
    assert canlink.health(vcan0).state == "up" and monitor.health().state == "up"
    monitor.close()
    with pytest.raises(canlink.CanLinkError, match="vcan0 cannot take a bitrate"):
        canlink.set_bitrate(vcan0, 1_000_000)


def test_link_monitor_wakes_on_the_drivers_error_frames_not_on_data(vcan0: str) -> None:
    """The supervisor's link monitor on a real CAN socket: data frames never reach it (its
    kernel filter), error frames of the watched classes do (vcan has no controller: they are
    injected as the c_can driver sends them, counters in bytes 6-7), and a bus-off is reported
    as such; a bus-error flood class is not watched."""
    m = canlink.LinkMonitor(vcan0)
    tx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    tx.bind((vcan0,))
    frame = CAN_FRAME
    try:
        assert m.health().state == "up" and not m.wait(0.05)
        tx.send(frame.pack(110, 6, bytes(8)))
        tx.send(frame.pack(canlink.ERR_FLAG | 0x80, 8, bytes(8)))  # CAN_ERR_BUSERROR: unwatched
        assert not m.wait(0.3)
        passive = canlink.ERR_FLAG | canlink.ERR_CRTL | canlink.ERR_CNT
        tx.send(frame.pack(passive, 8, bytes([0, 0x10, 0, 0, 0, 0, 5, 128])))
        assert m.wait(2.0)
        assert m.health() == canlink.LinkHealth("error-passive", 5, 128)
        tx.send(frame.pack(canlink.ERR_FLAG | canlink.ERR_BUSOFF, 8, bytes(8)))
        assert m.wait(2.0) and m.health().state == "bus-off"
        canlink.set_state(vcan0, up=False)
        assert m.health().state == "bus-off"  # the driver takes the carrier down with it
        canlink.set_state(vcan0, up=True)
        assert not m.wait(0.2)  # its socket reports the link's down (ENETDOWN): it lets it go
        m._socket()  # ... and opens a new one at its next wait (here: before the frame)
        tx.close()
        tx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        tx.bind((vcan0,))
        tx.send(frame.pack(canlink.ERR_FLAG | canlink.ERR_RESTARTED, 8, bytes(8)))
        assert m.wait(2.0) and m.health().state == "error-active" and m.restarts == 1
    finally:
        tx.close()
        m.close()


def test_bring_up_runs_apart_and_a_refusal_names_the_link(vcan0: str) -> None:
    canlink.set_state(vcan0, up=False)
    canlink.bring_up_apart(CanConfig(interface="socketcan", channel=vcan0))
    assert canlink.health(vcan0).state == "up"
    with pytest.raises(canlink.CanLinkError, match="no network interface 'can7'"):
        canlink.bring_up_apart(CanConfig(interface="socketcan", channel="can7"))


def write_config(tmp_path: Path, channel: str, nodes: list[dict]) -> Path:
    data = yaml.safe_load(bundled("sim").read_text())
    data["can"] = {"interface": "socketcan", "channel": channel, "bring_up": True}
    data["nodes"] = nodes
    # The UML guest is one virtual CPU on a shared CI host: with the host busy, the whole guest
    # (the simulated H2 board included) was seen to stop for 143 ms, a real silence on vcan0 that
    # trips the 100 ms limit; node starts took 20 s. Wider limits here, as a lab engineer would
    # set them for a slow machine; silence detection itself is tested on the host (test_watchdog).
    # 1 s was not enough once in five full runs: the watchdog saw no angle frame for 1.6 s while
    # a CLI process started in the guest (its imports take seconds of the one UML CPU).
    # The holder's keep-alive too: a CLI process starting takes the one CPU for seconds.
    data["watchdog"].update(
        pulse_silence_ms=3000,
        heartbeat_deadline_ms=2000,
        start_grace_ms=60_000,
        operator_lost_ms=15_000,
    )
    data["clock"] = {"from_laptop": True}  # as on the board: the guest runs no time server
    path = tmp_path / "appliance.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*EXOLINK, *args, "--timeout", "5"], capture_output=True, text=True, timeout=60
    )


class Phases:
    """Seconds each phase of a long guest test took, printed even when it fails: a timeout then
    says which phase ran long."""

    def __init__(self) -> None:
        self.last = time.monotonic()
        self.took: dict[str, float] = {}

    def mark(self, name: str) -> None:
        now = time.monotonic()
        self.took[name], self.last = round(now - self.last, 1), now

    def __str__(self) -> str:
        return json.dumps(self.took)


def wait_status(pred, timeout: float = 60) -> dict:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        r = cli("status", "--json")
        if r.returncode == 0:
            s = json.loads(r.stdout)
            if pred(s):
                return s
        time.sleep(0.3)
    raise AssertionError("status condition not met")


# A hang guard, not a performance bound: each CLI call is a fresh Python process that takes 6-7 s
# to import in the UML guest (syscall-heavy), and this test makes about a dozen; it took 97 s alone
# and more than the default 120 s in one CI run. The phases it prints say where the time went.
@pytest.mark.timeout(300)
def test_appliance_on_vcan_kill9_disables_and_bcm_timing(vcan0: str, tmp_path: Path) -> None:
    nodes = [
        {"name": "simulator", "plugin": "simulator"},
        {"name": "h2_reader", "plugin": "h2_reader", "critical": True},
        {
            "name": "controller_manager",  # the one writer: set-points every 20 ms, as on the board
            "plugin": "controller_manager",
            "critical": True,
            "params": {"cycles_per_update": 2, "h2_timeout_ms": 300},
        },
        {
            "name": "pattern_player",
            "plugin": "pattern_player",
            "critical": True,
            "params": {"speed": 10, "selected": ["r_hip", "r_knee", "l_hip", "l_knee"]},
        },
        {"name": "timing_monitor", "plugin": "timing_monitor", "params": {"ids": [70]}},
    ]
    cfg = write_config(tmp_path, vcan0, nodes)
    log = (tmp_path / "up.log").open("wb")
    up = subprocess.Popen([*EXOLINK, "up", "-c", str(cfg)], stdout=log, stderr=subprocess.STDOUT)
    bus = listener(vcan0)
    phases = Phases()
    try:
        wait_status(lambda s: all(n["heartbeat_age_s"] is not None for n in s["nodes"]))
        phases.mark("all beating")
        assert cli("send", "position", "r_knee", "20").returncode == 5  # not armed yet
        end = time.monotonic() + 20
        while (armed := cli("arm")).returncode != 0 and time.monotonic() < end:
            time.sleep(0.3)
        assert armed.returncode == 0, armed.stderr
        # the arming laptop's time taken by a board with none (it runs in this guest: ~0 ms;
        # at the first `arm`, which the loop above may have repeated)
        clock_now = json.loads(cli("status", "--json").stdout)["clock"]
        assert clock_now["source"] == "laptop" and abs(clock_now["offset_ms"]) < 1000
        phases.mark("armed")
        # the operator holds motion (as `exolink hold` in a terminal), the manager plays the
        # pattern; the timing monitor measures kernel timestamps
        holder = subprocess.Popen([*EXOLINK, "hold"], stdout=subprocess.PIPE, text=True)
        assert holder.stdout is not None and "holding motion" in holder.stdout.readline()
        started = cli("pattern", "start", "--detach")
        assert started.returncode == 0, started.stderr
        r = cli("timing", "70", "--motor", "1", "--dlc", "6", "--seconds", "10", "--json")
        assert r.returncode == 0, (r.stderr, cli("status").stdout)
        stats = json.loads(r.stdout)
        phases.mark("pattern timed")
        print("pattern timing in the UML guest:", json.dumps(stats))
        (Path(os.environ.get("EXOLINK_KERNEL_RESULTS", tmp_path)) / "bcm-timing.json").write_text(
            json.dumps(stats)
        )
        # behaviour, not a performance bound: the pattern goes out at the speed-10 rate
        assert stats["n"] > 300 and 18 < stats["mean_period_ms"] < 22
        assert stats["socket_dropped"] == 0
        # kill -9 of the reader: the watchdog's disable frames, seen by an independent socket
        pid = next(
            n["pid"]
            for n in json.loads(cli("status", "--json").stdout)["nodes"]
            if n["name"] == "h2_reader"
        )
        # A socket opened now, for id 70 only: the test's first listener has queued a minute of
        # 500 frames/s, more than python-can reads in a second in this guest (a full run once
        # drained only old frames for the whole window and saw no disable frame).
        bus.shutdown()
        bus = can.Bus(
            interface="socketcan",
            channel=vcan0,
            receive_own_messages=False,
            can_filters=[{"can_id": h2.JOINT_CONTROL, "can_mask": 0x7FF}],
        )
        phases.mark("reader found")
        os.kill(pid, signal.SIGKILL)
        frames = [h2.decode(m) for m in drain(bus, 3.0, {70})]
        disabled = {f for f in frames if isinstance(f, h2.JointControl) and f.mode == 4}
        assert disabled == {h2.JointControl(m, 4, 0, 0) for m in range(1, 7)}
        # and the pattern stopped with the trip: no more position frames
        time.sleep(0.3)
        drain(bus, 0.1)
        late = [
            f
            for f in (h2.decode(m) for m in drain(bus, 0.5, {70}))
            if isinstance(f, h2.JointControl) and f.mode == 1
        ]
        assert late == []
        phases.mark("disabled")
    finally:
        print("appliance test phases in the UML guest (s):", phases)
        if "holder" in locals():
            holder.kill()
        bus.shutdown()
        up.terminate()
        up.wait(30)
        log.close()
        phases.mark("stopped")
        print("appliance stopped (s):", phases.took["stopped"])


def test_stalled_reader_counts_every_frame_it_lost(vcan0: str) -> None:
    """SocketCAN: frames of its ids sent = received + dropped (the socket's kernel count), for a
    reader that did not read during the burst; frames of other ids are filtered, not counted."""
    from exolink.canbus import open_reader

    reader = open_reader(CanConfig(interface="socketcan", channel=vcan0), [110], rcvbuf=1 << 16)
    tx = listener(vcan0)
    sent = 2000
    try:
        for i in range(sent):
            data = i.to_bytes(2, "little")
            tx.send(can.Message(arbitration_id=110, data=data, is_extended_id=False))
            tx.send(can.Message(arbitration_id=120, data=data, is_extended_id=False))
        received = []
        while frames := reader.read(0.3):
            received += frames
        dropped = reader.dropped
        assert dropped is not None and dropped > 0
        assert len(received) + dropped == sent
        assert {f.arbitration_id for f in received} == {110}
    finally:
        reader.bus.shutdown()
        tx.shutdown()


def test_only_the_cycle_end_wakes_a_reader_on_socketcan(vcan0: str) -> None:
    """The h2 reader's and the watchdog's wake-ups on the board's kind of socket: 110 and 120
    wait on their quiet socket for the 130, and come out with it in kernel-timestamp order."""
    tx = listener(vcan0)
    reader = open_reader(
        CanConfig(interface="socketcan", channel=vcan0), [110, 120, 130], wake_on=[130]
    )
    try:
        for fid in (110, 120):
            tx.send(can.Message(arbitration_id=fid, data=bytes(6), is_extended_id=False))
        start = time.monotonic()
        got = reader.read(0.4)
        assert time.monotonic() - start >= 0.4  # no frame of a quiet id woke it
        assert [f.arbitration_id for f in got] == [110, 120]
        for fid in (110, 120, 130):
            tx.send(can.Message(arbitration_id=fid, data=bytes(6), is_extended_id=False))
        start = time.monotonic()
        got = reader.read(5.0)
        assert time.monotonic() - start < 4.0  # the 130 woke it
        assert [f.arbitration_id for f in got] == [110, 120, 130]
        assert reader.complete and reader.dropped == 0
    finally:
        reader.close()
        tx.shutdown()


def test_set_ids_moves_the_quiet_sockets_kernel_filter(vcan0: str) -> None:
    """The controller manager's reader after the loaded controllers stop reading torque and
    foot switches: their frames are no longer queued by the kernel (not dropped in Python:
    ``filtered`` stays 0), and come back when a controller reads them again."""
    reader = open_reader(
        CanConfig(interface="socketcan", channel=vcan0), [70, 110, 120, 130], wake_on=[110]
    )
    tx = listener(vcan0)

    def cycle() -> list[int]:
        return read_cycle(tx, reader, [70, 120, 130, 110])

    try:
        assert cycle() == [70, 120, 130, 110]
        reader.set_ids([70, 110])
        assert cycle() == [70, 110]
        reader.set_ids([70, 110, 120, 130])
        assert cycle() == [70, 120, 130, 110]
        assert reader.filtered == 0 and reader.quiet_bus._is_filtered  # type: ignore[union-attr]
    finally:
        reader.close()
        tx.shutdown()


@pytest.mark.parametrize("wake_on", [[110], None], ids=["two sockets", "one socket"])
def test_a_reader_does_not_read_back_what_its_writer_sends(
    vcan0: str, wake_on: list[int] | None
) -> None:
    """The controller manager's shapes: 110 wakes and 70 is read quietly (anyone's joint
    control, the watchdog's disable), or one socket reads both (``one_socket``); its set-points
    go out on 70 through ``reader.writer``, which sends on the socket that reads 70: SocketCAN
    never gives a socket its own frames, so the manager does not decode its own set-points;
    another process's 70 still arrives, and an independent listener sees every frame."""
    tx, watcher = listener(vcan0), listener(vcan0)
    reader = open_reader(
        CanConfig(interface="socketcan", channel=vcan0), [70, 110], wake_on=wake_on
    )
    try:
        mine = [
            can.Message(arbitration_id=70, data=bytes([m, 3, 0, 0, 0, 0]), is_extended_id=False)
            for m in (1, 2, 3, 4)
        ]
        reader.writer.send(mine)
        tx.send(
            can.Message(arbitration_id=70, data=bytes([5, 4, 0, 0, 0, 0]), is_extended_id=False)
        )
        tx.send(can.Message(arbitration_id=110, data=bytes(6), is_extended_id=False))
        got = reader.read(5.0)
        assert [(f.arbitration_id, f.data[0]) for f in got] == [(70, 5), (110, 0)]
        assert all(isinstance(f.timestamp, float) and f.timestamp > 1e9 for f in got)
        seen = drain(watcher, 0.5, {70})
        assert [m.data[0] for m in seen] == [1, 2, 3, 4, 5]
        assert reader.malformed == 0
    finally:
        reader.close()
        tx.shutdown()
        watcher.shutdown()


def test_content_filters_drop_in_the_kernel_what_a_reader_never_needs(vcan0: str) -> None:
    """The controller manager's and MACCEPA bridge's shape on id 70: the H2's set-points
    (6 bytes, mode 1) and board 0's status (8 bytes) never reach a reader whose rules drop them;
    a disable (mode 4), another length and the other ids do, in order. The kernel's socket
    filter drops them (nothing in Python: ``filtered`` 0), and not as losses: ``dropped`` 0."""
    from exolink.canbus.filters import Drop

    rules = [Drop(70, 6, byte=1, keep=frozenset({4, 5})), Drop(70, 8)]
    reader = open_reader(
        CanConfig(interface="socketcan", channel=vcan0), [70, 110], wake_on=[110], drop=rules
    )
    tx = listener(vcan0)
    try:
        sent = [
            (70, bytes([1, 1, 30, 0, 0, 0])),  # a set-point: dropped
            (70, bytes(8)),  # board 0's status: dropped
            (70, bytes([2, 4, 0, 0, 0, 0])),  # a disable: kept
            (70, bytes(7)),  # malformed for both protocols: kept, for the reader to count
            (70, bytes([3, 5, 0, 0, 0, 0])),  # a stop: kept
            (110, bytes(6)),
        ]
        for fid, data in sent:
            tx.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        got = reader.read(5.0)
        assert [(f.arbitration_id, f.data) for f in got] == [sent[2], sent[3], sent[4], sent[5]]
        assert reader.filtered == 0 and reader.dropped == 0
    finally:
        reader.close()
        tx.shutdown()


@pytest.mark.parametrize("wake_on", [[110], None], ids=["two sockets", "one socket"])
def test_a_parked_reader_hears_nothing_then_the_same_ids_with_its_rules(
    vcan0: str, wake_on: list[int] | None
) -> None:
    """The controller manager parks its reader while idle instead of closing it (a close
    freed the content filter's BPF program in a kworker: ~94 ms of the board proxy's CPU 0 at
    each gait's stop). Parked, the frames queued before and those sent meanwhile are never
    read; unparked, the same ids come back in order with the content rules still in force,
    and new ids apply after."""
    from exolink.canbus.filters import Drop

    rules = [Drop(70, 6, byte=1, keep=frozenset({4, 5}))]
    reader = open_reader(
        CanConfig(interface="socketcan", channel=vcan0), [70, 110], wake_on=wake_on, drop=rules
    )
    tx = listener(vcan0)

    def send(*frames: tuple[int, bytes]) -> None:
        for fid, data in frames:
            tx.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))

    try:
        assert reader.parkable
        send((70, bytes([2, 4, 0, 0, 0, 0])))  # queued before the park: never read
        time.sleep(0.05)
        reader.park()
        send((70, bytes([3, 4, 0, 0, 0, 0])), (110, bytes(6)))  # while parked: never queued
        time.sleep(0.05)
        assert reader.read(0.2) == []
        reader.unpark()
        sent = [(70, bytes([1, 1, 30, 0, 0, 0])), (70, bytes([4, 5, 0, 0, 0, 0])), (110, bytes(6))]
        send(*sent)
        got = reader.read(5.0)
        assert [(f.arbitration_id, f.data) for f in got] == [sent[1], sent[2]]  # the rule held
        reader.set_ids([70, 110, 120] if wake_on else [110, 120])
        send((120, bytes(8)), (110, bytes(6)))
        assert [f.arbitration_id for f in reader.read(5.0)] == [120, 110]
    finally:
        reader.close()
        tx.shutdown()


ANGLES_LEN = len(h2.encode(h2.JointAngles(40, 60, 0, 40, 60, 0)).data)  # the contract's (6)


def _angles(length: int = ANGLES_LEN) -> can.Message:
    """An H2 joint-angle frame (id 110) of ``length`` bytes (the contract's by default)."""
    return can.Message(arbitration_id=h2.JOINT_ANGLES, data=bytes(length), is_extended_id=False)


def test_kernel_timer_tells_only_the_start_a_length_change_and_silence(vcan0: str) -> None:
    """The broadcast manager's receive op (exolink.canbus.bcm): a steady stream of the id reaches
    user space once; a frame of another length is reported (then the return to the contract's); frames of
    other ids, or the id as an extended frame, neither report nor keep it alive; the silence is
    one timeout; the stream's return is reported with its kernel time."""
    from exolink.canbus.bcm import CyclicWatch

    tx = listener(vcan0)
    # Generous for one UML CPU on a shared host (the guest was seen to stop for 143 ms).
    with CyclicWatch(vcan0, h2.JOINT_ANGLES, 1.0) as watch:
        for _ in range(60):
            tx.send(_angles())
            time.sleep(0.005)
        first = watch.poll()
        assert [len(e.frame.data) for e in first if e.frame] == [ANGLES_LEN] and len(first) == 1
        tx.send(_angles(8))
        for _ in range(5):
            tx.send(_angles())
        time.sleep(0.1)
        changed = watch.poll()
        assert [len(e.frame.data) for e in changed if e.frame] == [8, ANGLES_LEN]
        assert len(changed) == 2
        for _ in range(10):  # neither is the watched frame
            tx.send(can.Message(arbitration_id=120, data=bytes(8), is_extended_id=False))
            tx.send(can.Message(arbitration_id=h2.JOINT_ANGLES, data=bytes(8), is_extended_id=True))
            time.sleep(0.1)
        silent = watch.poll()
        assert [e.frame for e in silent] == [None]  # one timeout, nothing else
        sent = time.time()
        tx.send(_angles())
        time.sleep(0.1)
        resumed = watch.poll()
        assert len(resumed) == 1 and resumed[0].frame is not None
        assert resumed[0].frame.arbitration_id == h2.JOINT_ANGLES
        assert abs(resumed[0].at - sent) < 1.0  # the frame's kernel receive time (wall clock)
    tx.shutdown()


def test_watchdog_on_socketcan_reads_no_angle_frame_and_trips_on_kernel_silence(
    vcan0: str, tmp_path: Path
) -> None:
    """The board's watchdog: the kernel times the H2 angle frames and compares id 70's mode
    byte; Python reads no frame. Not armed, MACCEPA board 0's frames on id 70 go unseen and a
    position frame is answered with the safe action (and the next one after it again); armed,
    id 70 is not watched at all (the gait's frames and board 0's alternate: no news reaches the
    watchdog), a silence of the angles trips it and the id-70 watch is back; a stream of malformed (8-byte) angle frames, which the
    kernel's timer takes as life, trips it too."""
    import threading

    from exolink import hardware
    from exolink.canbus.bcm import CyclicWatch
    from exolink.config import WatchdogConfig
    from exolink.supervisor.watchdog import Watchdog

    limit_s = 1.0  # wide for the UML guest, as write_config's
    cfg = WatchdogConfig(pulse_silence_ms=int(limit_s * 1000))
    reader = open_reader(CanConfig(interface="socketcan", channel=vcan0), [])  # sends only
    published: list = []
    wd = Watchdog(
        cfg,
        reader,
        published.append,
        hardware.load("h2"),
        CyclicWatch(vcan0, h2.JOINT_ANGLES, limit_s),
        CyclicWatch(vcan0, h2.JOINT_CONTROL, mask=h2.MODE_MASK),
        reopen=lambda: CyclicWatch(vcan0, h2.JOINT_CONTROL, mask=h2.MODE_MASK),
    )
    tx = listener(vcan0)
    rx = can.Bus(
        interface="socketcan",
        channel=vcan0,
        receive_own_messages=False,
        can_filters=[{"can_id": h2.JOINT_CONTROL, "can_mask": 0x7FF}],
    )
    length = {"n": ANGLES_LEN}
    last_sent = [0.0]
    stop = threading.Event()

    def stream() -> None:
        while not stop.is_set():
            tx.send(_angles(length["n"]))
            last_sent[0] = time.time()
            time.sleep(0.01)

    h2_tx = threading.Thread(target=stream, daemon=True)
    try:
        wd.start()
        h2_tx.start()
        wait_for(lambda: wd.silent_for() == 0.0)
        # MACCEPA board 0's controller frames (id 70, 8 bytes) at 100 Hz: not H2 motion
        for i in range(100):
            tx.send(can.Message(arbitration_id=70, data=bytes([i, 0, 5, 0, 7, 0, 0, 0])))
            time.sleep(0.01)
        assert wd.snapshot().violations == 0
        drain(rx, 0.2)
        for n in (1, 2):  # each answered: the safe action between them is a change of mode
            tx.send(h2.encode_joint_control(2, h2.MODES["position"], 20, 0))
            wait_for(lambda: wd.snapshot().violations == n)  # noqa: B023
            got = {h2.decode(m) for m in drain(rx, 0.5, {h2.JOINT_CONTROL})}
            assert {h2.JointControl(m, 4, 0, 0) for m in range(1, 7)} <= got
        wd.arm([])
        news = wd.control_events
        # Armed with the gait running: the manager's 6-byte frames and board 0's 8-byte ones
        # alternate on id 70, each a length change for an id-70 op; armed, there is none.
        for i in range(100):
            tx.send(h2.encode_joint_control(1 + i % 4, h2.MODES["position"], 20, 0))
            if i % 4 == 3:
                tx.send(can.Message(arbitration_id=70, data=bytes([i, 0, 5, 0, 7, 0, 0, 0])))
                time.sleep(0.01)
        time.sleep(2 * limit_s)  # streaming: armed throughout
        assert wd.snapshot().state == "armed"
        assert wd.control_events == news and wd.control is None
        assert reader.frames == 0  # not one angle frame (~200 sent) was read in Python
        drain(rx, 0.1)
        stop.set()
        h2_tx.join()
        wait_for(lambda: wd.snapshot().state == "tripped")
        s = wd.snapshot()
        assert s.reason == "h2 data silent" and "kernel timer" in s.detail
        assert s.violations == 2  # the armed window's motion frames are none
        got = drain(rx, 1.0, {h2.JOINT_CONTROL})
        frames = [h2.decode(m) for m in got]
        assert {f for f in frames if isinstance(f, h2.JointControl) and f.mode == 4} == {
            h2.JointControl(m, 4, 0, 0) for m in range(1, 7)
        }
        # a figure, not a bound: last angle frame -> first disable frame (kernel time)
        first = min(m.timestamp for m, f in zip(got, frames, strict=True) if f.mode == 4)
        reaction = {
            "limit_ms": limit_s * 1e3,
            "silence_to_disable_ms": (first - last_sent[0]) * 1e3,
        }
        print("kernel-timed silence in the UML guest:", json.dumps(reaction))
        out = Path(os.environ.get("EXOLINK_KERNEL_RESULTS", tmp_path)) / "kernel-silence.json"
        out.write_text(json.dumps(reaction))
        # Tripped: the id-70 watch is back, and a motion frame is answered again.
        assert wd.control is not None
        tx.send(h2.encode_joint_control(2, h2.MODES["position"], 20, 0))
        wait_for(lambda: wd.snapshot().violations == 3)
        # Malformed frames keep the kernel's timer going; they are not H2 data here.
        stop.clear()
        h2_tx = threading.Thread(target=stream, daemon=True)
        h2_tx.start()
        wait_for(lambda: wd.silent_for() == 0.0)
        wd.arm([])
        length["n"] = 8
        wait_for(lambda: wd.snapshot().state == "tripped")
        s = wd.snapshot()
        assert s.reason == "h2 data silent" and "110 bad length" in s.malformed
        assert wd.silent_for() is not None and wd.silent_for() > 0
    finally:
        stop.set()
        h2_tx.join(2)
        wd.close()
        reader.close()
        tx.shutdown()
        rx.shutdown()


def test_simulated_h2_streams_on_the_kernel_timer(vcan0: str) -> None:
    """On SocketCAN the simulator's H2 frames come from the broadcast manager, as the board's
    hardware timer sends them: ids 110, 120, 130 each cycle in that order, the contents
    following the model (a position command moves the angle), a silent fault stops them and
    they come back, and the stop-stream command (id 85) stops them."""

    cfg = CanConfig(interface="socketcan", channel=vcan0)
    bus = open_bus(cfg, filters=id_filters(Simulator.command_ids(SimParams())))
    rx = open_bus(cfg, filters=id_filters([h2.JOINT_ANGLES, h2.JOINT_TORQUES, h2.FOOT_SWITCHES]))
    tx = listener(vcan0)
    sim = Simulator(bus, SimParams())
    assert sim.stream is not None
    stop = threading.Event()
    runner = threading.Thread(target=sim.run, args=(stop,), daemon=True)
    runner.start()
    cycle = (h2.JOINT_ANGLES, h2.JOINT_TORQUES, h2.FOOT_SWITCHES)
    try:
        tx.send(h2.encode_stream(True))
        assert wait_for(lambda: sim.stream.running, timeout=5)
        drain(rx, 0.2)  # what came before the window
        got = drain(rx, 1.0, set(cycle))
        ids = [m.arbitration_id for m in got]
        print("kernel-timed H2 frames in 1 s:", {i: ids.count(i) for i in cycle})
        assert 80 <= ids.count(h2.JOINT_ANGLES) <= 120, ids.count(h2.JOINT_ANGLES)
        k0 = ids.index(h2.JOINT_ANGLES)
        assert all(i == cycle[(k - k0) % 3] for k, i in enumerate(ids[k0:], k0)), ids[:30]

        def r_knee() -> int:
            angles = [h2.decode(m) for m in drain(rx, 0.05, {h2.JOINT_ANGLES})]
            return angles[-1].r_knee if angles else -999  # type: ignore[union-attr]

        before = r_knee()
        tx.send(h2.encode_joint_control("r_knee", "position", before + 20))
        assert wait_for(lambda: r_knee() >= before + 15, timeout=5)

        sim.inject("silent", 0.5)
        assert wait_for(lambda: not sim.stream.running, timeout=2)
        drain(rx, 0.05)
        assert drain(rx, 0.2, set(cycle)) == []
        assert wait_for(lambda: len(drain(rx, 0.1, {h2.JOINT_ANGLES})) >= 5, timeout=5)

        tx.send(h2.encode_stream(False))
        assert wait_for(lambda: not sim.stream.running, timeout=2)
        drain(rx, 0.05)
        assert drain(rx, 0.3, set(cycle)) == []
    finally:
        stop.set()
        runner.join(2)
        sim.stream.stop()
        for b in (bus, rx, tx):
            b.shutdown()


def test_simulated_maccepa_board_on_the_kernel_timer_reads_commands_in_batches(
    vcan0: str,
) -> None:
    """On SocketCAN a simulated MACCEPA board's state frames come from the broadcast manager as
    the H2's do (100 Hz each, whatever Python does meanwhile), the simulator takes its commands
    through the batch reader (a burst of 40 set-points is read there and handled, each once), the board
    follows a set-point, and a silent fault stops its frames until it ends."""
    from exolink.protocol import maccepa

    cfg = CanConfig(interface="socketcan", channel=vcan0)
    params = SimParams(maccepa_boards=[1])
    reader = open_reader(cfg, Simulator.command_ids(params))
    ids = set(maccepa.data_ids([1]))
    rx = open_bus(cfg, filters=id_filters(sorted(ids)))
    tx = listener(vcan0)
    sim = Simulator(reader.bus, params, reader)
    assert sim.mc_stream is not None
    stop = threading.Event()
    runner = threading.Thread(target=sim.run, args=(stop,), daemon=True)
    runner.start()
    try:
        assert wait_for(lambda: sim.mc_stream.running, timeout=5)
        drain(rx, 0.2)
        got = [m.arbitration_id for m in drain(rx, 1.0, ids)]
        print("kernel-timed MACCEPA frames in 1 s:", {i: got.count(i) for i in sorted(ids)})
        assert all(80 <= got.count(i) <= 120 for i in ids), got[:30]

        before, read_before = sim.stats.commands, reader.frames
        tx.send(maccepa.encode_gain(1, "kp", 2.0, "position"))
        for _ in range(40):
            tx.send(maccepa.encode_setpoint(1, 30.0, "position"))
        assert wait_for(lambda: sim.stats.commands - before == 41, timeout=5)
        # every command came through the batch reader (how many per read depends on how fast
        # this thread sends against the simulator's wake-ups, so that is not asserted)
        assert reader.frames - read_before == 41

        def lever() -> int:
            pos = [maccepa.decode(m) for m in drain(rx, 0.05, {maccepa.POSITIONS_BASE + 1})]
            return pos[-1].lever if pos else -999  # type: ignore[union-attr]

        assert wait_for(lambda: abs(lever() - 30) <= 1, timeout=5)

        sim.inject("silent", 0.5)
        assert wait_for(lambda: not sim.mc_stream.running, timeout=2)
        drain(rx, 0.05)
        assert drain(rx, 0.2, ids) == []
        assert wait_for(lambda: len(drain(rx, 0.1, ids)) >= 10, timeout=5)
    finally:
        stop.set()
        runner.join(2)
        sim.mc_stream.stop()
        reader.close()
        for b in (rx, tx):
            b.shutdown()


def test_simulator_updating_every_fourth_period_still_streams_every_period(vcan0: str) -> None:
    """``update_cycles: 4`` (the board proxy's): the kernel sends the H2's frames every 10 ms
    while the model steps, the contents change and commands are read every 40 ms, so a moving
    joint's angle changes at most every fourth frame, and a position command is still followed."""
    cfg = CanConfig(interface="socketcan", channel=vcan0)
    params = SimParams(update_cycles=4)
    reader = open_reader(cfg, Simulator.command_ids(params))
    rx = open_bus(cfg, filters=id_filters([h2.JOINT_ANGLES]))
    tx = listener(vcan0)
    sim = Simulator(reader.bus, params, reader)
    stop = threading.Event()
    runner = threading.Thread(target=sim.run, args=(stop,), daemon=True)
    runner.start()
    try:
        tx.send(h2.encode_stream(True))
        assert wait_for(lambda: sim.stream is not None and sim.stream.running, timeout=5)
        drain(rx, 0.2)
        tx.send(h2.encode_joint_control("r_knee", "position", 90))
        knees = [h2.decode(m).r_knee for m in drain(rx, 1.0, {h2.JOINT_ANGLES})]  # type: ignore[union-attr]
        print("angle frames in 1 s:", len(knees), "distinct knee runs:", len(dedup_runs(knees)))
        assert 80 <= len(knees) <= 120, len(knees)
        runs = dedup_runs(knees)
        assert len(runs) >= 5 and runs in (sorted(runs), sorted(runs, reverse=True)), runs
        assert len(runs) <= len(knees) / 4 + 2, (len(runs), len(knees))  # every 4th at most
    finally:
        stop.set()
        runner.join(2)
        if sim.stream is not None:
            sim.stream.stop()
        reader.close()
        for b in (rx, tx):
            b.shutdown()


def dedup_runs(values: list[int]) -> list[int]:
    return [v for i, v in enumerate(values) if i == 0 or v != values[i - 1]]


@pytest.mark.timeout(180)
def test_the_reader_hears_of_foot_switches_only_when_they_change(  # type: ignore[no-untyped-def]
    vcan0: str, tmp_path: Path, spawn
) -> None:
    """On SocketCAN the h2 reader's raw socket takes no foot-switch frame: the kernel's watch
    (nodes/h2_reader.py) reports the first, each change and a silence. Every transition is
    still published in order, on its frame's kernel time, and an unchanged state as a refresh."""
    from exolink import messaging
    from exolink.config import load

    params = {
        "start_stream": False,
        "foot_switches_refresh_s": 0.3,
        "wake_on_id": 0,
        "cycles_per_read": 4,
    }
    cfg_path = write_config(
        tmp_path, vcan0, [{"name": "h2_reader", "plugin": "h2_reader", "params": params}]
    )
    cfg = load(cfg_path)
    hub = messaging.open_hub_session(cfg)
    sub, got = feet_subscriber(hub)
    spawn("node", "run", "h2_reader", "-c", str(cfg_path))

    def stats() -> dict | None:
        return reader_stats(hub, timeout_s=5)

    bus = listener(vcan0)
    try:
        wait_for(lambda: stats() is not None, timeout=90)
        before = stats()
        assert before is not None
        stream_feet(bus)
        silences = before["missing"]["130"]  # one already if the op's timer ran before a frame
        # the end's silence, and every angle frame read (a read that stopped at its batch
        # limit leaves the rest for the next wake, after that wake's watch report)
        wait_for(
            lambda: (
                (st := stats())
                and st["missing"]["130"] > silences
                and st["frames"]["110"] == len(FEET_STATES)
            ),
            timeout=20,
        )
        st = stats()
    finally:
        bus.shutdown()
        sub.undeclare()
        hub.close()
    assert st is not None
    assert st["feet_on_change"] is True
    assert feet_runs(got) == FEET_RUNS  # every transition, in order, none invented
    print("reader with the kernel's foot-switch watch:", json.dumps(st))
    # the first frame and 4 changes; a silence (this guest stalls its sender at times) makes
    # the next frame a report too, and ends with one at the end
    silences = st["missing"]["130"] - before["missing"]["130"]
    assert silences >= 1
    assert 5 <= st["frames"]["130"] <= 5 + silences - 1 and st["foot_switch_changes"] == 4
    # the raw socket read the angle and torque frames alone: two a cycle, no foot switch
    raw = st["receive"]["frames"] - before["receive"]["frames"]
    assert raw == 2 * len(FEET_STATES), raw
    assert st["frames"]["110"] == len(FEET_STATES)
