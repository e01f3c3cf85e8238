"""A second device under the same supervisor: a one-joint test rig described by its own DBC
and a hardware class in a lab's package (exolink.hardware), installed as a third party installs
it (a dist-info on the path with an ``exolink.hardware`` entry point). The supervisor and its
watchdog run it with no edit: its pulse's silence trips, the e-stop sends its safe action, a
motion frame while not armed is answered, a malformed frame is counted. The rig itself is this
test's thread on the sim bus, as the H2 is the simulator's."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator

import can
import pytest

from benchmarks.harness import EXOLINK, Appliance, DrainedBus, FrameStream, collect, wait_for
from exolink.canbus import open_bus

RIG_DBC = """VERSION ""

BU_: RIG LAB

BO_ 512 RigAngle: 2 RIG
 SG_ angle : 0|16@1- (0.1,0) [-180|180] "deg" LAB

BO_ 513 RigCommand: 3 LAB
 SG_ mode : 0|8@1+ (1,0) [0|2] "" RIG
 SG_ setpoint : 8|16@1- (0.1,0) [-180|180] "deg" RIG

VAL_ 513 mode 0 "off" 1 "position" 2 "hold" ;
"""

RIG_PY = '''
"""The lab's one-joint rig: its DBC, and what the watchdog needs of it."""
from pathlib import Path

import can
import cantools
from exolink.hardware import Seen

DB = cantools.database.load_file(str(Path(__file__).with_name("rig.dbc")))
ANGLE, COMMAND = DB.get_message_by_name("RigAngle"), DB.get_message_by_name("RigCommand")


class Rig:
    pulse = "rig data"
    pulse_id = ANGLE.frame_id
    command_id = COMMAND.frame_id
    command_mask = bytes([0xFF, 0, 0])  # the mode

    def safe_action(self, cfg):
        data = COMMAND.encode({"mode": 0, "setpoint": 0})
        return [can.Message(arbitration_id=COMMAND.frame_id, data=data, is_extended_id=False)]

    def judge(self, msg):
        try:
            m = DB.get_message_by_frame_id(msg.arbitration_id)
        except KeyError:
            return Seen.MALFORMED, "unknown id"
        if msg.is_extended_id or len(msg.data) != m.length:
            return Seen.MALFORMED, "bad length"
        if m is ANGLE:
            return Seen.PULSE, ""
        mode = m.decode(bytes(msg.data), decode_choices=False)["mode"]
        if mode > 2:  # a lab's bug on purpose: its judge raises on a mode the DBC lacks
            raise ValueError(f"rig: mode {mode}")
        return (Seen.MOTION, "") if mode != 0 else (Seen.OTHER, "")
'''

ANGLE_ID, COMMAND_ID = 512, 513
OFF = bytes([0, 0, 0])


@pytest.fixture
def rig_package(lab_package) -> None:  # type: ignore[no-untyped-def]
    """The lab's package on the path of the supervisor the test starts."""
    entry = "[exolink.hardware]\nrig = lab_rig:Rig\n"
    lab_package("lab_rig", entry, {"lab_rig.py": RIG_PY, "rig.dbc": RIG_DBC})


@pytest.fixture
def rig(write_config, spawn, rig_package, mbus) -> Iterator[tuple[Appliance, FrameStream]]:  # type: ignore[no-untyped-def]
    # one node, whatever the device: the timing monitor, on the rig's ids (a laptop finds the
    # appliance by its nodes' tokens)
    monitor = {
        "name": "timing_monitor",
        "plugin": "timing_monitor",
        "params": {"ids": [ANGLE_ID, COMMAND_ID]},
    }
    cfg = write_config(nodes=[monitor], hardware="rig", watchdog={"h2_silence_ms": 300})
    app = Appliance(cfg, spawn)
    # the rig's angle frame every 10 ms
    angle = can.Message(arbitration_id=ANGLE_ID, data=bytes([100, 0]), is_extended_id=False)
    board = FrameStream(open_bus(app.cfg.can), [angle])
    try:
        yield app, board
    finally:
        board.close()


def offs(frames: list[can.Message]) -> list[bytes]:
    return [bytes(m.data) for m in frames if m.arbitration_id == COMMAND_ID]


def test_a_toy_rig_runs_under_the_supervisor_with_no_edit_to_it(
    rig: tuple[Appliance, FrameStream], mbus: DrainedBus
) -> None:
    app, board = rig
    app.arm()
    # its pulse stops: the watchdog trips with the rig's name and sends the rig's safe action
    mbus.q.queue.clear()
    board.sending.clear()
    wait_for(lambda: app.status()["watchdog"]["state"] == "tripped", timeout=5)
    wd = app.status()["watchdog"]
    assert wd["reason"] == "rig data silent", wd
    assert OFF in offs(collect(mbus, 0.5, {COMMAND_ID}))  # queued since the clear, and repeats
    # pulse back, armed again; the operator's e-stop sends the same safe action
    board.sending.set()
    app.arm()
    mbus.q.queue.clear()
    assert app.cli("estop").returncode == 0
    assert OFF in offs(collect(mbus, 0.5, {COMMAND_ID}))
    assert app.status()["watchdog"]["reason"] == "operator e-stop"
    # not armed: a motion frame from anyone is answered with the safe action and counted
    bus = open_bus(app.cfg.can)
    try:
        mbus.q.queue.clear()
        before = app.status()["watchdog"]["violations"]
        move = bytes([1, 0x64, 0])  # position 10.0 deg
        bus.send(can.Message(arbitration_id=COMMAND_ID, data=move, is_extended_id=False))
        wait_for(lambda: app.status()["watchdog"]["violations"] == before + 1, timeout=5)
        assert OFF in offs(collect(mbus, 0.3, {COMMAND_ID}))
        # a command frame the rig's own judge raises on: counted, taken as motion (answered
        # with the safe action), and the watchdog's reader lives on
        mbus.q.queue.clear()
        bus.send(
            can.Message(arbitration_id=COMMAND_ID, data=bytes([9, 0, 0]), is_extended_id=False)
        )
        wait_for(lambda: app.status()["watchdog"]["violations"] == before + 2, timeout=5)
        assert app.status()["watchdog"]["malformed"]["513 device judge raised ValueError"] == 1
        assert OFF in offs(collect(mbus, 0.3, {COMMAND_ID}))
        # a frame of the rig's id with a length its DBC does not have: counted, not fatal
        bus.send(can.Message(arbitration_id=ANGLE_ID, data=bytes(5), is_extended_id=False))
        wait_for(lambda: "512 bad length" in app.status()["watchdog"]["malformed"], timeout=5)
    finally:
        bus.shutdown()
    assert app.status()["watchdog"]["state"] == "tripped"


def test_an_unknown_device_is_a_config_error_naming_those_installed(write_config) -> None:  # type: ignore[no-untyped-def]
    cfg = write_config(nodes=[], hardware="exo9000")
    for args in (["config", str(cfg)], ["up", "-c", str(cfg)]):
        r = subprocess.run([*EXOLINK, *args], capture_output=True, text=True, timeout=60)
        assert r.returncode == 3, (args, r.stderr)
        assert "hardware: unknown device 'exo9000' (available: h2" in r.stderr, r.stderr
