"""The controller manager's replies, one schema each: what its handlers build
(exolink.nodes.controller_manager.api) and what the CLI, the dashboard and the pattern player
read back (``read``).

A controller type's own words (its ``status`` and its answer to a ``command``) are that type's
schema, not the manager's: they travel whole in ``own`` and ``said``, never spread among the
manager's fields, where a plugin's ``state`` would have overwritten the manager's.
"""

from __future__ import annotations

from typing import Any

from exolink.wire.replies import UNSET, Reply, UnsetType, plain, read

__all__ = ["plain", "read"]


class Done(Reply):
    """A request that has nothing to report but that it was done (``unload``)."""


class ControllerInfo(Reply):
    """One loaded controller: its slot in the manager and what its type says of itself."""

    name: str
    type: str
    state: str  # inactive | active | stopped
    claims: list[str]
    error: str
    updates: int = 0
    update_ms_mean: float | None = None  # None: never updated
    update_ms_max: float = 0.0
    budget_ms: float = 0.0
    overruns: int = 0
    limited: int = 0  # set-points the limits or the step limit changed
    written: int = 0
    own: dict[str, Any] = {}  # the controller type's own status (Controller.status)


class Loaded(ControllerInfo):
    """A controller loaded, and what is active if it was activated with it."""

    active: list[str] | UnsetType = UNSET


class StateOf(Reply):
    """One controller's state and why it stopped: what the pattern player asks while it plays."""

    name: str
    state: str | None  # None: no such controller
    error: str
    written: int = 0


class Types(Reply):
    types: dict[str, str]  # type -> where its class lives (its entry point)


class Active(Reply):
    active: list[str]


class HolderInfo(Reply):
    login: str
    what: str
    since_ns: int
    renewed_s_ago: float


class PresenceInfo(Reply):
    holder: HolderInfo | None  # None: nobody holds motion
    lost_after_s: float
    losses: int


class Held(Reply):
    """``exolink hold``'s keep-alive answered: who holds, and what drives now."""

    holder: HolderInfo
    renewed: bool
    driving: list[str]
    presence_lost_after_s: float


class Released(Reply):
    released: bool  # False: that holder did not hold motion


class JointLimits(Reply):
    min: int
    max: int
    torque: int
    torque_step: int
    stiffness: int


class LimitsInfo(Reply):
    """The limits in force for every way in, and who narrowed them."""

    joints: dict[str, JointLimits]
    max_step_deg: float
    set_by: str | None  # None: the config's
    set_at_ns: int | None
    source: str  # config | operator
    unreadable: str | None = None  # the kept limits could not be read: motion refused


class Frames(Reply):
    """What went on the bus at once (``ID#DATA``)."""

    frames: list[str]


class LimitsSet(Frames):
    limits: LimitsInfo


class Commanded(Reply):
    """A command held by a controller, and its answer (the controller type's own words)."""

    controller: str
    said: dict[str, Any] = {}
    frames: list[str] = []  # an operator's command is written by the cycle, not at once


class BoardInfo(Reply):
    """A MACCEPA board the manager drives, as last written."""

    controller: str
    setpoint: float | None
    gains: list[float] | None


class ManagerStatus(Reply):
    """``exolink controllers list``: the controllers, who owns what, the limits, the presence
    and the loop's counters."""

    controllers: list[ControllerInfo]
    owners: dict[str, str]  # "r_knee/position" -> controller
    cycles: int
    limits: LimitsInfo
    presence: PresenceInfo
    written: int
    safe: int  # safe-action frames sent
    maccepa: dict[str, BoardInfo] = {}
    gaps: int = 0
    overhead_us: dict[str, Any] = {}
    late_cycles: int = 0
    cycles_per_update: int = 1
    timer: dict[str, Any] = {}  # the kernel's timer (on_timer.TimerLoop.status)
    maccepa_written: int = 0
    maccepa_safe: int = 0
    malformed: dict[str, int] = {}
    reading: bool = False
    reader_opens: int = 0
    read_ids: list[int] = []
    receive: dict[str, Any] | None = None  # the reader's losses (FrameReader.counters)
    watchdog_word: dict[str, Any] | None = None
    loop_cpu: dict[str, Any] = {}
    gc: dict[str, Any] = {}


class PatternInfo(Reply):
    """The pattern player's state (every ``exolink pattern`` action answers with it; the same
    fields go out on ``pattern_state``)."""

    state: str  # stopped | running | paused
    reason: str
    index: int  # the display's estimate of the row the manager plays
    length: int
    speed: int
    period_ms: float
    selected: list[str]
    file: str
    sent: int  # set-points the manager wrote for the gait
    operator: str  # the login that started it
    timing: str = "manager"  # who times the set-points (PatternState's timing_mode)
    watchdog_word: dict[str, Any] | None = None
