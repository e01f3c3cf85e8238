"""The node base class: typed params, configure -> run -> shutdown, and the loop's ``beat()``.

What runs a node (its process, session, heartbeat, signals) is ``exolink.runtime``; this module
stays light because every plugin imports it.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import msgspec
import structlog
import zenoh

from exolink import messaging
from exolink.config import ApplianceConfig
from exolink.liveness import Beater, Pace

if TYPE_CHECKING:
    from exolink.loops import Loop

HEARTBEAT_PERIOD_S = 0.1  # the heartbeat thread's shortest period (see beat_period_s)
TELEMETRY_PERIOD_S = 1.0  # the heartbeat on Zenoh: for people, not the watchdog
R = TypeVar("R")
# How an owned resource is released, in this order of preference: our readers, publishers and
# arming views close; a Zenoh declaration undeclares; a python-can bus shuts down; a server
# (Foxglove's) stops.
_RELEASE = ("close", "undeclare", "shutdown", "stop")


def beat_period_s(deadline_s: float, stall_s: float) -> float:
    """How often the runtime's heartbeat thread wakes. It vouches for a loop that beat within
    ``stall_s`` only when ``stall_s`` is longer than the node's liveness deadline (a loop that
    may block past it: the recorder's fsync under a short deadline), three times per deadline,
    at least every 0.1 s. Otherwise the loop's own beats are the only proof of life and the
    thread wakes once a second for the telemetry: a vouch at its own time let a motion node's
    loop hang for ``stall_s`` + deadline (90 ms for the controller manager's 50 ms) before the
    watchdog knew, and each wake costs ~1 ms of the board's one core (benchmarks/board/units.py)."""
    if not vouches(deadline_s, stall_s):
        return TELEMETRY_PERIOD_S
    return min(TELEMETRY_PERIOD_S, max(HEARTBEAT_PERIOD_S, deadline_s / 3))


def vouches(deadline_s: float, stall_s: float) -> bool:
    """Whether the heartbeat thread beats for a loop that beat within ``stall_s``."""
    return stall_s > deadline_s


HEARTBEAT_TOPIC = "heartbeat"
HEARTBEAT_TYPE = "exolink_msgs/msg/Heartbeat"


class NoParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    pass


@dataclass
class NodeContext:
    name: str
    config: ApplianceConfig
    session: zenoh.Session
    messaging: messaging.Messaging
    log: structlog.typing.FilteringBoundLogger


class Node:
    """Subclass, set ``Params`` to a msgspec Struct, implement ``run``.

    ``configure`` opens what the node needs (buses, publishers, queryables) through ``own``
    and may raise to refuse to start; ``run`` loops until ``stop`` is set, calling ``beat()``
    at least every ``stall_s``; ``shutdown`` does what must happen while everything is still
    open (a motion node's safe action) and must not raise. The runtime then releases what the
    node owns, last opened first, also when ``configure`` raised half way: no node checks
    which of its attributes exist.
    """

    Params: ClassVar[type[msgspec.Struct]] = NoParams
    stall_s: ClassVar[float] = 0.5
    # While the loop says it is idle (``beat(idle=True)``): it beats at least this often, and
    # the supervisor holds it to the appliance's default deadline (see exolink.liveness).
    idle_stall_s: ClassVar[float] = 0.4

    def __init__(self, ctx: NodeContext, params: Any) -> None:
        self.ctx = ctx
        self.params = params
        self.log = ctx.log
        self._last_beat = time.monotonic()
        self._stall_limit = self.stall_s
        # While the loop says its motion runs on a lease (``beat(Pace.LEASED)``): it beats at
        # least this often (a node that leases sets its own, from its wake).
        self.leased_stall_s = self.stall_s
        self.on_stall: Callable[[float, float], None] | None = None  # (gap s, limit s)
        self.liveness = Beater(None)  # the runtime connects it to the supervisor's pipe
        self._owned = contextlib.ExitStack()

    def own(self, resource: R) -> R:
        """``resource``, released by the runtime after ``shutdown`` (``release``)."""
        for method in _RELEASE:
            fn = getattr(resource, method, None)
            if callable(fn):
                self._owned.callback(self._release_one, fn, type(resource).__name__)
                return resource
        raise TypeError(f"{type(resource).__name__} has none of {', '.join(_RELEASE)}")

    def _release_one(self, fn: Callable[[], Any], what: str) -> None:
        """One failed release must not keep the others open."""
        try:
            fn()
        except Exception as exc:  # logged: the rest are still released
            self.log.warning("release_failed", resource=what, error=str(exc))

    def release(self) -> None:
        """Release everything ``own`` was given, last first (idempotent)."""
        self._owned.close()

    @property
    def name(self) -> str:
        return self.ctx.name

    def beat(self, pace: Pace = Pace.OWN) -> None:
        """The loop is alive: straight to the supervisor, so the node is judged on its loop's own
        beats. ``pace``: the deadline it is judged by until its next beat (exolink.liveness:
        idle, nothing to drive; leased, its motion ends with a lease). A beat that ends a gap
        longer than the loop's stall limit reports it (``on_stall``, set by the runtime: the
        journal's ``loop_stalled``)."""
        now = time.monotonic()
        gap = now - self._last_beat
        self._last_beat = now
        self.liveness.beat(now, pace)
        if gap > self._stall_limit and self.on_stall is not None:
            self.on_stall(gap, self._stall_limit)
        self._stall_limit = (
            self.idle_stall_s
            if pace == Pace.IDLE
            else self.leased_stall_s
            if pace == Pace.LEASED
            else self.stall_s
        )

    @property
    def last_beat(self) -> float:
        return self._last_beat

    def healthy(self) -> bool:
        return time.monotonic() - self._last_beat < self._stall_limit

    def restart_stall_clock(self) -> None:
        """From now on: what came before the loop (configure) is no stall."""
        self._last_beat = time.monotonic()

    def configure(self) -> None:
        pass

    def loop(self) -> Loop:
        """How the node wakes and what it does then (exolink.loops: ``Every``, ``Frames``),
        declared after ``configure``; ``run`` runs it, beating on every wake."""
        raise NotImplementedError(f"{type(self).__name__} declares neither loop() nor run()")

    def run(self, stop: threading.Event) -> None:
        """The declared loop until ``stop``. A node whose loop is its job (a clocked model, the
        controller manager's cycle) overrides this instead and beats itself."""
        self.loop().run(self.beat, stop)

    def shutdown(self) -> None:
        pass

    def set_param(self, key: str, value: Any) -> Any:
        """Change one param at run time; nodes that allow it override ``apply_params``."""
        data = msgspec.to_builtins(self.params)
        if key not in data:
            raise messaging.Refused(f"{self.name} has no param {key!r} (has: {', '.join(data)})")
        data[key] = value
        try:
            new = msgspec.convert(data, type(self.params))
        except msgspec.ValidationError as exc:
            raise messaging.Refused(f"{self.name}.{key}: {exc}") from None
        self.apply_params(new)
        self.params = new
        return getattr(new, key)

    def apply_params(self, new: Any) -> None:
        raise messaging.Refused(f"{self.name} does not change params at run time")
