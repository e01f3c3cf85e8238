"""The broadcast manager's interval trimmed to its timer's lateness
(``exolink.canbus.leases.PeriodTrim``), against a model of the kernel's rule: each frame's
timer is armed when the last one went out, ``now + ival``, and fires ``late`` after it. The
model is arithmetic, not a clock (the real op is measured on vcan in the UML guest and on the
board proxy: docs/performance.md)."""

from __future__ import annotations

import itertools
import random

from exolink.canbus.leases import TRIM_MAX, PeriodTrim

PERIOD = 0.005
RENEW_S = 0.030


def run(late: list[float], trim: PeriodTrim, stall_at: int | None = None) -> list[float]:
    """Send ``len(late)`` frames as the kernel does, renewing every ``RENEW_S`` from what was
    sent by then; the send times. ``stall_at``: that frame goes out 100 ms late (the machine
    stopped)."""
    times = [0.0]
    trim.restart(0.0, 1)
    ival, next_renewal = trim.ival_s, RENEW_S
    for k in range(1, len(late)):
        due = times[-1] + ival + late[k] + (0.1 if k == stall_at else 0.0)
        while next_renewal < due:  # renewals before this frame see k frames sent
            ival = trim.update(next_renewal, k)
            next_renewal += RENEW_S
        times.append(due)
    return times


def mean_period(times: list[float]) -> float:
    return (times[-1] - times[0]) / (len(times) - 1)


def test_the_interval_makes_up_for_the_timers_lateness() -> None:
    rnd = random.Random(7)
    late = [0.0003 + rnd.uniform(-0.0002, 0.0002) for _ in range(3000)]  # B67's 0.3 ms
    untrimmed = [0.0] + [PERIOD * k + sum(late[1 : k + 1]) for k in range(1, 3000)]
    times = run(late, PeriodTrim(PERIOD))
    assert mean_period(untrimmed[-400:]) > PERIOD * 1.05  # the drift the trim is for
    assert abs(mean_period(times[-400:]) - PERIOD) < PERIOD * 0.005
    # every interval stays within the trim's bound: no frame is sent early by more
    assert min(b - a for a, b in itertools.pairwise(times)) > PERIOD * (1 - TRIM_MAX)


def test_a_stall_shifts_the_phase_and_is_not_caught_up() -> None:
    late = [0.0] * 3000
    times = run(late, PeriodTrim(PERIOD), stall_at=1500)
    after = [b - a for a, b in itertools.pairwise(times[1501:1900])]
    # an exact timer: trimmed only by the count's rounding before, and the stall's 100 ms not
    # made up by short frames after
    assert abs(mean_period(times[:1500]) - PERIOD) < PERIOD * 0.001
    assert min(after) >= PERIOD * 0.99


def test_a_new_phase_keeps_what_was_learnt() -> None:
    trim = PeriodTrim(PERIOD)
    run([0.0005] * 1000, trim)
    learnt = trim.ival_s
    trim.restart(10.0, 500)
    assert trim.ival_s == learnt
    assert learnt < PERIOD - 0.0004
