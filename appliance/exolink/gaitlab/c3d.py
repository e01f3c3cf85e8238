"""The C3D writer (``write_c3d``, through ezc3d from the ``gaitlab`` extra, imported only
when a C3D file is written): analog channels, the EVENT group, the trial's labels and losses."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from exolink.gaitlab.model import FOOT_OFF, FOOT_STRIKE, RESAMPLING, TRIGGER, Trial
from exolink.gaitlab.output import _parent, _partial, _replace
from exolink.recordings.check import RecordingError, iso

EXTRA = "gaitlab"  # pip install 'exolink[gaitlab]': the C3D writer (ezc3d), laptop side only
C3D_MAX_FRAMES = 65534  # the header's 16-bit frame count (65535 trips some readers)
ICONS = {FOOT_STRIKE: 1, FOOT_OFF: 2, TRIGGER: 0}  # Vicon's event icon ids


class MissingExtra(RecordingError):
    """An optional dependency of the export is not installed (says which extra brings it)."""


def samples_per_frame(frames: int, rate_hz: float) -> int:
    """Analog samples per C3D frame: 1, or the smallest divisor of the rate that keeps the
    frame count within the header's 16 bits (a 1 h trial at 100 Hz: 10, frames at 10 Hz)."""
    whole = max(1, round(rate_hz))
    for k in range(1, whole + 1):
        if whole % k == 0 and -(-frames // k) <= C3D_MAX_FRAMES:
            return k
    raise RecordingError(
        f"{frames} samples at {rate_hz} Hz do not fit a C3D file (at most "
        f"{C3D_MAX_FRAMES} frames of {whole} samples): export a shorter stretch"
    )


def require_ezc3d() -> Any:
    """ezc3d, or MissingExtra naming the extra that brings it (imported only for --c3d)."""
    try:
        import ezc3d  # lazy: the gaitlab extra (a laptop); the board has none
    except ImportError:
        raise MissingExtra(
            f"C3D export needs ezc3d: pip install 'exolink[{EXTRA}]' (laptop side)"
        ) from None
    return ezc3d


def write_c3d(trial: Trial, out: str | Path) -> Path:
    """The trial as a C3D file: channels as analogs (float, SCALE 1, OFFSET 0, NaN where not
    measured), no markers, events in the EVENT group as Vicon and Visual3D read them, labels
    and losses in the EXOLINK group, the subject in SUBJECTS."""
    import numpy as np  # lazy: the gaitlab extra

    ezc3d = require_ezc3d()
    out = Path(out)
    if out.suffix.lower() != ".c3d":
        raise RecordingError(f"{out}: a C3D file's name ends in .c3d")
    k = samples_per_frame(trial.frames, trial.rate_hz)
    frames = -(-trial.frames // k)
    n = frames * k
    data = np.full((1, len(trial.channels), n), np.nan)
    for j, ch in enumerate(trial.channels):
        data[0, j, : trial.frames] = ch.values
    c = ezc3d.c3d()
    p = c["parameters"]
    p["POINT"]["RATE"]["value"] = np.array([trial.rate_hz / k])
    p["ANALOG"]["RATE"]["value"] = np.array([trial.rate_hz])
    p["ANALOG"]["LABELS"]["value"] = [ch.label for ch in trial.channels]
    p["ANALOG"]["DESCRIPTIONS"]["value"] = [ch.description for ch in trial.channels]
    p["ANALOG"]["UNITS"]["value"] = [ch.unit for ch in trial.channels]
    p["ANALOG"]["SCALE"]["value"] = np.ones(len(trial.channels))
    p["ANALOG"]["OFFSET"]["value"] = np.zeros(len(trial.channels))
    p["ANALOG"]["GEN_SCALE"]["value"] = np.array([1.0])
    c["data"]["analogs"] = data
    c["data"]["points"] = np.zeros((4, 0, frames))
    subject = trial.labels.get("subject", "")
    c.add_parameter("SUBJECTS", "USED", 1 if subject else 0)
    c.add_parameter("SUBJECTS", "NAMES", [subject])
    c.add_parameter("SUBJECTS", "IS_STATIC", 0)
    _ints(c, "TRIAL", "ACTUAL_START_FIELD", _words(1))
    _ints(c, "TRIAL", "ACTUAL_END_FIELD", _words(frames))
    c.add_parameter("TRIAL", "CAMERA_RATE", trial.rate_hz / k)
    c.add_parameter("MANUFACTURER", "COMPANY", "exolink")
    c.add_parameter("MANUFACTURER", "SOFTWARE", "exolink export")
    _events(c, trial, subject)
    c.add_parameter("EVENT_CONTEXT", "USED", 3)
    c.add_parameter("EVENT_CONTEXT", "LABELS", ["General", "Left", "Right"])
    _ints(c, "EVENT_CONTEXT", "ICON_IDS", [0, 1, 2])
    c.add_parameter("EVENT_CONTEXT", "DESCRIPTIONS", ["General", "Left side", "Right side"])
    keys = list(trial.labels) or [""]
    c.add_parameter("EXOLINK", "SOURCE", Path(trial.source).name)
    c.add_parameter("EXOLINK", "LABEL_KEYS", keys)
    c.add_parameter("EXOLINK", "LABEL_VALUES", [trial.labels.get(x, "") for x in keys])
    c.add_parameter("EXOLINK", "ZERO", trial.zero)
    c.add_parameter("EXOLINK", "ZERO_TIME", iso(trial.zero_ns))
    c.add_parameter("EXOLINK", "RESAMPLING", RESAMPLING)
    c.add_parameter("EXOLINK", "DEBOUNCE_S", trial.debounce_s)
    c.add_parameter("EXOLINK", "INVALID", [ch.invalid for ch in trial.channels])
    c.add_parameter("EXOLINK", "LOSS_NAMES", list(trial.losses))
    c.add_parameter("EXOLINK", "LOSS_COUNTS", list(trial.losses.values()))
    _parent(out)
    tmp = _partial(out)
    try:
        c.write(str(tmp))
        _replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def _events(c: Any, trial: Trial, subject: str) -> None:
    """The EVENT group in one go (ezc3d's add_event rewrites the whole group per event: hours
    of gait are thousands of events). TIMES is 2 x n: minutes, then seconds from frame 1."""
    import numpy as np  # lazy: the gaitlab extra

    times = np.array([trial.time_s(e.time_ns) for e in trial.events], dtype=np.float64)
    minutes = np.floor(times / 60)
    c.add_parameter("EVENT", "USED", len(trial.events))
    c.add_parameter("EVENT", "TIMES", np.vstack([minutes, times - 60 * minutes]).reshape(2, -1))
    c.add_parameter("EVENT", "CONTEXTS", [e.context for e in trial.events] or [""])
    c.add_parameter("EVENT", "LABELS", [e.label for e in trial.events] or [""])
    c.add_parameter("EVENT", "DESCRIPTIONS", [e.description for e in trial.events] or [""])
    c.add_parameter("EVENT", "SUBJECTS", [subject] * len(trial.events) or [""])
    _ints(c, "EVENT", "ICON_IDS", [ICONS.get(e.label, 0) for e in trial.events] or [0])
    _ints(c, "EVENT", "GENERIC_FLAGS", [0] * len(trial.events) or [0])


def _ints(c: Any, group: str, name: str, values: list[int]) -> None:
    """An integer (int16) array parameter: ezc3d's add_parameter stores every list as floats,
    where C3D readers expect integers (ICON_IDS, TRIAL's fields). Through ezc3d's own
    Parameter type (its documented SWIG API) into the file's parameters (ezc3d 1.x)."""
    from ezc3d import ezc3d as swig  # lazy: the gaitlab extra

    param = swig.Parameter(name, "")
    param.set(swig.VecInt([int(v) for v in values]))
    c._storage["parameters"].add_parameter(group, param)


def _words(n: int) -> list[int]:
    """A 32-bit frame number as C3D's TRIAL group stores it: two 16-bit words, low first
    (each written as the int16 with the same bits)."""
    return [w - 65536 if w > 32767 else w for w in (n & 0xFFFF, (n >> 16) & 0xFFFF)]
