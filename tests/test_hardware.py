"""A second device under the same supervisor: a one-joint test rig described by its own DBC,
a hardware class and two nodes in a lab's package (tests/lab_rig), installed as a third party
installs it (a dist-info on the path with its entry points). The supervisor, its watchdog and
the CLI run it with no edit: its pulse's silence trips, the e-stop sends its safe action, a
motion frame while not armed is answered, a malformed frame is counted (the rig there is this
test's thread on the sim bus); under ``make sim`` its own simulator stands in for it, its
driver moves the joint once armed, and a hung driver is stopped by the watchdog."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import tomllib
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
import yaml

from benchmarks.harness import (
    EXOLINK,
    Appliance,
    DrainedBus,
    FrameStream,
    collect,
    free_port,
    wait_for,
)
from exolink.canbus import open_bus

ANGLE_ID, COMMAND_ID = 512, 513
OFF = bytes([0, 0, 0])


RIG = Path(__file__).with_name("lab_rig")  # the lab's package: pyproject.toml, lab_rig/, rig.yaml


@pytest.fixture
def rig_package(lab_package) -> None:  # type: ignore[no-untyped-def]
    """The lab's package (tests/lab_rig), installed as pip would, on the path of the
    supervisor the test starts."""
    project = tomllib.loads((RIG / "pyproject.toml").read_text())["project"]
    entry = "".join(
        f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items())
        for group, eps in project["entry-points"].items()
    )
    files = {f"lab_rig/{f.name}": f.read_text() for f in (RIG / "lab_rig").iterdir() if f.is_file()}
    lab_package("lab_rig", entry, files)


@pytest.fixture
def rig(write_config, spawn, rig_package, mbus) -> Iterator[tuple[Appliance, FrameStream]]:  # type: ignore[no-untyped-def]
    # one node, whatever the device: the timing monitor, on the rig's ids (a laptop finds the
    # appliance by its nodes' tokens)
    monitor = {
        "name": "timing_monitor",
        "plugin": "timing_monitor",
        "params": {"ids": [ANGLE_ID, COMMAND_ID]},
    }
    cfg = write_config(nodes=[monitor], hardware="rig", watchdog={"pulse_silence_ms": 300})
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


def test_the_rig_runs_under_make_sim_with_its_simulator_and_a_driver_the_watchdog_stops(
    rig_package, spawn, tmp_path, group, mbus
) -> None:  # type: ignore[no-untyped-def]
    """``make sim`` with the lab's config: the rig's simulator stands in for the rig (not the
    H2's), its driver moves the joint once armed, and when the driver hangs the watchdog
    stops the rig: its safe action on the bus and the joint still."""
    data = yaml.safe_load((RIG / "rig.yaml").read_text())
    data["can"]["channel"] = group
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    cfg = tmp_path / "rig.yaml"
    cfg.write_text(yaml.safe_dump(data))
    app = Appliance(cfg, spawn, sim=True)
    assert {n["name"] for n in app.call("status")["nodes"]} == {"rig_sim", "rig"}
    r = app.cli("echo", "rig/angle", "-n", "1", "--json")
    assert r.returncode == 0 and "data" in r.stdout, r.stderr

    def angles(seconds: float) -> list[float]:
        frames = collect(mbus, seconds, {ANGLE_ID})
        return [int.from_bytes(f.data[:2], "little", signed=True) / 10 for f in frames]

    assert set(angles(0.3)) == {0.0}  # not armed: nothing moves it
    app.arm()
    wait_for(lambda: max(map(abs, angles(0.3)), default=0) > 2, timeout=10)  # the sweep
    pid = app.node("rig")["pid"]
    os.kill(pid, signal.SIGSTOP)
    try:
        wait_for(lambda: app.call("status")["watchdog"]["state"] == "tripped", timeout=5)
        wd = app.call("status")["watchdog"]
        assert (wd["reason"], wd["detail"][:17]) == ("heartbeat late", "rig: no heartbeat"), wd
        mbus.clear()
        frames = collect(mbus, 0.5, {ANGLE_ID, COMMAND_ID})
    finally:
        with contextlib.suppress(ProcessLookupError):  # the supervisor kills a hung node
            os.kill(pid, signal.SIGCONT)
    assert offs(frames) and set(offs(frames)) == {OFF}  # only the safe action, repeated
    still = {bytes(f.data) for f in frames if f.arbitration_id == ANGLE_ID}
    assert len(still) == 1, still  # the rig stopped where it was


def test_a_device_that_names_no_simulator_is_a_config_error_under_sim(  # type: ignore[no-untyped-def]
    write_config, lab_package
) -> None:
    """A lab's device class from before ``Device.simulator``: ``exolink up --sim`` says what is
    missing and starts nothing, rather than a traceback."""
    bare = (
        "class Bare:\n    pulse, pulse_id, command_id, command_mask = 'bare data', 1, 2, bytes(1)\n"
    )
    lab_package("lab_bare", "[exolink.hardware]\nbare = lab_bare:Bare\n", {"lab_bare.py": bare})
    cfg = write_config(nodes=[], hardware="bare")
    r = subprocess.run(
        [*EXOLINK, "up", "--sim", "-c", str(cfg)], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 3, r.stderr
    assert "hardware 'bare' names no simulator (Device.simulator)" in r.stderr, r.stderr
