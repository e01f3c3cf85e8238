"""The gait lab's export (exolink.gaitlab, `exolink export --c3d/--opensim/--events`).

Written with ezc3d, read back with an independent reader: py-c3d (``c3d`` on PyPI, pure
Python, no code in common with ezc3d). The MCAP side is read with mcap's reader and rosbags
(test_recording.rosbags_decode), not with the export's own reading. The .mot/.sto files are
read by OpenSim's own Python package (``opensim``, dev extra on x86-64 Linux) and by a plain
parser that follows OpenSim's documented storage header."""

from __future__ import annotations

import csv
import math
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_recording import recordings, rosbags_decode

from benchmarks.bench_gaitlab import synthetic
from benchmarks.harness import EXOLINK, Appliance
from exolink import gaitlab
from exolink.config import bundled
from exolink.protocol.h2 import JOINTS
from exolink.recordings.readback import RecordingError, info

C3D = pytest.importorskip("c3d")  # the independent reader (dev extra)

MACCEPA = (
    "current_ma",
    "temperature_c",
    "velocity_rpm",
    "load_n",
    "link_deg",
    "lever_deg",
    "extra_position",
    "extra_sensor",
    "setpoint",
    "actuation",
    "process_variable",
)


def read_c3d(path: Path) -> dict:
    """Everything the tests look at, through py-c3d: analogs as [channel, sample]."""
    with path.open("rb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No point data found": there are no markers
        r = C3D.Reader(f)
        frames = [analog for _i, _p, analog in r.read_frames()]
        ev = r.get("EVENT")
        ex = r.get("EXOLINK")
        out = {
            "labels": [s.strip() for s in r.analog_labels],
            "units": [s.strip() for s in r.get("ANALOG").get("UNITS").string_array],
            "scale": r.get("ANALOG").get("SCALE").float_array,
            "rate": r.analog_rate,
            "point_rate": r.point_rate,
            "analogs": np.concatenate(frames, axis=1) if frames else np.zeros((0, 0)),
            "subject": [s.strip() for s in r.get("SUBJECTS").get("NAMES").string_array],
            "label_keys": [s.strip() for s in ex.get("LABEL_KEYS").string_array],
            "label_values": [s.strip() for s in ex.get("LABEL_VALUES").string_array],
            "loss_names": [s.strip() for s in ex.get("LOSS_NAMES").string_array],
            "loss_counts": [int(x) for x in ex.get("LOSS_COUNTS").float_array],
            "zero": ex.get("ZERO").string_value.strip(),
            "trial_end": tuple(
                int(x) & 0xFFFF for x in r.get("TRIAL").get("ACTUAL_END_FIELD").int16_array
            ),
            "icon_ids": r.get("EVENT").get("ICON_IDS").int16_array.tolist(),
            "events": [],
        }
        used = int(ev.get("USED").int16_value) if ev.get("USED").bytes_per_element == 2 else 0
        if used:
            times = ev.get("TIMES").float_array.reshape(-1, 2)
            out["events"] = [
                (60 * m + s, label.strip(), ctx.strip())
                for (m, s), label, ctx in zip(
                    times,
                    ev.get("LABELS").string_array,
                    ev.get("CONTEXTS").string_array,
                    strict=True,
                )
            ]
    return out


def read_sto(path: Path) -> tuple[dict[str, str], list[str], np.ndarray]:
    """OpenSim's storage format as documented: a name line, key=value lines (version=1,
    nRows, nColumns, inDegrees), endheader, a tab-separated header row, tab-separated rows."""
    lines = path.read_text().splitlines()
    end = lines.index("endheader")
    head = {"name": lines[0]}
    for line in lines[1:end]:
        k, sep, v = line.partition("=")
        assert sep, f"header line without '=': {line!r}"
        head[k] = v
    columns = lines[end + 1].split("\t")
    rows = np.array([[float(x) for x in row.split("\t")] for row in lines[end + 2 :]])
    assert head["version"] == "1"
    assert int(head["nRows"]) == len(rows) and int(head["nColumns"]) == len(columns)
    assert rows.shape[1] == len(columns)
    return head, columns, rows


def contact_changes(feet: list[tuple[int, object]], side: str) -> list[tuple[int, bool]]:
    """(stamp, new contact) at each change of heel-or-toe of one side, from decoded messages."""
    out, state = [], None
    for ns, m in feet:
        c = bool(getattr(m, f"{side}_heel") or getattr(m, f"{side}_toe"))
        if state is not None and c != state:
            out.append((ns, c))
        state = c
    return out


def stamp(m: object) -> int:
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec  # type: ignore[attr-defined]


@pytest.mark.slow
def test_simulator_walking_exported_to_c3d_and_opensim(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The simulator walking the default pattern (the bundled sim config: the pattern player,
    MACCEPA board 0), recorded with labels and a trigger edge, exported by the CLI; the C3D
    read back by py-c3d and compared with the MCAP read by mcap + rosbags."""
    rec_dir = tmp_path / "rec"
    nodes = yaml.safe_load(bundled("sim").read_text())["nodes"]
    nodes = [n for n in nodes if n["name"] != "timing_monitor"]
    for n in nodes:
        if n["name"] == "recorder":
            n["params"]["directory"] = str(rec_dir)
        if n["name"] == "controller_manager":  # silence limits above this shared machine's
            n["heartbeat_deadline_ms"] = 300  # stalls (as test_controllers): not what this
            n["params"]["h2_timeout_ms"] = 300  # test is about, and a trip stops the walk
    app = Appliance(write_config(nodes=nodes, watchdog={"pulse_silence_ms": 500}), spawn)
    app.arm_and_hold()
    assert app.cli("pattern", "start", "--detach").returncode == 0
    r = app.cli("record", "start", "--label", "subject=S01", "--label", "session=walk1")
    assert r.returncode == 0, r.stderr
    time.sleep(0.5)
    assert app.cli("trigger", "fire").returncode == 0
    time.sleep(4)
    assert app.cli("record", "stop").returncode == 0
    [path] = recordings(rec_dir)

    joints = [(stamp(m), m) for _d, m in rosbags_decode(path, "/h2/joint_states")]
    feet = [(stamp(m), m) for _d, m in rosbags_decode(path, "/h2/foot_switches")]
    board = [(stamp(m), m) for _d, m in rosbags_decode(path, "/h2/maccepa/b0/state")]
    [trigger_ns] = info(path).triggers
    assert len(joints) > 300 and len(feet) > 4 and len(board) > 300

    out = tmp_path / "out"
    r = subprocess.run(
        [*EXOLINK, "export", str(path), "--c3d", str(out / "start.c3d"), "--zero", "start"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "resampling: nearest recorded sample" in r.stdout
    c = read_c3d(out / "start.c3d")
    expect = [f"{j}_{w}" for j in JOINTS for w in ("angle", "torque")]
    expect += ["r_heel", "r_toe", "l_heel", "l_toe", "battery"] + [f"b0_{f}" for f in MACCEPA]
    assert c["labels"] == expect
    assert c["units"][:2] == ["deg", "N.m"] and c["units"][16] == "V"
    assert c["units"][12:16] == ["1"] * 4 and c["units"][17:21] == ["mA", "degC", "rpm", "N"]
    assert list(c["scale"]) == [1.0] * len(expect)
    assert c["rate"] == 100.0 and c["analogs"].shape[0] == len(expect)
    assert c["subject"] == ["S01"] and c["zero"] == "start"
    assert dict(zip(c["label_keys"], c["label_values"], strict=True)) == {
        "subject": "S01",
        "session": "walk1",
    }
    a = c["analogs"]
    # the first frame is the first joint sample; the feet and the board: their first messages
    first, last = joints[0][1], joints[-1][1]
    for k, _j in enumerate(JOINTS):
        assert a[2 * k, 0] == pytest.approx(math.degrees(first.position[k]), abs=1e-4)
        assert a[2 * k + 1, 0] == pytest.approx(first.effort[k], abs=1e-5)
    if feet[0][0] <= joints[0][0]:  # a state held from before the first joint sample
        assert a[16, 0] == pytest.approx(feet[0][1].battery_volts, abs=1e-5)
    # the last frame: the joint sample nearest its time (the last one, or one before if the
    # clock's last tick fell nearer to it)
    t_last = joints[0][0] + (a.shape[1] - 1) * 10_000_000
    near = min(joints[-3:], key=lambda x: abs(x[0] - t_last))[1]
    assert near is last or near is joints[-2][1]
    for k, _j in enumerate(JOINTS):
        assert a[2 * k, -1] == pytest.approx(math.degrees(near.position[k]), abs=1e-4)
        assert a[2 * k + 1, -1] == pytest.approx(near.effort[k], abs=1e-5)
    # every value shown was measured: each board current is one the board sent
    currents = {float(m.current_ma) for _t, m in board}
    assert set(a[17][~np.isnan(a[17])].tolist()) <= currents

    # time zero at the trigger: its edge the first event, at 0; the gait events at the foot
    # switch transitions of the recording
    r = subprocess.run(
        [*EXOLINK, "export", str(path), "--c3d", str(out / "walk.c3d"), "--opensim", str(out)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    c = read_c3d(out / "walk.c3d")
    assert c["zero"] == "first-trigger"
    assert c["events"][0][1:] == ("Trigger", "General") and c["events"][0][0] == 0.0
    assert c["icon_ids"] == [
        {"Trigger": 0, "Foot Strike": 1, "Foot Off": 2}[e[1]] for e in c["events"]
    ]
    lost = dict(zip(c["loss_names"], c["loss_counts"], strict=True))
    for side, ctx in (("r", "Right"), ("l", "Left")):
        changes = {ns: on for ns, on in contact_changes(feet, side)}
        found = [(t, lab) for t, lab, cx in c["events"] if cx == ctx]
        strikes = [t for t, lab in found if lab == "Foot Strike"]
        offs = [t for t, lab in found if lab == "Foot Off"]
        assert strikes and offs, (side, c["events"])  # it walked
        for t, lab in found:  # each at a transition of that side's switches, the right way
            ns = min(changes, key=lambda x: abs((x - trigger_ns) / 1e9 - t))
            assert abs((ns - trigger_ns) / 1e9 - t) < 5e-5, (t, lab)
            assert changes[ns] == (lab == "Foot Strike")
        # every transition that held 30 ms (and followed one that did) is an event
        stamps = sorted(changes)
        held = [
            ns
            for prev, ns, nxt in zip([0, *stamps[:-1]], stamps, [*stamps[1:], 2**63], strict=True)
            if nxt - ns >= 30_000_000
            and ns - prev >= 30_000_000
            and ns >= trigger_ns
            and ns <= joints[-1][0]
        ]
        assert len(found) >= len(held) - lost.get("events_at_gaps", 0), (held, found)
    with (out / "walk_events.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(float(x["time_s"]), x["label"], x["context"]) for x in rows] == [
        (pytest.approx(t, abs=1e-5), lab, cx) for t, lab, cx in c["events"]
    ]

    # the .mot: OpenSim's columns, degrees, the angles of the C3D's frames
    head, cols, rows_mot = read_sto(out / f"{path.stem}.mot")
    assert head["inDegrees"] == "yes"
    assert cols == [
        "time",
        "hip_flexion_r",
        "knee_angle_r",
        "ankle_angle_r",
        "hip_flexion_l",
        "knee_angle_l",
        "ankle_angle_l",
    ]
    assert rows_mot.shape[0] == c["analogs"].shape[1] or rows_mot.shape[0] <= c["analogs"].shape[1]
    assert rows_mot[1, 0] == pytest.approx(0.01)
    np.testing.assert_allclose(rows_mot[:, 2], c["analogs"][2, : len(rows_mot)], atol=1e-4)
    try:
        labels, _t, values, _m = opensim_table(out / f"{path.stem}.mot")
    except pytest.skip.Exception:
        pass  # no OpenSim wheel for this machine: the plain parser above
    else:
        assert labels == cols[1:]
        np.testing.assert_array_equal(values, rows_mot[:, 1:])
    head, cols, rows_sto = read_sto(out / f"{path.stem}_torques.sto")
    assert head["inDegrees"] == "no" and cols[1:4] == [
        "hip_flexion_r_moment",
        "knee_angle_r_moment",
        "ankle_angle_r_moment",
    ]
    np.testing.assert_allclose(rows_sto[:, 1], c["analogs"][1, : len(rows_sto)], atol=1e-4)


def test_gaps_and_stale_frames_are_nan_and_counted(tmp_path: Path) -> None:
    """Half a second without H2 frames and every 50th MACCEPA sensors frame stale: NaN there
    and nowhere else, counted, and the CLI says it; never a value the recording lacks."""
    src = tmp_path / "walk.mcap"
    synthetic(src, 12, gaps=[(5.0, 0.5)], stale_every=50, dropped=3)
    out = tmp_path / "out"
    r = subprocess.run(
        [*EXOLINK, "export", str(src), "--c3d", str(out / "w.c3d"), "--zero", "start"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "r_hip_angle 50" in r.stdout and "lost_frames_joints 50" in r.stdout
    assert "recorder_dropped 3" in r.stdout and "stale_maccepa/b0 24" in r.stdout
    c = read_c3d(out / "w.c3d")
    a = c["analogs"]
    assert a.shape[1] == 1200
    lost = dict(zip(c["loss_names"], c["loss_counts"], strict=True))
    assert lost["lost_frames_joints"] == 50 and lost["recorder_dropped"] == 3
    hole = np.isnan(a[0])
    assert hole.sum() == 50 and hole[500:550].all()  # exactly the gap's ticks
    for k in range(17):  # joints, switches, battery: the same CAN cycle, the same hole
        assert (np.isnan(a[k]) == hole).all(), c["labels"][k]
    stale = np.isnan(a[17])
    assert stale.sum() == 24 and stale[::50].all()
    assert not np.isnan(a[21:]).any()  # the positions frame was never stale
    # nothing invented: every angle shown is one of the recording's whole degrees
    assert np.all(a[0][~hole] == np.round(a[0][~hole]))
    # no gait event inside the gap, and the transition right after it is not one either
    inside = [t for t, lab, _c in c["events"] if 5.0 <= t <= 5.51 and lab != "Trigger"]
    assert inside == []


def test_a_long_trial_fits_c3d_frames_and_reads_back_whole(tmp_path: Path) -> None:
    """12 minutes at 100 Hz: 72000 samples, more than a C3D header counts: 2 analog samples
    a frame (points at 50 Hz), and every sample read back as written."""
    src = tmp_path / "long.mcap"
    synthetic(src, 720, gaps=[(100.0, 0.3)])
    trial = gaitlab.build_trial(src, "start")
    assert gaitlab.samples_per_frame(trial.frames, trial.rate_hz) == 2
    gaitlab.write_c3d(trial, tmp_path / "long.c3d")
    c = read_c3d(tmp_path / "long.c3d")
    assert c["rate"] == 100.0 and c["point_rate"] == 50.0
    frames = -(-trial.frames // 2)
    assert c["trial_end"] == (frames & 0xFFFF, frames >> 16)
    a = c["analogs"][:, : trial.frames]
    for k, ch in enumerate(trial.channels):
        np.testing.assert_array_equal(np.isnan(a[k]), np.isnan(ch.values), err_msg=ch.label)
        ok = ~np.isnan(a[k])
        np.testing.assert_allclose(a[k][ok], ch.values[ok], rtol=1e-6, err_msg=ch.label)
    assert np.isnan(c["analogs"][:, trial.frames :]).all()  # the last frame's padding


def test_opensim_models_sign_and_trigger_fallback(tmp_path: Path) -> None:
    src = tmp_path / "walk.mcap"
    synthetic(src, 3, triggers=())
    r = subprocess.run(
        [*EXOLINK, "export", str(src), "--opensim", str(tmp_path / "raj")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "no trigger edge in the recording" in r.stderr
    r = subprocess.run(
        [
            *EXOLINK,
            "export",
            str(src),
            "--opensim",
            str(tmp_path / "g"),
            "--opensim-model",
            "gait2392",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    _h, cols, raj = read_sto(tmp_path / "raj" / "walk.mot")
    _h, _c, g = read_sto(tmp_path / "g" / "walk.mot")
    knee = cols.index("knee_angle_r")
    assert (raj[:, knee] >= 0).all() and raj[:, knee].max() > 20  # flexion +, as the H2
    np.testing.assert_array_equal(g[:, knee], -raj[:, knee])  # gait2392: flexion -
    hip = cols.index("hip_flexion_r")
    np.testing.assert_array_equal(g[:, hip], raj[:, hip])
    assert (tmp_path / "raj" / "walk_events.csv").exists()


def opensim_table(path: Path) -> tuple[list[str], np.ndarray, np.ndarray, dict[str, str]]:
    """OpenSim's own reader (TimeSeriesTable, what its 4.x tools read): column labels, time,
    values, header metadata."""
    osim = pytest.importorskip("opensim")
    osim.Logger.removeFileSink()  # else OpenSim writes opensim.log into the working directory
    t = osim.TimeSeriesTable(str(path))
    meta = {k: t.getTableMetaDataAsString(k) for k in t.getTableMetaDataKeys()}
    times = np.array([t.getIndependentColumn()[i] for i in range(t.getNumRows())])
    return list(t.getColumnLabels()), times, t.getMatrix().to_numpy(), meta


def test_opensim_reads_the_mot_and_sto(tmp_path: Path) -> None:
    """OpenSim itself reads both files: its model's coordinate names, degrees, every row, the
    values of the C3D's channels, NaN where the recording has a gap. Its older Storage class
    (the GUI's loader) reads a file without NaN whole; it stops at the first NaN row (said in
    docs/gaitlab)."""
    osim = pytest.importorskip("opensim")
    for name, gaps in (("gap", [(2.0, 0.3)]), ("whole", [])):
        src = tmp_path / f"{name}.mcap"
        synthetic(src, 6, gaps=gaps)
        trial = gaitlab.build_trial(src, "start")
        mot, sto = gaitlab.write_opensim(trial, tmp_path / name)
        labels, times, values, meta = opensim_table(mot)
        assert labels == [
            "hip_flexion_r",
            "knee_angle_r",
            "ankle_angle_r",
            "hip_flexion_l",
            "knee_angle_l",
            "ankle_angle_l",
        ]
        assert meta["inDegrees"] == "yes" and meta["exolink_model"] == "rajagopal"
        assert len(times) == trial.frames and times[1] == pytest.approx(0.01)
        for k, j in enumerate(JOINTS):
            np.testing.assert_allclose(values[:, k], trial.channel(f"{j}_angle").values, atol=1e-6)
        labels, _t, torques, meta = opensim_table(sto)
        assert labels[0] == "hip_flexion_r_moment" and meta["inDegrees"] == "no"
        np.testing.assert_allclose(torques[:, 1], trial.channel("r_knee_torque").values, atol=1e-6)
        nan_rows = int(np.isnan(values).any(axis=1).sum())
        assert nan_rows == (30 if gaps else 0)
        storage = osim.Storage(str(mot))
        assert storage.isInDegrees()
        if not gaps:
            assert storage.getSize() == trial.frames


def test_debounce_ignores_a_blip(tmp_path: Path) -> None:
    """A 20 ms contact blip in swing is not a Foot Strike (debounce 30 ms); at 10 ms it is."""
    ns = 1_000_000_000
    t = np.array([0, 100, 400, 420, 700, 1000]) * 1_000_000 + ns
    heel = np.array([1, 0, 1, 0, 1, 1], dtype=float)
    zeros = np.zeros(len(t))
    feet = gaitlab.Stream(
        "feet", t, {"r_heel": heel, "r_toe": zeros, "l_heel": zeros, "l_toe": zeros}
    )
    ev, skipped = gaitlab.foot_events(feet, "r", 0.030)
    assert [(e.label, (e.time_ns - ns) // 1_000_000) for e in ev] == [
        ("Foot Off", 100),
        ("Foot Strike", 700),
    ] and skipped == 0
    ev, _ = gaitlab.foot_events(feet, "r", 0.010)
    assert [(e.label, (e.time_ns - ns) // 1_000_000) for e in ev] == [
        ("Foot Off", 100),
        ("Foot Strike", 400),
        ("Foot Off", 420),
        ("Foot Strike", 700),
    ]


def test_without_the_extra_the_error_names_it_and_nothing_is_written(tmp_path: Path) -> None:
    src = tmp_path / "walk.mcap"
    synthetic(src, 2)
    code = (
        "import sys; sys.modules['ezc3d'] = None\n"
        "from exolink.cli.main import main\n"
        f"sys.exit(main(['export', {str(src)!r}, '--c3d', {str(tmp_path / 'x.c3d')!r}]))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode != 0 and "pip install 'exolink[gaitlab]'" in r.stderr, r.stderr
    assert list(tmp_path.iterdir()) == [src]


def test_a_damaged_recording_is_refused_before_any_output(tmp_path: Path) -> None:
    src = tmp_path / "walk.mcap"
    synthetic(src, 5)
    bad = tmp_path / "bad.mcap"
    shutil.copy(src, bad)
    data = bytearray(bad.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError):
        gaitlab.build_trial(bad)
    r = subprocess.run(
        [*EXOLINK, "export", str(bad), "--c3d", str(tmp_path / "o" / "x.c3d")],
        capture_output=True,
        text=True,
    )
    assert r.returncode != 0 and not (tmp_path / "o").exists()


def test_the_board_gets_nothing_new() -> None:
    """ezc3d is an extra, never a runtime dependency, and not in the image's pins."""
    import tomllib

    root = Path(__file__).parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    assert not any("ezc3d" in d or d.startswith("c3d") for d in project["dependencies"])
    assert project["optional-dependencies"]["gaitlab"] == ["ezc3d>=1.7,<2"]
    assert "ezc3d" not in (root / "image/python-requirements.txt").read_text()
    lock = (root / "requirements.lock").read_text().split()
    assert "ezc3d==1.7.2" in lock and "c3d==0.6.0" in lock
