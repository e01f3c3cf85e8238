"""The broadcast manager's send op with a lease (exolink.cyclic.CyclicLease) on vcan0 in the
UML guest: set-points on the kernel's timer, renewed without a gap or a skip, and bounded when
their owner is stopped, killed or stops them. Counts are asserted; times are printed."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest
from exolink.cyclic import CyclicLease

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


def plan(n: int, ahead: int = 8) -> dict[int, bytes]:
    return {k: slot(k) for k in range(n, n + ahead)}


def _results(name: str, data: dict) -> None:
    print(name, json.dumps(data))
    where = Path(os.environ.get("EXOLINK_KERNEL_RESULTS", "/tmp"))
    (where / f"{name}.json").write_text(json.dumps(data))


def test_renewed_set_points_leave_on_the_kernels_timer_without_gap_or_skip(vcan0: str) -> None:
    bus = listen(vcan0)
    op = CyclicLease(vcan0, ID, PERIOD)
    try:
        op.start([slot(k) for k in range(8)], LEASE)
        renewals, end = 0, time.monotonic() + 3.0
        while time.monotonic() < end:
            time.sleep(2 * PERIOD)  # the owner wakes every second period, as the manager
            n = op.sent()
            op.renew(plan(n), LEASE)
            renewals += 1
        op.stop()
        frames = drain(bus, 0.3)
    finally:
        op.close()
        bus.shutdown()
    got = slots_of(frames)
    steps = [b - a for a, b in itertools.pairwise(got)]
    assert got[0] == 0 and set(steps) <= {0, 1}, steps  # never a skip, never backwards
    assert len(got) > 250  # 3 s at 10 ms
    periods = sorted(
        abs((b.timestamp - a.timestamp) - PERIOD) * 1e3 for a, b in itertools.pairwise(frames)
    )
    _results(
        "lease-timing",
        {
            "frames": len(got),
            "renewals": renewals,
            "repeated": steps.count(0),
            "mean_period_ms": round(
                (frames[-1].timestamp - frames[0].timestamp) / (len(frames) - 1) * 1e3, 4
            ),
            "period_dev_ms_p50": round(periods[len(periods) // 2], 4),
            "period_dev_ms_p99": round(periods[int(len(periods) * 0.99)], 4),
            "period_dev_ms_max": round(periods[-1], 4),
        },
    )


OWNER = """
import sys, time
from exolink.cyclic import CyclicLease
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
