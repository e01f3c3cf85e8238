"""Updates (exolink.board.update): the supervisor's side of taking a bundle (sizes, order, checksum,
header, refused while armed, the role each action needs), the laptop's checks of a file, and
RAUC's custom boot backend (image/rauc/rauc-boot-backend) on a scratch state file. The install,
the reboot and the fallback need the card under qemu: tests/image/test_update.py.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import subprocess
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from exolink import messaging, roles
from exolink.board import update, update_agent
from exolink.cli import update as cli_update
from exolink.client import Refused
from exolink.supervisor.api import ManagementApi
from exolink.wire import management, replies
from exolink.wire.replies import UploadAt
from exolink.wire.requests import decode

REPO = Path(__file__).resolve().parents[1]
BACKEND = REPO / "image/rauc/rauc-boot-backend"


def bundle_bytes(n: int = 3000) -> bytes:
    return update.SQUASHFS_MAGIC + os.urandom(n - 4)


def begin(rx: update.Receiver, data: bytes, **over: Any) -> UploadAt:
    """A begin as the supervisor hands it on: decoded from the laptop's JSON object."""
    req = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest(), "name": "b.raucb"}
    ask = decode({"action": "begin", **req, **over}, management.Update, "update action")
    return rx.begin(ask, "admin")


def chunk(rx: update.Receiver, data: bytes | str, offset: int) -> UploadAt:
    text = data if isinstance(data, str) else base64.b64encode(data).decode()
    return rx.chunk(management.Chunk(offset=offset, data=text))


def test_a_bundle_in_chunks_becomes_a_request_for_the_agent(tmp_path: Path) -> None:
    rx, data = update.Receiver(tmp_path), bundle_bytes()
    assert begin(rx, data).offset == 0
    assert chunk(rx, data[:1000], 0) == UploadAt(1000)
    assert chunk(rx, data[1000:], 1000) == UploadAt(len(data))
    assert rx.commit("admin").accepted
    req = json.loads((tmp_path / update.REQUEST).read_text())
    assert req["sha256"] == hashlib.sha256(data).hexdigest() and req["by"] == "admin"
    assert (tmp_path / update.INCOMING).read_bytes() == data
    assert rx.installing  # from now on the supervisor refuses to arm
    with pytest.raises(update.UpdateRefused, match="already being installed"):
        begin(rx, data)


@pytest.mark.parametrize(
    ("over", "error"),
    [
        ({"size": 0}, r"Expected `int` >= 1 - at `\$.size`"),
        ({"size": "12"}, r"Expected `int`, got `str` - at `\$.size`"),
        ({"size": True}, r"Expected `int`, got `bool` - at `\$.size`"),
        ({"size": update.MAX_BUNDLE_BYTES + 1}, "the largest is"),
        ({"sha256": "abc"}, r"Expected `str` matching regex .* - at `\$.sha256`"),
        ({"sha256": "A" * 64}, r"at `\$.sha256`"),
        ({"bytes": 12}, r"Object contains unknown field `bytes`"),
    ],
)
def test_begin_names_what_is_wrong(tmp_path: Path, over: dict[str, Any], error: str) -> None:
    with pytest.raises(Refused, match=error):
        begin(update.Receiver(tmp_path), bundle_bytes(), **over)


def test_a_bundle_larger_than_the_free_space_is_refused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(update.shutil, "disk_usage", lambda _p: SimpleNamespace(free=10 << 20))
    with pytest.raises(update.UpdateRefused, match="does not fit: 10 MiB free"):
        begin(update.Receiver(tmp_path), bundle_bytes(), size=20 << 20)


def test_chunks_out_of_order_bad_data_or_header_are_refused(tmp_path: Path) -> None:
    rx, data = update.Receiver(tmp_path), bundle_bytes()
    with pytest.raises(update.UpdateRefused, match="no upload under way"):
        chunk(rx, data, 0)
    begin(rx, data)
    with pytest.raises(update.UpdateRefused, match="offset 5 refused: expected 0"):
        chunk(rx, data, 5)
    with pytest.raises(update.UpdateRefused, match="not valid base64"):
        chunk(rx, "!!", 0)
    with pytest.raises(update.UpdateRefused, match="past the announced size"):
        chunk(rx, data + b"x", 0)
    with pytest.raises(update.UpdateRefused, match="incomplete: 0 of"):
        rx.commit("admin")
    other = b"PK\x03\x04" + data[4:]
    begin(rx, other)
    with pytest.raises(update.UpdateRefused, match="not a RAUC bundle"):
        chunk(rx, other, 0)
    assert not (tmp_path / update.INCOMING).exists()


def test_a_bundle_whose_sha256_differs_is_dropped(tmp_path: Path) -> None:
    rx, data = update.Receiver(tmp_path), bundle_bytes()
    begin(rx, data, sha256="0" * 64)
    chunk(rx, data, 0)
    with pytest.raises(update.UpdateRefused, match="sha256 differs"):
        rx.commit("admin")
    assert not (tmp_path / update.REQUEST).exists() and not (tmp_path / update.INCOMING).exists()


def _sup(tmp_path: Path, armed: bool) -> Any:
    """The API over what its ``update`` uses of the supervisor: the watchdog's armed and the
    receiver (``.sup``)."""
    sup = SimpleNamespace(watchdog=SimpleNamespace(armed=armed), update=update.Receiver(tmp_path))
    return ManagementApi(sup)  # type: ignore[arg-type]


def test_update_is_refused_while_armed_and_says_why(tmp_path: Path) -> None:
    data = bundle_bytes()
    req = {"action": "begin", "size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    caller = messaging.Caller("admin")
    with pytest.raises(messaging.Refused, match="armed: an update ends in a reboot"):
        _sup(tmp_path, armed=True).update(req, caller)
    api = _sup(tmp_path, armed=False)
    assert replies.plain(api.update(req, caller))["offset"] == 0
    b64 = base64.b64encode(data).decode()
    api.update({"action": "chunk", "offset": 0, "data": b64}, caller)
    api.sup.watchdog.armed = True  # armed between the last chunk and the commit
    with pytest.raises(messaging.Refused, match="Disarm first"):
        api.update({"action": "commit"}, caller)
    assert not (tmp_path / update.REQUEST).exists()
    with pytest.raises(messaging.Refused, match="unknown update action 'frob'"):
        api.update({"action": "frob"}, caller)


def test_update_actions_need_admin_and_its_status_any_role(monkeypatch) -> None:
    """The route the supervisor serves (ManagementApi.routes) and the check serve() makes."""
    _handler, needs = ManagementApi(SimpleNamespace()).routes()["update"]  # type: ignore[arg-type]
    assert needs({}) == roles.OBSERVER
    roles.check(roles.OBSERVER, needs({"action": "status"}), "update")
    for action in ("begin", "chunk", "commit", "abort"):
        assert needs({"action": action}) == roles.ADMIN
        for login in (roles.OBSERVER, roles.OPERATOR):
            with pytest.raises(roles.Forbidden, match="needs the admin role"):
                roles.check(login, needs({"action": action}), "update")
        roles.check(roles.ADMIN, needs({"action": action}), "update")
    # A chunk's request (1 MiB base64 in JSON) fits the admin's request size.
    body = json.dumps({"action": "chunk", "offset": 0, "data": "A" * (4 * update.MAX_CHUNK // 3)})
    assert len(body) < roles.MAX_REQUEST_BYTES[roles.ADMIN]


def test_the_laptop_checks_the_file_before_sending(tmp_path: Path) -> None:
    with pytest.raises(Refused, match="no such file"):
        cli_update.check_bundle(tmp_path / "missing.raucb")
    (tmp_path / "x.img").write_bytes(b"\x00" * 100)
    with pytest.raises(Refused, match="not a RAUC bundle"):
        cli_update.check_bundle(tmp_path / "x.img")
    data = bundle_bytes()
    (tmp_path / "b.raucb").write_bytes(data)
    assert cli_update.check_bundle(tmp_path / "b.raucb") == (
        len(data),
        hashlib.sha256(data).hexdigest(),
    )


def test_status_line_names_version_slot_and_last_result() -> None:
    line = cli_update.describe(
        replies.Software("0.1.0", "B", "0.1.0+abc", "good", "slot B runs version 0.1.0+abc",
                         "2026-11-28T03:00:00Z", installing=False)
    )  # fmt: skip
    assert line.startswith("software exolink 0.1.0 on slot B (bundle 0.1.0+abc); last update: good")


def test_u_boot_text_env_is_read_with_its_nul() -> None:
    env = update.parse_boot_env("BOOT_A_LEFT=2\nBOOT_B_LEFT=0\nBOOT_ORDER=B A\n\0")
    assert env == {"BOOT_A_LEFT": "2", "BOOT_B_LEFT": "0", "BOOT_ORDER": "B A"}
    assert update.parse_boot_env(update.format_boot_env(env)) == env


def backend(state: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["sh", str(BACKEND), *args],
        env={"PATH": os.environ["PATH"], "EXOLINK_BOOT_ENV": str(state)},
        capture_output=True,
        text=True,
    )


def test_custom_backend_speaks_raucs_u_boot_conventions(tmp_path: Path) -> None:
    """What RAUC does around an install (mark the target bad, write it, make it primary) and
    after a good boot (mark-good), on the file U-Boot's boot script reads."""
    state = tmp_path / "exolink-boot.env"
    assert backend(state, "get-primary").stdout == "A\n"  # no file yet: U-Boot's defaults
    state.write_text("BOOT_A_LEFT=2\nBOOT_B_LEFT=3\nBOOT_ORDER=A B\n\0")  # as U-Boot writes it
    assert backend(state, "set-state", "B", "bad").returncode == 0
    assert backend(state, "get-state", "B").stdout == "bad\n"
    assert backend(state, "set-primary", "B").returncode == 0
    assert update.parse_boot_env(state.read_text()) == {
        "BOOT_ORDER": "B A",
        "BOOT_A_LEFT": "2",
        "BOOT_B_LEFT": "3",
    }
    assert backend(state, "get-primary").stdout == "B\n"
    state.write_text("BOOT_ORDER=B A\nBOOT_A_LEFT=2\nBOOT_B_LEFT=0\n")  # B's attempts ran out
    assert backend(state, "get-primary").stdout == "A\n"
    assert backend(state, "set-state", "A", "good").returncode == 0
    assert "BOOT_A_LEFT=3" in state.read_text()
    r = backend(state, "set-state", "C", "good")
    assert r.returncode == 1 and "unknown slot 'C'" in r.stderr
    r = backend(state, "set-state", "A", "fine")
    assert r.returncode == 1 and "expected good or bad" in r.stderr


def test_a_running_appliance_refuses_an_update_while_armed_and_arming_while_installing(
    write_config, spawn, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    """The sim appliance, the real CLI over Zenoh: what the board's safety rests on. No RAUC
    here: the request stays in the supervisor's folder (exolink.board.update.local_dir)."""
    from benchmarks.harness import Appliance, motion_nodes

    app = Appliance(write_config(nodes=motion_nodes(deadline_ms=300, h2_timeout_ms=300)), spawn)
    bundle = tmp_path / "next.raucb"
    bundle.write_bytes(bundle_bytes(3 * update.MAX_CHUNK + 123))  # four chunks
    app.arm()
    r = app.cli("update", str(bundle), "--wait", "0")
    assert r.returncode == 5, r.stdout + r.stderr
    assert "armed: an update ends in a reboot, never under a walking patient" in r.stderr
    assert app.cli("disarm").returncode == 0
    r = app.cli("update", str(bundle), "--wait", "0")
    assert r.returncode == 0, r.stderr
    assert "sent in" in r.stdout and "installs it into the other slot" in r.stdout
    r = app.cli("arm")
    assert r.returncode == 5 and "an update is being installed" in r.stderr, r.stderr
    sw = app.status()["software"]
    assert sw["installing"] and sw["version"]
    assert "INSTALLING an update" in app.cli("status").stdout
    r = app.cli("update", str(bundle), "--wait", "0")
    assert r.returncode == 5 and "already being installed" in r.stderr


def test_a_refusal_names_raucs_reason_before_openssls_stack() -> None:
    """What the board's rauc info said of the tampered bundle under qemu (stderr), reduced."""
    stderr = (
        "rauc-Message: 03:50:40.1: Verifying bundle signature... \n"
        "C0BDFBB6:error:02000072:rsa routines:rsa_ossl_public_decrypt:padding check failed:"
        "../crypto/rsa/rsa_ossl.c:802:\n"
        "signature verification failed: error:0200008A:rsa routines::invalid padding\n"
        "C0BDFBB6:error:1700009E:CMS routines:CMS_SignerInfo_verify:verification failure:"
        "../crypto/cms/cms_sd.c:1004:\n"
    )
    r = subprocess.CompletedProcess([], 1, "", stderr)
    assert update_agent._rauc_error(r) == (
        "signature verification failed: error:0200008A:rsa routines::invalid padding"
    )
    only_openssl = subprocess.CompletedProcess([], 1, "", stderr.splitlines()[1] + "\n")
    assert "padding check failed" in update_agent._rauc_error(only_openssl)
    assert update_agent._rauc_error(subprocess.CompletedProcess([], 7, "", "")) == "rauc exited 7"


def test_the_update_folder_is_the_boards_only_where_its_agent_is_installed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A machine with /var/lib/exolink but no root agent (a laptop that once ran the board's
    config) kept every appliance's update requests in one folder: one test's install request
    then kept the others from arming."""
    shared = tmp_path / "var-lib-exolink" / "update"
    shared.parent.mkdir()
    agent = tmp_path / "exolink-update.path"
    monkeypatch.setattr(update, "UPDATE_DIR", shared)
    monkeypatch.setattr(update, "AGENT_UNIT", agent)
    work = tmp_path / "work"
    assert update.local_dir(work) == work / "update"
    agent.write_text("[Path]\n")
    assert update.local_dir(work) == shared


@pytest.mark.parametrize("text", ["not json", '{"bundle": "incoming.raucb"}', '{"name": 5}'])
def test_the_root_agent_refuses_a_request_file_that_is_not_one(tmp_path: Path, text: str) -> None:
    """The agent runs as root on a file the unprivileged service wrote: read typed, anything
    else is dropped before rauc is asked anything (none is installed here to ask)."""
    (tmp_path / update.REQUEST).write_text(text)
    assert update_agent.agent_install(tmp_path, reboot=False) == 1
    assert not (tmp_path / update.REQUEST).exists()
