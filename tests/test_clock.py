"""The board's clock against a laptop's (exolink.board.clock): the offset, its warnings, refusals of
a step, and what a recording says of its clock. Stepping a real clock: tests/kernel/test_wall_clock.py
(a recording's clock: tests/test_recording.py; the host's clock is never stepped here: the sim appliance has clock.from_laptop false)."""

from __future__ import annotations

import time

import pytest

from benchmarks.harness import Appliance
from exolink.board import clock
from exolink.cli import clock as cli_clock
from exolink.wire.replies import ClockStatus, ClockStep


def test_the_shortest_round_trip_sets_the_offset() -> None:
    # The board is 2 s ahead; the second reply came back fast, the others were delayed.
    delays = iter([0.05, 0.0, 0.03])

    def ask() -> float:
        d = next(delays)
        time.sleep(d / 2)
        now = time.time() + 2.0
        time.sleep(d / 2)
        return now

    off = clock.measure(ask, samples=3)
    assert abs(off.offset_s - 2.0) < 0.005
    assert off.error_s < 0.005
    assert off.off()


def test_offsets_within_the_round_trip_are_not_called_off() -> None:
    assert not clock.Offset(0.060, 0.020).off()  # could be 40 ms
    assert clock.Offset(-0.080, 0.020).off()


def test_the_status_line_warns_when_the_time_cannot_be_trusted() -> None:
    unsynced = ClockStatus(0.0, False, None, "unsynchronised", from_laptop=True)
    text = cli_clock.describe(unsynced, clock.Offset(3600.0, 0.001))
    assert "UNSYNCHRONISED" in text and "exolink clock sync" in text
    assert "3600000 ms off" in text
    step = ClockStep("operator", "2026-11-27T10:00:00Z", 1.0, 1.0, 0.0)
    stepped = ClockStatus(0.0, False, None, "laptop", from_laptop=True, last_step=step)
    text = cli_clock.describe(stepped, clock.Offset(0.002, 0.001))
    assert "set from a laptop by operator" in text and "WARNING" not in text


@pytest.mark.parametrize(
    ("offset", "error", "why"),
    [
        (float("nan"), 0.001, "finite"),
        ("5", 0.001, "finite"),
        (True, 0.001, "finite"),
        (1e12, 0.001, "not a clock's error"),
        (1.0, -1.0, "not a clock's error"),
    ],
)
def test_a_bad_step_is_refused_with_what_was_wrong(offset, error, why, tmp_path) -> None:  # type: ignore[no-untyped-def]
    board = clock.BoardClock(tmp_path, from_laptop=True)
    with pytest.raises(clock.ClockRefused, match=why):
        board.step(offset, error, "operator", armed=False)
    assert not (tmp_path / clock.CLOCK_FILE).exists()


def test_the_simulator_never_steps_its_hosts_clock(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    reader = {"name": "h2_reader", "plugin": "h2_reader"}  # a node: the CLI finds the device
    app = Appliance(write_config(nodes=[reader]), spawn)
    out = app.cli("clock")
    assert out.returncode == 0, out.stderr
    assert "board - this laptop" in out.stdout
    refused = app.cli("clock", "sync")
    assert refused.returncode != 0
    assert "clock.from_laptop: false" in refused.stderr
    status = app.cli("status")
    assert "clock    " in status.stdout
    assert "clock.from_laptop is false" in status.stdout  # no advice that cannot work
    st = app.status()
    assert st["clock"]["from_laptop"] is False and isinstance(st["clock"]["now"], float)
