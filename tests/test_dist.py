"""`make dist`: the wheel a laptop installs with pipx has the CLI and everything it reads at run
time (configs, DBC files, message definitions, patterns), built the way the target builds it."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import REPO

pytestmark = pytest.mark.slow


def shipped(rel: str) -> str | None:
    """Where a tracked file of the checkout belongs in the wheel (None: it does not)."""
    top, _, rest = rel.partition("/")
    if top not in ("appliance", "nodes") or rel.endswith(".md"):
        return None
    if rel.endswith(".py") and not (REPO / rel).with_name("__init__.py").exists():
        return None  # a script beside data (nodes/patterns/make_default.py), not a module
    return rest if top == "appliance" else f"exolink/nodes/{rest}"  # appliance/exolink/...


def test_wheel_has_the_cli_and_its_data(tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "build", "--outdir", str(tmp_path / "dist"), str(REPO)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("exolink-*-py3-none-any.whl")
    assert len(list((tmp_path / "dist").glob("exolink-*.tar.gz"))) == 1  # the wheel's source
    names = set(zipfile.ZipFile(wheel).namelist())
    tracked = subprocess.run(
        ["git", "ls-files", "appliance", "nodes"], cwd=REPO, capture_output=True, text=True
    ).stdout.split()
    expected = {s for rel in tracked if (s := shipped(rel))}
    assert {"exolink/configs/sim.yaml", "exolink/protocol/h2.dbc"} <= expected
    assert any(n.endswith(".msg") for n in expected) and any(n.endswith(".csv") for n in expected)
    assert expected - names == set()
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "[console_scripts]\nexolink = exolink.cli.main:main" in text

    # Installed alone (no checkout on the path), its `exolink` runs and finds its data.
    target = tmp_path / "site"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--target",
            str(target),
            str(wheel),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    env = {**os.environ, "PYTHONPATH": str(target)}
    r = subprocess.run(
        [str(target / "bin" / "exolink"), "--version"], capture_output=True, text=True, env=env
    )
    assert r.returncode == 0 and r.stdout.startswith("exolink "), r.stderr
    probe = (
        "import exolink, exolink.config as c, exolink.protocol.dbc as d, exolink.messaging as m;"
        "from exolink.nodes import pattern_player as p;"
        "print(exolink.__file__); c.load(c.bundled('sim')); d.load(d.bundled('h2'));"
        "m.type_hash('exolink_msgs/msg/JointCommand'); assert p.DEFAULT_PATTERN.is_file()"
    )
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(str(target)), r.stdout  # the wheel's copy, not the checkout's
