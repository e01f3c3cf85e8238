"""The OpenSim writer (``write_opensim``): joint angles as ``.mot``, torques as ``.sto``, in
OpenSim's storage format with its models' coordinate names and signs."""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

from exolink.gaitlab.model import RESAMPLING, Trial
from exolink.gaitlab.output import _partial, _replace
from exolink.recordings.check import RecordingError, iso

MODELS = ("rajagopal", "gait2392")
# H2 joint -> (OpenSim coordinate, sign for rajagopal, sign for gait2392)
OPENSIM = {
    "r_hip": ("hip_flexion_r", 1, 1),
    "r_knee": ("knee_angle_r", 1, -1),
    "r_ankle": ("ankle_angle_r", 1, 1),
    "l_hip": ("hip_flexion_l", 1, 1),
    "l_knee": ("knee_angle_l", 1, -1),
    "l_ankle": ("ankle_angle_l", 1, 1),
}


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
    import numpy as np  # lazy: the gaitlab extra

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
