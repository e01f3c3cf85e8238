"""The MACCEPA boards' state (exolink.hardware.maccepa: the bridge's and the h2 reader's): a
board's sensors, positions and controller frames become one MaccepaState per 10 ms cycle; a
lost frame is marked, never hidden, and never costs the cycle's other frames. First without a
transport, then published by the h2 reader from its own read."""

from __future__ import annotations

import itertools
import statistics
import time
from typing import Any

from benchmarks.harness import Appliance, wait_for
from exolink import messaging
from exolink.hardware.maccepa import BoardCycle
from exolink.protocol import maccepa


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


def test_a_frames_fields_after_board_are_maccepa_states_values_in_order() -> None:
    """BoardCycle keeps a frame's fields after ``board`` as MaccepaState's int16 values."""
    msg = (messaging.MSG_DIR / "exolink_msgs" / "msg" / "MaccepaState.msg").read_text()
    values = [ln.split()[1] for ln in msg.splitlines() if ln.startswith("int16 ")]
    kinds = (maccepa.Sensors, maccepa.Positions, maccepa.Controller)
    fields = [f for cls in kinds for f in cls._fields[1:]]
    assert len(values) == len(fields), (values, fields)
    assert all(v.startswith(f) for v, f in zip(values, fields, strict=True)), (values, fields)


def test_a_bridge_that_starts_mid_cycle_marks_what_it_never_saw() -> None:
    cycle = BoardCycle()
    assert cycle.add(controller(30), 1.002) == [(1.002, 3, [0] * 8 + [30, 31, 32])]


# --- the boards read by the h2 reader (maccepa_boards): the whole bus in one process -----------

READER_NODES = [
    {"name": "simulator", "plugin": "simulator", "params": {"maccepa_boards": [0]}},
    {
        "name": "h2_reader",
        "plugin": "h2_reader",
        "critical": True,
        "params": {"maccepa_boards": [0], "cycles_per_read": 4},  # as the board's bridge read
    },
]


def _states(app: Appliance, seconds: float) -> list[Any]:
    """maccepa/b0/state as a laptop gets it, for ``seconds``."""
    s = messaging.open_client_session(app.at)
    got: list[Any] = []
    key = messaging.topic_key(0, "h2", "maccepa/b0/state", "exolink_msgs/msg/MaccepaState")
    sub = s.declare_subscriber(
        key,
        lambda x: got.append(
            messaging.deserialize(x.payload.to_bytes(), "exolink_msgs/msg/MaccepaState")
        ),
    )
    try:
        wait_for(lambda: got, timeout=10)
        time.sleep(seconds)
    finally:
        sub.undeclare()
        s.close()
    return list(got)


def test_the_h2_reader_publishes_the_boards_state_from_its_own_read(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    """One message per 10 ms board cycle with all three of its frames, in order, beside
    joint_states, from the one process (no bridge configured); the MACCEPA frames are counted
    apart from the H2's and none is malformed."""
    app = Appliance(write_config(nodes=READER_NODES), spawn)
    got = _states(app, 1.0)
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got]
    assert len(stamps) >= 60 and stamps == sorted(stamps)
    assert 9e6 < statistics.median(b - a for a, b in itertools.pairwise(stamps)) < 11e6
    assert [m.stale for m in got[1:]] == [0] * (len(got) - 1)
    assert {m.board for m in got} == {0}
    stats = app.call("nodes/h2_reader/stats")
    assert stats["maccepa"]["boards"] == [0] and stats["maccepa"]["malformed"] == 0, stats
    assert stats["maccepa"]["published"] >= len(got)
    assert stats["published_joint_states"] > 0 and stats["unknown"] == 0, stats


def test_a_board_read_by_both_the_reader_and_the_bridge_is_refused(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    """Two publishers of one board's state: the reader refuses to start (a config error's exit
    code) and says why."""
    bridge = {"name": "maccepa_bridge", "plugin": "maccepa_bridge", "params": {"boards": [0]}}
    app = Appliance(write_config(nodes=[*READER_NODES, bridge]), spawn, wait_nodes=False)
    wait_for(lambda: app.node("h2_reader")["last_exit"] == "exit 3", timeout=20)
    r = app.cli("logs", "h2_reader")
    assert "maccepa_boards [0] are also read by the enabled maccepa_bridge" in r.stdout + r.stderr
