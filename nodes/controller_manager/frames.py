"""The controller manager's frames: each command encoded once (a held set-point costs a look-up
per cycle, not an encode), and what its reader reads of the bus and lets the kernel drop."""

from __future__ import annotations

from functools import lru_cache

import can

from exolink.canbus.filters import Drop
from exolink.protocol import h2, maccepa

SAFE_MODES = {h2.MODES["disabled"], h2.MODES["stopped"]}
# Always read: the angle frame starts a cycle; anyone's joint control (a disable or stop from
# anyone stops that joint's controllers). The others only while a loaded controller reads them.
READ_IDS = [h2.JOINT_ANGLES, h2.JOINT_CONTROL]
EXTRA_IDS = {"torque": h2.JOINT_TORQUES, "feet": h2.FOOT_SWITCHES}


@lru_cache(maxsize=4096)
def joint_frame(motor: int, mode: int, setpoint: int, stiffness: int) -> can.Message:
    """Encoded once per distinct command (the codec checks ranges again): a holding joint costs
    a dictionary look-up per cycle, not an encode."""
    return h2.encode_joint_control(motor, mode, setpoint, stiffness)


@lru_cache(maxsize=4096)
def joint_payload(motor: int, mode: int, setpoint: int, stiffness: int) -> bytes:
    """A joint-control frame's bytes for the timer's plan (values the manager held to the
    limits; the DBC's bounds checked again by the codec)."""
    return h2.joint_control_payload(motor, mode, setpoint, stiffness)


@lru_cache(maxsize=4096)
def board_frame(board: int, kind: str, value: float, controller: str) -> can.Message:
    """A MACCEPA command through the MACCEPA codec (which checks ranges again), cached like
    ``joint_frame``: a held set-point costs a look-up per cycle."""
    if kind == "setpoint":
        return maccepa.encode_setpoint(board, value, controller)
    if kind == "duty":
        return maccepa.encode_duty(board, value)
    return maccepa.encode_gain(board, kind, value, controller)


def one_socket(interface: str, read_ids: list[int], board_ids: set[int]) -> bool:
    """One socket reads all: every id besides the angle frame reaches this process only as
    rare news, which may then wake the loop (on SocketCAN, whose kernel runs the content
    filters: of id 70 only anyone's disable or stop, board 0's status when it is not driven
    being dropped too). A second socket for them cost each update a second receive call and a
    merge, for a socket almost always empty. The simulated bus filters in Python, after the
    wake-up, and gives a socket its own frames back: two sockets there."""
    return (
        interface == "socketcan"
        and set(read_ids) <= {h2.JOINT_ANGLES, h2.JOINT_CONTROL}
        and 0 not in board_ids
    )


def drop_rules(board_ids: set[int], mc_ids: list[int]) -> list[Drop]:
    """What the manager's reader never needs of the ids it reads (exolink.canbus.filters: the kernel
    drops them on SocketCAN). Of the H2's joint control only a disable or stop matters here (the
    gait's set-points come from this process and are never read back; the MACCEPA bridge and
    the timing monitor read them); board 0's status shares id 70 and matters only when board 0
    is driven; an H2 frame on a driven board's id is the H2's."""
    jc = h2.JOINT_CONTROL
    rules = [Drop(jc, h2.dlc_of(jc) or 0, h2.MODE_BYTE, frozenset(SAFE_MODES))]
    if 0 not in board_ids:
        rules.append(Drop(jc, maccepa.dlc_of(jc) or 0))
    rules += [Drop(i, n) for i, n in maccepa.h2_shaped(mc_ids) if i != jc]
    return rules
