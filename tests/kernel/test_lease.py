"""The broadcast manager's send op with a lease (exolink.canbus.leases.CyclicLease) on vcan0 in the
UML guest: set-points on the kernel's timer, renewed without a gap or a skip, and bounded when
their owner is stopped, killed or stops them. Counts are asserted; times are printed."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest

from benchmarks.harness import EXOLINK, motion_nodes
from exolink.canbus.leases import CyclicLease, OpLost
from exolink.cli.remote import watchdog_body
from exolink.client import DEFAULT_AT, remote
from exolink.protocol import h2

pytestmark = pytest.mark.kernel
ID, PERIOD, LEASE = 0x46, 0.010, 6


def slot(n: int) -> bytes:
    return n.to_bytes(4, "big") + b"\xee\xee"


def slots_of(frames: list[can.Message]) -> list[int]:
    return [int.from_bytes(m.data[:4], "big") for m in frames]


def listen(channel: str) -> can.BusABC:
    return can.Bus(
        interface="socketcan",
        channel=channel,
        receive_own_messages=False,
        can_filters=[{"can_id": ID, "can_mask": 0x7FF}],
    )


def drain(bus: can.BusABC, seconds: float) -> list[can.Message]:
    out, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        m = bus.recv(left)
        if m is not None:
            out.append(m)
    return out


def steps_of(frames: list[can.Message]) -> tuple[list[int], list[int]]:
    """The slots the bus carried and the steps between them (all 1: every slot once, in
    order)."""
    got = slots_of(frames)
    return got, [b - a for a, b in itertools.pairwise(got)]


def plan(n: int, ahead: int = 8) -> dict[int, bytes]:
    return {k: slot(k) for k in range(n, n + ahead)}


def renew_at_the_last_frame(op: CyclicLease, monkeypatch: pytest.MonkeyPatch) -> int:
    """A lease of 3 started, then renewed (to 6) when one frame is left, with the renewal's
    read-to-setup window made longer than a period (a starved owner): the last frame goes out
    and the timer ends inside it. The renewal's slot."""
    import exolink.canbus.leases as leases

    check = leases._check_lease

    def slow(*args: int) -> None:  # the window outlasts the last frame's due time
        check(*args)
        time.sleep(1.5 * PERIOD)

    op.start([slot(k) for k in range(8)], 3)
    while op.remaining() > 1:  # slots 0 and 1 out, 2 due
        pass
    monkeypatch.setattr(leases, "_check_lease", slow)
    return op.renew(plan(op.sent(), 12), 6)


def _results(name: str, data: dict) -> None:
    print(name, json.dumps(data))
    where = Path(os.environ.get("EXOLINK_KERNEL_RESULTS", "/tmp"))
    (where / f"{name}.json").write_text(json.dumps(data))


def test_renewed_set_points_leave_on_the_kernels_timer_without_gap_or_skip(vcan0: str) -> None:
    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], LEASE)
        renewals, end, walls = 0, time.monotonic() + 3.0, []
        while time.monotonic() < end:
            time.sleep(2 * PERIOD)  # the owner wakes every second period, as the manager
            t0 = time.perf_counter()
            n = op.sent()
            op.renew(plan(n, 16), LEASE)  # two leases ahead, as the manager's ring (on_timer)
            walls.append(time.perf_counter() - t0)
            renewals += 1
        op.stop()
        frames = drain(bus, 0.3)
    finally:
        op.close()
        bus.shutdown()
    got, steps = steps_of(frames)
    # every slot once, in order: a frame sent while a renewal was on its way was already at its
    # ring position, so it is neither repeated nor skipped
    assert got[0] == 0 and set(steps) == {1}, steps
    # 3 s at 10 ms: ~300; fewer when the owner was once later than its lease on a loaded host
    # (the op then ends: a renewal never restarts it), never none
    assert len(got) > 50, len(got)
    periods = sorted(
        abs((b.timestamp - a.timestamp) - PERIOD) * 1e3 for a, b in itertools.pairwise(frames)
    )
    _results(
        "lease-timing",
        {
            "frames": len(got),
            "renewals": renewals,
            # a read and a renewal, wall time (the guest's UML system calls dominate)
            "renewal_wall_us_p50": round(sorted(walls)[len(walls) // 2] * 1e6, 1),
            "repeated": steps.count(0),
            "mean_period_ms": round(
                (frames[-1].timestamp - frames[0].timestamp) / (len(frames) - 1) * 1e3, 4
            ),
            "period_dev_ms_p50": round(periods[len(periods) // 2], 4),
            "period_dev_ms_p99": round(periods[int(len(periods) * 0.99)], 4),
            "period_dev_ms_max": round(periods[-1], 4),
        },
    )


def test_a_renewal_the_timer_races_loses_no_slot_the_kernels_count_finds_them(
    vcan0: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A renewal whose read and setup are 3 ms apart (the board proxy's Python between the
    two; a 10 ms period here) is raced by the timer in about a third of renewals, and the
    kernel's count loses that frame each time. Counted alone, it was 15-30 frames behind
    within 20 s and the op sent slots a ring old (steps of -35 and +37). With the broadcast
    manager's own count of the op's frames (SentCounts), every slot goes out once, in order,
    and the count ends right."""
    import exolink.canbus.leases as leases

    check = leases._check_lease

    def slow(*args: int) -> None:  # Python between the read and the setup, as on TCG before
        check(*args)
        until = time.perf_counter() + 0.003
        while time.perf_counter() < until:
            pass

    monkeypatch.setattr(leases, "_check_lease", slow)
    bus = listen(vcan0)
    ring, lease = 36, 20
    op = CyclicLease(vcan0, ID, PERIOD, ring=ring)
    frames: list[can.Message] = []
    try:
        op.start([slot(k) for k in range(ring)], lease)
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            time.sleep(3 * PERIOD)
            while (m := bus.recv(0)) is not None:
                frames.append(m)
            n = op.renew(plan(op.sent(), 4 * ring), lease)
            frames += drain(bus, 0.0005)
            assert n <= len(frames), (n, len(frames))  # never ahead of the bus
        time.sleep(0.05)
        counted = op.sent()
        op.stop()
        frames += drain(bus, 0.3)
    finally:
        op.close()
        bus.shutdown()
    got, steps = steps_of(frames)
    assert got[0] == 0 and set(steps) == {1}, sorted(set(steps))
    assert len(got) > 300, len(got)
    # the count after the last renewal: at most that renewal's own race short
    assert len(got) - 1 <= counted <= len(got), (counted, len(got))


def test_a_renewal_at_the_leases_last_frame_keeps_the_timer_going(
    vcan0: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A renewal that reads one frame left and sets its count only after that frame went out
    (a read-to-setup window longer than a period: a starved owner) would set a count on an
    ended timer: silent until a later renewal saw no progress (B69: 50 and 87 ms gaps under
    the 50 % cap). The renewal starts it again: the slots go on, in order, each once."""
    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD)
    try:
        n = renew_at_the_last_frame(op, monkeypatch)
        frames = drain(bus, 0.15)
    finally:
        op.close()
        bus.shutdown()
    got, steps = steps_of(frames)
    assert got[:3] == [0, 1, 2] and set(steps) == {1}, got
    # the lease set was 6 from slot 2: five after the restart, one of them maybe before it
    assert 7 <= len(got) <= 8, got
    assert op.restarted == 1 and n == 2


def test_a_renewal_whose_setup_lands_late_sends_no_slot_it_did_not_place(
    vcan0: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The owner preempted between its reads and its setup for 3.5 periods (a starved
    manager), while the old count still runs: the new count starts where the op is when the
    setup lands. Bounded by the read alone (``n + lease`` within the plan), it went two slots
    past the plan, from ring positions a ring old (C74: the gait jumped back 280 ms, a knee
    45 -> 0 -> 58 deg). Bounded from the old count's end, every frame on the bus is the next
    placed slot."""
    import exolink.canbus.leases as leases

    check = leases._check_lease

    def preempted(*args: int) -> None:
        check(*args)
        time.sleep(3.5 * PERIOD)

    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD, ring=16)
    try:
        op.start([slot(k) for k in range(8)], 6)  # slots 0..7 placed, 0..5 leased
        while op.remaining() > 4:  # slots 0 and 1 out
            pass
        monkeypatch.setattr(leases, "_check_lease", preempted)
        n = op.renew(plan(op.sent(), 6), 6)  # nothing past slot 7 to place
        frames = drain(bus, 0.2)
    finally:
        op.close()
        bus.shutdown()
    got, steps = steps_of(frames)
    _results("late-setup", {"renewal_at": n, "slots": got})
    assert got[:2] == [0, 1] and set(steps) == {1} and got[-1] <= 7, got


def test_an_op_the_supervisor_deleted_mid_renewal_is_not_started_again(
    vcan0: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The supervisor's copy of the socket deletes the op at a safe action; one that lands
    between a renewal's reads and its setup makes that setup create a new op (index 0, count
    0 sent). The renewal's restart, and a later resume, find the kernel's count gone back
    and delete it: nothing reaches the bus after the delete."""
    import exolink.canbus.leases as leases
    from exolink.canbus.bcm import tx_delete

    check = leases._check_lease
    deleted: list[float] = []

    def safe_action(*args: int) -> None:  # the watchdog's TX_DELETE, then the window runs on
        check(*args)
        tx_delete(op._sock, ID)
        deleted.append(time.time())
        time.sleep(1.5 * PERIOD)

    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], 3)
        while op.remaining() > 1:
            pass
        monkeypatch.setattr(leases, "_check_lease", safe_action)
        op.renew(plan(op.sent(), 12), 6)
        monkeypatch.setattr(leases, "_check_lease", check)
        with pytest.raises(leases.OpLost):  # deleted, or made again where it is not known
            op.renew(plan(op.sent(), 12), 6)
        op.resume()
        frames = drain(bus, 0.2)
    finally:
        op.close()
        bus.shutdown()
    after = [m for m in frames if m.timestamp > deleted[0]]
    assert deleted and after == [], slots_of(after)


def _link(channel: str, up: bool) -> None:
    from pyroute2 import IPRoute

    with IPRoute() as ip:
        ip.link("set", index=ip.link_lookup(ifname=channel)[0], state="up" if up else "down")


def test_frames_the_device_refused_end_the_op(vcan0: str) -> None:
    """Since 6.1 the kernel counts a frame sent only when the device took it, while the op's
    index goes on: frames refused (the interface down for a few periods) leave the op's own
    count ahead of the kernel's, so where the op is is not known. The next renewal says so
    (OpLost) and deletes the op: nothing more on the bus once the device takes frames again."""
    op = CyclicLease(vcan0, ID, PERIOD)
    bus = None
    try:
        op.start([slot(k) for k in range(8)], LEASE)
        time.sleep(2 * PERIOD)
        op.renew(plan(op.sent(), 16), LEASE)
        _link(vcan0, up=False)
        time.sleep(3 * PERIOD)  # ~3 frames refused (ENETDOWN), counted down all the same
        _link(vcan0, up=True)
        bus = listen(vcan0)
        # the device's going down left an error pending on the op's socket (ENETDOWN), which
        # the renewal's TX_READ would take for its answer: cleared, to reach the count check
        op._sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        with pytest.raises(OpLost, match="the op"):
            op.renew(plan(op.sent(), 16), LEASE)
        t = time.time()
        late = [m for m in drain(bus, 0.2) if m.timestamp > t]
    finally:
        op.close()
        if bus is not None:
            bus.shutdown()
    assert late == [], slots_of(late)


def test_a_restarted_timer_stops_at_once(vcan0: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The restart at a lease's end is a motion path of its own: a stop (every trip path's
    TX_DELETE) right after it leaves nothing more on the bus."""
    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD)
    try:
        renew_at_the_last_frame(op, monkeypatch)
        assert op.restarted == 1
        op.stop()
        t = time.time()
        late = [m for m in drain(bus, 0.1) if m.timestamp > t]
    finally:
        op.close()
        bus.shutdown()
    assert late == []


def test_the_kernels_count_is_the_ops_own_whatever_else_is_on_the_bus(vcan0: str) -> None:
    """The count that makes a renewal's race good is the broadcast manager's own (SentCounts):
    byte-exact copies of the op's next slots from another sender (a raw socket; python-can's
    frames differ in their len8_dlc byte) during the op and right after its stop move neither
    a renewal nor ``settled``: they count the op's own frames on the bus exactly. A second op on
    the same socket (the supervisor's held one serves every gait of a spawn) counts from its
    own start."""
    import socket

    from exolink.canbus.bcm import open_bcm
    from exolink.canbus.frames import CAN_FRAME

    def forge(k: int) -> None:
        forger.send(CAN_FRAME.pack(ID, 6, slot(k).ljust(8, b"\0")))

    forger = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    forger.bind((vcan0,))
    sock = open_bcm(vcan0)
    bus = listen(vcan0)
    out = []
    try:
        for _ in range(2):
            op = CyclicLease(vcan0, ID, PERIOD, ring=32, sock=sock)
            forged = 0
            try:
                op.start([slot(k) for k in range(32)], 20)
                for _ in range(10):
                    time.sleep(2 * PERIOD)
                    n = op.sent()
                    for k in range(n + 1, n + 4):  # the slots the op sends next
                        forge(k)
                        forged += 1
                    op.renew(plan(n, 24), 20)
                counted = op.sent()
                time.sleep(2.5 * PERIOD)  # two or three frames go out after the read
                op.stop()
                for k in range(counted, counted + 10):
                    forge(k)
                    forged += 1
                settled = op.settled(counted)
            finally:
                op.close()
            own = len(drain(bus, 0.1)) - forged
            out.append({"counted": counted, "settled": settled, "own_on_bus": own})
    finally:
        bus.shutdown()
        sock.close()
        forger.close()
    _results("settled-forged", {"ops": out})
    for op_out in out:
        assert op_out["settled"] == op_out["own_on_bus"] > op_out["counted"], out


OWNER = """
import sys, time
from exolink.canbus.leases import CyclicLease, OpLost
from exolink.protocol import h2
ID, PERIOD, LEASE = 0x46, 0.010, 6
slot = lambda n: n.to_bytes(4, "big") + b"\\xee\\xee"
op = CyclicLease(sys.argv[1], ID, PERIOD)
op.start([slot(k) for k in range(8)], LEASE)
print("started", flush=True)
while True:
    time.sleep(2 * PERIOD)
    n = op.sent()
    op.renew({k: slot(k) for k in range(n, n + 8)}, LEASE)
"""


@pytest.mark.parametrize("how", [signal.SIGSTOP, signal.SIGKILL])
def test_an_owner_stopped_or_killed_leaves_at_most_its_lease(vcan0: str, how: int) -> None:
    bus = listen(vcan0)
    owner = subprocess.Popen(
        [sys.executable, "-c", OWNER, vcan0], stdout=subprocess.PIPE, text=True
    )
    try:
        assert owner.stdout is not None and owner.stdout.readline().strip() == "started"
        drain(bus, 1.0)
        t0 = time.time()
        os.kill(owner.pid, how)
        after = [m for m in drain(bus, 0.5) if m.timestamp > t0]
    finally:
        owner.kill()
        owner.wait()
        bus.shutdown()
    # what the last renewal allowed, and one frame the kernel may send during a renewal
    assert len(after) <= LEASE + 1, slots_of(after)
    _results(
        f"lease-after-{signal.Signals(how).name}",
        {
            "frames_after": len(after),
            "last_frame_ms_after": round((after[-1].timestamp - t0) * 1e3, 2) if after else None,
            "lease_ms": LEASE * PERIOD * 1e3,
        },
    )
    if how == signal.SIGSTOP:  # a hung owner: the kernel went on, within the lease
        assert after, "the kernel's timer sent nothing after the owner stopped"


HELD_OWNER = """
import os, signal, sys
from exolink.canbus.held import held_socket
from exolink.canbus.leases import CyclicLease, OpLost
ID, PERIOD = 0x46, 0.010
slot = lambda n: n.to_bytes(4, "big") + b"\\xee\\xee"
op = CyclicLease(sys.argv[1], ID, PERIOD, ring=64, sock=held_socket())
op.start([slot(k) for k in range(64)], 60)  # 600 ms leased, never renewed
print("started", flush=True)
os.kill(os.getpid(), signal.SIGSTOP)  # stopped: it can delete nothing
"""


def test_the_supervisors_copy_deletes_an_op_its_stopped_owner_cannot(vcan0: str) -> None:
    """An owner's op on the socket the supervisor passed it (exolink.canbus.held), the owner
    stopped with 600 ms of lease left: the supervisor's ``delete`` (each safe action of its
    watchdog) ends the op at once, and the copy released at the owner's exit is closed."""
    from exolink.canbus.held import HELD_ENV, HeldOps

    held = HeldOps(vcan0, (ID,))
    sock = held.open()
    bus = listen(vcan0)
    owner = subprocess.Popen(
        [sys.executable, "-c", HELD_OWNER, vcan0],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, HELD_ENV: str(sock.fileno())},
        pass_fds=(sock.fileno(),),
    )
    try:
        assert owner.stdout is not None and owner.stdout.readline().strip() == "started"
        before = drain(bus, 0.1)
        assert held.delete() == 1  # the op was there, and it was deleted
        t0 = time.time()  # (a frame may go out while the delete is on its way)
        after = [m for m in drain(bus, 0.3) if m.timestamp > t0]
        assert held.delete() == 0  # none left
    finally:
        owner.kill()
        owner.wait()
        bus.shutdown()
    held.release(sock)
    _results("held-delete", {"frames_before": len(before), "frames_after": len(after)})
    assert len(before) >= 5, slots_of(before)  # the stopped owner's op was sending
    assert after == [], slots_of(after)
    assert sock.fileno() == -1  # released: closed


def test_after_a_stop_the_kernels_count_settles_what_the_bus_carried(vcan0: str) -> None:
    """The count read before a stop misses what the timer sent after it: ``settled`` counts
    the op's frames on the bus exactly (the step limit goes on from the slot the joint is at,
    Timed.leave), not a slot or two short."""
    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD, ring=32)
    try:
        op.start([slot(k) for k in range(32)], 30)
        time.sleep(5 * PERIOD)
        counted = op.sent()
        time.sleep(2.5 * PERIOD)  # two or three frames go out after the read
        op.stop()
        settled = op.settled(counted)
        frames = drain(bus, 0.1)
    finally:
        op.close()
        bus.shutdown()
    _results("settled", {"counted": counted, "settled": settled, "on_bus": len(frames)})
    assert slots_of(frames) == list(range(len(frames)))
    assert settled == len(frames) > counted, (counted, settled, len(frames))


def test_a_lapsed_lease_resumes_at_its_next_slot_in_order(vcan0: str) -> None:
    """A renewal, then ``resume``, after the lease ran out and after the race's state (a
    renewal's count set on an ended timer): the kernel's next frame is the next slot, then on
    in order, each slot once: the index is kept, only the phase is new."""
    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], 3)
        assert slots_of(drain(bus, 0.1)) == [0, 1, 2]  # the lease ran out
        assert op.renew(plan(op.sent()), 3) == 3  # a count on the ended timer
        op.resume()
        assert slots_of(drain(bus, 0.1)) == [3, 4, 5]
        op.renew(plan(op.sent()), 3)  # a count on an ended timer: silent, as after the race
        assert drain(bus, 0.05) == []
        assert op.renew(plan(op.sent()), 4) == 6
        op.resume()
        got = slots_of(drain(bus, 0.1))
    finally:
        op.close()
        bus.shutdown()
    assert got == [6, 7, 8, 9], got


def test_stop_is_at_once_and_a_lease_that_ran_out_stays_out(vcan0: str) -> None:
    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], 3)
        assert slots_of(drain(bus, 0.2)) == [0, 1, 2]  # three, then the op's timer ended
        assert op.remaining() == 0
        op.renew(plan(op.sent()), 3)  # a renewal never restarts a lapsed lease
        assert drain(bus, 0.1) == []
        op.start([slot(k) for k in range(8)], 8)  # a new phase, on purpose
        time.sleep(0.025)
        op.stop()
        t = time.time()
        late = [m for m in drain(bus, 0.2) if m.timestamp > t]
        assert late == []
        with pytest.raises(ValueError, match="lease of 9 frames"):
            op.start([slot(k) for k in range(8)], 9)
    finally:
        op.close()
        bus.shutdown()


# --- the controller manager's timer, the whole appliance on vcan0 ---------------------------------


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*EXOLINK, *args, "--timeout", "5"], capture_output=True, text=True, timeout=60
    )


def _manager() -> dict:
    return json.loads(_cli("controllers", "list", "--json").stdout)


def _until(pred, what: str, timeout: float = 60.0):  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with contextlib.suppress(Exception):
            if got := pred():
                return got
        time.sleep(0.3)
    raise AssertionError(f"{what}: not within {timeout} s")


def _sending() -> dict | None:
    """The manager's timer status while it sends, else None."""
    timer = _manager()["timer"]
    return timer if timer["sending"] else None


_ESTOP_ARGS = argparse.Namespace(
    at=DEFAULT_AT, device=None, zenoh_config=None, timeout=5.0, domain=0, ns="h2"
)


def _restarted(pid: int) -> int:
    """The controller manager's pid once a new one replaced ``pid``."""

    def new() -> int | None:
        nodes = json.loads(_cli("status", "--json").stdout)["nodes"]
        now = next(n for n in nodes if n["name"] == "controller_manager")["pid"]
        return now if now not in (None, pid) else None

    return int(_until(new, "restarted"))


def _walk() -> None:
    """Armed, held, the gait on the manager's timer."""
    _until(lambda: _cli("arm").returncode == 0, "armed")
    assert _cli("pattern", "start", "--detach").returncode == 0
    _until(lambda: _manager()["timer"]["sending"], "the gait on the timer")


def _after(channel: str, act, seconds: float = 1.0) -> dict:  # type: ignore[no-untyped-def]
    """``act()`` mid-gait; the joint-control frames an independent socket saw after it: the
    last set-point and the first disable, in ms from the act."""
    bus = can.Bus(
        interface="socketcan",
        channel=channel,
        receive_own_messages=False,
        can_filters=[{"can_id": h2.JOINT_CONTROL, "can_mask": 0x7FF}],
    )
    got: list[can.Message] = []
    try:
        drain(bus, 0.1)
        # read while ``act`` runs (a CLI process takes seconds here): an unread socket's queue
        # holds ~300 frames, 1.5 s of the gait, and then drops the newest
        reader = threading.Thread(target=lambda: got.extend(drain(bus, seconds)))
        t0 = time.time()
        reader.start()
        act()
        reader.join()
        frames = [(m.timestamp, h2.decode(m)) for m in got]
    finally:
        bus.shutdown()
    moving = [t for t, f in frames if isinstance(f, h2.JointControl) and f.mode == 1 and t > t0]
    disabled = [t for t, f in frames if isinstance(f, h2.JointControl) and f.mode == 4 and t > t0]
    first = disabled[0] if disabled else None
    return {
        "set_points_after": len(moving),
        "last_set_point_ms": round((moving[-1] - t0) * 1e3, 2) if moving else None,
        "first_disable_ms": round((first - t0) * 1e3, 2) if first else None,
        "set_points_after_first_disable": len([t for t in moving if first and t > first]),
        "last_set_point_after_first_disable_ms": round((max(moving) - first) * 1e3, 2)
        if first and moving and max(moving) > first
        else 0.0,
    }


def _motor_timing(channel: str, motor: int, seconds: float, slot_ms: float = 20.0) -> dict:
    """One joint's set-points for ``seconds``: their count, mean period and deviation from the
    slot (ms), from an independent socket's kernel timestamps, read while they come, and the
    largest step between two of them (deg): what the step limit allowed, unless the op sent a
    slot out of its order (a count behind by a ring sent slots a ring old)."""
    bus = can.Bus(
        interface="socketcan",
        channel=channel,
        receive_own_messages=False,
        can_filters=[{"can_id": h2.JOINT_CONTROL, "can_mask": 0x7FF}],
    )
    try:
        frames = drain(bus, seconds)
    finally:
        bus.shutdown()
    ours = [m for m in frames if len(m.data) == 6 and m.data[0] == motor and m.data[1] == 1]
    stamps = [m.timestamp for m in ours]
    points = [h2.decode(m).setpoint for m in ours]  # type: ignore[union-attr]
    dev = sorted(abs((b - a) * 1e3 - slot_ms) for a, b in itertools.pairwise(stamps))
    if len(stamps) < 2:
        return {"n": len(stamps)}
    return {
        "n": len(stamps),
        "mean_period_ms": round((stamps[-1] - stamps[0]) / (len(stamps) - 1) * 1e3, 4),
        "p50_dev_ms": round(dev[len(dev) // 2], 4),
        "p99_dev_ms": round(dev[int(len(dev) * 0.99)], 4),
        "max_dev_ms": round(dev[-1], 4),
        "max_step_deg": max(abs(b - a) for a, b in itertools.pairwise(points)),
    }


@pytest.mark.timeout(900)
def test_the_managers_timer_ends_with_its_owner_and_every_trip(vcan0: str, tmp_path: Path) -> None:
    """The gait on the broadcast manager's timer under the controller manager's lease (200 ms,
    the board's; nice -10): a trip, a CPU hog at the manager's priority, SIGSTOP and kill -9 of
    the manager mid-gait, and a trip while it is stopped. No set-point may reach the bus more
    than 60 ms after the watchdog's first disable frame."""
    import yaml

    from exolink.config import bundled

    data = yaml.safe_load(bundled("sim").read_text())
    data["can"] = {"interface": "socketcan", "channel": vcan0, "bring_up": True}
    data["nodes"] = motion_nodes(
        {
            "name": "pattern_player",
            "plugin": "pattern_player",
            "critical": True,
            "params": {"speed": 10, "selected": ["r_hip", "r_knee", "l_hip", "l_knee"]},
        },
        {"name": "timing_monitor", "plugin": "timing_monitor", "params": {"ids": [70]}},
        # The board's 50 ms tripped at random here: the whole UML guest stops for tens of ms
        # when the host is busy (test_socketcan.py). 200 ms, and the lease the board's.
        deadline_ms=200,
        h2_timeout_ms=300,
        priority={"nice": -10},
        restart={"policy": "always", "max_restarts": 10, "window_s": 600},
    )
    # one UML CPU, CLI processes importing for seconds: wide limits for everything but the
    # manager, as tests/kernel/test_socketcan.py explains
    data["watchdog"].update(
        pulse_silence_ms=3000,
        heartbeat_deadline_ms=2000,
        start_grace_ms=60_000,
        operator_lost_ms=60_000,
    )
    data["clock"] = {"from_laptop": True}
    cfg = tmp_path / "appliance.yaml"
    cfg.write_text(yaml.safe_dump(data))
    log = (tmp_path / "up.log").open("wb")
    up = subprocess.Popen([*EXOLINK, "up", "-c", str(cfg)], stdout=log, stderr=subprocess.STDOUT)
    holder = None
    out: dict = {}
    try:
        _until(
            lambda: all(
                n["heartbeat_age_s"] is not None
                for n in json.loads(_cli("status", "--json").stdout)["nodes"]
            ),
            "every node beating",
            120,
        )
        holder = subprocess.Popen([*EXOLINK, "hold"], stdout=subprocess.PIPE, text=True)
        assert holder.stdout is not None and "holding motion" in holder.stdout.readline()
        _walk()
        # timing of the kernel's timer, alone and with a CPU hog at the manager's priority, from
        # an independent socket's kernel timestamps (r_hip, motor 1)
        out["timing"] = _motor_timing(vcan0, 1, 10.0)
        hog = subprocess.Popen([sys.executable, "-c", "import os; os.nice(-10)\nwhile True: pass"])
        try:
            out["timing_with_hog"] = _motor_timing(vcan0, 1, 10.0)
        finally:
            hog.kill()
            hog.wait()
        out["timer_with_hog"] = _manager()["timer"]
        assert out["timing"]["n"] > 300 and out["timing_with_hog"]["n"] > 300, out
        # what the bus carried is what the manager checked: a slot's step within the limit
        step = data["limits"]["max_step_deg"] * 2  # two 10 ms cycles a 20 ms slot
        assert out["timing"]["max_step_deg"] <= step, out["timing"]
        assert out["timing_with_hog"]["max_step_deg"] <= step, out["timing_with_hog"]
        # a trip: the manager hears it and deletes the op (the e-stop from a client that found
        # the device before: an `exolink estop` process took 3.6-4.6 s to import and connect in
        # this guest, and over 10 s once on a slower host: its start is not what is measured)
        with remote(_ESTOP_ARGS) as r:
            assert r.device
            out["estop"] = _after(vcan0, lambda: r.call("watchdog", body=watchdog_body("estop")))
        # SIGSTOP of the manager: the kernel sends out the lease, the watchdog trips
        _walk()
        pid = next(
            n["pid"]
            for n in json.loads(_cli("status", "--json").stdout)["nodes"]
            if n["name"] == "controller_manager"
        )
        # the timer sending right before the signal (a loaded guest's stall can hand the joints
        # back to the cycle loop for a moment, and a stopped cycle loop sends nothing)
        out["timer_before_sigstop"] = _until(_sending, "the timer sends")
        try:
            out["sigstop"] = _after(vcan0, lambda: os.kill(pid, signal.SIGSTOP))
        finally:  # hung-killed by the supervisor meanwhile, as a rule
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        # SIGSTOP of the (restarted) manager and an e-stop at once, well inside its 200 ms
        # lease: the manager cannot delete the op, the watchdog does (the supervisor holds
        # the op's socket: exolink.canbus.held), before its first disable frame
        pid = _restarted(pid)
        _walk()
        out["timer_before_stop_estop"] = _until(_sending, "the timer sends")
        with remote(_ESTOP_ARGS) as r:
            assert r.device  # found now, not inside the measured act
            estop = watchdog_body("estop")
            try:
                out["sigstop_estop"] = _after(
                    vcan0, lambda: (os.kill(pid, signal.SIGSTOP), r.call("watchdog", body=estop))
                )
            finally:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)
        # kill -9 of the (restarted) manager: the supervisor's copy of its socket is released
        # at its exit, the op deleted with it
        pid = _restarted(pid)
        _walk()
        out["timer_before_sigkill"] = _until(_sending, "the timer sends")
        out["sigkill"] = _after(vcan0, lambda: os.kill(pid, signal.SIGKILL))
    finally:
        _results("manager-timer", out)
        if holder is not None:
            holder.kill()
        up.terminate()
        up.wait(30)
        log.close()
    for case in ("estop", "sigstop", "sigstop_estop", "sigkill"):
        assert out[case]["first_disable_ms"] is not None, (case, out[case])
        assert out[case]["last_set_point_after_first_disable_ms"] <= 60, (case, out[case])
    assert out["sigstop"]["last_set_point_ms"] is not None  # the kernel went on, leased
    assert out["sigstop"]["last_set_point_ms"] <= 200 + 20, out["sigstop"]  # lease + a slot
    # the watchdog deleted the stopped manager's op before its first disable frame
    assert out["sigstop_estop"]["set_points_after_first_disable"] == 0, out["sigstop_estop"]
    # kill -9: the op ends when the supervisor reaps the process (it releases its copy of the
    # socket and trips the watchdog then), never after the first disable frame and never later
    # than the lease would have. How soon is the guest's exit time, not a behaviour: 1-7
    # set-points (5-35 ms) in CI runs, reported in the results line, not asserted (a bound of
    # 4 failed CI on a loaded host)
    assert out["sigkill"]["set_points_after_first_disable"] == 0, out["sigkill"]
    assert (out["sigkill"]["last_set_point_ms"] or 0) <= 200 + 20, out["sigkill"]  # lease + a slot
