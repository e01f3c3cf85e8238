"""The liveness pipe on its own: whole records only, the newest wins, never in the future."""

from __future__ import annotations

import os
import struct

from exolink import liveness


def test_newest_whole_beat_wins_and_partial_records_wait() -> None:
    ch = liveness.Channel()
    try:
        beater = liveness.Beater(ch.child_fd)
        assert ch.drain(100.0) is None
        beater.beat(10.0)
        beater.beat(10.001)  # inside MIN_INTERVAL_S: not written
        beater.beat(10.5)
        assert ch.fileno() and liveness.with_beats([ch]) == {ch}
        assert ch.drain(100.0) == 10.5
        assert liveness.with_beats([ch]) == set()
        raw = struct.pack("=d", 11.0)
        os.write(ch.child_fd, raw[:3])  # a torn record cannot come from one write, but be strict
        assert ch.drain(100.0) is None
        os.write(ch.child_fd, raw[3:])
        assert ch.drain(100.0) == 11.0
        beater.beat(500.0)
        assert ch.drain(100.0) == 100.0  # a beat from the future is clamped to now
    finally:
        ch.close()


def test_without_a_supervisor_beats_go_nowhere(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.delenv(liveness.ENV, raising=False)
    b = liveness.Beater.from_env()
    assert b.fd is None
    b.beat()  # no error


def test_a_gone_supervisor_does_not_break_the_node() -> None:
    ch = liveness.Channel()
    fd = os.dup(ch.child_fd)
    ch.close()
    b = liveness.Beater(fd)
    b.beat(1.0)  # EPIPE is swallowed
    os.close(fd)
