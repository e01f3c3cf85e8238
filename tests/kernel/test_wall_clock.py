"""A laptop's step of the board's wall clock on a real kernel (the UML guest's own clock, which
a test may step; on the host these skip: its clock is never stepped)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from exolink.board import clock

pytestmark = pytest.mark.kernel


def test_an_unsynchronised_board_takes_a_laptops_time_and_says_so(
    own_clock: None, tmp_path: Path
) -> None:
    assert not clock.kernel().synchronised  # the guest runs no time server
    board = clock.BoardClock(tmp_path, from_laptop=True)
    assert board.status().source == "unsynchronised"
    # The board booted an hour and a bit ahead (the time saved at the last shutdown, say).
    time.clock_settime(time.CLOCK_REALTIME, time.time() + 3600.25)
    laptop_now = time.time() - 3600.25
    measured = clock.measure(lambda: time.time())  # the board's own "reply": offset ~0
    assert abs(measured.offset_s) < 0.01
    before = time.time()
    step = board.step(3600.25, 0.002, "operator", armed=False)
    after = time.time()
    assert abs((before - after) - 3600.25) < 0.5  # stepped back by the hour and a quarter second
    assert abs(after - laptop_now) < 0.5
    saved = json.loads((tmp_path / clock.CLOCK_FILE).read_text())
    assert saved["by"] == "operator" and saved["step_s"] == -3600.25
    assert saved["boot_id"] == clock.boot_id() == step.boot_id
    status = board.status()
    assert status.source == "laptop" and status.last_step and status.last_step.by == "operator"
    assert clock.recorded(str(tmp_path))["source"] == "laptop"
    assert clock.recorded(str(tmp_path))["stepped_by"] == "operator"


def test_a_step_is_refused_while_armed_and_a_step_of_a_past_boot_no_longer_counts(
    own_clock: None, tmp_path: Path
) -> None:
    board = clock.BoardClock(tmp_path, from_laptop=True)
    wall = time.time()
    with pytest.raises(clock.ClockRefused, match="armed"):
        board.step(5.0, 0.001, "operator", armed=True)
    assert abs(time.time() - wall) < 1  # not stepped
    past = {"by": "operator", "at": "2026-11-27T10:00:00Z", "step_s": 5.0, "error_ms": 1.0}
    (tmp_path / clock.CLOCK_FILE).write_text(json.dumps({**past, "was": 0.0, "boot_id": "other"}))
    assert board.status().source == "unsynchronised"
