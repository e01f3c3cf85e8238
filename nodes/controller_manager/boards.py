"""The MACCEPA boards' side of a cycle (``Manager.cycle``): per owned board its set-point (or
duty) inside the board's range and step, written when it changes and re-sent every
``refresh_cycles`` updates while it holds (a frame lost on the bus is repaired soon), and its
gains only when they change; what each board was last written, for the step limit of the next
owner and for the status."""

from __future__ import annotations

from typing import Any

from exolink.nodes.controller_manager.slots import Cycle, MaccepaWrite, ManagerRefused, Slot

from exolink.control.controller import State
from exolink.control.replies import BoardInfo
from exolink.limits.maccepa import GAINS, BoardLimits
from exolink.limits.maccepa import target as board_name

# An unchanged MACCEPA set-point or duty is re-sent every this many H2 cycles (100 ms), so a
# frame lost on the bus is repaired soon; a changed one goes out in its own cycle. Every cycle
# would be 100 frames/s per board for no news: one bus send per cycle doubled the manager's
# overhead on this machine (benchmarks/bench_controllers.py).
MACCEPA_REFRESH_CYCLES = 10


class BoardOutputs:
    """Not thread-safe: the manager calls it under its lock."""

    def __init__(self, boards: list[BoardLimits], cycles_per_update: int) -> None:
        self.limits: dict[int, BoardLimits] = {b.board: b for b in boards}
        self.last_sp: dict[int, float] = {}  # board -> last set-point written
        self.gains_written: dict[int, tuple[float, float, float]] = {}  # board -> last gains
        # board -> (kind, value) last written and cycles since, for the refresh above
        self.drive_written: dict[int, tuple[str, float, int]] = {}
        self.refresh_cycles = max(1, round(MACCEPA_REFRESH_CYCLES / cycles_per_update))

    def status(self) -> dict[str, BoardInfo]:
        return {
            board_name(b): BoardInfo(
                lim.controller,
                self.last_sp.get(b),
                list(self.gains_written[b]) if b in self.gains_written else None,
            )
            for b, lim in self.limits.items()
        }

    def conflicts(self, owners: dict[str, str]) -> None:
        """One drive per board: a set-point and a duty never both."""
        for b in self.limits:
            sp, duty = owners.get(f"{board_name(b)}/setpoint"), owners.get(f"{board_name(b)}/duty")
            if sp and duty:
                raise ManagerRefused(
                    f"cannot switch: {board_name(b)}/setpoint ({sp}) and {board_name(b)}/duty ({duty}) "
                    f"would both drive MACCEPA board {b}"
                )

    def claim(self, b: int, kind: str, state: State, written_sp: dict[int, float]) -> None:
        """A set-point handed over continues from what its previous owner last wrote; one
        nobody was writing starts from where the board is (its lever; 0 for a velocity
        controller)."""
        if kind == "setpoint":
            lever = state.board(b).lever  # type: ignore[union-attr]
            here = float(lever or 0) if self.limits[b].controller == "position" else 0.0
            self.last_sp[b] = written_sp.get(b, here)

    def release(self, b: int, kind: str) -> None:
        if kind in ("setpoint", "duty"):
            self.last_sp.pop(b, None)
            self.drive_written.pop(b, None)  # the next owner writes at once
        elif kind == "gains":
            self.gains_written.pop(b, None)  # the next owner writes all three

    def compose(
        self, out: Cycle, owners: dict[str, str], held: dict[str, Any], slots: dict[str, Slot]
    ) -> int:
        """Each owned board's writes into ``out``; a board whose value is not known yet gets
        no frame. Returns how many such gaps there were."""
        gaps = 0
        for b, lim in self.limits.items():
            if b in out.safe_boards:
                continue
            key = f"{board_name(b)}/"
            g_owner = owners.get(key + "gains")
            if g_owner is not None:
                g = held.get(key + "gains")
                if g is None:
                    self.gains_written.pop(b, None)
                else:
                    new = tuple(lim.saturate_gain(x) for x in g)
                    if new != tuple(g):
                        slots[g_owner].limited += 1
                    old = self.gains_written.get(b)
                    for i, which in enumerate(GAINS):
                        if old is None or old[i] != new[i]:
                            out.maccepa.append(MaccepaWrite(b, which, new[i], lim.controller))
                    self.gains_written[b] = new  # type: ignore[assignment]
            sp_owner = owners.get(key + "setpoint")
            if sp_owner is not None:
                v = held.get(key + "setpoint")
                if v is None:
                    gaps += 1
                    continue
                sp = lim.saturate_setpoint(v, self.last_sp.get(b))
                if sp != v:
                    slots[sp_owner].limited += 1
                if lim.violation("setpoint", sp) is not None:  # cannot happen: belt
                    continue
                self.last_sp[b] = sp
                self._drive(out, b, "setpoint", sp, lim.controller)
                continue
            duty_owner = owners.get(key + "duty")
            if duty_owner is not None:
                v = held.get(key + "duty")
                if v is None:
                    gaps += 1
                    continue
                d = lim.saturate_duty(v)
                if d != v:
                    slots[duty_owner].limited += 1
                self._drive(out, b, "duty", d, lim.controller)
        return gaps

    def _drive(self, out: Cycle, board: int, kind: str, value: float, controller: str) -> None:
        last = self.drive_written.get(board)
        if last is not None and last[:2] == (kind, value) and last[2] + 1 < self.refresh_cycles:
            self.drive_written[board] = (kind, value, last[2] + 1)
            return
        self.drive_written[board] = (kind, value, 0)
        out.maccepa.append(MaccepaWrite(board, kind, value, controller))
