"""The trial model: the constants of the export, the recorded ``Stream``, and the ``Trial`` on
its uniform clock with its ``Channel``s and ``Event``s."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

DEBOUNCE_S = 0.030
GAP_FACTOR = 1.5  # an interval longer than this many periods is a gap (h2_reader.GapCounter)
RESAMPLING = "nearest recorded sample (no interpolation); states (foot switches, battery) held"

SIDES = {"r": "Right", "l": "Left"}
FOOT_STRIKE, FOOT_OFF, TRIGGER = "Foot Strike", "Foot Off", "Trigger"


@dataclass
class Stream:
    """One recorded stream: sample times (ns) and its columns (NaN: not measured)."""

    topic: str
    t: Any  # numpy int64 [n]
    columns: dict[str, Any]  # name -> numpy float64 [n]

    def period_ns(self) -> float:
        """The stream's period: the median interval (robust to gaps and jitter)."""
        import numpy as np  # lazy: the gaitlab extra (numpy: not on the board)

        d = np.diff(self.t)
        d = d[d > 0]
        return float(np.median(d)) if len(d) else 0.0

    def lost_frames(self) -> int:
        """Samples lost in gaps, counted as the h2 reader counts them."""
        import numpy as np  # lazy: the gaitlab extra

        p = self.period_ns()
        if p <= 0:
            return 0
        d = np.diff(self.t)
        gaps = d[d > GAP_FACTOR * p]
        return int(np.sum(np.maximum(0, np.round(gaps / p) - 1)))


@dataclass
class Channel:
    label: str
    unit: str
    description: str
    values: Any  # numpy float64 on the trial's clock; NaN where not measured
    source_rate_hz: float

    @property
    def invalid(self) -> int:
        import numpy as np  # lazy: the gaitlab extra

        return int(np.count_nonzero(np.isnan(self.values)))


@dataclass
class Event:
    time_ns: int  # absolute (the recording's clock)
    label: str  # Foot Strike, Foot Off, Trigger
    context: str  # Left, Right, General
    description: str


@dataclass
class Trial:
    """A recording on one uniform clock, with its events and what was lost."""

    source: str
    rate_hz: float
    zero_ns: int  # time zero (frame 0), absolute
    zero: str  # what zero is: first-trigger or start
    frames: int
    channels: list[Channel]
    events: list[Event]
    labels: dict[str, str]
    losses: dict[str, int] = field(default_factory=dict)
    debounce_s: float = DEBOUNCE_S

    def time_s(self, t_ns: int) -> float:
        return (t_ns - self.zero_ns) / 1e9

    def channel(self, label: str) -> Channel:
        return next(c for c in self.channels if c.label == label)
