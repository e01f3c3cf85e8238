"""The gait's speed, as the thesis' player had it: levels 1..10, one pattern row every
``20 ms x (11 - level)`` (speed 10: a row every 20 ms, the fastest the H2's set-points go).
Shared by the pattern player, which shows and selects it, and the controller manager's gait
controller, which plays it: one definition, so the two never disagree on a row's time."""

from __future__ import annotations


def period_s(level: int) -> float:
    """A row's time at speed ``level`` (1..10)."""
    return 0.020 * (11 - level)
