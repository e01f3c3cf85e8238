"""Recordings over the network, as a laptop sees them: a real appliance on the simulator whose
router enforces the board's logins, and every command a laptop process of its own (observer
lists, operator fetches, admin deletes); the card filled on purpose on a real small filesystem."""

from __future__ import annotations

import argparse
import base64
import hashlib
import json
import os
import subprocess
import time
from pathlib import Path

import pytest
from test_recording import nodes
from test_roles import _guarded

from benchmarks.harness import EXOLINK, Appliance, wait_for
from exolink import messaging, roles
from exolink.client import Remote
from exolink.dashboard.hub import Hub
from exolink.recordings import fetching
from exolink.recordings import store as recstore
from exolink.recordings.readback import info
from exolink.recordings.replies import FileEntry
from exolink.refusal import Refused


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def listing(app: Appliance, login: Path) -> dict:
    r = app.cli("record", "list", "--json", login=login)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def record(app: Appliance, login: Path, seconds: float) -> None:
    r = app.cli("record", "start", "--label", "subject=S01", login=login)
    assert r.returncode == 0, r.stderr
    time.sleep(seconds)
    r = app.cli("record", "stop", login=login)
    assert r.returncode == 0 and "idle" in r.stdout, (r.stdout, r.stderr)


def dashboard_hub(app: Appliance, login: Path) -> Hub:
    """A laptop dashboard's hub (`exolink dashboard`) with a role's login."""
    args = argparse.Namespace(
        at=app.at, timeout=10.0, domain=0, ns="h2", zenoh_config=str(login), device="sim"
    )
    return Hub(Remote(args))


def ask(app: Appliance, login_file: Path, role: str, body: dict) -> dict:
    """One raw request to the recorder's ``recordings`` as a role (what a hostile laptop may
    send, past the CLI's own checks)."""
    s = messaging.open_client_session(app.at, str(login_file))
    try:
        key = messaging.mgmt_key("sim", "recordings")
        return messaging.request(s, key, body, 10, role)
    finally:
        s.close()


def test_a_laptop_lists_fetches_checks_and_deletes_by_role(tmp_path, write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    app, _board, logins = _guarded(tmp_path, write_config, spawn)
    obs, op, admin = (logins[r] for r in roles.ROLES)
    rec, laptop = tmp_path / "rec", tmp_path / "laptop"

    # While recording: listed as such, never handed out nor deleted.
    r = app.cli("record", "start", login=op)
    assert r.returncode == 0, r.stderr
    live = wait_for(lambda: [f for f in listing(app, obs)["files"] if f["state"] == "recording"])
    name = live[0]["name"]  # type: ignore[index]
    r = app.cli("record", "fetch", name, "-o", str(laptop), login=op)
    assert r.returncode == 5 and "still being recorded" in r.stderr, r.stderr
    r = app.cli("record", "delete", name, login=admin)
    assert r.returncode == 5 and "still being recorded" in r.stderr, r.stderr
    assert not (laptop / (name + ".part")).exists()
    time.sleep(2)
    r = app.cli("record", "stop", login=op)
    assert r.returncode == 0, r.stderr

    # Closed: an observer lists it (and the card) but cannot fetch it; an operator can.
    files = listing(app, obs)
    [entry] = files["files"]
    assert entry["name"] == name and entry["state"] == "closed"
    assert entry["size"] == (rec / name).stat().st_size
    assert files["card"]["free"] > 0 and files["card"]["reserve"] == 256 * 2**20
    r = app.cli("record", "list", login=obs)
    assert r.returncode == 0 and name in r.stdout and "closed" in r.stdout, r.stderr
    r = app.cli("record", "fetch", name, "-o", str(laptop), login=obs)
    assert r.returncode == 5 and "needs the operator role" in r.stderr, r.stderr
    r = app.cli("record", "fetch", name, "-o", str(laptop), "--chunk", "65536", login=op)
    assert r.returncode == 0, r.stderr
    board_sum = sha256(rec / name)
    assert f"sha256 {board_sum} checked" in r.stdout
    assert sha256(laptop / name) == board_sum
    assert not (laptop / (name + ".part")).exists()
    assert info(laptop / name).topics["/h2/joint_states"]["count"] > 50
    # The board's sha256 is computed once and then listed with the file.
    assert listing(app, obs)["files"][0]["sha256"] == board_sum
    r = app.cli("record", "fetch", name, "-o", str(laptop), login=op)
    assert r.returncode == 0 and "already here" in r.stdout, r.stdout

    # Resumed: a .part left by an interrupted fetch is continued from its size.
    again = tmp_path / "again"
    again.mkdir()
    data = (rec / name).read_bytes()
    (again / (name + ".part")).write_bytes(data[: len(data) // 2])
    r = app.cli("record", "fetch", name, "-o", str(again), "--chunk", "4096", login=op)
    assert r.returncode == 0 and "resumed at" in r.stdout, (r.stdout, r.stderr)
    assert sha256(again / name) == board_sum
    # A .part that is not the file's beginning fails the check: removed, said, not renamed.
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / (name + ".part")).write_bytes(b"\0" * 1000)
    r = app.cli("record", "fetch", name, "-o", str(bad), login=op)
    assert r.returncode == 3 and "sha256" in r.stderr and "fetch it again" in r.stderr, r.stderr
    assert list(bad.iterdir()) == []

    # Untrusted names and sizes: only what the board lists, inside its directory.
    outside = tmp_path / "secret.mcap"
    outside.write_bytes(b"not yours")
    (rec / "link.mcap").symlink_to(outside)
    assert [f["name"] for f in listing(app, obs)["files"]] == [name]
    for evil in ("../secret.mcap", str(outside), "link.mcap", "..", "", ".hidden.mcap", None):
        got = ask(app, op, "operator", {"action": "fetch", "name": evil, "offset": 0, "length": 10})
        assert not got["ok"] and "data" not in got, (evil, got)
    got = ask(
        app, op, "operator", {"action": "fetch", "name": name, "offset": 0, "length": 4 << 20}
    )
    assert not got["ok"] and "length must be" in got["error"]
    got = ask(app, op, "operator", {"action": "fetch", "name": name, "offset": -1, "length": 10})
    assert not got["ok"]
    got = ask(app, op, "operator", {"action": "delete", "name": "link.mcap"})
    assert not got["ok"] and outside.exists()

    # sync: what the laptop lacks, then nothing.
    record(app, op, 1.5)
    r = app.cli("record", "sync", str(laptop), login=op)
    assert r.returncode == 0 and "synced 1 files" in r.stdout and "1 were already" in r.stdout, (
        r.stdout,
        r.stderr,
    )
    for f in listing(app, obs)["files"]:
        assert sha256(laptop / f["name"]) == sha256(rec / f["name"])
    r = app.cli("record", "sync", str(laptop), login=op)
    assert r.returncode == 0 and "synced 0 files" in r.stdout, r.stdout

    # The dashboard's Recording page on a laptop: the file comes from the board, by role.
    cache = tmp_path / "cache"
    os.environ["XDG_CACHE_HOME"] = str(cache)
    observer_hub, operator_hub = dashboard_hub(app, obs), dashboard_hub(app, op)
    try:
        with pytest.raises(Refused, match="needs the operator role"):
            observer_hub.recording(str(rec / name))
        elsewhere = str(tmp_path / "on-the-board" / name)  # not a file on this machine
        got_path = operator_hub.recording(elsewhere)
        assert got_path == cache / "exolink" / "recordings" / "sim" / name
        assert sha256(got_path) == board_sum
    finally:
        del os.environ["XDG_CACHE_HOME"]
        observer_hub.remote.close()
        operator_hub.remote.close()

    # delete: the admin's alone.
    r = app.cli("record", "delete", name, login=op)
    assert r.returncode == 5 and "needs the admin role; this login is operator" in r.stderr
    r = app.cli("record", "delete", name, login=admin)
    assert r.returncode == 0 and f"deleted {name}" in r.stdout, r.stderr
    assert not (rec / name).exists() and name not in str(listing(app, obs))
    assert outside.read_bytes() == b"not yours"
    # The chunks were not each a command-log entry; the node took no harm.
    assert app.node("recorder")["state"] == "running"


@pytest.fixture
def small_card(tmp_path: Path):  # type: ignore[no-untyped-def]
    """A real 24 MiB ext4 filesystem (a loop device) as the recordings card."""
    image, mnt = tmp_path / "card.img", tmp_path / "card"
    mnt.mkdir()
    with image.open("wb") as f:
        f.truncate(24 << 20)
    mkfs = subprocess.run(["mkfs.ext4", "-q", "-m", "0", "-F", str(image)], capture_output=True)
    r = subprocess.run(
        ["mount", "-o", "loop", str(image), str(mnt)], capture_output=True, text=True
    )
    if mkfs.returncode != 0 or r.returncode != 0:
        pytest.skip(f"cannot loop-mount a small ext4 here (needs root): {r.stderr.strip()}")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], check=False)


def fill(card: Path, leave: int) -> Path:
    """A ballast file that leaves ``leave`` bytes free on the card."""
    ballast = card / "ballast.bin"
    with ballast.open("wb") as f:
        free = os.statvfs(card).f_bavail * os.statvfs(card).f_frsize
        f.write(b"\0" * max(0, free - leave))
        f.flush()
        os.fsync(f.fileno())
    return ballast


def test_a_full_card_stops_the_recorder_cleanly_and_status_says_so(  # type: ignore[no-untyped-def]
    write_config, spawn, small_card
) -> None:
    reserve_mb = 4
    fill(small_card, (reserve_mb << 20) + (400 << 10))
    params = {
        "compression": "none",
        "reserve_mb": reserve_mb,
        "fsync_interval_s": 0.2,
        "fetch_mb_s": 0.2,
    }
    app = Appliance(write_config(nodes=nodes(small_card, **params)), spawn)
    assert app.cli("record", "start").returncode == 0
    wait_for(lambda: "card full" in app.cli("record", "status").stdout, timeout=90)
    st = json.loads(app.cli("record", "status", "--json").stdout)
    assert st["state"] == "error" and st["error"].startswith("card full: "), st
    assert "recording stopped" in st["error"] and "closed" in st["error"]
    assert st["card"]["free"] < reserve_mb << 20 and st["card"]["free"] > (reserve_mb - 1) << 20
    [path] = sorted(small_card.glob("*.mcap"))
    i = info(path)  # closed and indexed: a summary, every chunk's CRC good
    assert i.topics["/h2/joint_states"]["count"] > 0 and i.integrity["summary_crc"] == "checked", i
    # exolink status: the recorder's health and the card; the rest of the appliance runs on.
    wait_for(lambda: app.node("recorder")["health"].startswith("error: card full"), timeout=5)
    out = app.cli("status").stdout
    assert "error: card full" in out and "MiB free of" in out and " 0.0 h of recording" in out, out
    assert all(n["state"] == "running" for n in app.status()["nodes"])
    # No new recording on a full card, said plainly; listing and fetching still work.
    r = app.cli("record", "start")
    assert r.returncode == 5 and "card full" in r.stderr and "record sync" in r.stderr, r.stderr
    r = app.cli("record", "list")
    assert r.returncode == 0 and path.name in r.stdout and "closed" in r.stdout
    # A fetch cut off (the laptop killed; the board serves 0.2 MB/s here), then the end of
    # the day's sync: it resumes from the .part and checks the whole.
    laptop = small_card.parent / "laptop"
    part = laptop / (path.name + ".part")
    at = ["--at", app.at, "--timeout", "10"]
    cut = subprocess.Popen(
        [*EXOLINK, "record", "fetch", path.name, "-o", str(laptop), "--chunk", "65536", *at]
    )
    try:
        wait_for(lambda: part.is_file() and part.stat().st_size >= 128 << 10, timeout=20)
    finally:
        cut.kill()
        cut.wait()
    assert 0 < part.stat().st_size < path.stat().st_size
    r = app.cli("record", "sync", str(laptop))
    assert r.returncode == 0 and "resumed at" in r.stdout, (r.stdout, r.stderr)
    assert sha256(laptop / path.name) == sha256(path) and not part.exists()
    r = app.cli("record", "delete", path.name)
    assert r.returncode == 0, r.stderr
    (small_card / "ballast.bin").unlink()
    r = app.cli("record", "start")  # room again
    assert r.returncode == 0, r.stderr
    wait_for(lambda: "hours left" not in app.cli("status").stdout, timeout=10)
    out = app.cli("status").stdout
    assert " h of recording left at " in out, out


def test_booted_onto_a_full_card_the_recorder_says_so_and_opens_nothing(  # type: ignore[no-untyped-def]
    write_config, spawn, small_card
) -> None:
    fill(small_card, 1 << 20)
    params = {"autostart": True, "reserve_mb": 4}
    app = Appliance(write_config(nodes=nodes(small_card, **params)), spawn)
    st = json.loads(app.cli("record", "status", "--json").stdout)
    assert st["state"] == "error" and "card full" in st["error"] and "not recording" in st["error"]
    wait_for(lambda: app.node("recorder")["health"].startswith("error: card full"), timeout=5)
    assert list(small_card.glob("*.mcap")) == []


def test_the_reserve_changes_at_run_time_and_a_recording_under_it_stops(  # type: ignore[no-untyped-def]
    write_config, spawn, tmp_path
) -> None:
    """What the qemu-booted card's test fills the card with: the reserve raised over the free
    space while recording (exolink params, admin) stops it as a full card does."""
    rec = tmp_path / "rec"
    app = Appliance(write_config(nodes=nodes(rec, fsync_interval_s=0.2)), spawn)
    assert app.cli("record", "start").returncode == 0
    free_mb = json.loads(app.cli("record", "list", "--json").stdout)["card"]["free"] >> 20
    r = app.cli("params", "recorder", "--set", "reserve_mb", str(free_mb + 1))
    assert r.returncode == 0 and f"recorder.reserve_mb = {free_mb + 1}" in r.stdout, r.stderr
    wait_for(lambda: "card full" in app.cli("record", "status").stdout, timeout=10)
    [path] = sorted(rec.glob("*.mcap"))
    assert info(path).integrity["summary_crc"] == "checked"  # closed and indexed
    # Only the reserve and the pace change at run time; anything else is refused, unchanged.
    r = app.cli("params", "recorder", "--set", "compression", "lz4")
    assert r.returncode == 5 and "only reserve_mb, fetch_mb_s change at run time" in r.stderr
    r = app.cli("params", "recorder")
    assert json.loads(r.stdout)["compression"] == "zstd", r.stdout
    assert app.cli("params", "recorder", "--set", "fetch_mb_s", "4").returncode == 0
    assert app.cli("params", "recorder", "--set", "reserve_mb", "1").returncode == 0
    r = app.cli("record", "start")  # room again
    assert r.returncode == 0, r.stderr
    assert app.cli("record", "stop").returncode == 0


def test_names_from_the_network_stay_in_the_directory(tmp_path: Path) -> None:
    """The store on its own: every odd name is refused before any path is made of it."""
    d = tmp_path / "rec"
    d.mkdir()
    (d / "a.mcap").write_bytes(b"x" * 100)
    (tmp_path / "b.mcap").write_bytes(b"y")
    (d / "b.mcap").symlink_to(tmp_path / "b.mcap")
    (d / "sub.mcap").mkdir()
    store = recstore.Store(d, lambda: None)
    assert [e.name for e in store.entries()] == ["a.mcap"]
    for name in ("../b.mcap", "/etc/passwd", "b.mcap", "sub.mcap", "a.mcap/..", "a", "a\nb.mcap"):
        with pytest.raises(recstore.StoreError):
            store.chunk(name, 0, 10)
    assert base64.b64decode(store.chunk("a.mcap", 90, 50).data) == b"x" * 10
    writing = recstore.Store(d, lambda: d / "a.mcap")
    assert writing.entries()[0].state == "recording"
    with pytest.raises(recstore.StoreError, match="still being recorded"):
        writing.delete("a.mcap")
    assert fetching.missing([FileEntry("../x.mcap", 1, 0.0, "closed", None)], d) == []


def test_the_write_rate_and_hours_left() -> None:
    rate = recstore.Rate(window_s=10)
    assert rate.note(0, now=0.0) == 0.0  # one point: no rate yet
    assert rate.note(50_000, now=0.5) == 0.0  # under a second: none either
    assert rate.note(100_000, now=2.0) == 50_000
    for t in range(3, 30):  # the window moves on: a slower rate replaces the first
        rate.note(100_000 + (t - 2) * 10_000, now=float(t))
    assert rate.last == pytest.approx(10_000)
    gib = 2**30
    assert recstore.hours_left(gib + 256 * 2**20, 256 * 2**20, 10_000) == pytest.approx(
        gib / 10_000 / 3600
    )
    assert recstore.hours_left(100, 256 * 2**20, 10_000) == 0
    assert recstore.hours_left(gib, 0, 0.0) is None


def test_pace_keeps_a_fetch_to_its_rate() -> None:
    pace = recstore.Pace(bytes_per_s=4e6)
    t = time.monotonic()
    for _ in range(5):
        pace.wait(200_000)  # 5 x 0.2 MB at 4 MB/s: the last four wait 50 ms each
    assert 0.18 <= time.monotonic() - t < 0.5
    t = time.monotonic()
    recstore.Pace(0).wait(10**9)  # 0: no limit
    assert time.monotonic() - t < 0.05
