"""A recording into one ``Trial``: its streams read with the file's own schemas
(``read_streams``), put on the H2's clock, with its events and losses (``build_trial``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import structlog
import yaml

from exolink.gaitlab.model import (
    DEBOUNCE_S,
    GAP_FACTOR,
    SIDES,
    TRIGGER,
    Channel,
    Event,
    Stream,
    Trial,
)
from exolink.gaitlab.resample import foot_events, hold, nearest
from exolink.recordings.check import RecordingError
from exolink.recordings.readback import decode, info, iter_messages, message_time_ns

log = structlog.get_logger("exolink.gaitlab")

ZERO_CHOICES = ("first-trigger", "start")
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
    import numpy as np  # lazy: the gaitlab extra

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
        stamps = np.asarray(ts, dtype=np.int64)[order]
        streams[kind] = Stream(
            kind, stamps, {k: np.asarray(v, dtype=np.float64)[order] for k, v in cs.items()}
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


# --- the trial ----------------------------------------------------------------------------------


def _refresh_s(metadata: dict[str, dict[str, str]]) -> float:
    """The h2 reader's foot_switches_refresh_s in the recording's config (1.0 if not said)."""

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
    trigger events, the labels and the losses (see the package's docstring for every rule)."""
    import numpy as np  # lazy: the gaitlab extra

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
