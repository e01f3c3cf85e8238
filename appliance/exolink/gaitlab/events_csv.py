"""The trial's events as CSV (``write_events_csv``), written beside a C3D or OpenSim export."""

from __future__ import annotations

import csv
from pathlib import Path

from exolink.gaitlab.model import Trial
from exolink.gaitlab.output import _parent, _partial, _replace


def write_events_csv(trial: Trial, out: str | Path) -> Path:
    """The events, one a row: time from zero (s), C3D frame number (1 at zero), label,
    context, description, subject."""
    out = Path(out)
    _parent(out)
    tmp = _partial(out)
    try:
        with tmp.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["time_s", "frame", "label", "context", "description", "subject"])
            for e in trial.events:
                t = trial.time_s(e.time_ns)
                w.writerow(
                    [
                        f"{t:.6f}",
                        round(t * trial.rate_hz) + 1,  # C3D's frame number: 1 at zero
                        e.label,
                        e.context,
                        e.description,
                        trial.labels.get("subject", ""),
                    ]
                )
        _replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out
