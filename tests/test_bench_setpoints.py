"""The board bench's check of what the set-points said (benchmarks/board/setpoints.py): frames
as the probe keeps them (the kernel's struct can_frame), made by the one H2 encoder."""

from __future__ import annotations

from benchmarks.board import setpoints
from exolink.canbus.frames import CAN_FRAME
from exolink.protocol import h2

LIMITS = {"max_step_deg": 5, "joints": {"r_hip": {"min": -20, "max": 100}}}


def frame(motor: int, mode: str, setpoint: int) -> bytes:
    m = h2.encode_joint_control(motor, mode, setpoint, 0)
    return CAN_FRAME.pack(m.arbitration_id, m.dlc, bytes(m.data).ljust(8, b"\0"))


def test_steps_per_motor_against_the_limit_for_a_slot() -> None:
    raw = b"".join(
        [
            frame(1, "position", 10),
            frame(2, "position", 50),
            frame(1, "position", 18),  # 8 deg: inside 5 deg x 2 cycles
            frame(1, "position", 40),  # 22 deg: a slot from elsewhere
            frame(2, "disabled", 0),  # not a set-point
            CAN_FRAME.pack(70, 8, bytes(8)),  # MACCEPA board 0's status on the id
        ]
    )
    out = setpoints.steps(raw, LIMITS, slot_ms=20)
    assert out["frames"] == 6 and out["not_position"] == 2
    assert out["motors"]["1"] == {"n": 3, "max_step": 22, "over": 1, "min": 10, "max": 40}
    assert out["motors"]["2"]["max_step"] == 0
    assert out["step_limit_deg"] == 10 and out["over_step_limit"] == 1
    assert out["out_of_range"] == []


def test_a_set_point_outside_the_joints_range_is_named() -> None:
    narrow = {"max_step_deg": 5, "joints": {"r_hip": {"min": 0, "max": 30}}}
    out = setpoints.steps(frame(1, "position", 10) + frame(1, "position", 35), narrow)
    assert out["out_of_range"] == [1]
