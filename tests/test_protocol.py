"""H2 and MACCEPA codecs: the captured frames, agreement with `cantools decode` on the shipped
DBC files, round trips (hypothesis), and refusals that make no frame."""

from __future__ import annotations

import math
import struct

import can
import cantools
import pytest
from hypothesis import given
from hypothesis import strategies as st

from exolink.protocol import ProtocolError, dbc, h2, maccepa
from exolink.protocol.make_dbc import render

H2_DB = cantools.database.load_file(str(dbc.bundled("h2")))
MC_DB = cantools.database.load_file(str(dbc.bundled("maccepa")))


def frame(fid: int, hexdata: str) -> can.Message:
    return can.Message(arbitration_id=fid, data=bytes.fromhex(hexdata), is_extended_id=False)


def test_captured_frames_decode_as_documented() -> None:
    # candump lines from shared/protocol/h2-can.md
    assert h2.decode(frame(0x06E, "4C5E004C5D0B")) == h2.JointAngles(76, 94, 0, 76, 93, 11)
    assert h2.decode(frame(0x078, "FEFCFE01CDEF")) == h2.JointTorques(-2, -4, -2, 1, -51, -17)
    fs = h2.decode(frame(0x082, "000000004264"))
    assert fs == h2.FootSwitches(0, 0, 0, 0, 0x42)


def test_committed_dbc_files_match_generator() -> None:
    for name, text in render().items():
        assert (dbc.HERE / name).read_text() == text, f"{name} is stale: run make dbc"


def test_dbc_covers_every_documented_frame() -> None:
    assert {m.frame_id for m in H2_DB.messages} == {70, 75, 80, 85, 110, 120, 130}
    expected = {base + b for b in range(10) for base in (10, 20, 30, 40, 50, 60, 70, 80)}
    assert {m.frame_id for m in MC_DB.messages} == expected


int8s = st.integers(-128, 127)


@given(st.lists(int8s, min_size=6, max_size=6), st.sampled_from([110, 120]))
def test_h2_joint_frames_agree_with_cantools(values: list[int], fid: int) -> None:
    msg = frame(fid, struct.pack("<6b", *values).hex())
    ours = h2.decode(msg)
    theirs = H2_DB.decode_message(fid, bytes(msg.data), decode_choices=False)
    assert ours._asdict() == theirs
    assert h2.encode(ours).data == msg.data
    assert h2.model_message(ours).data == msg.data  # the simulator's unchecked packing


@given(st.lists(st.integers(0, 255), min_size=6, max_size=6))
def test_foot_switch_frames_agree_with_cantools(raw: list[int]) -> None:
    msg = frame(130, bytes(raw).hex())
    theirs = H2_DB.decode_message(130, bytes(msg.data))
    assert h2.decode(msg)._asdict() == theirs
    feet = h2.decode(msg)
    assert h2.model_message(feet).data == h2.encode(feet).data  # type: ignore[arg-type]


@given(st.integers(1, 6), st.sampled_from(["position", "stiffness"]), st.integers(0, 100))
def test_joint_control_round_trip(motor: int, mode: str, stiffness: int) -> None:
    joint = h2.JOINTS[motor - 1]
    lo, hi = h2.RANGES[joint]
    sp = (lo + hi) // 2
    msg = h2.encode_joint_control(joint, mode, sp, stiffness if mode == "stiffness" else 0)
    theirs = H2_DB.decode_message(70, bytes(msg.data), decode_choices=False)
    assert h2.decode(msg)._asdict() == theirs
    assert theirs["setpoint"] == sp and theirs["motor"] == motor


@given(
    st.integers(0, 9),
    st.sampled_from(["kp", "ki", "kd"]),
    st.floats(-1e6, 1e6, allow_nan=False, width=32),
    st.integers(0, 1),
)
def test_maccepa_gain_round_trip_agrees_with_cantools(b: int, which: str, v: float, c: int) -> None:
    msg = maccepa.encode_gain(b, which, v, c)
    assert msg.arbitration_id == maccepa.GAIN_BASE[which] + b
    ours = maccepa.decode(msg)
    theirs = MC_DB.decode_message(msg.arbitration_id, bytes(msg.data), decode_choices=False)
    assert ours == maccepa.Gain(b, which, v, c)
    assert math.isclose(theirs[which], v, rel_tol=0, abs_tol=0) and theirs["controller"] == c


@given(st.integers(0, 9), st.lists(st.integers(-32768, 32767), min_size=4, max_size=4))
def test_maccepa_board_frames_agree_with_cantools(b: int, vals: list[int]) -> None:
    for base, cls in ((50, maccepa.Sensors), (60, maccepa.Positions)):
        msg = frame(base + b, struct.pack("<4h", *vals).hex())
        ours = maccepa.decode(msg)
        assert isinstance(ours, cls) and ours.board == b
        theirs = MC_DB.decode_message(base + b, bytes(msg.data))
        assert ours._asdict() | {} == {"board": b, **theirs}
        assert maccepa.encode(ours).data == msg.data
        assert maccepa.model_message(ours).data == msg.data  # the simulator's unchecked packing


def test_maccepa_duty_and_stop() -> None:
    assert maccepa.decode(maccepa.encode_duty(3, 40)) == maccepa.Duty(3, 40, 1)
    stop = maccepa.encode_stop(3)
    assert stop.arbitration_id == 83 and maccepa.decode(stop) == maccepa.Duty(3, 0, 0)
    assert MC_DB.decode_message(83, bytes(stop.data))["action"] == "stop_control"


@pytest.mark.parametrize(
    ("call", "error"),
    [
        (lambda: h2.encode_joint_control(7, "position", 0), "motor id 7 is outside 1..6"),
        (lambda: h2.encode_joint_control("r_elbow", "position", 0), "unknown joint 'r_elbow'"),
        (lambda: h2.encode_joint_control(2, 9, 0), "control mode 9 is outside 1..5"),
        (
            lambda: h2.encode_joint_control("r_knee", "position", 101),
            "r_knee position set-point 101 deg is outside 0..100",
        ),
        (lambda: h2.encode_joint_control("r_ankle", "position", -25), "outside -20..20"),
        (lambda: h2.encode_joint_control(1, "position", 10.5), "10.5 is not a whole number"),
        (lambda: h2.encode_joint_control(1, "position", float("nan")), "not a finite number"),
        (
            lambda: h2.encode_joint_control(1, "stiffness", 10, 101),
            "JointControl.stiffness: 101 is outside 0..100",
        ),
        (lambda: h2.encode_joint_control(1, "position", 10, 50), "only valid in stiffness mode"),
        (lambda: h2.encode_joint_control(1, "torque", 200), "setpoint: 200 is outside -128..127"),
        (lambda: h2.encode_accepted_angles("min", [0] * 5), "need 6 values"),
        (
            lambda: h2.encode_accepted_angles("max", [0, 0, 30, 0, 0, 0]),
            "MaxAngles.r_ankle: 30 is outside -20..20",
        ),
        (lambda: maccepa.encode_gain(10, "kp", 1.0, 0), "board id 10 is outside 0..9"),
        (lambda: maccepa.encode_gain(1, "kq", 1.0, 0), "unknown gain 'kq'"),
        (lambda: maccepa.encode_gain(1, "kp", float("inf"), 0), "not a finite number"),
        (lambda: maccepa.encode_setpoint(1, 5.0, 2), "controller type 2"),
        (lambda: maccepa.encode_duty(1, 101), "duty cycle 101 must be a whole percentage 0..100"),
        (lambda: maccepa.encode_duty(1, -1), "0..100"),
    ],
)
def test_invalid_commands_raise_and_make_no_frame(call, error: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ProtocolError, match=error.replace("(", r"\(").replace(".", r"\.")):
        call()


def test_unknown_and_malformed_frames_decode_to_unknown() -> None:
    assert h2.decode(frame(0x123, "00")) == h2.Unknown(0x123, "unknown id", b"\x00")
    assert h2.decode(frame(110, "0102")).reason == "bad length"
    ext = can.Message(arbitration_id=110, data=bytes(6), is_extended_id=True)
    assert h2.decode(ext).reason == "unknown id"
    assert maccepa.decode(frame(55, "01")).reason == "bad length"
    assert maccepa.decode(frame(99, "")).reason == "unknown id"


def test_safe_action_frames() -> None:
    frames = h2.safe_action("disable")
    assert [h2.decode(f) for f in frames] == [h2.JointControl(m, 4, 0, 0) for m in range(1, 7)]
    assert {h2.decode(f).mode for f in h2.safe_action("stop")} == {5}
    with pytest.raises(ProtocolError):
        h2.safe_action("explode")


def test_layout_cache_is_used(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("EXOLINK_CACHE", str(tmp_path))
    dbc.load.cache_clear()
    first = dbc.load(dbc.bundled("h2"))
    cached = list((tmp_path / "exolink").glob("h2-*.json"))
    assert len(cached) == 1
    dbc.load.cache_clear()
    assert dbc.load(dbc.bundled("h2")).by_id.keys() == first.by_id.keys()


def test_mode_mask_covers_the_joint_control_mode_byte_only() -> None:
    """The watchdog's broadcast-manager op on id 70 compares these bits (h2.dbc's mode)."""
    mask = int.from_bytes(h2.MODE_MASK, "little")
    position = h2.encode_joint_control(1, "position", 20, 0).data
    disabled = h2.encode_joint_control(3, "disabled", 0, 0).data
    assert len(h2.MODE_MASK) == 8
    changed = int.from_bytes(bytes(position) + bytes(2), "little") ^ int.from_bytes(
        bytes(disabled) + bytes(2), "little"
    )
    assert changed & mask == (1 ^ 4) << 8  # only the mode byte, not the motor or set-point


def test_the_planned_set_points_cheap_path_packs_what_encode_packs_and_refuses_the_rest() -> None:
    for motor in range(1, 7):
        for mode in (1, 2, 3):
            for sp in (-20, 0, 30, 95):
                st = 40 if mode == 2 else 0
                try:
                    want = bytes(h2.encode_joint_control(motor, mode, sp, st).data)
                except ProtocolError:
                    continue  # outside the joint's range: the manager's limits never plan it
                assert h2.joint_control_payload(motor, mode, sp, st) == want
    for bad in ((0, 1, 10, 0), (1, 9, 10, 0), (1, 1, 300, 0), (1, 2, 10, 101), (1, 1, 1.5, 0)):
        with pytest.raises(ProtocolError):
            h2.joint_control_payload(*bad)  # type: ignore[arg-type]
