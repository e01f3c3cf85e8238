"""exolink.loops: the rules every declared loop keeps, here for ``Frames`` on a cadence (the h2
reader's): a beat on every wake, after the read, and after the handling, before the phases
that follow (publishing)."""

from __future__ import annotations

import threading
from typing import Any

from exolink.canbus.opening import Cadence
from exolink.loops import Frames


class ThreeWakes:
    """The ``Reads`` protocol over a fixed script: three reads that bring frames, then a stop."""

    def __init__(self, events: list[str], stop: threading.Event) -> None:
        self.events, self.stop, self.reads = events, stop, 0

    def read(self, timeout: float) -> list[Any]:
        self.reads += 1
        self.events.append("read")
        if self.reads == 3:
            self.stop.set()
        return [self.reads]


def test_a_cadence_beats_on_waking_after_its_read_and_after_its_handling() -> None:
    events: list[str] = []
    stop = threading.Event()
    loop = Frames(
        ThreeWakes(events, stop),
        lambda frames: events.append("handle"),
        Cadence(0.01, 20),
        after=[("publish", lambda: events.append("publish"))],
    )
    loop.run(lambda: events.append("beat"), stop)
    wake = ["beat", "read", "beat", "handle", "beat", "publish"]
    assert events == wake * 3, events


def test_a_fixed_timeout_beats_once_a_wake() -> None:
    """Without a cadence (a loop woken by anything on its bus) a wake is short: one beat."""
    events: list[str] = []
    stop = threading.Event()
    loop = Frames(ThreeWakes(events, stop), lambda frames: events.append("handle"), 0.01)
    loop.run(lambda: events.append("beat"), stop)
    assert events == ["beat", "read", "handle"] * 3, events
