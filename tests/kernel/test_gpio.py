"""Real libgpiod v2 on a gpio-sim chip (qemu guest): trigger edges with kernel timestamps and
debounce, and the trigger output observed by a second line request."""

from __future__ import annotations

import itertools
import time
from datetime import timedelta

import pytest

from exolink.config import TriggerConfig
from exolink.supervisor import trigger

pytestmark = pytest.mark.kernel


def test_trigger_edges_with_kernel_timestamps(gpio_sim) -> None:  # type: ignore[no-untyped-def]
    edges: list[trigger.Edge] = []
    src = trigger.GpioTrigger(
        TriggerConfig(chip=gpio_sim.chip, line=7, edge="rising", debounce_ms=5), edges.append
    )
    try:
        before = time.time_ns()
        for _ in range(3):
            gpio_sim.pull(7, True)
            time.sleep(0.2)
            gpio_sim.pull(7, False)
            time.sleep(0.2)
        time.sleep(0.5)
    finally:
        src.close()
    assert len(edges) == 3 and all(e.rising and e.source == "gpio" for e in edges)
    assert all(before <= e.stamp_ns <= time.time_ns() for e in edges)  # REALTIME kernel stamps
    gaps = [(b.stamp_ns - a.stamp_ns) / 1e9 for a, b in itertools.pairwise(edges)]
    assert all(g > 0.3 for g in gaps)  # one edge per toggle, 0.4 s apart (stamped by the kernel)


def test_debounce_swallows_a_glitch(gpio_sim) -> None:  # type: ignore[no-untyped-def]
    edges: list[trigger.Edge] = []
    src = trigger.GpioTrigger(
        TriggerConfig(chip=gpio_sim.chip, line=3, edge="both", debounce_ms=50), edges.append
    )
    try:
        gpio_sim.pull(3, True)
        gpio_sim.pull(3, False)  # a glitch far shorter than 50 ms
        time.sleep(0.3)
        gpio_sim.pull(3, True)
        time.sleep(0.3)
    finally:
        src.close()
    assert [e.rising for e in edges] == [True]


def test_trigger_output_seen_by_a_second_request(gpio_sim) -> None:  # type: ignore[no-untyped-def]
    import gpiod
    from gpiod.line import Edge

    out = trigger.TriggerOutput(gpio_sim.chip, 2, pulse_ms=100)
    try:
        assert gpio_sim.value(2) == 0
        t = __import__("threading").Thread(target=out.fire)
        t.start()
        time.sleep(0.05)
        assert gpio_sim.value(2) == 1  # the line is driven high during the pulse
        t.join()
        assert gpio_sim.value(2) == 0
    finally:
        out.close()
    # a second request on another line observes edges: the path a second board would use
    req = gpiod.request_lines(
        gpio_sim.chip, consumer="observer", config={4: gpiod.LineSettings(edge_detection=Edge.BOTH)}
    )
    try:
        gpio_sim.pull(4, True)
        assert req.wait_edge_events(timedelta(seconds=2))
        assert len(req.read_edge_events()) >= 1
    finally:
        req.release()
