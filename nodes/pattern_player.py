"""Gait pattern player [thesis: H2patternSender, patternSenderUi]: the pattern, its joints, speed
and state; the controller manager plays it.

Speed levels: period = 20 ms x (11 - level), so level 10 is a row every 20 ms (about one
51-point step per second, the thesis' fastest) and level 1 every 200 ms.

The manager runs the pattern as its ``gait_pattern`` controller named ``pattern`` (one writer
per joint: an operator's ``send position`` to a joint the pattern drives is refused with the
owner named; an operator's own one-off hold on a joint is taken over). It checks the whole
sequence against the limits in force before any of it is written, and stops it itself (a trip,
a disable or stop on the bus, the operator holding motion lost, a failing controller); this
node writes nothing and reads no bus: it keeps the CLI, the selection and the state it
publishes, and follows the manager's ``controllers/activity``.

Nothing starts while no joint is selected, while the watchdog is not armed, or while nobody
holds motion (``exolink hold``; the CLI's attached ``pattern start`` holds it); a trip stops the
pattern (it does not resume by itself).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from exolink import roles
from exolink.control import replies, requests
from exolink.control.arming import ArmingState
from exolink.control.controller import ACTIVITY_TOPIC, ACTIVITY_TYPE
from exolink.control.gait import period_s
from exolink.control.patterns import load_pattern, parse_pattern, pattern_in
from exolink.loops import Every
from exolink.messaging import Caller, Refused
from exolink.node import Node
from exolink.protocol import ProtocolError, h2
from exolink.wire import cdr
from exolink.wire.requests import with_default

DEFAULT_PATTERN = Path(__file__).with_name("patterns") / "normal_walking.csv"
STATE_TYPE = "exolink_msgs/msg/PatternState"
MAX_UPLOAD = 1 << 20
GAIT = "pattern"  # the controller the manager runs the gait as
MANAGER_WAIT_S = 2.0  # a switch waits up to 1 s for an H2 cycle
# Starting the gait: the manager loads it and waits for a cycle to activate it at. On the board
# proxy the first start outran 2 s (imports and a cold reader on a full core). The manager is
# told to give up ENGAGE_MARGIN_S before this node does, so it never starts a pattern this node
# has already reported as failed.
ENGAGE_WAIT_S = 5.0
ENGAGE_MARGIN_S = 1.0
# The gait's CPU budget per update in the manager: its update is a few look-ups per joint
# (docs/performance.md), but its first updates are slower on a slow CPU (under qemu: code the
# emulator translates then), and two over the default 2 ms in a row stop the gait at its start. Still well inside
# the board's 20 ms update period; a lab's own controllers keep the manager's default.
GAIT_BUDGET_MS = 8.0
# The manager stops a running pattern's controller itself (a trip, a disable on the bus, the
# holder lost, a failure) and says so on controllers/activity; this node looks the controller up
# then, and at least this often in case that message was lost ...
MANAGER_POLL_S = 2.0
# ... and at most this often: anyone who reaches an open appliance can publish on that topic, and
# a flood of it must not become a flood of questions to the manager.
ACTIVITY_GAP_S = 0.2
GONE = ("is not active", "no controller")  # a deactivation that finds the gait stopped: done
# The loop only answers nothing and publishes the state: it wakes this often (the motion is the
# manager's) and keeps the default liveness deadline.
BEAT_S = 0.25
STATE_EVERY = 4  # beats: the state goes out once a second, and at every change
Joint = Literal["r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"]


class PlayerParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    pattern: str = str(DEFAULT_PATTERN)
    # `pattern load NAME` reads only files in here (or content the operator uploads).
    patterns_dir: str = str(DEFAULT_PATTERN.parent)
    speed: Annotated[int, msgspec.Meta(ge=1, le=10)] = 5
    selected: list[Joint] = []
    require_armed: bool = True


class PatternPlayer(Node):
    Params = PlayerParams
    stall_s = 3 * BEAT_S

    def configure(self) -> None:
        p = self.params
        self._beats = 0  # the loop's wakes: the state goes out every STATE_EVERY
        self.limits = self.ctx.config.joint_limits()
        self.pattern = load_pattern(p.pattern, self.limits)
        self.arming = self.own(ArmingState(self.ctx.messaging)) if p.require_armed else None
        self.lock = threading.RLock()
        self.state, self.reason, self.index = "stopped", "", 0
        self.speed = p.speed
        self.selected = [j in p.selected for j in h2.JOINTS]
        self.operator = ""  # the login that started it
        self.sent = 0  # set-points the manager wrote for the pattern (as of its last answer)
        self._engaged = 0  # the manager accepted the running pattern: which start (0: none)
        self._starts = 0
        self._t0, self._i0 = time.monotonic(), 0  # where the pattern was when it (re)started
        self.pub = self.own(self.ctx.messaging.publisher("pattern_state", STATE_TYPE, raw=True))
        self._activity = threading.Event()  # the manager changed a controller's state
        self._disengage_due = False  # stopped here without the manager knowing: tell it
        self.own(
            self.ctx.messaging.subscribe_raw(
                ACTIVITY_TOPIC, ACTIVITY_TYPE, lambda _payload: self._activity.set()
            )
        )
        self.own(
            self.ctx.messaging.serve("pattern", self.on_command, roles.status_or(roles.OPERATOR))
        )

    # --- commands -------------------------------------------------------------------------

    def on_command(self, req: dict[str, Any], caller: Caller) -> replies.PatternInfo:
        cmd = requests.decode(with_default(req, "status"), requests.Pattern, "pattern action")
        action = requests.tag_of(cmd)
        handlers: dict[str, Callable[[Any, Caller], None]] = {
            "start": self._start,
            "stop": self._stop,
            "pause": self._pause,
            "restart": self._restart,
            "speed": self._speed,
            "select": self._select,
            "disable": self._disable,
            "load": self._load,
            "status": lambda _r, _c: None,
        }
        handlers[action](cmd, caller)
        with self.lock:
            status = self.status()
        self._publish()
        if action != "status":
            self.log.info("pattern_command", action=action, state=status.state)
        return status

    def status(self) -> replies.PatternInfo:
        self._track_index()
        return replies.PatternInfo(
            state=self.state,
            reason=self.reason,
            index=self.index,
            length=len(self.pattern.points),
            speed=self.speed,
            period_ms=round(period_s(self.speed) * 1000, 3),
            selected=[j for j, s in zip(h2.JOINTS, self.selected, strict=True) if s],
            file=self.pattern.file,
            sent=self.sent,
            operator=self.operator,
            watchdog_word=self.arming.counters() if self.arming is not None else None,
        )

    def _start(self, _req: Any, caller: Caller) -> None:
        with self.lock:
            if not any(self.selected):
                raise Refused(
                    "no joint selected: select joints first (pattern select r_hip r_knee ...)"
                )
            if self.arming is not None and (why := self.arming.check()):
                raise Refused(why)
            self.operator = caller.login
            self.state, self.reason = "running", ""
            self._t0, self._i0 = time.monotonic(), self.index
        self._engage()

    def _engage(self) -> None:
        """The gait to the manager, with what is selected, from the current row. Its refusal
        (not armed, nobody holding motion, a joint another controller drives, a row outside
        the limits in force) refuses the command that asked for it."""
        with self.lock:
            params = {
                "rows": self.pattern.points,
                "joints": [j for j, s in zip(h2.JOINTS, self.selected, strict=True) if s],
                "speed": self.speed,
                "start": self.index,
            }
            self._engaged = 0  # until the manager has it: what it says meanwhile is of the last
        body = requests.body(
            requests.Load(
                GAIT,
                "gait_pattern",
                params,
                activate=True,
                replace=True,
                budget_ms=GAIT_BUDGET_MS,
                within_s=ENGAGE_WAIT_S - ENGAGE_MARGIN_S,
            )
        )
        try:
            self.ctx.messaging.command("controllers", body=body, timeout_s=ENGAGE_WAIT_S)
        except Refused as exc:
            if str(exc).startswith("nothing answers"):  # its answer may be what was lost
                self._disengage()
            with self.lock:
                self._halt("stopped", str(exc))
            self._publish()
            raise
        with self.lock:
            if self.state == "running":
                self._starts += 1
                self._engaged = self._starts

    def _halt(self, state: str, reason: str = "") -> None:
        self._track_index()
        self.state, self.reason, self._engaged = state, reason, 0

    def _stop(self, _req: Any, _caller: Caller) -> None:
        with self.lock:
            was = self.state
            self._halt("stopped")
            self.index, self.operator = 0, ""
        if was == "running":
            self._deactivate()

    def _pause(self, _req: Any, _caller: Caller) -> None:
        with self.lock:
            if self.state != "running":
                raise Refused(f"cannot pause: pattern is {self.state}")
            self._halt("paused")
        self._deactivate()

    def _restart(self, _req: Any, _caller: Caller) -> None:
        with self.lock:
            self.index = 0
            running = self.state == "running"
            self._t0, self._i0 = time.monotonic(), 0
        if running:
            self._manager(_gait_command(index=0))

    def _speed(self, req: requests.PatternSpeed, _caller: Caller) -> None:
        level = req.speed
        if not 1 <= level <= 10:
            raise Refused(f"speed must be a whole level 1..10, got {level!r}")
        with self.lock:
            running = self.state == "running"
        if running:  # the manager checks the pattern's steps at the new speed first
            self._manager(_gait_command(speed=level))
        with self.lock:
            self._track_index()
            self._t0, self._i0 = time.monotonic(), self.index
            self.speed = level

    def _joints(self, req: requests.PatternSelect | requests.PatternDisable) -> list[int]:
        names = req.joints
        if not names:
            raise Refused("give one or more joints (r_hip r_knee r_ankle l_hip l_knee l_ankle)")
        try:
            return [h2.motor_id(n) - 1 for n in names]
        except ProtocolError as exc:
            raise Refused(str(exc)) from None

    def _select(self, req: requests.PatternSelect, _caller: Caller) -> None:
        with self.lock:
            if self.state != "stopped":
                raise Refused(
                    f"stop the pattern before changing the selection (it is {self.state})"
                )
            idx = self._joints(req)
            self.selected = [i in idx for i in range(6)]

    def _disable(self, req: requests.PatternDisable, _caller: Caller) -> None:
        """These joints disabled now (the manager sends type 4 and stops what drives them), and
        the pattern goes on with the others, if any."""
        idx = self._joints(req)
        with self.lock:
            for i in idx:
                self.selected[i] = False
            running = self.state == "running"
            # the manager stops the gait for this disable: its word on that is no stop of the
            # pattern's (the follower ignores what it says until _engage hands it the rest)
            self._engaged = 0
        for i in idx:
            body = requests.body(requests.Joint(h2.JOINTS[i], "disabled"))
            self.ctx.messaging.command("h2", "command", body=body, timeout_s=MANAGER_WAIT_S)
        if not running:
            return
        with self.lock:
            if not any(self.selected):
                self._halt("stopped", "all driven joints disabled")
                return
            self._track_index()
            self._t0, self._i0 = time.monotonic(), self.index
        self._engage()

    def _load(self, req: requests.PatternLoad, _caller: Caller) -> None:
        with self.lock:
            if self.state != "stopped":
                raise Refused(f"stop the pattern before loading another (it is {self.state})")
            p = self.params
            try:
                if req.content is not None:  # uploaded by the operator's CLI from the laptop
                    content, name = req.content, req.name
                    if len(content) > MAX_UPLOAD:
                        raise ProtocolError(
                            f"{name}: content must be CSV text under {MAX_UPLOAD} B"
                        )
                    self.pattern = parse_pattern(content, name, self.limits)
                else:
                    path = pattern_in(p.patterns_dir, req.file or "")
                    self.pattern = load_pattern(path, self.limits)
            except ProtocolError as exc:
                raise Refused(str(exc)) from None
            self.index = 0

    # --- the manager ----------------------------------------------------------------------

    def _manager(self, body: dict[str, Any], tolerate: tuple[str, ...] = ()) -> dict[str, Any]:
        return self.ctx.messaging.command(
            "controllers", body=body, timeout_s=MANAGER_WAIT_S, tolerate=tolerate
        )

    def _deactivate(self) -> None:
        """The gait's deactivation in the manager; one that finds it stopped counts as done."""
        self._manager(requests.body(requests.Deactivate([GAIT])), GONE)

    def _disengage(self) -> None:
        """``_deactivate`` where nobody waits for its answer (logged instead)."""
        try:
            self._deactivate()
        except Refused as exc:
            self.log.error("pattern_disengage_unanswered", error=str(exc))

    def _follow_manager(self, stop: threading.Event) -> None:
        """The manager plays the pattern and stops it itself, so this node asks whether the
        pattern still runs when the manager says a controller changed (``controllers/activity``:
        anyone may publish there, so it only prompts the question, never answers it), and every
        MANAGER_POLL_S in case that message was lost."""
        while not stop.wait(ACTIVITY_GAP_S):
            self._activity.wait(MANAGER_POLL_S - ACTIVITY_GAP_S)
            self._activity.clear()
            if stop.is_set():
                return
            if self._disengage_due:
                self._disengage_due = False
                self._disengage()
            with self.lock:
                engaged = self._engaged
            if not engaged:
                continue
            why = self._manager_stopped()
            if why is None:
                continue
            with self.lock:
                if self._engaged != engaged:  # stopped or restarted meanwhile: not the manager's
                    continue
                self._halt("stopped", why)
            self.log.warning("pattern_stopped_by_manager", reason=why)
            self._publish()

    def _manager_stopped(self) -> str | None:
        """Why the manager no longer runs the pattern (None: it does, or it did not answer:
        the pattern's safety is the manager's and the watchdog's, not this display's)."""
        try:
            gait = self._manager(requests.body(requests.ControllerState(GAIT)))
        except Refused as exc:
            self.log.warning("manager_status_unavailable", error=str(exc))
            return None
        try:
            now = replies.read(gait, replies.StateOf)
        except ValueError as exc:  # not the manager's answer: as if it did not answer
            self.log.warning("manager_status_unreadable", error=str(exc))
            return None
        if now.state is None:
            return "the controller manager no longer has the pattern"
        self.sent = now.written
        if now.state == "active":
            return None
        return now.error or f"the pattern's controller is {now.state}"

    # --- the loop -------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        follow = threading.Thread(
            target=self._follow_manager, args=(stop,), daemon=True, name="follow"
        )
        follow.start()
        try:
            Every(BEAT_S, self._tick).run(self.beat, stop)
        finally:
            self._activity.set()  # the follower looks at `stop` now
            follow.join(1)

    def _tick(self) -> None:
        self._guard()
        self._beats += 1
        if self._beats % STATE_EVERY == 0:
            self._publish()

    def _guard(self) -> None:
        """The watchdog no longer allows motion: the state says so at once (the manager has
        stopped the gait on the trip; it is told anyway, by the follower: "no word from the
        watchdog" may be this node's own view while the watchdog stayed armed)."""
        if self.arming is None or (why := self.arming.check()) is None:
            return
        with self.lock:
            if self.state != "running":
                return
            self._halt("stopped", why)
            self._disengage_due = True
        self.log.warning("pattern_stopped_by_watchdog", reason=why)
        self._activity.set()

    def _track_index(self) -> None:
        """Where the pattern is now (the manager plays it by the H2's clock; this is the
        display's estimate, from the time it started at the speed it has)."""
        if self.state != "running":
            return
        rows = int((time.monotonic() - self._t0) / period_s(self.speed))
        self.index = (self._i0 + rows) % len(self.pattern.points)

    def _publish(self) -> None:
        with self.lock:
            s = self.status()
        now = time.time_ns()
        self.pub.put(cdr.pattern_state(now, s, self.selected), now)


def _gait_command(**values: int) -> dict[str, Any]:
    """A command to the manager's gait controller (its own fields: ``speed``, ``index``)."""
    return {**requests.body(requests.ControllerCommand(GAIT)), **values}
