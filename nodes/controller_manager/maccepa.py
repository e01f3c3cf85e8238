"""The built-in MACCEPA controllers, registered under ``exolink.controllers`` beside the joint
ones (builtin.py):

- ``maccepa_setpoint``: a MACCEPA board's set-point (and optionally its gains) an operator sends,
  checked against the board's configured limits, with forward_command's timeout (hold or stop).
- ``maccepa_operator``: one board's set-point, duty or gains as ``exolink maccepa`` last sent
  them (made by the manager).
"""

from __future__ import annotations

import time
from typing import Annotated, Any, Literal

import msgspec
from exolink.nodes.controller_manager.builtin import NO_EXTRA_READS, expire

from exolink.control.controller import BoardLimits, Controller, Refused, State, maccepa_interface
from exolink.limits.maccepa import GAINS, BoardId, target


class MaccepaGains(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    kp: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    ki: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    kd: Annotated[float, msgspec.Meta(ge=0)] = 0.0


class MaccepaSetpointParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    board: BoardId
    # No command for this long (0 = never): 'hold' keeps the last set-point, 'stop' the board's
    # safe action (stop control), as forward_command's 'disable' does for a joint.
    timeout_s: Annotated[float, msgspec.Meta(ge=0, le=3600)] = 0.0
    on_timeout: Literal["hold", "stop"] = "hold"
    # First set-point at activation (the manager's step limit ramps to it); None: hold the
    # lever where it is (position controller) or 0 (velocity controller).
    initial: float | None = None
    # Given: this controller also claims maccepa<N>/gains and writes them at activation (the
    # simulated board, like a real one, does not move on a set-point with all gains 0).
    gains: MaccepaGains | None = None


def _board_limits(name: str, board: int, boards: dict[int, BoardLimits]) -> BoardLimits:
    lim = boards.get(board)
    if lim is None:
        configured = ", ".join(str(b) for b in sorted(boards)) or "none"
        raise ValueError(
            f"MACCEPA board {board} is not in the controller manager's params.maccepa "
            f"(configured: {configured})"
        )
    return lim


def _checked(name: str, lim: BoardLimits, kind: str, value: Any) -> float:
    why = lim.violation(kind, value)
    if why is not None:
        raise Refused(f"{name}: {why}")
    return float(value)


def _start(lim: BoardLimits, state: State) -> float:
    """Where a set-point starts when none was given: the lever (position controller), else 0."""
    board = state.board(lim.board)
    lever = board.lever if board is not None else None
    if lim.controller == "position" and lever is not None:
        return float(lever)
    return 0.0


class MaccepaSetpoint(Controller):
    """One MACCEPA board's set-point from operator commands (``exolink controllers command NAME
    maccepa0=30``; ``maccepa0/kp=2`` tunes a gain when ``gains`` is given), each checked against
    the board's configured range before it is taken: a refused one changes nothing, so no frame
    carries it. Held until the next; the command timeout holds or stops the board."""

    Params = MaccepaSetpointParams
    reads = NO_EXTRA_READS

    def configure(self) -> None:
        p = self.params
        self.lim = _board_limits(self.name, p.board, self.boards)
        self.target = target(p.board)
        self.sp_key = maccepa_interface(p.board, "setpoint")
        self.gains_key = maccepa_interface(p.board, "gains") if p.gains is not None else None
        checks = [("setpoint", p.initial)] if p.initial is not None else []
        checks += [(g, getattr(p.gains, g)) for g in GAINS] if p.gains is not None else []
        for kind, value in checks:
            if why := self.lim.violation(kind, value):
                raise ValueError(why)
        self.values: dict[str, Any] = {}
        self.last_command = 0.0
        self.timed_out = False

    def claims(self) -> list[str]:
        return [self.sp_key] + ([self.gains_key] if self.gains_key else [])

    def activate(self, state: State) -> None:
        p = self.params
        sp = p.initial if p.initial is not None else _start(self.lim, state)
        values: dict[str, Any] = {self.sp_key: sp}
        if self.gains_key is not None and p.gains is not None:
            values[self.gains_key] = (p.gains.kp, p.gains.ki, p.gains.kd)
        self.values = values
        self.last_command, self.timed_out = time.monotonic(), False

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        """``{"values": {"maccepa0": 30}}`` (or ``maccepa0/setpoint``), ``maccepa0/kp`` ..."""
        values = request.get("values")
        if not isinstance(values, dict) or not values:
            raise Refused(
                f"{self.name} needs 'values': {{{self.target}: set-point}} "
                f"(or {self.target}/kp, /ki, /kd with params.gains)"
            )
        new = dict(self.values)
        gains = list(new.get(self.gains_key, (0.0, 0.0, 0.0))) if self.gains_key else []
        for key, v in values.items():
            board, _, kind = str(key).partition("/")
            if board != self.target:
                raise Refused(f"{self.name} drives {self.target}, not {key!r}")
            kind = kind or "setpoint"
            if kind == "setpoint":
                new[self.sp_key] = _checked(self.name, self.lim, "setpoint", v)
            elif kind in GAINS and self.gains_key is not None:
                gains[GAINS.index(kind)] = _checked(self.name, self.lim, kind, v)
            elif kind in GAINS:
                raise Refused(f"{self.name} does not claim {self.target}/gains (no params.gains)")
            else:
                raise Refused(f"{self.name}: {key!r} is not setpoint, kp, ki or kd")
        if self.gains_key is not None:
            new[self.gains_key] = tuple(gains)
        # One assignment of a new dict: the loop sees the old or the new, never half of it.
        self.values = new
        self.last_command, self.timed_out = time.monotonic(), False
        return {"values": {k: list(v) if isinstance(v, tuple) else v for k, v in new.items()}}

    def update(self, state: State, time_s: float, period: float) -> dict[str, Any]:
        expire(self, "stop")
        return self.values

    def status(self) -> dict[str, Any]:
        shown = {k: list(v) if isinstance(v, tuple) else v for k, v in self.values.items()}
        return {"command": shown, "timed_out": self.timed_out}


class MaccepaOperatorParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    board: BoardId
    kind: Literal["setpoint", "duty", "gains"]


class MaccepaOperator(Controller):
    """One board's set-point, duty or gains, held at what the MACCEPA bridge last forwarded
    (``exolink maccepa N setpoint|duty|gains``).

    The manager makes one per board and kind on demand (``operator.maccepa<N>.<kind>``). Gains
    not named in a command keep this controller's last value (0 before the first)."""

    Params = MaccepaOperatorParams
    reads = NO_EXTRA_READS

    def configure(self) -> None:
        p = self.params
        self.lim = _board_limits(self.name, p.board, self.boards)
        self.key = maccepa_interface(p.board, p.kind)
        self.value: Any = None

    def claims(self) -> list[str]:
        return [self.key]

    def activate(self, state: State) -> None:
        if self.value is None:  # activated without a command: hold, or no drive at all
            kind = self.params.kind
            self.value = {"setpoint": _start(self.lim, state), "duty": 0.0}.get(kind, (0.0,) * 3)

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        if self.params.kind == "gains":
            gains = list(self.value) if self.value is not None else [0.0, 0.0, 0.0]
            given = [g for g in GAINS if request.get(g) is not None]
            if not given:
                raise Refused(f"{self.name}: gains needs at least one of kp, ki, kd")
            for g in given:
                gains[GAINS.index(g)] = _checked(self.name, self.lim, g, request[g])
            self.value = tuple(gains)
            return {"command": dict(zip(GAINS, gains, strict=True))}
        self.value = _checked(self.name, self.lim, self.params.kind, request.get("value"))
        return {"command": {self.key: self.value}}

    def update(self, state: State, time_s: float, period: float) -> dict[str, Any]:
        return {self.key: self.value}

    def status(self) -> dict[str, Any]:
        v = self.value
        return {"command": {self.key: list(v) if isinstance(v, tuple) else v}}


__all__ = ["MaccepaOperator", "MaccepaSetpoint"]
