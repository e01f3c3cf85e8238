"""The CLI's own edges (issue 19): option placement, one-line errors, negative lists, units,
playback namespaces, the status table. Parsing is checked in-process; behaviour against a
simulated appliance through real `exolink` processes."""

from __future__ import annotations

import subprocess

import pytest
from conftest import EXOLINK, Appliance
from exolink.cli.main import parse
from exolink.cli.remote import DEFAULT_AT

SIM_NODES = [
    {"name": "simulator", "plugin": "simulator"},
    {"name": "h2_reader", "plugin": "h2_reader"},
]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*EXOLINK, *args], capture_output=True, text=True, timeout=30)


# --- appliance options before or after the command --------------------------------------------


def test_appliance_options_before_the_command(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("EXOLINK_AT", raising=False)
    a = parse(["--at", "tcp/1.2.3.4:7447", "--timeout", "7", "--device", "exo-02", "status"])
    assert (a.at, a.timeout, a.device, a.command) == ("tcp/1.2.3.4:7447", 7.0, "exo-02", "status")
    a = parse(["--zenoh-config", "login.json5", "send", "stream", "on"])  # nested subcommand
    assert a.zenoh_config == "login.json5" and a.at == DEFAULT_AT and a.timeout == 3.0
    # after the command, as before; after wins over before
    a = parse(["status", "--at", "tcp/5.6.7.8:7447"])
    assert a.at == "tcp/5.6.7.8:7447"
    a = parse(["--at", "tcp/1.2.3.4:7447", "--ns", "x", "echo", "t", "--at", "tcp/5.6.7.8:7447"])
    assert (a.at, a.ns) == ("tcp/5.6.7.8:7447", "x")
    # neither: the environment, then the default
    monkeypatch.setenv("EXOLINK_AT", "tcp/9.9.9.9:7447")
    assert parse(["status"]).at == "tcp/9.9.9.9:7447"
    assert parse(["--at", "tcp/1.2.3.4:7447", "status"]).at == "tcp/1.2.3.4:7447"


def test_appliance_options_refused_by_board_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        parse(["--at", "tcp/1.2.3.4:7447", "config", "x.yaml"])
    assert e.value.code == 2
    assert "--at: `exolink config` does not talk to an appliance" in capsys.readouterr().err


def test_options_before_the_command_reach_the_appliance(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    app = Appliance(write_config(nodes=SIM_NODES), spawn)
    r = run("--at", app.at, "--timeout", "3", "status")
    assert r.returncode == 0, r.stderr
    assert "h2_reader" in r.stdout
    # a value after the command wins: an unreachable endpoint before it does not matter
    r = run("--at", "tcp/127.0.0.1:9", "nodes", "--at", app.at)
    assert r.returncode == 0, r.stderr
