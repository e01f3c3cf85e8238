"""The CLI against what a person or a pipe hands it: a reader that leaves early (`| head`),
numbers typed in another script's digits, a fractional value for a whole-number field, a
pattern CSV saved with a byte-order mark. Real `exolink` processes on a sim appliance, real
pipes and real files; the parser in-process where the refusal is argparse's."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

import pytest
import yaml

from benchmarks.harness import EXOLINK, Appliance
from exolink.cli.main import parse
from exolink.config import bundled
from exolink.control.patterns import load_pattern, parse_pattern
from exolink.limits.joints import Limits, default_max, default_min
from exolink.protocol import ProtocolError, h2

HEADER = "r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle"
LIMITS = Limits.of(default_min(), default_max(), [127] * 6, [100] * 6, "test")
FULL_WIDTH_12 = "\uff11\uff12"  # full-width 12: Python's int() and float() read it as 12


def _nodes(tmp_path: Path) -> list[dict]:  # type: ignore[type-arg]
    nodes = yaml.safe_load(bundled("sim").read_text())["nodes"]
    for n in nodes:
        if n["name"] == "recorder":
            n["params"]["directory"] = str(tmp_path / "rec")
    return nodes


def _to_closed_pipe(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[bytes]:
    """Run `exolink ARGS` with stdout a pipe whose reader has already gone (`| head -1` once
    head has its line): every write fails with EPIPE. With SIGINT ignored, as a background
    job of a script starts it: a simulated SIGINT is then dropped, and the streaming commands
    ran on until killed."""
    r, w = os.pipe()
    os.close(r)
    try:
        return subprocess.run(
            [*EXOLINK, *args],
            stdout=w,
            stderr=subprocess.PIPE,
            timeout=timeout,
            check=False,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
        )
    finally:
        os.close(w)


def _quiet(p: subprocess.CompletedProcess[bytes]) -> None:
    err = p.stderr.decode(errors="replace")
    assert p.returncode == 0, (p.args, p.returncode, err)
    for noise in ("Traceback", "BrokenPipe", "Exception ignored", "Broken pipe"):
        assert noise not in err, (p.args, err)


def test_a_closed_stdout_ends_every_command_quietly(tmp_path, write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    """Main-thread writers (status, nodes, params, logs, config, --help) and a callback-thread
    writer (maccepa watch: it printed a traceback per sample and never ended)."""
    cfg = write_config(nodes=_nodes(tmp_path))
    app = Appliance(cfg, spawn)
    at = ["--at", app.at, "--timeout", "10"]
    for args in (
        ["status", *at],
        ["nodes", *at],
        ["params", "h2_reader", *at],
        ["logs", "h2_reader", "-n", "5", *at],
        ["maccepa", "0", "watch", *at],
        ["echo", "joint_states", *at],
        ["config", str(cfg)],
        ["--help"],
    ):
        _quiet(_to_closed_pipe(*args))
    # The reader still there: the output is whole, as before.
    r = subprocess.run([*EXOLINK, "status", *at], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0 and "h2_reader" in r.stdout, r.stderr


def test_numbers_only_in_ascii_digits() -> None:
    """Full-width digits were read as numbers: `send position r_knee` with full-width 12 moved the knee."""
    for argv in (
        ["send", "position", "r_knee", FULL_WIDTH_12],
        ["send", "limits", "--min", f"-10,0,-20,-10,0,{FULL_WIDTH_12}"],
        ["maccepa", FULL_WIDTH_12, "duty", "10"],
        ["maccepa", "0", "setpoint", FULL_WIDTH_12],
        ["logs", "h2_reader", "-n", FULL_WIDTH_12],
        ["status", "--timeout", FULL_WIDTH_12],
        ["timing", FULL_WIDTH_12],
        ["pattern", "speed", FULL_WIDTH_12],
        ["dashboard", "--port", FULL_WIDTH_12],
        ["controllers", "command", "x", f"r_knee={FULL_WIDTH_12}"],
    ):
        nowhere = ["--at", "tcp/127.0.0.1:9"]  # had it parsed, nothing would be reached
        r = subprocess.run([*EXOLINK, *argv, *nowhere], capture_output=True, text=True, timeout=30)
        assert r.returncode == 2, (argv, r.stdout, r.stderr)
        assert f"'{FULL_WIDTH_12}'" in r.stderr and "ASCII" in r.stderr, (argv, r.stderr)
        assert "Traceback" not in r.stderr
    # ASCII numbers as before: signs, points, exponents, hex CAN ids.
    assert parse(["send", "position", "r_knee", "-1.5"]).value == -1.5
    assert parse(["send", "position", "r_knee", "12"]).value == 12
    assert parse(["send", "limits", "--min", "-10,0,-20,-10,0,-2e1"]).min[-1] == -20
    assert parse(["timing", "0x46"]).id == 70 and parse(["timing", "70"]).id == 70
    assert parse(["logs", "h2_reader", "-n", "12"]).lines == 12
    assert parse(["status", "--timeout", ".5"]).timeout == 0.5


def test_whole_number_errors_name_the_fields_unit() -> None:
    """`send torque r_knee 1.5` said '(the protocol carries 1 deg)': torque is in counts."""
    cases = [
        (lambda: h2.encode_joint_control(2, "torque", 1.5), "whole torque counts"),
        (lambda: h2.encode_joint_control(2, "position", 10.5), "whole degrees"),
        (lambda: h2.encode_joint_control(2, "stiffness", 10, 1.5), "whole percent"),
        (lambda: h2.encode_accepted_angles("min", [0, 0, 0, 0, 0, 0.5]), "whole degrees"),
    ]
    for encode, unit in cases:
        with pytest.raises(ProtocolError, match=f"is not a whole number .*{unit}"):
            encode()


def test_pattern_csv_with_a_bom_and_full_width_digits(tmp_path: Path) -> None:
    """A spreadsheet's 'CSV UTF-8' starts with a BOM: it was refused as a bad header."""
    rows = f"{HEADER}\n1,2,3,4,5,6\n2,3,4,5,6,7\n"
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + rows.encode())
    assert load_pattern(str(bom), LIMITS).points == [[1, 2, 3, 4, 5, 6], [2, 3, 4, 5, 6, 7]]
    wide = f"{HEADER}\n1,2,3,4,5,6\n2,{FULL_WIDTH_12},4,5,6,7\n"
    with pytest.raises(ProtocolError) as e:
        parse_pattern(wide, "wide.csv", LIMITS)
    assert "wide.csv:3: values must be whole degrees in ASCII digits" in str(e.value)
    assert f"r_knee '{FULL_WIDTH_12}'" in str(e.value)


def test_the_appliance_sees_what_the_cli_says(tmp_path, write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    """The same three through `exolink` on a sim appliance: a BOM pattern loads, a full-width
    value in an uploaded pattern is refused by name, and the torque refusal says counts."""
    app = Appliance(write_config(nodes=_nodes(tmp_path)), spawn)
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + f"{HEADER}\n1,2,3,4,5,6\n2,3,4,5,6,7\n".encode())
    r = app.cli("pattern", "load", str(bom))
    assert r.returncode == 0 and "point 0/2" in r.stdout, r.stderr
    wide = tmp_path / "wide.csv"
    wide.write_text(f"{HEADER}\n1,2,3,4,5,6\n2,{FULL_WIDTH_12},4,5,6,7\n", encoding="utf-8")
    r = app.cli("pattern", "load", str(wide))
    assert r.returncode == 5, r.stdout
    assert "wide.csv:3: values must be whole degrees in ASCII digits" in r.stderr, r.stderr
    r = app.cli("send", "torque", "r_knee", "1.5")
    assert r.returncode == 5, r.stdout
    assert "1.5 is not a whole number (the protocol carries whole torque counts)" in r.stderr
