"""The tests' own bus listener (benchmarks.harness.DrainedBus) keeps what the kernel received
in a window even when the host stalls the test past it: CI's did, and a window's frames,
already received, were reported as never sent."""

from __future__ import annotations

import os
import subprocess
import sys

from benchmarks.harness import DrainedBus, collect

SEND = """
import sys, time, can
from exolink.canbus import open_reader
from exolink.config import CanConfig
r = open_reader(CanConfig(interface="udp_multicast", channel=sys.argv[1]))
time.sleep(0.3)
r.bus.send(can.Message(arbitration_id=70, data=b"x", is_extended_id=False))
r.close()
"""


def test_a_window_stalled_past_its_end_keeps_the_frames_received_in_it(group: str) -> None:
    """This process stopped (SIGSTOP, by another) from 0.1 s into a 1 s window to 1.6 s; a
    frame sent meanwhile by a third process is in the window's frames."""
    bus = DrainedBus(group)
    try:
        pid = os.getpid()
        stall = subprocess.Popen(
            ["sh", "-c", f"sleep 0.1; kill -STOP {pid}; sleep 1.5; kill -CONT {pid}"]
        )
        sender = subprocess.Popen([sys.executable, "-c", SEND, group])
        got = collect(bus, 1.0, {70})
        assert sender.wait(10) == 0 and stall.wait(10) == 0
        assert [bytes(m.data) for m in got] == [b"x"], got
        assert bus.dropped == 0
    finally:
        bus.close()
