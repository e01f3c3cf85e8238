"""The CDR templates against rosbags' serializer (the reference), byte for byte, and the type
hash table against rosbags' RIHS01 hashes: either drifting would make ROS 2 peers misread us."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from exolink import messaging
from exolink.control.replies import PatternInfo
from exolink.protocol import h2
from exolink.wire import cdr, srvtypes

NS = st.integers(min_value=0, max_value=(2**31 - 1) * 10**9)  # Time.sec is an int32
F64 = st.floats(allow_nan=False, width=64)
SIX = st.lists(F64, min_size=6, max_size=6)


def assert_rosbags_cdr(payload: bytes, typename: str, **fields: Any) -> None:
    """``payload`` is, byte for byte, rosbags' CDR of the message with these fields."""
    ref = messaging.msg_class(typename)(**fields)
    assert payload == messaging.serialize(ref, typename)


def _joint_state(names: Sequence[str], ns: int, pos: Any, eff: Any) -> Any:
    """The same JointState as a rosbags message."""
    cls = messaging.msg_class(cdr.JointStateCdr.TYPE)
    empty = np.empty(0, dtype=np.float64)
    return cls(
        header=messaging.header(ns),
        name=list(names),
        position=np.array(pos, dtype=np.float64),
        velocity=empty,
        effort=empty if eff is None else np.array(eff, dtype=np.float64),
    )


@settings(deadline=None)  # rosbags generates its serializer on first use
@given(ns=NS, pos=SIX, eff=st.one_of(st.none(), SIX))
def test_joint_state_template_is_rosbags_cdr(ns: int, pos: list[float], eff: list[float]) -> None:
    payload = cdr.JointStateCdr(h2.JOINTS).encode(ns, pos, eff)
    ref = _joint_state(h2.JOINTS, ns, pos, eff)
    assert payload == messaging.serialize(ref, cdr.JointStateCdr.TYPE)


@settings(deadline=None)  # rosbags generates its serializer on first use
@given(ns=NS, sw=st.lists(st.booleans(), min_size=4, max_size=4), raw=st.integers(0, 255))
def test_foot_switches_template_is_rosbags_cdr(ns: int, sw: list[bool], raw: int) -> None:
    volts = float(raw) * 0.1
    payload = cdr.FootSwitchesCdr().encode(ns, sw, raw, volts)
    cls = messaging.msg_class(cdr.FootSwitchesCdr.TYPE)
    ref = cls(messaging.header(ns), *sw, raw, volts)
    assert payload == messaging.serialize(ref, cdr.FootSwitchesCdr.TYPE)


@settings(deadline=None)  # rosbags generates its serializer on first use
@given(ns=NS, count=st.integers(0, 2**64 - 1), pid=st.integers(1, 2**31 - 1))
def test_heartbeat_template_is_rosbags_cdr(ns: int, count: int, pid: int) -> None:
    payload = cdr.HeartbeatCdr("pattern_player", pid).encode(ns, count)
    cls = messaging.msg_class(cdr.HeartbeatCdr.TYPE)
    ref = cls(messaging.stamp(ns), "pattern_player", count, pid, "running")
    assert payload == messaging.serialize(ref, cdr.HeartbeatCdr.TYPE)


@settings(deadline=None)  # rosbags generates its serializer on first use
@given(
    ns=NS,
    level=st.sampled_from(sorted(messaging.LEVELS)),
    text=st.text(max_size=20),
    values=st.dictionaries(st.text(max_size=8), st.integers() | st.text(max_size=8), max_size=5),
)
def test_diagnostics_is_rosbags_cdr(ns: int, level: str, text: str, values: dict) -> None:
    payload = cdr.diagnostics(ns, "n/x", messaging.LEVELS[level], text, "hw", values)
    ref = messaging.diagnostics(ns, "n/x", level, text, "hw", values)
    assert payload == messaging.serialize(ref, messaging.DIAGNOSTICS_TYPE)


@settings(deadline=None)
@given(
    ns=NS,
    joint=st.text(max_size=10),
    mode=st.integers(0, 255),
    sp=st.integers(-32768, 32767),
    stiff=st.integers(0, 255),
    source=st.text(max_size=10),
)
def test_joint_command_is_rosbags_cdr(
    ns: int, joint: str, mode: int, sp: int, stiff: int, source: str
) -> None:
    payload = cdr.joint_command(ns, joint, mode, sp, stiff, source)
    assert_rosbags_cdr(
        payload,
        "exolink_msgs/msg/JointCommand",
        header=messaging.header(ns),
        joint=joint,
        mode=mode,
        setpoint=sp,
        stiffness=stiff,
        source=source,
    )


@settings(deadline=None)
@given(
    ns=NS,
    texts=st.lists(st.text(max_size=12), min_size=5, max_size=5),
    counts=st.lists(st.integers(0, 2**32 - 1), min_size=2, max_size=2),
    speed=st.integers(0, 255),
    period=st.floats(width=32, allow_nan=False),
    selected=st.lists(st.booleans(), min_size=6, max_size=6),
)
def test_pattern_state_is_rosbags_cdr(ns, texts, counts, speed, period, selected) -> None:  # type: ignore[no-untyped-def]
    state, reason, file, operator, timing = texts
    status = PatternInfo(state, reason, counts[0], counts[1], speed, period, [], file, 0, operator)
    status.timing = timing
    cls = messaging.msg_class("exolink_msgs/msg/PatternState")
    ref = cls(
        stamp=messaging.stamp(ns),
        state=state,
        reason=reason,
        index=counts[0],
        length=counts[1],
        speed=speed,
        period_ms=period,
        selected=np.array(selected, dtype=bool),
        file=file,
        operator=operator,
        timing_mode=timing,
    )
    payload = cdr.pattern_state(ns, status, selected)
    assert payload == messaging.serialize(ref, "exolink_msgs/msg/PatternState")


@settings(deadline=None)
@given(
    ns=NS,
    version=st.integers(0, 2**32 - 1),
    controllers=st.lists(st.lists(st.text(max_size=12), min_size=4, max_size=4), max_size=4),
)
def test_controller_activity_is_rosbags_cdr(
    ns: int, version: int, controllers: list[list[str]]
) -> None:
    columns = ("names", "types", "states", "errors")
    lists = {k: [c[i] for c in controllers] for i, k in enumerate(columns)}
    payload = cdr.controller_activity(ns, version, controllers)
    typename = "exolink_msgs/msg/ControllerActivity"
    assert_rosbags_cdr(payload, typename, stamp=messaging.stamp(ns), version=version, **lists)


@settings(deadline=None)
@given(
    ns=NS,
    texts=st.lists(st.text(max_size=30), min_size=3, max_size=3),
    frames=st.integers(0, 2**32 - 1),
)
def test_watchdog_event_decodes_rosbags_cdr(ns: int, texts: list[str], frames: int) -> None:
    cls = messaging.msg_class("exolink_msgs/msg/WatchdogEvent")
    ref = cls(
        stamp=messaging.stamp(ns),
        state=texts[0],
        reason=texts[1],
        detail=texts[2],
        frames_sent=frames,
    )
    payload = messaging.serialize(ref, "exolink_msgs/msg/WatchdogEvent")
    assert cdr.watchdog_event(payload) == (*texts, frames)
    for cut in (0, 5, 13, len(payload) - 1):
        with pytest.raises(ValueError):
            cdr.watchdog_event(payload[:cut])


@settings(deadline=None)
@given(
    ns=NS,
    texts=st.lists(st.text(max_size=30), min_size=3, max_size=3),
    frames=st.integers(0, 2**32 - 1),
)
def test_watchdog_event_is_rosbags_cdr(ns: int, texts: list[str], frames: int) -> None:
    payload = cdr.watchdog_event_msg(ns, *texts, frames)
    state, reason, detail = texts
    assert_rosbags_cdr(
        payload,
        "exolink_msgs/msg/WatchdogEvent",
        stamp=messaging.stamp(ns),
        state=state,
        reason=reason,
        detail=detail,
        frames_sent=frames,
    )


@settings(deadline=None)
@given(
    ns=NS,
    texts=st.lists(st.text(max_size=12), min_size=3, max_size=3),
    line=st.integers(0, 2**32 - 1),
    count=st.integers(0, 2**64 - 1),
)
def test_trigger_event_is_rosbags_cdr(ns: int, texts: list[str], line: int, count: int) -> None:
    edge, chip, source = texts
    payload = cdr.trigger_event(ns, edge, chip, line, count, source)
    assert_rosbags_cdr(
        payload,
        "exolink_msgs/msg/TriggerEvent",
        stamp=messaging.stamp(ns),
        edge=edge,
        chip=chip,
        line=line,
        count=count,
        source=source,
    )


@settings(deadline=None)
@given(
    ns=NS,
    texts=st.lists(st.text(max_size=12), min_size=5, max_size=5),
    selected=st.lists(st.booleans(), min_size=6, max_size=6),
)
def test_pattern_state_decodes_its_state_and_operator(
    ns: int, texts: list[str], selected: list[bool]
) -> None:
    state, reason, file, operator, timing = texts
    status = PatternInfo(state, reason, 3, 51, 10, 20.0, [], file, 0, operator, timing)
    payload = cdr.pattern_state(ns, status, selected)
    assert cdr.pattern_state_of(payload) == (state, operator)
    for cut in (0, 5, 13, len(payload) - 1):
        with pytest.raises(ValueError):
            cdr.pattern_state_of(payload[:cut])


@settings(deadline=None)
@given(
    ns=NS,
    statuses=st.lists(
        st.tuples(
            st.integers(0, 3),
            st.lists(st.text(max_size=10), min_size=3, max_size=3),
            st.dictionaries(st.text(max_size=8), st.text(max_size=8), max_size=4),
        ),
        max_size=3,
    ),
)
def test_diagnostic_statuses_decode_rosbags_cdr(ns: int, statuses: list) -> None:  # type: ignore[type-arg]
    """What the supervisor reads of every node's diagnostics, without a typestore; a payload
    cut short, or one claiming more statuses than it holds, is refused by name."""
    typename = messaging.DIAGNOSTICS_TYPE
    store = messaging.prepare(typename)
    status_cls = store.types["diagnostic_msgs/msg/DiagnosticStatus"]
    kv_cls = store.types["diagnostic_msgs/msg/KeyValue"]
    ref = messaging.msg_class(typename)(
        header=messaging.header(ns),
        status=[
            status_cls(
                level=level,
                name=texts[0],
                message=texts[1],
                hardware_id=texts[2],
                values=[kv_cls(key=k, value=v) for k, v in values.items()],
            )
            for level, texts, values in statuses
        ],
    )
    payload = messaging.serialize(ref, typename)
    got = cdr.diagnostic_statuses(payload)
    want = [
        cdr.Status(level, *texts, [cdr.KeyValue(k, v) for k, v in values.items()])
        for level, texts, values in statuses
    ]
    assert got == want
    for cut in (0, 5, 13):
        with pytest.raises(ValueError):
            cdr.diagnostic_statuses(payload[:cut])
    if statuses:
        with pytest.raises(ValueError, match="DiagnosticArray"):
            cdr.diagnostic_statuses(payload[:-1])
    huge = bytearray(payload)
    huge[4 + 8 + 4 + 4 : 4 + 8 + 4 + 8] = (2**31).to_bytes(4, "little")  # the status count
    with pytest.raises(ValueError, match="DiagnosticArray"):
        cdr.diagnostic_statuses(bytes(huge))


MACCEPA_STATE = (
    "current_ma",
    "temperature_c",
    "velocity_rpm",
    "load_n",
    "link_deg",
    "lever_deg",
    "extra_position",
    "extra_sensor",
    "setpoint",
    "actuation",
    "process_variable",
)


@settings(deadline=None)
@given(
    ns=NS,
    board=st.integers(0, 255),
    stale=st.integers(0, 7),
    values=st.lists(st.integers(-32768, 32767), min_size=11, max_size=11),
)
def test_maccepa_state_is_rosbags_cdr(ns: int, board: int, stale: int, values: list[int]) -> None:
    typename = cdr.MaccepaStateCdr.TYPE
    ref = messaging.msg_class(typename)(
        header=messaging.header(ns),
        board=board,
        stale=stale,
        **dict(zip(MACCEPA_STATE, values, strict=True)),
    )
    payload = cdr.MaccepaStateCdr().encode(ns, board, stale, values)
    assert payload == messaging.serialize(ref, typename)


@given(text=st.text(max_size=200))
def test_string_is_rosbags_cdr(text: str) -> None:
    ref = messaging.msg_class("std_msgs/msg/String")(data=text)
    assert cdr.string_msg(text) == messaging.serialize(ref, "std_msgs/msg/String")


def test_type_hash_table_matches_rosbags() -> None:
    table = json.loads(messaging.TYPE_HASHES.read_text())
    store = messaging.typestore()
    # Services are in the table as the whole service type (the key's hash), not their parts;
    # they are hashed with ServiceEventInfo corrected (tests/test_exolink_msgs.py checks them).
    services = set(srvtypes.srv_definitions(messaging.MSG_DIR))
    parts = {f"{s}_{p}" for s in services for p in ("Request", "Response", "Event")}
    assert set(table) == set(store.types) - parts, "run `make msgs` after editing a .msg file"
    for name, value in table.items():
        if name not in services:
            assert value == str(store.hash_rihs01(name)), name


def test_schema_table_matches_rosbags() -> None:
    """The recorder's schemas without a typestore (MSGDEFS) are rosbags' own, for every
    exolink_msgs message and the standard types the appliance publishes."""
    table = json.loads(messaging.MSGDEFS.read_text())
    assert table == messaging.msgdef_table(), "run `make msgs` after editing a .msg file"
    for name in (cdr.JointStateCdr.TYPE, messaging.DIAGNOSTICS_TYPE, "exolink_msgs/msg/Heartbeat"):
        assert messaging.msgdef(name) == table[name]
    other = "geometry_msgs/msg/Twist"  # not in the table: rosbags writes it
    assert other not in table and "Vector3 linear" in messaging.msgdef(other)
