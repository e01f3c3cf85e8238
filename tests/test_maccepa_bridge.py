"""The MACCEPA bridge's cycle assembly, without a transport: a board's sensors, positions and
controller frames become one MaccepaState per 10 ms cycle; a lost frame is marked, never hidden,
and never costs the cycle's other frames."""

from __future__ import annotations

from exolink.protocol import maccepa
from nodes.maccepa_bridge import BoardCycle


def sensors(v: int) -> maccepa.Sensors:
    return maccepa.Sensors(0, v, v + 1, v + 2, v + 3)


def positions(v: int) -> maccepa.Positions:
    return maccepa.Positions(0, v, v + 1, v + 2, v + 3)


def controller(v: int) -> maccepa.Controller:
    return maccepa.Controller(0, v, v + 1, v + 2)


def values(s: int, p: int, c: int) -> list[int]:
    return [s, s + 1, s + 2, s + 3, p, p + 1, p + 2, p + 3, c, c + 1, c + 2]


def test_a_whole_cycle_is_one_message_stamped_at_its_first_frame() -> None:
    cycle = BoardCycle()
    assert cycle.add(sensors(10), 1.000) == []
    assert cycle.add(positions(20), 1.001) == []
    assert cycle.add(controller(30), 1.002) == [(1.000, 0, values(10, 20, 30))]
    assert cycle.add(sensors(11), 1.010) == []
    assert cycle.add(positions(21), 1.011) == []
    assert cycle.add(controller(31), 1.012) == [(1.010, 0, values(11, 21, 31))]


def test_a_lost_frame_keeps_its_last_values_and_sets_its_stale_bit() -> None:
    cycle = BoardCycle()
    cycle.add(sensors(10), 1.000)
    cycle.add(positions(20), 1.001)
    cycle.add(controller(30), 1.002)
    # positions lost in the next cycle
    cycle.add(sensors(11), 1.010)
    assert cycle.add(controller(31), 1.012) == [(1.010, 2, values(11, 20, 31))]
    # the controller frame lost: the next cycle's sensors frame ends the cycle
    cycle.add(sensors(12), 1.020)
    cycle.add(positions(22), 1.021)
    assert cycle.add(sensors(13), 1.030) == [(1.020, 4, values(12, 22, 31))]
    cycle.add(positions(23), 1.031)
    assert cycle.add(controller(33), 1.032) == [(1.030, 0, values(13, 23, 33))]


def test_a_bridge_that_starts_mid_cycle_marks_what_it_never_saw() -> None:
    cycle = BoardCycle()
    assert cycle.add(controller(30), 1.002) == [(1.002, 3, [0] * 8 + [30, 31, 32])]
