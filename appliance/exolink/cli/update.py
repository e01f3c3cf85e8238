"""`exolink update BUNDLE`: a new root file system for the board, over the network (admin).

The bundle (``make bundle``: a RAUC bundle signed with the lab's key) goes to the supervisor in
chunks; the board checks it (sha256 here, the signature by RAUC there), installs it into the other
A/B slot, reboots into it and keeps it only once every critical node beats; otherwise U-Boot falls
back to the old slot by itself (exolink.board.update). Refused while the exoskeleton is armed. This
command waits for the outcome (``--no-wait`` returns once the board has the bundle).

``exolink update-agent`` is the board's root side, run by systemd (not by hand).
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import sys
import time
from pathlib import Path
from typing import Any

from exolink import logs, messaging
from exolink.board import update, update_agent
from exolink.cli.errors import EXIT_REFUSED, fail
from exolink.cli.options import common, guard
from exolink.client import Refused, Remote, remote
from exolink.wire import management
from exolink.wire.replies import UNSET, Software, UploadAt, read
from exolink.wire.requests import body

POLL_S = 5.0


def describe(sw: Software | None) -> str:
    """The software line of ``exolink status``."""
    if sw is None:
        return ""
    text = f"software exolink {sw.version} on slot {sw.slot or '?'}"
    if sw.bundle_version:
        text += f" (bundle {sw.bundle_version})"
    if sw.result:
        text += f"; last update: {sw.result}"
        if sw.detail:
            text += f" ({sw.detail})"
        if sw.since:
            text += f" at {sw.since}"
    if sw.installing:
        text += "; INSTALLING an update (arming refused until the reboot)"
    return text + "\n"


def check_bundle(path: Path) -> tuple[int, str]:
    """Size and sha256 of a file that looks like a RAUC bundle, or a clear error."""
    if not path.is_file():
        raise Refused(f"{path}: no such file (build one with `make bundle`)")
    size = path.stat().st_size
    with open(path, "rb") as f:
        if f.read(4) != update.SQUASHFS_MAGIC:
            raise Refused(
                f"{path}: not a RAUC bundle (no squashfs header; `make bundle` makes one)"
            )
        f.seek(0)
        h = hashlib.sha256()
        while chunk := f.read(1 << 20):
            h.update(chunk)
    if size > update.MAX_BUNDLE_BYTES:
        raise Refused(f"{path}: {size} bytes, over the board's limit of {update.MAX_BUNDLE_BYTES}")
    return size, h.hexdigest()


def send(r: Remote, path: Path, size: int, sha: str, out: Any = sys.stdout) -> float:
    """Chunks in order; a lost reply is asked again at the same offset. Returns seconds taken."""
    t0 = time.monotonic()
    begun = read(r.call("update", body=body(management.Begin(size, sha, path.name))), UploadAt)
    chunk = update.MAX_CHUNK if begun.max_chunk is UNSET else begun.max_chunk
    chunk = min(chunk, update.MAX_CHUNK)
    offset, shown = 0, -1
    with open(path, "rb") as f:
        while offset < size:
            f.seek(offset)
            data = base64.b64encode(f.read(chunk)).decode()
            for attempt in range(5):
                try:
                    ask = management.Chunk(offset=offset, data=data)
                    at = read(r.call("update", body=body(ask)), UploadAt).offset
                    break
                except messaging.Unreachable:
                    if attempt == 4:
                        raise
                except Refused as exc:
                    # A chunk that arrived after all (its reply was lost): carry on from there.
                    if "expected" in str(exc) and attempt:
                        at = int(str(exc).rsplit(" ", 1)[-1])
                        break
                    raise
            offset = at
            pct = offset * 100 // size
            if pct // 10 != shown // 10:
                shown = pct
                rate = offset / max(time.monotonic() - t0, 1e-3) / 1e6
                out.write(f"sent {offset >> 20} of {size >> 20} MiB ({pct}%, {rate:.1f} MB/s)\n")
                out.flush()
    r.call("update", body=body(management.Commit()))
    return time.monotonic() - t0


def wait_outcome(args: argparse.Namespace, before: Software, out: Any) -> int:
    """Polls the board through its reboot until the update is good, rolled back or refused."""
    deadline = time.monotonic() + args.wait
    seen_down = False
    last = ""
    while time.monotonic() < deadline:
        time.sleep(POLL_S)
        try:
            with remote(args) as r:
                sw = read(r.call("update"), Software)
        except (messaging.Unreachable, Refused):
            if not seen_down:
                out.write("board rebooting...\n")
                out.flush()
            seen_down = True
            continue
        line = describe(sw)
        if line != last:
            out.write(line)
            out.flush()
            last = line
        result = sw.result
        if sw.since == before.since:
            continue  # the board's word from before this update (an earlier one's result)
        if result == "refused":
            return fail(f"update refused by the board: {sw.detail}", EXIT_REFUSED)
        if result == "good":
            return 0
        if result == "rolled back":
            return fail(f"update rolled back: {sw.detail}", 1)
    return fail(f"no outcome within {args.wait:g} s; `exolink status` shows the board's word", 1)


@guard
def cmd_update(args: argparse.Namespace) -> int:
    path = Path(args.bundle)
    size, sha = check_bundle(path)
    out = sys.stdout
    with remote(args) as r:
        before = read(r.call("update"), Software)
        out.write(describe(before))
        out.write(f"sending {path.name} ({size >> 20} MiB, sha256 {sha[:12]}...)\n")
        took = send(r, path, size, sha, out)
    out.write(
        f"sent in {took:.0f} s; the board checks the signature, installs it into the other slot "
        "and reboots into it\n"
    )
    out.flush()
    if args.wait <= 0:
        return 0
    return wait_outcome(args, before, out)


def cmd_update_agent(args: argparse.Namespace) -> int:
    """The board's root side (systemd units; exolink.board.update_agent)."""
    logs.setup("update-agent")
    action = {
        "install": update_agent.agent_install,
        "boot-check": update_agent.agent_boot_check,
        "mark-good": update_agent.agent_mark_good,
    }[args.action]
    return int(action())


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "update",
        parents=[common()],
        help="install a bundle (make bundle) on the board: other slot, reboot, kept if it comes up",
    )
    p.add_argument("bundle", help="the .raucb file")
    p.add_argument(
        "--wait",
        type=float,
        default=1800.0,
        metavar="S",
        help="seconds to wait for the outcome through the reboot (0: return once sent)",
    )
    p.set_defaults(func=cmd_update)
    p = sub.add_parser(
        "update-agent", help="board side, run by systemd as root (exolink.board.update_agent)"
    )
    p.add_argument("action", choices=["install", "boot-check", "mark-good"])
    p.set_defaults(func=cmd_update_agent)
