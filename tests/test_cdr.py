"""The CDR templates against rosbags' serializer (the reference), byte for byte, and the type
hash table against rosbags' RIHS01 hashes: either drifting would make ROS 2 peers misread us."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np
from exolink import cdr, messaging
from exolink.protocol import h2
from hypothesis import given, settings
from hypothesis import strategies as st

NS = st.integers(min_value=0, max_value=(2**31 - 1) * 10**9)  # Time.sec is an int32
F64 = st.floats(allow_nan=False, width=64)
SIX = st.lists(F64, min_size=6, max_size=6)


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


@given(text=st.text(max_size=200))
def test_string_is_rosbags_cdr(text: str) -> None:
    ref = messaging.msg_class("std_msgs/msg/String")(data=text)
    assert cdr.string_msg(text) == messaging.serialize(ref, "std_msgs/msg/String")


def test_type_hash_table_matches_rosbags() -> None:
    table = json.loads(messaging.TYPE_HASHES.read_text())
    store = messaging.typestore()
    assert set(table) == set(store.types), "run `make msgs` after editing a .msg file"
    for name, value in table.items():
        assert value == str(store.hash_rihs01(name)), name
