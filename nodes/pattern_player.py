"""Gait pattern player [thesis: H2patternSender, patternSenderUi]: position set-points (id 70,
type 1) for the selected joints, one row of the pattern per period.

Speed levels: period = 20 ms x (11 - level), so level 10 sends a set-point every 20 ms (about one
51-point step per second, the thesis' fastest) and level 1 every 200 ms.

Timing modes:
- ``thread`` (default): absolute deadlines (deadline k = t0 + k x period, so errors never
  accumulate), ``time.sleep`` to just before the deadline and a short spin for the rest; run it
  with SCHED_FIFO priority (config ``priority: {fifo: N}``) on the board.
- ``periodic``: python-can ``send_periodic``; on SocketCAN that is the kernel's broadcast manager,
  which then does the timing. BCM sends one sequence of frames sharing one id round-robin, so the
  selected joints' frames are spread evenly over the period and a sequence may hold at most 256
  frames (the kernel's limit). A BCM task keeps running in the kernel while its process is alive
  even if the process hangs: the supervisor therefore SIGKILLs a node whose heartbeat is late,
  which closes the socket and ends the task.

- ``manager``: the controller manager plays the pattern as its ``gait_pattern`` controller named
  ``pattern`` (one writer per joint: an operator's ``send position`` to a joint the pattern
  drives is refused with the owner named). This node keeps the CLI, the selection and the state
  it publishes; it writes no set-point and reads no bus: the manager stops the pattern itself
  (a trip, a disable or stop below, a failing controller) and this node's state follows it.

Nothing is sent while no joint is selected or while the watchdog is not armed; a trip stops the
pattern (it does not resume by itself).

In thread and periodic timing the player also watches the bus for a disable or stop (type 4/5) of
a joint it drives, from any sender: the watchdog's safe action, ``exolink send disable``, a hand-held stop. Its next set-point
would switch that joint back on, so the pattern stops at once. It is also the fast path for a trip:
the safe action is on the bus before the trip's state reaches Zenoh, and in periodic mode the
kernel keeps sending until this process deletes its task. The Zenoh arming state stays the path
that refuses a start.
"""

from __future__ import annotations

import csv
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import can
import msgspec
from exolink import cdr, roles
from exolink.arming import ArmingState
from exolink.canbus import FrameReader, open_bus, open_reader
from exolink.controller import ACTIVITY_TOPIC, ACTIVITY_TYPE
from exolink.messaging import CommandRefused
from exolink.node import Node
from exolink.protocol import ProtocolError, h2

DEFAULT_PATTERN = Path(__file__).with_name("patterns") / "normal_walking.csv"
STATE_TYPE = "exolink_msgs/msg/PatternState"
MAX_POINTS = 10_000
BCM_MAX_FRAMES = 256
SPIN_S = 0.0003
MAX_UPLOAD = 1 << 20
WHOLE = re.compile(r"[+-]?[0-9]+")  # ASCII: int() also takes other scripts' digits
GAIT = "pattern"  # the controller the manager runs the gait as (timing: manager)
MANAGER_WAIT_S = 2.0  # a switch waits up to 1 s for an H2 cycle
# Starting the gait: the manager loads it and waits for a cycle to activate it at. On the board
# proxy the first start outran 2 s (imports and a cold reader on a full core). The manager is
# told to give up ENGAGE_MARGIN_S before this node does, so it never starts a pattern this node
# has already reported as failed.
ENGAGE_WAIT_S = 5.0
ENGAGE_MARGIN_S = 1.0
# timing: manager: the manager stops a running pattern's controller itself (a trip, a disable on
# the bus, a failure) and says so on controllers/activity; this node looks the controller up then,
# and at least this often in case that message was lost.
MANAGER_POLL_S = 2.0
# ... and at most this often: anyone who reaches an open appliance can publish on that topic, and
# a flood of it must not become a flood of questions to the manager (the old poll's rate)
ACTIVITY_GAP_S = 0.2
GONE = ("is not active", "no controller")  # a deactivation that finds the gait stopped: done
# A motion node (timing thread or periodic): its loop beats at least this often, running or
# idle, so the supervisor can hold it to a short liveness deadline (heartbeat_deadline_ms: 50).
BEAT_S = 0.02
# timing: manager: the manager writes the set-points and stops them; this node only answers
# commands and follows the manager's state, so it is not a motion node: its loop wakes this
# often (the 5 ms and 20 ms wake-ups of a motion node were 70-300 of the board's wake-ups a
# second, ~0.9 ms of the proxy's CPU each; 10/s still ~1 %) and keeps the default liveness
# deadline. What it checks then (the watchdog's word, for its display) the manager checks
# itself every cycle.
MANAGER_BEAT_S = 0.25
SAFE_MODES = {h2.MODES["disabled"], h2.MODES["stopped"]}


def period_s(level: int) -> float:
    return 0.020 * (11 - level)


class PlayerParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    pattern: str = str(DEFAULT_PATTERN)
    # `pattern load NAME` reads only files in here (or content the operator uploads).
    patterns_dir: str = str(DEFAULT_PATTERN.parent)
    speed: Annotated[int, msgspec.Meta(ge=1, le=10)] = 5
    selected: list[Literal["r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"]] = []
    timing: Literal["thread", "periodic", "manager"] = "thread"
    min_angles: Annotated[list[int], msgspec.Meta(min_length=6, max_length=6)] = msgspec.field(
        default_factory=lambda: [h2.RANGES[j][0] for j in h2.JOINTS]
    )
    max_angles: Annotated[list[int], msgspec.Meta(min_length=6, max_length=6)] = msgspec.field(
        default_factory=lambda: [h2.RANGES[j][1] for j in h2.JOINTS]
    )
    require_armed: bool = True


@dataclass(frozen=True)
class Pattern:
    """Validated set-points and their frames, built once at load (the tick only sends)."""

    file: str
    points: list[list[int]]  # [row][joint index 0..5]
    frames: list[list[can.Message]]  # [row][joint index]


def load_pattern(path: str, min_angles: list[int], max_angles: list[int]) -> Pattern:
    """A pattern file the board's own config names (the start-up pattern)."""
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ProtocolError(f"{path}: cannot read pattern: {exc.strerror or exc}") from None
    return parse_pattern(text, path, min_angles, max_angles)


def pattern_in(directory: str, name: str) -> str:
    """A file name inside the patterns directory; anything else (a path out of it, a link out of
    it) is refused: a network request must not make the board read /etc/shadow."""
    base = Path(directory).resolve()
    if not name or "/" in name or name in (".", ".."):
        raise ProtocolError(f"pattern name {name!r}: give a file name in {base}, not a path")
    target = (base / name).resolve()
    if target.parent != base or not target.is_file():
        raise ProtocolError(f"no pattern {name!r} in {base}")
    return str(target)


def parse_pattern(text: str, source: str, min_angles: list[int], max_angles: list[int]) -> Pattern:
    """CSV with a header of joint names (all six), one row per set-point, whole degrees.
    Errors name the line and what is wrong; a file that may not be a pattern (no six-joint
    header) never has its content shown, a pattern's bad value is (its first 16 characters)."""
    path = source
    # A byte-order mark (a spreadsheet's "CSV UTF-8") is not part of the first joint's name.
    rows = list(csv.reader(text.removeprefix("\ufeff").splitlines()))
    if not rows:
        raise ProtocolError(f"{path}: empty pattern file")
    header = [c.strip() for c in rows[0]]
    if sorted(header) != sorted(h2.JOINTS):
        raise ProtocolError(f"{path}:1: header must name the six joints {', '.join(h2.JOINTS)}")
    order = [header.index(j) for j in h2.JOINTS]
    body = [r for r in rows[1:] if any(c.strip() for c in r)]
    if not 2 <= len(body) <= MAX_POINTS:
        raise ProtocolError(f"{path}: a pattern needs 2..{MAX_POINTS} set-points, got {len(body)}")
    points, frames = [], []
    for n, row in enumerate(body, start=2):
        if len(row) != 6:
            raise ProtocolError(f"{path}:{n}: expected 6 values, got {len(row)}")
        cells = [row[i].strip() for i in order]
        for j, cell in enumerate(cells):
            if not WHOLE.fullmatch(cell):
                ascii_only = "" if cell.isascii() else " in ASCII digits"
                raise ProtocolError(
                    f"{path}:{n}: values must be whole degrees{ascii_only} "
                    f"({h2.JOINTS[j]} {cell[:16]!r})"
                )
        vals = [int(c) for c in cells]
        for j, v in enumerate(vals):
            if not min_angles[j] <= v <= max_angles[j]:
                raise ProtocolError(
                    f"{path}:{n}: {h2.JOINTS[j]} {v} deg is outside the limits {min_angles[j]}..{max_angles[j]}"
                )
        try:
            frames.append(
                [h2.encode_joint_control(j + 1, "position", v) for j, v in enumerate(vals)]
            )
        except ProtocolError as exc:
            raise ProtocolError(f"{path}:{n}: {exc}") from None
        points.append(vals)
    return Pattern(source, points, frames)


class PatternPlayer(Node):
    Params = PlayerParams
    stall_s = 2 * BEAT_S  # the heartbeat thread must not vouch for a loop hung longer than this

    def configure(self) -> None:
        p = self.params
        self.pattern = load_pattern(p.pattern, p.min_angles, p.max_angles)
        self.bus = self.own(open_bus(self.ctx.config.can, filters=[]))  # sends only; _watch_bus
        self.watch: FrameReader | None = None
        self.arming = self.own(ArmingState(self.ctx.messaging)) if p.require_armed else None
        self.lock = threading.RLock()
        self.wake = threading.Event()
        self.state, self.reason, self.index = "stopped", "", 0
        self.speed = p.speed
        self.selected = [j in p.selected for j in h2.JOINTS]
        self.operator = ""
        self.timing = p.timing
        if self.timing == "manager":
            self.stall_s = 3 * MANAGER_BEAT_S
        self.task: Any = None
        self._op: tuple[Any, ...] | None = None  # what to ask the manager (timing: manager)
        self._engaged = 0  # the manager accepted the running pattern: which start (0: none)
        self._starts = 0
        self._periodic_t0, self._periodic_i0 = time.monotonic(), 0
        self.sent = 0
        self.pub = self.own(self.ctx.messaging.publisher("pattern_state", STATE_TYPE, raw=True))
        self._activity = threading.Event()  # the manager changed a controller's state
        self._disengage_due = False  # stopped here without the manager knowing: tell it
        if self.timing == "manager":
            self.own(
                self.ctx.messaging.subscribe_raw(
                    ACTIVITY_TOPIC, ACTIVITY_TYPE, lambda _payload: self._activity.set()
                )
            )
        self.own(
            self.ctx.messaging.serve("pattern", self.on_command, roles.status_or(roles.OPERATOR))
        )

    # --- commands -------------------------------------------------------------------------

    def on_command(self, req: dict[str, Any]) -> dict[str, Any]:
        action = req.get("action", "status")
        handler = {
            "start": self._start,
            "stop": self._stop,
            "pause": self._pause,
            "restart": self._restart,
            "speed": self._speed,
            "select": self._select,
            "disable": self._disable,
            "load": self._load,
            "status": lambda _r: None,
        }.get(action)
        if handler is None:
            raise CommandRefused(
                f"unknown pattern action {action!r} (start, stop, pause, restart, speed, select, disable, load, status)"
            )
        with self.lock:
            handler(req)
            op, self._op = self._op, None
            self.wake.set()
        if op is not None:  # outside the lock: the loop must keep beating while the manager works
            try:
                self._manager(op)
                with self.lock:
                    if self.state == "running" and not self._engaged:
                        self._starts += 1
                        self._engaged = self._starts
            except CommandRefused as exc:
                with self.lock:
                    self._halt("stopped", str(exc), tell_manager=False)
                self._publish()
                raise
        with self.lock:
            status = self.status()
        self._publish()
        self.log.info("pattern_command", action=action, state=status["state"])
        return status

    def status(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "reason": self.reason,
            "index": self.index,
            "length": len(self.pattern.points),
            "speed": self.speed,
            "period_ms": round(period_s(self.speed) * 1000, 3),
            "selected": [j for j, s in zip(h2.JOINTS, self.selected, strict=True) if s],
            "file": self.pattern.file,
            "timing": self.timing,
            "sent": self.sent,
            "operator": self.operator,
            "watchdog_word": self.arming.counters() if self.arming is not None else None,
        }

    def _start(self, req: dict[str, Any]) -> None:
        if not any(self.selected):
            raise CommandRefused(
                "no joint selected: select joints first (pattern select r_hip r_knee ...)"
            )
        if self.arming is not None and (why := self.arming.check()):
            raise CommandRefused(why)
        if self.timing == "periodic":
            n = sum(self.selected) * len(self.pattern.points)
            if n > BCM_MAX_FRAMES:
                raise CommandRefused(
                    f"periodic timing needs {n} frames in one sequence; the broadcast manager takes at most "
                    f"{BCM_MAX_FRAMES}: select fewer joints or use timing 'thread'"
                )
        self.operator = str(req.get("operator", ""))
        if self.watch is None and self.timing != "manager":
            # before the first set-point: no stop frame can slip past (the manager watches the
            # bus for the pattern it plays, see _follow_manager)
            self.watch = open_reader(self.ctx.config.can, [h2.JOINT_CONTROL])
        self.state, self.reason = "running", ""
        self._start_periodic()

    def _halt(self, state: str, reason: str = "", tell_manager: bool = True) -> None:
        """``tell_manager`` False where the manager stops the gait itself (a trip, a disable
        frame on the bus) or never started it."""
        if self.task is not None:
            self.task.stop()
            self.task = None
        if self.timing == "manager" and tell_manager and self.state == "running":
            self._op = ("halt",)
        self.state, self.reason, self._engaged = state, reason, 0

    def _stop(self, _req: dict[str, Any]) -> None:
        self._halt("stopped")
        self.index, self.operator = 0, ""

    def _pause(self, _req: dict[str, Any]) -> None:
        if self.state != "running":
            raise CommandRefused(f"cannot pause: pattern is {self.state}")
        self._halt("paused")

    def _restart(self, _req: dict[str, Any]) -> None:
        self.index = 0
        if self.state == "running":
            self._start_periodic()
            if self.timing == "manager":
                self._op = ("command", {"index": 0})

    def _speed(self, req: dict[str, Any]) -> None:
        level = req.get("speed")
        if isinstance(level, bool) or not isinstance(level, int) or not 1 <= level <= 10:
            raise CommandRefused(f"speed must be a whole level 1..10, got {level!r}")
        self.speed = level
        if self.state == "running":
            self._start_periodic()
            if self.timing == "manager":
                self._op = ("command", {"speed": level})

    def _joints(self, req: dict[str, Any]) -> list[int]:
        names = req.get("joints")
        if not isinstance(names, list) or not names:
            raise CommandRefused(
                "give one or more joints (r_hip r_knee r_ankle l_hip l_knee l_ankle)"
            )
        try:
            return [h2.motor_id(n) - 1 for n in names]
        except ProtocolError as exc:
            raise CommandRefused(str(exc)) from None

    def _select(self, req: dict[str, Any]) -> None:
        if self.state != "stopped":
            raise CommandRefused(
                f"stop the pattern before changing the selection (it is {self.state})"
            )
        idx = self._joints(req)
        self.selected = [i in idx for i in range(6)]

    def _disable(self, req: dict[str, Any]) -> None:
        """Type 4 for these joints now, and the pattern stops driving them (safe at any time)."""
        idx = self._joints(req)
        for i in idx:
            self.selected[i] = False  # first: our own frame must not look like someone else's
            self.bus.send(h2.encode_joint_control(i + 1, "disabled"))
        if self.state == "running":
            if any(self.selected):
                self._start_periodic()
            else:
                self._halt("stopped", "all driven joints disabled")

    def _load(self, req: dict[str, Any]) -> None:
        if self.state != "stopped":
            raise CommandRefused(f"stop the pattern before loading another (it is {self.state})")
        p = self.params
        try:
            if "content" in req:  # uploaded by the operator's CLI from the laptop
                content, name = req["content"], str(req.get("name", "uploaded"))
                if not isinstance(content, str) or len(content) > MAX_UPLOAD:
                    raise ProtocolError(f"{name}: content must be CSV text under {MAX_UPLOAD} B")
                self.pattern = parse_pattern(content, name, p.min_angles, p.max_angles)
            else:
                path = pattern_in(p.patterns_dir, str(req.get("file", "")))
                self.pattern = load_pattern(path, p.min_angles, p.max_angles)
        except ProtocolError as exc:
            raise CommandRefused(str(exc)) from None
        self.index = 0

    # --- sending --------------------------------------------------------------------------

    def _row_frames(self, index: int) -> list[can.Message]:
        row = self.pattern.frames[index]
        return [row[j] for j in range(6) if self.selected[j]]

    def _start_periodic(self) -> None:
        """periodic mode: hand the whole sequence (from the current row) to python-can / the kernel;
        manager mode: to the controller manager."""
        if self.timing == "manager":
            self._op = ("engage",)
            self._engaged = 0  # until the manager has it: what it says meanwhile is of the last
            self._periodic_t0, self._periodic_i0 = time.monotonic(), self.index
            return
        if self.timing != "periodic":
            return
        if self.task is not None:
            self.task.stop()
        n = len(self.pattern.points)
        seq = [f for k in range(n) for f in self._row_frames((self.index + k) % n)]
        per_frame = period_s(self.speed) / sum(self.selected)
        self.task = self.bus.send_periodic(seq, per_frame)
        self._periodic_t0, self._periodic_i0 = time.monotonic(), self.index

    def _tick(self) -> None:
        frames = self._row_frames(self.index)
        for f in frames:
            self.bus.send(f)
        self.sent += len(frames)
        self.index = (self.index + 1) % len(self.pattern.points)

    def _manager(self, op: tuple[Any, ...]) -> None:
        """One change of the gait controller in the manager; its refusal (a joint another
        controller drives, not armed) refuses the command that asked for it."""

        def call(
            body: dict[str, Any], tolerate: tuple[str, ...] = (), wait: float = MANAGER_WAIT_S
        ) -> None:
            self.ctx.messaging.command("controllers", body=body, timeout_s=wait, tolerate=tolerate)

        if op[0] == "halt":
            self._deactivate()
        elif op[0] == "command":
            call({"action": "command", "name": GAIT, **op[1]})
        else:
            with self.lock:
                params = {
                    "rows": self.pattern.points,
                    "joints": [j for j, s in zip(h2.JOINTS, self.selected, strict=True) if s],
                    "speed": self.speed,
                    "start": self.index,
                }
            load = {"action": "load", "name": GAIT, "type": "gait_pattern", "params": params}
            within = ENGAGE_WAIT_S - ENGAGE_MARGIN_S
            try:
                call(
                    {**load, "replace": True, "activate": True, "within_s": within},
                    (),
                    ENGAGE_WAIT_S,
                )
            except CommandRefused as exc:
                if str(exc).startswith("nothing answers"):  # its answer may be what was lost
                    self._disengage()
                raise

    def _deactivate(self) -> None:
        """The gait's deactivation in the manager; one that finds it stopped counts as done."""
        self.ctx.messaging.command(
            "controllers",
            body={"action": "deactivate", "names": [GAIT]},
            timeout_s=MANAGER_WAIT_S,
            tolerate=GONE,
        )

    def _disengage(self) -> None:
        """``_deactivate`` where nobody waits for its answer (logged instead): after a start
        that got no answer (the manager handles requests in order, so this comes after whatever
        the start did) or a stop this node made on its own."""
        try:
            self._deactivate()
        except CommandRefused as exc:
            self.log.error("pattern_disengage_unanswered", error=str(exc))

    def _guard(self) -> bool:
        """False (and the pattern stopped) when the watchdog no longer allows motion."""
        if self.arming is None:
            return True
        why = self.arming.check()
        if why is None:
            return True
        with self.lock:
            if self.state == "running":
                self._halt("stopped", why, tell_manager=False)  # a trip stops every controller
                self.log.warning("pattern_stopped_by_watchdog", reason=why)
                # ... but not every reason here is a trip: "no word from the watchdog" is this
                # node's own view (the board proxy saw it while the watchdog stayed armed). So
                # the manager is always told (after a trip it finds the gait stopped already),
                # by the follower thread: this loop must keep beating while the manager answers
                self._disengage_due = self.timing == "manager"
        if self._disengage_due:
            self._activity.set()
        self._publish()
        return False

    def _watch_bus(self, stop: threading.Event) -> None:
        """A type 4/5 frame for a driven joint stops the pattern (see the module docstring).

        Only while the pattern runs or is paused: id 70 also carries MACCEPA board 0's 100 Hz
        controller frames, and reading them with nothing to stop cost the idle player 14 % of
        the board proxy's CPU 0. ``_start`` opens the socket before the first set-point; this
        thread, its only reader, closes it once the pattern is stopped."""
        if self.timing == "manager":
            self._follow_manager(stop)
            return
        while not stop.is_set():
            with self.lock:
                reader = self.watch
                if reader is not None and self.state == "stopped":
                    self.watch = None
                    reader.close()
                    reader = None
            if reader is None:
                stop.wait(0.1)
                continue
            try:
                frames = reader.read(0.1)
            except (can.CanError, OSError) as exc:
                self.log.error("bus_watch_error", error=str(exc))
                stop.wait(0.1)
                continue
            for msg in frames:
                self._on_joint_control(h2.decode(msg))

    def _follow_manager(self, stop: threading.Event) -> None:
        """timing: manager: the manager plays the pattern and stops it itself (a trip, a disable
        or stop frame for one of its joints from anyone, a failure), so this node does not read
        the bus (id 70 then carries the manager's 100 Hz set-points: ~500 frames/s to decode for
        a display); it asks the manager whether the pattern still runs when the manager says a
        controller changed (``controllers/activity``: anyone may publish there, so it only
        prompts the question, never answers it), and every MANAGER_POLL_S in case that message
        was lost."""
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
                self._halt("stopped", why, tell_manager=False)
            self.log.warning("pattern_stopped_by_manager", reason=why)
            self._publish()

    def _manager_stopped(self) -> str | None:
        """Why the manager no longer runs the pattern (None: it does, or it did not answer:
        the pattern's safety is the manager's and the watchdog's, not this display's)."""
        try:
            gait = self.ctx.messaging.command(
                "controllers", body={"action": "state", "name": GAIT}, timeout_s=MANAGER_WAIT_S
            )
        except CommandRefused as exc:
            self.log.warning("manager_status_unavailable", error=str(exc))
            return None
        if gait.get("state") is None:
            return "the controller manager no longer has the pattern"
        if gait.get("state") == "active":
            return None
        return str(gait.get("error") or f"the pattern's controller is {gait.get('state')}")

    def _on_joint_control(self, frame: object) -> None:
        if not isinstance(frame, h2.JointControl) or frame.mode not in SAFE_MODES:
            return
        with self.lock:
            joint = frame.motor - 1
            if self.state == "stopped" or not 0 <= joint < 6 or not self.selected[joint]:
                return
            why = f"{h2.JOINTS[joint]} {h2.MODE_NAMES[frame.mode]} by a frame on the bus"
            self._halt("stopped", why, tell_manager=False)  # the manager saw the frame too
        self.log.warning("pattern_stopped_by_bus", reason=why)
        self._publish()

    def run(self, stop: threading.Event) -> None:
        watch = threading.Thread(target=self._watch_bus, args=(stop,), daemon=True, name="watch")
        watch.start()
        try:
            self._play(stop)
        finally:
            self._activity.set()  # the manager follower looks at `stop` now
            watch.join(1)

    def _play(self, stop: threading.Event) -> None:
        next_t = time.monotonic()
        last_state = 0.0
        while not stop.is_set():
            self.beat()
            now = time.monotonic()
            if now - last_state >= 1.0:
                last_state = now
                self._publish()
            with self.lock:
                running, period, mode = self.state == "running", period_s(self.speed), self.timing
            if not running or mode != "thread":
                if running:
                    self._guard()
                    self._track_periodic_index()
                if self.wake.wait(self._idle_wait(running, mode)):
                    self.wake.clear()
                next_t = time.monotonic()
                continue
            if self.wake.is_set():  # a command changed speed or position: re-anchor the schedule
                self.wake.clear()
                next_t = max(next_t, time.monotonic())
            while (delay := next_t - time.monotonic()) > SPIN_S:  # slow speeds: 200 ms periods
                time.sleep(min(delay - SPIN_S, BEAT_S))
                self.beat()
            while time.monotonic() < next_t:
                pass
            if not self._guard():
                continue
            with self.lock:
                if self.state == "running":
                    self._tick()
            next_t += period
            if time.monotonic() - next_t > 5 * period:  # stalled far behind: resync, do not burst
                next_t = time.monotonic() + period

    @staticmethod
    def _idle_wait(running: bool, mode: str) -> float:
        """Between looks when no set-point is due here: periodic timing tracks the kernel's
        broadcast manager every 5 ms; manager timing has nothing due here at all."""
        if mode == "manager":
            return MANAGER_BEAT_S
        return 0.005 if running else BEAT_S

    def _track_periodic_index(self) -> None:
        with self.lock:
            if self.task is None and self.timing != "manager":
                return
            elapsed = time.monotonic() - self._periodic_t0
            rows = int(elapsed / period_s(self.speed))
            self.index = (self._periodic_i0 + rows) % len(self.pattern.points)

    def _publish(self) -> None:
        with self.lock:
            s = self.status()
        now = time.time_ns()
        self.pub.put(cdr.pattern_state(now, s, self.selected), now)

    def shutdown(self) -> None:
        with self.lock:
            if self.task is not None:
                self.task.stop()
            if self.watch is not None:  # opened per start, not owned
                self.watch.close()
