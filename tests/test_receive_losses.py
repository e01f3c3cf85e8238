"""Receive losses are visible: frames the h2 reader's socket dropped while the reader stalled
are counted exactly, shown in `exolink status`, and written into the recording."""

from __future__ import annotations

import os
import signal
from typing import Any

from benchmarks.harness import Appliance, wait_for
from exolink import messaging
from exolink.canbus import open_bus
from exolink.protocol import h2
from exolink.recordings.readback import info


def test_stalled_reader_losses_in_status_and_recording(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    rec_dir = tmp_path / "rec"
    cfg = write_config(
        nodes=[
            {
                "name": "h2_reader",
                "plugin": "h2_reader",
                # every frame handled or counted dropped: none skipped as stale here
                "params": {"start_stream": False, "stale_after_s": 0},
                # stalled on purpose below: not to be killed as hung meanwhile
                "heartbeat_deadline_ms": 60_000,
            },
            {"name": "recorder", "plugin": "recorder", "params": {"directory": str(rec_dir)}},
        ]
    )
    app = Appliance(cfg, spawn)
    s = messaging.open_client_session(app.at)

    def stats() -> dict[str, Any]:
        return messaging.request(s, "exolink/sim/nodes/h2_reader/stats")

    tx = open_bus(app.cfg.can)
    try:
        assert app.cli("record", "start").returncode == 0
        before = stats()
        assert before["receive"]["dropped"] == 0 and before["frames"]["110"] == 0
        # More frames than the reader's receive queue holds (a frame takes >= 256 B of it).
        sent = before["receive"]["rcvbuf"] // 256 + 1000
        frame = h2.encode(h2.JointAngles(10, 20, 5, 10, 20, 5))
        pid = app.node("h2_reader")["pid"]
        os.kill(pid, signal.SIGSTOP)
        try:
            for _ in range(sent):
                tx.send(frame)
        finally:
            os.kill(pid, signal.SIGCONT)
        # Every frame sent was either handled by the reader or counted as dropped.
        wait_for(lambda: stats()["frames"]["110"] + stats()["receive"]["dropped"] == sent)
        after = stats()
        dropped = after["receive"]["dropped"]
        assert dropped > 0 and after["socket_dropped"] == dropped
        assert after["receive"]["late"] > 0  # read long after arrival: the stall

        def shown() -> bool:
            return app.node("h2_reader").get("receive", {}).get("dropped") == dropped

        wait_for(shown, timeout=5)  # through the reader's diagnostics (1 s period)
        row = next(
            line for line in app.cli("status").stdout.splitlines() if line.startswith("h2_reader")
        )
        assert f"rx dropped {dropped} " in row
        r = app.cli("record", "stop")
        assert r.returncode == 0, r.stderr
    finally:
        tx.shutdown()
        s.close()
    [path] = sorted(rec_dir.glob("*.mcap"))
    rx = info(path).metadata["exolink.receive"]
    assert rx["h2_reader.dropped"] == str(dropped)
    assert rx["h2_reader.dropped_in_file"] == str(dropped)  # none before the file was opened
    assert rx["h2_reader.frames_in_file"] == str(sent - dropped)
