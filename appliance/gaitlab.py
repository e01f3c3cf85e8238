"""Recordings into the gait lab's tools: C3D (analog channels + gait events) and OpenSim files.

One trial is built from an MCAP recording (``build_trial``) and written by the writers below
(``write_c3d``, ``write_opensim``, ``write_events_csv``). The rules, also in
docs/gaitlab/README.md:

Uniform clock. All channels go onto one clock at the H2's recorded rate (the median interval of
``joint_states``, rounded to a whole Hz: 100 Hz from the 10 ms stream). Time zero is the first
trigger edge (``zero="first-trigger"``, when the file has one; what was recorded before it is
not exported) or the first joint sample (``zero="start"``); frame k is at zero + k / rate.

Resampling: nearest recorded sample, never interpolated. Each clock tick takes the value of the
stream's sample nearest in time (so a value in the export is always one that was measured, at
most 0.75 of the stream's period from where it is shown; half a period on a steady stream). Foot switches and battery are published on
change (and refreshed every ``foot_switches_refresh_s``): they are states and are held, each
tick taking the last state published at or before it.

Losses are NaN, never filled. A stream's gap is an interval longer than 1.5 of its periods (the
h2 reader's own ``GapCounter`` rule): ticks inside it farther than 0.75 period from a sample
are NaN, and the frames lost are counted as that rule counts them. A MACCEPA frame the board's
cycle missed (its ``stale`` bit) is NaN for that frame's fields. Foot switches and battery are
NaN where the H2 stream has a gap (they come in the same 10 ms CAN cycle) and where their
messages stopped longer than 1.5 refresh periods. The recorder's own dropped count and any
``recover`` losses from the file's metadata are carried into the export's summary.

Gait events, per side, from the recorded foot-switch messages (the frames' own kernel times,
not the clock ticks): contact = heel OR toe. Foot Strike at contact 0 -> 1, Foot Off at 1 -> 0;
a new contact state counts only once it has held for ``debounce_s`` (default 30 ms, three H2
cycles), and the event is at the time of its first frame. A transition right after an H2 gap
(its moment is unknown) is not an event; it is counted instead.

OpenSim: joint angles in degrees, columns as the Rajagopal 2015 and gait2392 models name them.
H2 angles are hip flexion +, knee flexion +, ankle dorsiflexion + (shared/protocol/h2-can.md);
Rajagopal's knee_angle is flexion + as well, gait2392's is flexion - (``model="gait2392"``
negates the knee). Torques: the joint's N·m in the same sign as its angle, columns
``<coordinate>_moment`` as OpenSim's inverse dynamics writes them.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog
from exolink.mcapcheck import RecordingError, iso
from exolink.recording import decode, info, iter_messages, message_time_ns

log = structlog.get_logger("exolink.gaitlab")

EXTRA = "gaitlab"  # pip install 'exolink[gaitlab]': the C3D writer (ezc3d), laptop side only
ZERO_CHOICES = ("first-trigger", "start")
MODELS = ("rajagopal", "gait2392")
DEBOUNCE_S = 0.030
GAP_FACTOR = 1.5  # an interval longer than this many periods is a gap (h2_reader.GapCounter)
C3D_MAX_FRAMES = 65534  # the header's 16-bit frame count (65535 trips some readers)
RESAMPLING = "nearest recorded sample (no interpolation); states (foot switches, battery) held"

SIDES = {"r": "Right", "l": "Left"}
FOOT_STRIKE, FOOT_OFF, TRIGGER = "Foot Strike", "Foot Off", "Trigger"
ICONS = {FOOT_STRIKE: 1, FOOT_OFF: 2, TRIGGER: 0}  # Vicon's event icon ids
# H2 joint -> (OpenSim coordinate, sign for rajagopal, sign for gait2392)
OPENSIM = {
    "r_hip": ("hip_flexion_r", 1, 1),
    "r_knee": ("knee_angle_r", 1, -1),
    "r_ankle": ("ankle_angle_r", 1, 1),
    "l_hip": ("hip_flexion_l", 1, 1),
    "l_knee": ("knee_angle_l", 1, -1),
    "l_ankle": ("ankle_angle_l", 1, 1),
}
MACCEPA_FIELDS = {  # field -> (unit, the frame's stale bit)
    "current_ma": ("mA", 1),
    "temperature_c": ("degC", 1),
    "velocity_rpm": ("rpm", 1),
    "load_n": ("N", 1),
    "link_deg": ("deg", 2),
    "lever_deg": ("deg", 2),
    "extra_position": ("count", 2),
    "extra_sensor": ("count", 2),
    "setpoint": ("count", 4),
    "actuation": ("count", 4),
    "process_variable": ("count", 4),
}


class MissingExtra(RecordingError):
    """An optional dependency of the export is not installed (says which extra brings it)."""


@dataclass
class Stream:
    """One recorded stream: sample times (ns) and its columns (NaN: not measured)."""

    topic: str
    t: Any  # numpy int64 [n]
    columns: dict[str, Any]  # name -> numpy float64 [n]

    def period_ns(self) -> float:
        """The stream's period: the median interval (robust to gaps and jitter)."""
        import numpy as np

        d = np.diff(self.t)
        d = d[d > 0]
        return float(np.median(d)) if len(d) else 0.0

    def lost_frames(self) -> int:
        """Samples lost in gaps, counted as the h2 reader counts them."""
        import numpy as np

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
        import numpy as np

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


# --- reading ------------------------------------------------------------------------------------


def _kind(topic: str, typename: str) -> str | None:
    if typename == "sensor_msgs/msg/JointState" and topic.endswith("/joint_states"):
        return "joints"
    if typename.endswith("/FootSwitches"):
        return "feet"
    if typename.endswith("/MaccepaState"):
        return "maccepa"
    if typename.endswith("/TriggerEvent"):
        return "trigger"
    return None


def read_streams(path: str | Path) -> tuple[dict[str, Stream], list[tuple[int, str]], Any]:
    """The streams the export needs, decoded with the file's own schemas, after the whole file
    checked out (``info``: a damaged file is refused before anything is written). Returns the
    streams by kind (``joints``, ``feet``, ``maccepa/bN``), the trigger edges (ns, edge) and the
    file's ``Info``."""
    import numpy as np

    i = info(path)
    kinds = {t: _kind(t, v["type"]) for t, v in i.topics.items()}
    wanted = [t for t, k in kinds.items() if k is not None]
    if not any(k == "joints" for k in kinds.values()):
        raise RecordingError(f"{path}: no joint_states recorded: nothing to export")
    rows: dict[str, tuple[list[int], dict[str, list[float]]]] = {}
    triggers: list[tuple[int, str]] = []
    nan = math.nan
    for schema, channel, m in iter_messages(path, wanted):
        kind = kinds[channel.topic]
        msg = decode(schema, m.data)
        t = message_time_ns(msg, m.log_time)
        if kind == "trigger":
            triggers.append((t, str(msg.edge)))
            continue
        if kind == "joints":
            cols = _joint_columns(msg)
        elif kind == "feet":
            cols = {
                "r_heel": float(msg.r_heel),
                "r_toe": float(msg.r_toe),
                "l_heel": float(msg.l_heel),
                "l_toe": float(msg.l_toe),
                "battery": float(msg.battery_volts),
            }
        else:
            kind = f"maccepa/b{int(msg.board)}"
            stale = int(msg.stale)
            cols = {
                f: nan if stale & bit else float(getattr(msg, f))
                for f, (_u, bit) in MACCEPA_FIELDS.items()
            }
        ts, cs = rows.setdefault(kind, ([], {}))
        ts.append(t)
        for k, v in cols.items():
            cs.setdefault(k, []).append(v)
    streams = {}
    for kind, (ts, cs) in rows.items():
        order = np.argsort(np.asarray(ts, dtype=np.int64), kind="stable")
        t = np.asarray(ts, dtype=np.int64)[order]
        streams[kind] = Stream(
            kind, t, {k: np.asarray(v, dtype=np.float64)[order] for k, v in cs.items()}
        )
    return streams, sorted(triggers), i


def _joint_columns(msg: Any) -> dict[str, float]:
    """Degrees and N·m per joint; a joint without a torque in this message is NaN."""
    cols: dict[str, float] = {}
    for k, name in enumerate(msg.name):
        pos = msg.position[k] if k < len(msg.position) else math.nan
        eff = msg.effort[k] if k < len(msg.effort) else math.nan
        cols[f"{name}_angle"] = math.degrees(float(pos))
        cols[f"{name}_torque"] = float(eff)
    return cols


# --- resampling ---------------------------------------------------------------------------------


def nearest(t: Any, v: Any, grid: Any, period_ns: float) -> Any:
    """Each tick of ``grid`` takes the sample of (t, v) nearest in time, NaN where the nearest
    is more than GAP_FACTOR / 2 periods away: inside a gap (two samples more than GAP_FACTOR
    periods apart) and past the stream's ends. Never an interpolated value."""
    import numpy as np

    out = np.full(len(grid), np.nan)
    if len(t) == 0:
        return out
    nxt = np.searchsorted(t, grid, side="left").clip(0, len(t) - 1)
    prv = (nxt - 1).clip(0, len(t) - 1)
    d_prev = np.abs(grid - t[prv])
    d_next = np.abs(t[nxt] - grid)
    idx = np.where(d_next < d_prev, nxt, prv)
    dist = np.minimum(d_prev, d_next)
    out = v[idx].astype(np.float64)
    out[dist > GAP_FACTOR * period_ns / 2] = np.nan  # in a gap, or past the ends
    return out


def hold(t: Any, v: Any, grid: Any, max_age_ns: float) -> Any:
    """Each tick takes the last state published at or before it (states published on change);
    NaN before the first and where the last is older than ``max_age_ns`` (messages stopped)."""
    import numpy as np

    i = np.searchsorted(t, grid, side="right") - 1
    out = np.where(i >= 0, v[i.clip(0)], np.nan).astype(np.float64)
    age = grid - t[i.clip(0)]
    out[(i < 0) | (age > max_age_ns)] = np.nan
    return out


# --- events -------------------------------------------------------------------------------------


def foot_events(
    feet: Stream, side: str, debounce_s: float = DEBOUNCE_S, joints: Stream | None = None
) -> tuple[list[Event], int]:
    """Foot Strike / Foot Off of one side (``r`` or ``l``) from its heel and toe switches (the
    rule is in the module docstring). Returns the events and how many transitions were not
    events because they came right after an H2 gap."""
    t = feet.t
    contact = (feet.columns[f"{side}_heel"] > 0) | (feet.columns[f"{side}_toe"] > 0)
    heel = feet.columns[f"{side}_heel"] > 0
    toe = feet.columns[f"{side}_toe"] > 0
    debounce = int(debounce_s * 1e9)
    events: list[Event] = []
    skipped = 0
    state = bool(contact[0]) if len(t) else False
    js_t = joints.t if joints is not None else None
    js_gap = GAP_FACTOR * joints.period_ns() if joints is not None else 0.0
    k = 1
    while k < len(t):
        if bool(contact[k]) == state:
            k += 1
            continue
        # a change: does the new state hold for the debounce time?
        j = k
        while j + 1 < len(t) and bool(contact[j + 1]) == bool(contact[k]):
            j += 1
        end = t[j + 1] if j + 1 < len(t) else t[-1]
        if end - t[k] < debounce and j + 1 < len(t):
            k = j + 1  # a blip: ignored with its way back
            continue
        state = bool(contact[k])
        if js_t is not None and _after_gap(js_t, int(t[k]), js_gap):
            skipped += 1
        else:
            label = FOOT_STRIKE if state else FOOT_OFF
            at = k if state else k - 1  # the switches on at contact, or the last on before off
            which = " and ".join(w for w, on in (("heel", heel[at]), ("toe", toe[at])) if on)
            what = f"{which} first on" if state else f"{which} last off"
            events.append(Event(int(t[k]), label, SIDES[side], what))
        k = j + 1
    return events, skipped


def _after_gap(js_t: Any, at_ns: int, gap_ns: float) -> bool:
    """Is ``at_ns`` the first H2 news after a gap (the change happened somewhere in it)?"""
    import numpy as np

    i = int(np.searchsorted(js_t, at_ns, side="left"))
    if i == 0:
        return True
    return bool(at_ns - js_t[i - 1] > gap_ns)


# --- the trial ----------------------------------------------------------------------------------


def _refresh_s(metadata: dict[str, dict[str, str]]) -> float:
    """The h2 reader's foot_switches_refresh_s in the recording's config (1.0 if not said)."""
    import yaml

    try:
        cfg = yaml.safe_load(metadata.get("exolink.config", {}).get("yaml", "")) or {}
        for node in cfg.get("nodes", []):
            if node.get("plugin") == "h2_reader":
                return float((node.get("params") or {}).get("foot_switches_refresh_s", 1.0))
    except (yaml.YAMLError, AttributeError, TypeError, ValueError):
        pass
    return 1.0


def build_trial(
    path: str | Path, zero: str = "first-trigger", debounce_s: float = DEBOUNCE_S
) -> Trial:
    """The recording at ``path`` as one trial: every channel on the H2's clock, the gait and
    trigger events, the labels and the losses (see the module docstring for every rule)."""
    import numpy as np

    if zero not in ZERO_CHOICES:
        raise RecordingError(f"zero must be one of {', '.join(ZERO_CHOICES)}, got {zero!r}")
    if not 0 <= debounce_s <= 1:
        raise RecordingError(f"the debounce must be 0 to 1000 ms, got {debounce_s * 1000:g}")
    streams, triggers, i = read_streams(path)
    js = streams["joints"]
    period = js.period_ns()
    if len(js.t) < 2 or period <= 0:
        raise RecordingError(f"{path}: fewer than two joint samples: no rate to export at")
    rate = float(round(1e9 / period)) or 1e9 / period
    step = 1e9 / rate
    used_zero = zero if zero == "start" or triggers else "start"
    zero_ns = int(triggers[0][0]) if used_zero == "first-trigger" else int(js.t[0])
    frames = round((js.t[-1] - zero_ns) / step) + 1
    if frames < 1:
        raise RecordingError(f"{path}: the first trigger edge is after the last joint sample")
    grid = zero_ns + np.round(np.arange(frames) * step).astype(np.int64)
    js_valid = ~np.isnan(nearest(js.t, np.zeros(len(js.t)), grid, period))

    channels: list[Channel] = []
    js_rate = 1e9 / period
    names = sorted({c.rsplit("_", 1)[0] for c in js.columns}, key=_joint_order)
    for name in names:
        for what, unit in (("angle", "deg"), ("torque", "N.m")):
            col = js.columns[f"{name}_{what}"]
            channels.append(
                Channel(
                    f"{name}_{what}",
                    unit,
                    f"{name} {what} ({unit}), H2 at {js_rate:.1f} Hz, nearest sample",
                    nearest(js.t, col, grid, period),
                    js_rate,
                )
            )
    feet = streams.get("feet")
    if feet is not None:
        refresh = _refresh_s(i.metadata)
        max_age = GAP_FACTOR * (refresh * 1e9 if refresh > 0 else period)
        for col, unit, what in (
            ("r_heel", "1", "right heel switch (1 pressed)"),
            ("r_toe", "1", "right toe switch (1 pressed)"),
            ("l_heel", "1", "left heel switch (1 pressed)"),
            ("l_toe", "1", "left toe switch (1 pressed)"),
            ("battery", "V", "battery (V)"),
        ):
            v = hold(feet.t, feet.columns[col], grid, max_age)
            v[~js_valid] = np.nan
            channels.append(Channel(col, unit, f"{what}, on change, held", v, 0.0))
    for kind in sorted(k for k in streams if k.startswith("maccepa/")):
        s = streams[kind]
        p = s.period_ns()
        board = kind.rsplit("/", 1)[-1]
        for col, (unit, _bit) in MACCEPA_FIELDS.items():
            channels.append(
                Channel(
                    f"{board}_{col}",
                    unit,
                    f"MACCEPA {board} {col} ({unit}) at {1e9 / p if p else 0:.1f} Hz, nearest",
                    nearest(s.t, s.columns[col], grid, p),
                    1e9 / p if p else 0.0,
                )
            )

    events = [Event(t, TRIGGER, "General", f"{edge} edge") for t, edge in triggers]
    skipped = 0
    if feet is not None and len(feet.t):
        for side in SIDES:
            found, n = foot_events(feet, side, debounce_s, js)
            events += found
            skipped += n
    end_ns = int(grid[-1])
    events = sorted((e for e in events if zero_ns <= e.time_ns <= end_ns), key=lambda e: e.time_ns)
    stats = i.metadata.get("exolink.stats", {})
    recovered = i.metadata.get("exolink.recovered", {})
    losses = {
        "recorder_dropped": int(stats.get("dropped", 0) or 0),
        "recovered_lost_messages": int(recovered.get("lost_messages", 0) or 0),
        "events_at_gaps": skipped,
        **{  # foot switches are published on change: their losses are the H2's (joints)
            f"lost_frames_{k}": s.lost_frames() for k, s in streams.items() if k != "feet"
        },
    }
    for kind, s in streams.items():
        if kind.startswith("maccepa/"):
            losses[f"stale_{kind}"] = int(np.count_nonzero(np.isnan(s.columns["current_ma"])))
    trial = Trial(
        str(path),
        rate,
        zero_ns,
        used_zero,
        frames,
        channels,
        events,
        dict(i.metadata.get("exolink.labels", {})),
        losses,
        debounce_s,
    )
    log.debug(
        "trial",
        source=str(path),
        rate_hz=rate,
        frames=frames,
        zero=used_zero,
        events=len(events),
        invalid=sum(c.invalid for c in channels),
    )
    return trial


def _joint_order(name: str) -> tuple[int, str]:
    from exolink.protocol import h2  # heavy: python-can; the joint order only

    return (h2.JOINTS.index(name) if name in h2.JOINTS else len(h2.JOINTS), name)


# --- writing ------------------------------------------------------------------------------------


def _partial(out: Path) -> Path:
    """Where a file is written before it takes its name: nothing half-written is left there."""
    return out.with_name(f".{out.stem}.partial{out.suffix}")


def _parent(out: Path) -> None:
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"cannot write into {out.parent}: {exc.strerror}") from None


def _replace(tmp: Path, out: Path) -> None:
    os.replace(tmp, out)


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
        import ezc3d
    except ImportError:
        raise MissingExtra(
            f"C3D export needs ezc3d: pip install 'exolink[{EXTRA}]' (laptop side)"
        ) from None
    return ezc3d


def write_c3d(trial: Trial, out: str | Path) -> Path:
    """The trial as a C3D file: channels as analogs (float, SCALE 1, OFFSET 0, NaN where not
    measured), no markers, events in the EVENT group as Vicon and Visual3D read them, labels
    and losses in the EXOLINK group, the subject in SUBJECTS."""
    import numpy as np

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
    import numpy as np

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
    from ezc3d import ezc3d as swig

    param = swig.Parameter(name, "")
    param.set(swig.VecInt([int(v) for v in values]))
    c._storage["parameters"].add_parameter(group, param)


def _words(n: int) -> list[int]:
    """A 32-bit frame number as C3D's TRIAL group stores it: two 16-bit words, low first
    (each written as the int16 with the same bits)."""
    return [w - 65536 if w > 32767 else w for w in (n & 0xFFFF, (n >> 16) & 0xFFFF)]


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


def _sto(
    out: Path,
    name: str,
    columns: list[str],
    rows: Iterable[list[float]],
    n: int,
    degrees: bool,
    comments: list[str],
) -> None:
    """OpenSim's storage format (.mot / .sto version 1): name line, version, nRows, nColumns,
    inDegrees, free comment lines, endheader, a tab-separated header row, then the rows."""
    tmp = _partial(out)
    try:
        with tmp.open("w") as f:
            f.write(f"{name}\nversion=1\nnRows={n}\nnColumns={len(columns)}\n")
            f.write(f"inDegrees={'yes' if degrees else 'no'}\n")
            for line in comments:
                f.write(f"{line}\n")
            f.write("endheader\n")
            f.write("\t".join(columns) + "\n")
            for r in rows:
                f.write("\t".join(_num(x) for x in r) + "\n")
        _replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)


def _num(x: float) -> str:
    return "NaN" if math.isnan(x) else f"{x:.8g}"


def write_opensim(trial: Trial, out_dir: str | Path, model: str = "rajagopal") -> list[Path]:
    """``<stem>.mot`` (joint angles, degrees) and ``<stem>_torques.sto`` (N·m) in ``out_dir``,
    OpenSim's coordinate names and signs for ``model`` (rajagopal or gait2392)."""
    import numpy as np

    if model not in MODELS:
        raise RecordingError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    d = Path(out_dir)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"cannot write into {d}: {exc.strerror}") from None
    stem = Path(trial.source).name.removesuffix(".mcap")
    time = np.arange(trial.frames) / trial.rate_hz
    angles, torques, names, moments = [time], [time], ["time"], ["time"]
    for joint, (coord, s_raj, s_2392) in OPENSIM.items():
        sign = s_raj if model == "rajagopal" else s_2392
        try:
            a = trial.channel(f"{joint}_angle").values
            tq = trial.channel(f"{joint}_torque").values
        except StopIteration:
            continue
        angles.append(sign * a)
        torques.append(sign * tq)
        names.append(coord)
        moments.append(f"{coord}_moment")
    comments = [  # key=value lines: OpenSim keeps them as the table's metadata
        f"exolink_source={Path(trial.source).name}",
        f"exolink_model={model}",
        f"exolink_time_zero={trial.zero} {iso(trial.zero_ns)}",
        f"exolink_rate_hz={trial.rate_hz:g}",
        f"exolink_resampling={RESAMPLING}",
        "exolink_nan=not measured (lost in the recording): see the export's loss counts",
    ]
    mot = d / f"{stem}.mot"
    sto = d / f"{stem}_torques.sto"
    _sto(mot, stem, names, np.column_stack(angles).tolist(), trial.frames, True, comments)
    _sto(
        sto,
        f"{stem}_torques",
        moments,
        np.column_stack(torques).tolist(),
        trial.frames,
        False,
        comments,
    )
    return [mot, sto]
