"""The timing monitor's statistics in plain Python match numpy's (the reference it replaced)."""

from __future__ import annotations

import random

import numpy as np
import pytest
from exolink.nodes.timing_monitor import HIST_EDGES_US, StampRing, deviation_stats


def reference(stamps: list[float], expected_s: float | None) -> dict:
    dt = np.diff(np.asarray(stamps))
    exp = float(np.median(dt)) if expected_s is None else expected_s
    dev = np.abs(dt - exp) * 1e3
    counts, _ = np.histogram(dev * 1e3, bins=[*HIST_EDGES_US, np.inf])
    return {
        "n": int(dt.size),
        "expected_ms": exp * 1e3,
        "mean_period_ms": float(dt.mean()) * 1e3,
        "mean_dev_ms": float(dev.mean()),
        "p99_dev_ms": float(np.percentile(dev, 99)),
        "max_dev_ms": float(dev.max()),
        "histogram": [int(c) for c in counts],
    }


@pytest.mark.parametrize("seed", range(20))
def test_deviation_stats_match_numpy(seed: int) -> None:
    rng = random.Random(seed)
    t, stamps = 0.0, []
    jitter = rng.choice([1e-6, 1e-4, 3e-3])
    for _ in range(rng.randint(3, 3000)):
        t += 0.02 + rng.gauss(0, jitter)
        stamps.append(t)
    expected = rng.choice([None, 0.02])
    got, ref = deviation_stats(stamps, expected), reference(stamps, expected)
    assert list(got["histogram"].values()) == ref.pop("histogram")
    for key, value in ref.items():
        assert got[key] == pytest.approx(value, abs=2e-4), key


@pytest.mark.parametrize("added", [0, 5, 7, 20])
def test_stamp_ring_keeps_the_last_frames_in_order_by_length_and_first_byte(added: int) -> None:
    """Against a plain list of what was added: the ring (7 slots) keeps the newest, oldest
    first, and answers each way of asking (any, by length, by first byte, both)."""
    rng = random.Random(added)
    ring, plain = StampRing(7), []
    for i in range(added):
        data = bytes(rng.randrange(256) % 3 for _ in range(rng.choice((0, 6, 8))))
        ring.add(float(i), data)
        plain.append((float(i), data))
    kept = plain[-7:]
    for dlc in (None, 0, 6, 8):
        for b0 in (None, 0, 1, 2):
            want = [
                t
                for t, d in kept
                if (dlc is None or len(d) == dlc) and (b0 is None or (d and d[0] == b0))
            ]
            assert ring.select(dlc, b0) == want
            assert ring.copy().select(dlc, b0) == want


def test_only_keeps_one_motors_set_points_and_refuses_other_ids() -> None:
    """``only``: of id 70 the monitor keeps motor 1's 6-byte joint control; the other motors'
    and MACCEPA board 0's 8-byte status on the same id are dropped (in the kernel on SocketCAN:
    the same rules, test_canfilter), other ids untouched; ``only`` for an unmonitored id or
    more ids than the filter takes is a bad config."""
    import msgspec
    from exolink.nodes.timing_monitor import TimingParams

    from exolink.canbus.filters import Predicate

    p = msgspec.convert(
        {"ids": [70, 110], "only": [{"id": 70, "dlc": 6, "first_byte": [1]}]}, TimingParams
    )
    pred = Predicate(p.drops())
    assert not pred.drops(70, bytes([1, 1, 30, 0, 0, 0]))
    assert pred.drops(70, bytes([2, 1, 30, 0, 0, 0]))
    assert pred.drops(70, bytes(8)) and pred.drops(70, bytes([1]))
    assert not pred.drops(110, bytes(6))
    with pytest.raises(msgspec.ValidationError, match=r"only names ids \[70\] that are not in ids"):
        msgspec.convert({"ids": [110], "only": [{"id": 70, "dlc": 6}]}, TimingParams)
    four = [{"id": i, "dlc": 6} for i in (1, 2, 3, 4)]
    with pytest.raises(msgspec.ValidationError, match="at most 3 ids"):
        msgspec.convert({"ids": [1, 2, 3, 4], "only": four}, TimingParams)
