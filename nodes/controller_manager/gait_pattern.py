"""The ``gait_pattern`` controller: the pattern player's rows at its speed levels (a row every
20 ms x (11 - level)), checked whole against the limits in force (angles, and the step limit
at its speed) before any is written; planned, so the manager puts it on the kernel's timer.
Registered under ``exolink.controllers`` like the other built-ins (builtin.py)."""

from __future__ import annotations

from typing import Annotated, Any

import msgspec
from exolink.nodes.controller_manager.builtin import NO_EXTRA_READS, JointList, unique_joints

from exolink.control.controller import Controller, Refused, State, interface
from exolink.control.gait import period_s
from exolink.protocol.h2 import JOINTS

Row = Annotated[list[int], msgspec.Meta(min_length=6, max_length=6)]  # deg, r_hip..l_ankle


class GaitParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    rows: Annotated[list[Row], msgspec.Meta(min_length=2, max_length=10_000)]  # deg, r_hip..l_ankle
    joints: JointList
    speed: Annotated[int, msgspec.Meta(ge=1, le=10)] = 5
    start: Annotated[int, msgspec.Meta(ge=0)] = 0
    # Between rows the set-point moves linearly to the next row: the manager writes every 10 ms
    # cycle, rows come every 20-200 ms, and a row's whole step in one cycle (the default pattern's
    # knee: 8 deg) would meet the manager's per-cycle step limit and lag. False: hold each row.
    interpolate: bool = True


class GaitPattern(Controller):
    """The pattern player's gait (``timing: manager``): row k of the pattern at controller time
    t0 + k x period(speed), so the frame's kernel timestamp, not this process's wake-up, sets
    the pace; each H2 cycle writes where the pattern is then, between row k and k+1 (a late
    cycle skips rows, never bunches them)."""

    Params = GaitParams
    reads = NO_EXTRA_READS
    planned = True
    t0: float | None  # the controller time of row i0 (None: the next update's)

    def configure(self) -> None:
        unique_joints(self.name, list(self.params.joints))
        if self.params.start >= len(self.params.rows):
            raise ValueError(f"{self.name}: start {self.params.start} is past the last row")
        self.period_s = period_s
        self.cols = [(interface(j, "position"), JOINTS.index(j)) for j in self.params.joints]
        self.speed, self.index = self.params.speed, self.params.start
        if self.limits is not None:  # the whole sequence, before any of it is written
            self._check_angles()
            self._check_steps(self.speed)
        self._anchor(self.index)

    def _check_angles(self) -> None:
        lim = self.limits
        assert lim is not None
        for n, row in enumerate(self.params.rows):
            for _key, j in self.cols:
                lo, hi = lim.min_angles[j], lim.max_angles[j]
                if not lo <= row[j] <= hi:
                    raise ValueError(
                        f"{self.name}: row {n + 1}: {JOINTS[j]} {row[j]} deg is outside the "
                        f"limits in force {lo}..{hi}"
                    )

    def _check_steps(self, speed: int) -> None:
        """Refuse a speed at which the pattern would outrun the step limit (the manager would
        saturate it: the joints lag the pattern instead of walking it)."""
        lim, rows = self.limits, self.params.rows
        if lim is None:
            return
        cycles = 1.0 if not self.params.interpolate else max(1.0, self.period_s(speed) / 0.01)
        worst, where = 0.0, ""
        for n in range(len(rows)):
            a, b = rows[n], rows[(n + 1) % len(rows)]
            for _key, j in self.cols:
                step = abs(b[j] - a[j]) / cycles
                if step > worst:
                    worst, where = step, f"row {n + 1} -> {(n + 1) % len(rows) + 1}, {JOINTS[j]}"
        if worst > lim.max_step_deg:
            raise ValueError(
                f"{self.name}: at speed {speed} the pattern moves {worst:.3g} deg per 10 ms "
                f"cycle ({where}), over the step limit {lim.max_step_deg} deg "
                "(limits.max_step_deg): choose a lower speed"
            )

    def _anchor(self, index: int) -> None:
        self.i0, self.t0 = index, None  # the next update's time is row i0's

    def claims(self) -> list[str]:
        return [k for k, _ in self.cols]

    def activate(self, state: State) -> None:
        self._anchor(self.index)

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        if "speed" in request:
            level = request["speed"]
            if isinstance(level, bool) or not isinstance(level, int) or not 1 <= level <= 10:
                raise Refused(f"{self.name}: speed must be a whole level 1..10, got {level!r}")
            try:
                self._check_steps(level)
            except ValueError as exc:
                raise Refused(str(exc)) from None
            self.speed = level
        if "index" in request:
            i = request["index"]
            if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < len(self.params.rows):
                raise Refused(f"{self.name}: index must be 0..{len(self.params.rows) - 1}")
            self.index = i
        self._anchor(self.index)
        return {"index": self.index, "speed": self.speed}

    def update(self, state: State, time_s: float, period: float) -> dict[str, float]:
        if self.t0 is None:
            self.t0 = time_s
        rows = self.params.rows
        x = max(0.0, (time_s - self.t0) / self.period_s(self.speed))
        k = int(x)
        self.index = (self.i0 + k) % len(rows)
        row = rows[self.index]
        if not self.params.interpolate:
            return {key: row[j] for key, j in self.cols}
        nxt, frac = rows[(self.index + 1) % len(rows)], x - k
        return {key: row[j] + frac * (nxt[j] - row[j]) for key, j in self.cols}

    def repeats_s(self) -> float:
        return len(self.params.rows) * self.period_s(self.speed)

    def status(self) -> dict[str, Any]:
        return {"index": self.index, "speed": self.speed, "length": len(self.params.rows)}


# --- PID ----------------------------------------------------------------------------------------
