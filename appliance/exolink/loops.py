"""The loops a node declares instead of writing its own (``Node.loop``): how it wakes, what it
reads and what it does after. The runtime runs the declared loop and beats for the node on every
wake, so a node is its handlers plus one line saying when they run, and the rules every loop
must keep (beat on every wake, and after a cadence's read and handling; read a wake's frames
in one batch, publish after the read, time the phases on the thread's CPU clock) are kept
here once.

- ``Every(period_s, step)``: wake every period, then ``step`` (None: the node's work is in its
  handlers and threads, the loop only proves it alive).
- ``Frames(reader, handle, wait, after)``: wake on the bus (exolink.canbus.open_reader), hand a
  wake's frames to ``handle`` in one call (``each(fn)``: to ``fn`` one by one), then each
  ``after`` phase (the outbox's flush, diagnostics); ``wait`` is a fixed timeout or the
  reader's ``Cadence``.

A node whose loop is its job keeps ``run`` (the controller manager's cycle and timer modes, the
recorder's intake, the simulator's clocked models): say which in its docstring.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from exolink.phaseclock import PhaseClock

if TYPE_CHECKING:
    from exolink.canbus import Cadence

Beat = Callable[[], None]


class Loop(Protocol):
    def run(self, beat: Beat, stop: threading.Event) -> None:
        """Until ``stop``: wake, ``beat()``, do the node's work."""
        ...


class Reads(Protocol):
    """What ``Frames`` reads: exolink.canbus's FrameReader (a batch per call, up to a timeout)."""

    def read(self, timeout: float) -> list[Any]: ...


@dataclass
class Every:
    period_s: float
    step: Callable[[], None] | None = None

    def run(self, beat: Beat, stop: threading.Event) -> None:
        step = self.step
        while not stop.wait(self.period_s):
            beat()
            if step is not None:
                step()


def each(handle: Callable[[Any], None]) -> Callable[[list[Any]], None]:
    """A wake's frames handed to ``handle`` one by one (``Frames``' handle)."""

    def handle_all(frames: list[Any]) -> None:
        for frame in frames:
            handle(frame)

    return handle_all


class _Untimed:
    """The clock of a loop whose phases nobody reads: no CPU clock read (a system call each)."""

    def start(self) -> None:
        pass

    def mark(self, phase: str) -> None:
        pass


@dataclass
class Frames:
    """``clock``: the CPU of each phase (``beat``, ``read``, ``handle``, then each ``after``'s
    name), sampled (exolink.phaseclock), for a node that reports it (the h2 reader's stats:
    ``loop_cpu``); None, not timed."""

    reader: Reads
    handle: Callable[[list[Any]], None]
    wait: Cadence | float
    after: Sequence[tuple[str, Callable[[], None]]] = ()
    clock: PhaseClock | None = None

    def run(self, beat: Beat, stop: threading.Event) -> None:
        read, handle, after = self.reader.read, self.handle, self.after
        clock = self.clock or _Untimed()
        wait = self.wait
        cadence, timeout = (
            (None, float(wait)) if isinstance(wait, int | float) else (wait, wait.idle_s)
        )
        while not stop.is_set():
            clock.start()
            beat()
            clock.mark("beat")
            frames = read(timeout)
            clock.mark("read")
            if cadence is not None:
                # Once more after a cadence's wait and read: the top's beat is a whole cadence
                # before this wake's work ends, and a wake starved under a CPU cap (the h2
                # reader: ~25 ms of the board proxy's CPU every 200 ms) crossed its 500 ms
                # deadline by 1-27 ms at a gait's start and stop (docs/performance.md). A loop
                # stuck in its read or its handling still misses it.
                beat()
                clock.mark("beat")  # the phase's sum: both beats, the read's figure unchanged
            if frames:
                handle(frames)
            clock.mark("handle")
            if cadence is not None and frames:
                # And after handling them: a cadence's wake is ~25 ms of the board proxy's CPU
                # (read 13, handle 6, publish 2), and under a 50 % cap the reader's beats came
                # 509-549 ms apart at the gait's stop and in a window (C65, G65, H65), its
                # deadline 500 ms. Each phase of real progress is proof of life; a stuck one
                # still misses it. (A beat is ~0.4 ms there; one in a wake of 25.)
                beat()
                clock.mark("beat")
            for phase, fn in after:
                fn()
                clock.mark(phase)
            if cadence is not None:
                timeout = cadence.timeout(bool(frames))


__all__ = ["Every", "Frames", "Loop", "Reads", "each"]
