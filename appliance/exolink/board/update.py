"""Updates of the board's root file system: signed RAUC bundles into the other A/B slot.

Three parties, so that the process a laptop talks to never holds root:

- the supervisor (user ``exolink``) takes a bundle from an admin laptop in chunks (``Upload``),
  checks its size, sha256 and squashfs header, refuses it while the exoskeleton is armed, and
  drops a request next to it in ``UPDATE_DIR``; from then on it refuses to arm (the board is about
  to reboot). Once every critical node beats after a boot (the first armable state) it leaves a
  ``healthy`` mark with the boot's id.
- the root agent (``exolink update-agent``, run by systemd path units, exolink-update.service and
  exolink-mark-good.service) installs a requested bundle with ``rauc install`` (RAUC checks the
  signature against /etc/rauc/ca.cert.pem and writes the other slot), reboots into it, and on the
  ``healthy`` mark of the same boot runs ``rauc status mark-good``. At every boot
  (exolink-boot-check.service) it works out what became of a pending update: on the new slot
  (on trial: marked good only by the mark), or back on the old one (the new one never came up:
  U-Boot's attempts ran out, image/boot.cmd).
- ``state.json`` in ``UPDATE_DIR`` (written by the agent, read by the supervisor's status): the
  booted slot, versions and the last update's result.

``UPDATE_DIR`` is on the data partition, shared by both slots, as are recordings.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import structlog

from exolink.refusal import Refused
from exolink.wire import management
from exolink.wire.replies import UNSET, Committed, Software, UploadAt, UploadProgress

log = structlog.get_logger("exolink.board.update")

UPDATE_DIR = Path("/var/lib/exolink/update")
# The root agent's path unit (services/etc/systemd/system/, installed by the image): where it
# exists, the agent watches UPDATE_DIR for install requests.
AGENT_UNIT = Path("/etc/systemd/system/exolink-update.path")
INCOMING = "incoming.raucb"
REQUEST = "install.request"
STATE = "state.json"
HEALTHY = "healthy"
BOOT_ENV = Path("/boot/firmware/exolink-boot.env")
SLOTS = ("A", "B")
# The largest bundle an admin may send (a root slot is 1.5 GiB; a bundle compresses it) and the
# space left on the data partition after it (recordings keep their room).
MAX_BUNDLE_BYTES = 1 << 30
KEEP_FREE_BYTES = 64 << 20
MAX_CHUNK = 1 << 20  # raw bytes per chunk (base64 in JSON: ~1.4 MB, under the admin's 2 MiB)
SQUASHFS_MAGIC = b"hsqs"
# A new slot on trial that is not marked good within this reboots (the watchdog-less hang: a
# supervisor that runs but never gets every critical node beating). U-Boot counts the attempt.
TRIAL_S = int(os.environ.get("EXOLINK_UPDATE_TRIAL_S", "900"))
TRIAL_UNIT = "exolink-update-trial"


def local_dir(workdir: Path) -> Path:
    """``UPDATE_DIR`` on a board (the root agent installed: it looks there), else a folder of
    the supervisor's working directory (``make sim`` on a laptop: uploads work, nothing installs
    them). Not by ``/var/lib/exolink`` alone: a laptop that once ran the board's config has it,
    and every appliance there, each test's included, then shared one update folder (one's
    install request kept the others from arming)."""
    if AGENT_UNIT.exists() and UPDATE_DIR.parent.is_dir() and os.access(UPDATE_DIR.parent, os.W_OK):
        return UPDATE_DIR
    return workdir / "update"


class UpdateRefused(Refused):
    """A request the supervisor will not act on; the message says what was wrong."""


def boot_id() -> str:
    return Path("/proc/sys/kernel/random/boot_id").read_text().strip()


def read_state(directory: Path = UPDATE_DIR) -> dict[str, Any]:
    """The agent's last word (``{}`` before the first boot check)."""
    try:
        data = json.loads((directory / STATE).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Atomic and on the card when it returns (the board loses power without warning)."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1, sort_keys=True)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# --- the boot state file (U-Boot's env export -t format) ------------------------------------


def parse_boot_env(text: str) -> dict[str, str]:
    """``NAME=value`` lines as U-Boot's ``env export -t`` writes them (NUL-terminated)."""
    out = {}
    for line in text.replace("\0", "\n").splitlines():
        name, eq, value = line.partition("=")
        if eq and re.fullmatch(r"[A-Z_]+", name):
            out[name] = value
    return out


def format_boot_env(env: dict[str, str]) -> str:
    return "".join(f"{k}={env[k]}\n" for k in ("BOOT_ORDER", "BOOT_A_LEFT", "BOOT_B_LEFT"))


# --- the supervisor's side: taking a bundle from a laptop --------------------------------------


@dataclass
class Upload:
    """One bundle on its way in: chunks in order, appended to ``INCOMING``."""

    size: int
    sha256: str
    name: str
    by: str
    received: int = 0
    started: float = 0.0


class InstallRequest(msgspec.Struct, frozen=True):
    """What the supervisor hands the root agent (``REQUEST``): a checked bundle to install.
    The agent reads it typed: the file is written by the unprivileged service."""

    bundle: str
    sha256: str
    size: int
    name: str
    by: str
    time: float


class Receiver:
    """The supervisor's half (runs as ``exolink``): begin, chunk, commit, abort."""

    def __init__(self, directory: Path = UPDATE_DIR) -> None:
        self.dir = directory
        self.upload: Upload | None = None
        self._hash: Any = None

    @property
    def installing(self) -> bool:
        """A bundle handed to the agent and not yet refused: the board reboots when it is in."""
        if (self.dir / REQUEST).exists():
            return True
        st = read_state(self.dir)
        return st.get("result") == "installing" and st.get("boot_id") == _boot_id_or_none()

    def begin(self, req: management.Begin, by: str) -> UploadAt:
        """``req`` decoded (exolink.wire.management: size and hash well formed); what the board
        can take is checked here."""
        size, sha, name = req.size, req.sha256, req.name
        if size > MAX_BUNDLE_BYTES:
            raise UpdateRefused(
                f"bundle of {size} bytes refused: the largest is {MAX_BUNDLE_BYTES} bytes"
            )
        if self.installing:
            raise UpdateRefused("an update is already being installed; the board reboots when done")
        self.dir.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(self.dir).free + self._partial_bytes()
        if size + KEEP_FREE_BYTES > free:
            raise UpdateRefused(
                f"bundle of {size >> 20} MiB does not fit: {free >> 20} MiB free on the data "
                f"partition, {KEEP_FREE_BYTES >> 20} MiB kept for recordings"
            )
        (self.dir / INCOMING).unlink(missing_ok=True)
        (self.dir / INCOMING).touch(mode=0o640)
        self.upload = Upload(size, sha, name[:120], by, started=time.monotonic())
        self._hash = hashlib.sha256()
        log.info("update_upload_started", size=size, name=self.upload.name, by=by)
        return UploadAt(0, MAX_CHUNK)

    def _partial_bytes(self) -> int:
        try:
            return (self.dir / INCOMING).stat().st_size
        except OSError:
            return 0

    def chunk(self, req: management.Chunk) -> UploadAt:
        up = self._current()
        offset, data = req.offset, req.data
        if offset != up.received:
            raise UpdateRefused(f"chunk at offset {offset} refused: expected {up.received}")
        try:
            raw = base64.b64decode(data, validate=True)
        except ValueError:
            raise UpdateRefused("data is not valid base64") from None
        if not raw or len(raw) > MAX_CHUNK:
            raise UpdateRefused(f"a chunk holds 1 to {MAX_CHUNK} bytes, not {len(raw)}")
        if up.received + len(raw) > up.size:
            raise UpdateRefused(f"chunk ends past the announced size of {up.size} bytes")
        if up.received == 0 and not raw.startswith(SQUASHFS_MAGIC):
            self.abort()
            raise UpdateRefused("not a RAUC bundle (no squashfs header): nothing installed")
        with open(self.dir / INCOMING, "ab") as f:
            f.write(raw)
        self._hash.update(raw)
        up.received += len(raw)
        return UploadAt(up.received)

    def commit(self, by: str) -> Committed:
        up = self._current()
        if up.received != up.size:
            raise UpdateRefused(f"bundle incomplete: {up.received} of {up.size} bytes received")
        digest = self._hash.hexdigest()
        if digest != up.sha256:
            self.abort()
            raise UpdateRefused(f"sha256 differs: received {digest}, announced {up.sha256}")
        with open(self.dir / INCOMING, "rb+") as f:
            os.fsync(f.fileno())
        request = InstallRequest(INCOMING, digest, up.size, up.name, by, time.time())
        write_json(self.dir / REQUEST, msgspec.structs.asdict(request))
        took = time.monotonic() - up.started
        log.warning("update_requested", size=up.size, name=up.name, by=by, upload_s=round(took, 1))
        self.upload = None
        return Committed(True, round(took, 1))

    def abort(self) -> None:
        self.upload = None
        (self.dir / INCOMING).unlink(missing_ok=True)

    def _current(self) -> Upload:
        if self.upload is None:
            raise UpdateRefused("no upload under way (begin first)")
        return self.upload

    def mark_healthy(self) -> None:
        """Every critical node beats: the agent may mark this boot's slot good."""
        self.dir.mkdir(parents=True, exist_ok=True)
        write_json(self.dir / HEALTHY, {"boot_id": boot_id(), "time": time.time()})
        log.info("update_healthy_marked")

    def status(self, version: str) -> Software:
        """From the agent's state file, whose values are the agent's (root's) own."""
        st = read_state(self.dir)
        up = self.upload
        return Software(
            version=version,
            slot=_text(st.get("slot")) or slot_from_cmdline(),
            bundle_version=_text(st.get("bundle_version")),
            result=_text(st.get("result")),
            detail=_text(st.get("detail")),
            since=_text(st.get("since")),
            installing=self.installing,
            upload=UNSET if up is None else UploadProgress(up.received, up.size),
        )


def _text(value: Any) -> str | None:
    return None if value is None else str(value)


def _boot_id_or_none() -> str | None:
    try:
        return boot_id()
    except OSError:
        return None


def slot_from_cmdline(cmdline: str | None = None) -> str | None:
    if cmdline is None:
        try:
            cmdline = Path("/proc/cmdline").read_text()
        except OSError:
            return None
    m = re.search(r"(?:^|\s)rauc\.slot=(\S+)", cmdline)
    return m.group(1) if m else None
