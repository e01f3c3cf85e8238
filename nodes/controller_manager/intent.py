"""The operator's intent, kept where motion is written: the joint limits in force and who holds
motion.

Limits: the config's ``limits:`` section, narrowed by what an operator sent (``exolink send
limits``), with the login that sent them and when. What an operator sent is written to a file in
the appliance's state directory before it takes effect, so a restart of the controller manager
(or of the board) keeps it: a forgotten limit would let a joint go where the operator had
forbidden. A file that cannot be read is never taken as "no limits sent": motion is refused
until an operator sends limits again.

Presence: nothing moves a joint without a holder, a client that renews its hold at least every
``lost_s`` (``watchdog.operator_lost_ms``). A frozen laptop keeps its TCP link and its Zenoh
session for the session lease (10 s), so the keep-alive is the application's own, not Zenoh's.
One holder at a time; a second is refused unless it takes over, and the first then learns it at
its next renewal.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog

from exolink.control.replies import HolderInfo, JointLimits, LimitsInfo, PresenceInfo
from exolink.limits.joints import Limits
from exolink.protocol import h2
from exolink.refusal import Refused

log = structlog.get_logger()
INTENT_FILE = "operator-limits.json"
MAX_WHAT = 120  # characters of a holder's own description kept (it is the client's text)
HOLDER_ID_CHARS = 64
MAX_TAKEN = 16  # replaced holders remembered, to tell each at its next renewal


class IntentRefused(Refused):
    """A request the operator's intent refuses; the text names why and what to do."""


@dataclass(frozen=True)
class SetBy:
    login: str
    at_ns: int


class OperatorLimits:
    """The limits in force: configured, narrowed by an operator, persisted."""

    def __init__(self, configured: Limits, state_dir: Path | None) -> None:
        self.configured = configured
        self.path = state_dir / INTENT_FILE if state_dir is not None else None
        self.in_force = configured
        self.set_by: SetBy | None = None
        self.unreadable = ""  # why the file could not be read: motion refused meanwhile
        self._lock = threading.Lock()
        self._load()

    def _load(self) -> None:
        if self.path is None or not self.path.exists():
            return
        try:
            data = json.loads(self.path.read_text())
            lo, hi = data["min"], data["max"]
            by = SetBy(str(data["by"]), int(data["at_ns"]))
            if not (_angles(lo) and _angles(hi)):
                raise ValueError("min and max must be six whole degrees each")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self.unreadable = f"{self.path}: {exc}"
            log.error("operator_limits_unreadable", path=str(self.path), error=str(exc))
            return
        # The stricter of the file and the config, joint by joint: a config narrowed since
        # the operator sent theirs wins where it is stricter.
        cfg = self.configured
        lo = [max(a, b) for a, b in zip(lo, cfg.min_angles, strict=True)]
        hi = [min(a, b) for a, b in zip(hi, cfg.max_angles, strict=True)]
        try:
            self.in_force = cfg.narrowed(lo, hi)
        except ValueError as exc:
            self.unreadable = f"{self.path}: no longer fits the config ({exc})"
            log.error("operator_limits_unreadable", path=str(self.path), error=str(exc))
            return
        self.set_by = by
        log.info("operator_limits_restored", min=lo, max=hi, by=by.login, at_ns=by.at_ns)

    def check(self) -> str | None:
        """Why no motion may start now (None: limits are known)."""
        if self.unreadable:
            return (
                f"the operator's joint limits could not be read ({self.unreadable}): send them "
                "again (`exolink send limits --min ... --max ...`, or `--reset` for the config's)"
            )
        return None

    def set(self, lo: list[int] | None, hi: list[int] | None, login: str) -> Limits:
        """An operator's accepted angles (None: that side as in force now; both None: back to
        the config's), written to the state file first; IntentRefused names what is wrong."""
        with self._lock:
            if lo is None and hi is None:
                new, by = self.configured, None
            else:
                cur = self.in_force if not self.unreadable else self.configured
                lo = list(cur.min_angles) if lo is None else lo
                hi = list(cur.max_angles) if hi is None else hi
                try:
                    new = self.configured.narrowed(lo, hi)
                except ValueError as exc:
                    raise IntentRefused(str(exc)) from None
                by = SetBy(login, time.time_ns())
            self._write(new, by)
            self.in_force, self.set_by, self.unreadable = new, by, ""
        log.warning(
            "operator_limits_set", min=list(new.min_angles), max=list(new.max_angles), by=login
        )
        return new

    def _write(self, new: Limits, by: SetBy | None) -> None:
        """Atomically (a crash leaves the old file or the new, never half of one); refused
        when it cannot be written: a limit that would not survive a restart is not taken."""
        if self.path is None:
            return
        try:
            if by is None:
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
                return
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            body = {
                "min": list(new.min_angles),
                "max": list(new.max_angles),
                "by": by.login,
                "at_ns": by.at_ns,
            }
            with open(tmp, "w") as f:
                f.write(json.dumps(body))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except OSError as exc:
            raise IntentRefused(
                f"the limits cannot be kept ({self.path}: {exc.strerror or exc}): not applied"
            ) from None

    def describe(self) -> LimitsInfo:
        lim = self.in_force
        return LimitsInfo(
            joints={j: JointLimits(**v) for j, v in lim.describe().items()},
            max_step_deg=lim.max_step_deg,
            set_by=None if self.set_by is None else self.set_by.login,
            set_at_ns=None if self.set_by is None else self.set_by.at_ns,
            source="config" if self.set_by is None else "operator",
            unreadable=self.unreadable or None,
        )


def _angles(v: Any) -> bool:
    return (
        isinstance(v, list)
        and len(v) == len(h2.JOINTS)
        and all(isinstance(x, int) and not isinstance(x, bool) for x in v)
    )


@dataclass
class Holder:
    id: str
    login: str
    what: str
    since_ns: int
    renewed: float  # monotonic

    def describe(self, now: float) -> HolderInfo:
        return HolderInfo(self.login, self.what, self.since_ns, round(now - self.renewed, 3))


class Presence:
    """Who holds motion now (one holder), and when that holder is lost."""

    def __init__(self, lost_s: float) -> None:
        self.lost_s = lost_s
        self.holder: Holder | None = None
        self.taken_from: dict[str, str] = {}  # a replaced holder's id -> who took over
        self.losses = 0
        self._lock = threading.Lock()

    def hold(self, hid: Any, login: str, what: Any, take_over: bool) -> tuple[HolderInfo, bool]:
        """Take or renew the hold (the holder, and whether it was a renewal); IntentRefused when another holds it (unless ``take_over``)
        or when this holder was replaced (it is told by whom)."""
        if not isinstance(hid, str) or not 8 <= len(hid) <= HOLDER_ID_CHARS:
            raise IntentRefused(f"holder must be an id of 8..{HOLDER_ID_CHARS} characters")
        text = str(what or "")[:MAX_WHAT]
        now = time.monotonic()
        with self._lock:
            if (by := self.taken_from.get(hid)) is not None and not take_over:
                raise IntentRefused(f"motion was taken over by {by}")
            h = self.holder
            if h is not None and h.id == hid:
                h.renewed = now
                return h.describe(now), True
            if h is not None and now - h.renewed <= self.lost_s and not take_over:
                raise IntentRefused(
                    f"motion is held by {_who(h)}: stop it there, or take over "
                    "(`--take-over`; it is told)"
                )
            if h is not None:
                self.taken_from[h.id] = f"{login} ({text})" if text else login
                while len(self.taken_from) > MAX_TAKEN:  # the oldest replaced holders forgotten
                    del self.taken_from[next(iter(self.taken_from))]
                log.warning("presence_taken_over", old=_who(h), new=login, what=text)
            self.taken_from.pop(hid, None)
            self.holder = Holder(hid, login, text, time.time_ns(), now)
            log.info("presence_held", login=login, what=text)
            return self.holder.describe(now), False

    def release(self, hid: Any) -> bool:
        """True when ``hid`` held motion (it no longer does)."""
        with self._lock:
            if isinstance(hid, str):
                self.taken_from.pop(hid, None)
            if self.holder is not None and self.holder.id == hid:
                log.info("presence_released", login=self.holder.login, what=self.holder.what)
                self.holder = None
                return True
            return False

    def check(self) -> str | None:
        """Why no motion may start now (None: someone holds it)."""
        with self._lock:
            h = self.holder
            if h is not None and time.monotonic() - h.renewed <= self.lost_s:
                return None
        return (
            "nobody holds motion: keep `exolink hold` (or an attached `exolink pattern start`, "
            "or the dashboard) running on the operator's laptop"
        )

    def lapsed(self) -> Holder | None:
        """The holder whose keep-alive ran out, now forgotten (None: none did)."""
        with self._lock:
            h = self.holder
            if h is None or time.monotonic() - h.renewed <= self.lost_s:
                return None
            self.holder = None
            self.losses += 1
            return h

    def describe(self) -> PresenceInfo:
        with self._lock:
            h = self.holder
            return PresenceInfo(
                None if h is None else h.describe(time.monotonic()), self.lost_s, self.losses
            )


def _who(h: Holder) -> str:
    return f"{h.login} ({h.what})" if h.what else h.login
