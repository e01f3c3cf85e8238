"""The root agent of board updates (``exolink update-agent``, run by systemd units): installs a
bundle the supervisor checked and handed over (``rauc install`` into the other slot, then a
reboot), works out at every boot what became of a pending update, and marks a slot good once
the supervisor left its ``healthy`` mark for that boot. The supervisor's side and the state they
share are exolink.board.update's; the process a laptop talks to never holds root.
"""

from __future__ import annotations

import json
import os
import pwd
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import msgspec
import structlog

from exolink.board.update import (
    HEALTHY,
    INCOMING,
    REQUEST,
    SLOTS,
    STATE,
    TRIAL_S,
    TRIAL_UNIT,
    UPDATE_DIR,
    InstallRequest,
    boot_id,
    read_state,
    slot_from_cmdline,
    write_json,
)

log = structlog.get_logger("exolink.board.update")


def _run(*cmd: str, timeout: float = 1800) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def _rauc_error(r: subprocess.CompletedProcess[str]) -> str:
    """RAUC's own error lines (``signature verification failed: ...``) before OpenSSL's stack
    (``C0BDFBB6:error:...:rsa_sig.c:1060:``), which the board showed alone at first."""
    lines = [ln.strip() for ln in (r.stderr + r.stdout).splitlines() if ln.strip()]
    own = [ln for ln in lines if not re.match(r"^[0-9A-Fa-f]{6,}:error:", ln)]
    for group in (own, lines):
        errors = [ln for ln in group if "rror" in ln or "fail" in ln.lower()]
        if errors:
            return " | ".join(errors[-3:])[:600]
    return " | ".join(lines[-3:])[:600] or f"rauc exited {r.returncode}"


def _booted_bundle_version() -> str | None:
    r = _run("rauc", "status", "--detailed", "--output-format=json", timeout=120)
    if r.returncode != 0:
        return None
    try:
        st = json.loads(r.stdout)
        booted = st.get("booted")
        for group in st.get("slots", []):
            for _name, slot in group.items():
                if slot.get("bootname") == booted:
                    return (slot.get("slot_status") or {}).get("bundle", {}).get("version")
    except (ValueError, AttributeError):
        return None
    return None


def _set_state(directory: Path, **changes: Any) -> dict[str, Any]:
    st = read_state(directory)
    st.update(changes)
    st["since"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    write_json(directory / STATE, st)
    log.info("update_state", **{k: v for k, v in st.items() if k != "pending"})
    return st


def agent_install(directory: Path = UPDATE_DIR, reboot: bool = True) -> int:
    """Install the requested bundle into the other slot and reboot into it (root)."""
    req_path = directory / REQUEST
    try:
        req = msgspec.json.decode(req_path.read_bytes(), type=InstallRequest)
    except (OSError, msgspec.DecodeError) as exc:
        log.error("update_request_unreadable", error=str(exc))
        req_path.unlink(missing_ok=True)
        return 1
    bundle = directory / INCOMING
    booted = slot_from_cmdline()
    target = next((s for s in SLOTS if s != booted), None)
    _set_state(directory, result="installing", detail=f"{req.name} into slot {target}",
               boot_id=boot_id())  # fmt: skip
    info = _run("rauc", "info", "--output-format=json", str(bundle), timeout=600)
    if info.returncode != 0:
        return _refused(directory, f"bundle refused by its signature or format check (rauc "
                        f"info): {_rauc_error(info)}")  # fmt: skip
    try:
        version = json.loads(info.stdout).get("version")
    except ValueError:
        version = None
    t0 = time.monotonic()
    r = _run("rauc", "install", str(bundle))
    if r.returncode != 0:
        return _refused(directory, f"install failed: {_rauc_error(r)}")
    took = round(time.monotonic() - t0, 1)
    bundle.unlink(missing_ok=True)
    req_path.unlink(missing_ok=True)
    _set_state(directory, result="installed", detail=f"slot {target}: version {version}, "
               f"installed in {took} s; rebooting into it", boot_id=boot_id(),
               pending={"slot": target, "from": booted, "version": version, "by": req.by})  # fmt: skip
    if reboot:
        subprocess.run(["systemctl", "reboot"], check=False)
    return 0


def _refused(directory: Path, why: str) -> int:
    log.error("update_refused", why=why)
    (directory / INCOMING).unlink(missing_ok=True)
    (directory / REQUEST).unlink(missing_ok=True)
    _set_state(directory, result="refused", detail=why, boot_id=boot_id())
    return 2


def agent_boot_check(directory: Path = UPDATE_DIR) -> int:
    """At each boot: the booted slot, and what became of a pending update."""
    directory.mkdir(parents=True, exist_ok=True)
    os.chown(directory, *_exolink_ids())
    booted = slot_from_cmdline()
    st = read_state(directory)
    pending = st.get("pending")
    # A request left by a boot that never got to install it is stale: drop it.
    if not (directory / REQUEST).exists():
        (directory / INCOMING).unlink(missing_ok=True)
    changes: dict[str, Any] = {"slot": booted, "bundle_version": _booted_bundle_version()}
    if isinstance(pending, dict):
        if pending.get("slot") == booted:
            changes.update(result="trial", detail=f"slot {booted} (version {pending.get('version')})"
                           " on trial: marked good once every critical node beats")  # fmt: skip
            _run("systemd-run", f"--unit={TRIAL_UNIT}", f"--on-active={TRIAL_S}",
                 "--description=exolink: a slot on trial that was not marked good",
                 "systemctl", "reboot", timeout=60)  # fmt: skip
        else:
            changes.update(result="rolled back", pending=None, detail=(
                f"slot {pending.get('slot')} (version {pending.get('version')}) did not come up; "
                f"back on slot {booted}"))  # fmt: skip
            log.error("update_rolled_back", failed=pending.get("slot"), booted=booted)
    _set_state(directory, **changes)
    return 0


def agent_mark_good(directory: Path = UPDATE_DIR) -> int:
    """The supervisor's healthy mark of this boot: tell RAUC (and U-Boot) this slot is good."""
    mark = directory / HEALTHY
    try:
        data = json.loads(mark.read_text())
    except (OSError, ValueError):
        data = {}
    mark.unlink(missing_ok=True)
    if data.get("boot_id") != boot_id():
        log.warning("update_healthy_mark_stale")
        return 0
    r = _run("rauc", "status", "mark-good", timeout=120)
    if r.returncode != 0:
        log.error("update_mark_good_failed", error=_rauc_error(r))
        return 1
    _run("systemctl", "stop", f"{TRIAL_UNIT}.timer", timeout=60)
    st = read_state(directory)
    booted = slot_from_cmdline()
    pending = st.get("pending")
    if isinstance(pending, dict) and pending.get("slot") == booted:
        _set_state(directory, result="good", pending=None, detail=f"slot {booted} runs version "
                   f"{pending.get('version')}, every critical node beating; marked good")  # fmt: skip
    log.info("update_marked_good", slot=booted)
    return 0


def _exolink_ids() -> tuple[int, int]:

    try:
        pw = pwd.getpwnam("exolink")
    except KeyError:
        return os.getuid(), os.getgid()
    return pw.pw_uid, pw.pw_gid
