"""The first vertical slice across real processes: simulator -> CAN (udp_multicast) -> reader ->
Zenoh -> a subscriber in another process, and CLI commands back through the controller manager."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import time
from pathlib import Path

import can
import numpy as np
import pytest
import zenoh
from conftest import (
    FEET_RUNS,
    FEET_STATES,
    feet_runs,
    feet_subscriber,
    reader_stats,
    stream_feet,
    wait_alive,
)
from rosbags.typesys import Stores, get_typestore

from benchmarks.harness import EXOLINK, collect, connect, wait_for
from exolink import messaging
from exolink.canbus import open_bus
from exolink.config import load
from exolink.control.holder import Holder
from exolink.protocol import h2

NODES = [
    {"name": "simulator", "plugin": "simulator"},
    {"name": "h2_reader", "plugin": "h2_reader"},
    {
        "name": "controller_manager",
        "plugin": "controller_manager",
        "params": {"require_armed": False},
    },
]
# The lab's limits (the config's `limits:` section): stricter than the mechanical ranges.
LIMITS = {
    "joints": {
        j: {"max": hi, "torque": cap, "stiffness": 50}
        for j, hi, cap in zip(
            h2.JOINTS, (90, 80, 15, 90, 80, 15), (20, 20, 10, 20, 20, 10), strict=True
        )
    }
}

SUBSCRIBER = r"""
import sys, time, zenoh
from exolink import messaging
from exolink.canbus import open_bus
from exolink.config import load
cfg = load(sys.argv[1])
s = messaging.open_client_session(messaging.local_endpoint(cfg.zenoh))
key = messaging.topic_key(0, "h2", "joint_states", "sensor_msgs/msg/JointState")
out = open(sys.argv[2], "wb")
def on(sample):
    att = sample.attachment.to_bytes()
    p = sample.payload.to_bytes()
    out.write(len(p).to_bytes(4, "little") + p + att + str(sample.key_expr).encode().ljust(200))
    out.flush()
sub = s.declare_subscriber(key, on)
time.sleep(float(sys.argv[3]))
sub.undeclare(); out.close(); s.close()
"""


def read_samples(path: Path) -> list[tuple[bytes, bytes, str]]:
    data, out, i = path.read_bytes(), [], 0
    while i + 4 <= len(data):
        n = int.from_bytes(data[i : i + 4], "little")
        payload = data[i + 4 : i + 4 + n]
        att = data[i + 4 + n : i + 37 + n]
        key = data[i + 37 + n : i + 237 + n].decode().strip()
        out.append((payload, att, key))
        i += 237 + n
    return out


@pytest.fixture
def appliance(write_config, spawn):  # type: ignore[no-untyped-def]
    cfg_path = write_config(nodes=NODES, limits=LIMITS)
    cfg = load(cfg_path)
    procs = {
        "simulator": spawn(
            "node",
            "run",
            "simulator",
            "-c",
            str(cfg_path),
            "--listen",
            cfg.zenoh.listen[0],
            name="simulator",
        ),
    }
    for n in ("h2_reader", "controller_manager"):
        procs[n] = spawn("node", "run", n, "-c", str(cfg_path), name=n)
    wait_alive(messaging.local_endpoint(cfg.zenoh), list(procs))
    return cfg_path, cfg, procs


def hold(cfg, spawn) -> Holder:  # type: ignore[no-untyped-def]
    """Motion held as `exolink hold` would hold it, for the rest of the test."""
    session = connect(messaging.local_endpoint(cfg.zenoh))
    key = messaging.mgmt_key(cfg.device, "controllers")
    holder = Holder(lambda b: messaging.request(session, key, b, 10.0), "test")
    holder.acquire()
    spawn.cleanups += [session.close, holder.release]
    return holder


def cli(cfg, *args: str, timeout: float = 20) -> subprocess.CompletedProcess[str]:  # type: ignore[no-untyped-def]
    at = messaging.local_endpoint(cfg.zenoh)
    return subprocess.run(
        [*EXOLINK, *args, "--at", at], capture_output=True, text=True, timeout=timeout
    )


def test_joint_states_reach_another_process_with_sim_values(appliance, tmp_path, mbus) -> None:  # type: ignore[no-untyped-def]
    cfg_path, _cfg, procs = appliance
    wait_for(lambda: collect(mbus, 0.2, {h2.JOINT_ANGLES}), timeout=15)  # reader started the stream
    out = tmp_path / "samples.bin"
    sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(cfg_path), str(out), "3"])
    # What the simulator put on the bus, seen by an independent listener meanwhile.
    bus_frames = collect(mbus, 3.5, {h2.JOINT_ANGLES, h2.JOINT_TORQUES})
    sub.wait(10)
    samples = read_samples(out)
    assert len(samples) > 200, [p.output() for p in procs.values()]
    stamps, seqs, gids = [], [], set()
    by_ts = {round(m.timestamp * 1e9): h2.decode(m) for m in bus_frames if m.arbitration_id == 110}
    matched = 0
    for payload, att, key in samples:
        # Independent decoder: rosbags' own typestore, not exolink's wrapper.
        msg = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(
            payload, "sensor_msgs/msg/JointState"
        )
        assert payload[:4] == b"\x00\x01\x00\x00"
        # key and attachment byte by byte, without exolink's own helpers
        rihs = get_typestore(Stores.ROS2_JAZZY).hash_rihs01("sensor_msgs/msg/JointState")
        assert key == f"0/h2/joint_states/sensor_msgs::msg::dds_::JointState_/{rihs}"
        assert len(att) == 33 and att[16] == 16
        seq = int.from_bytes(att[0:8], "little", signed=True)
        ts = int.from_bytes(att[8:16], "little", signed=True)
        gid = att[17:33]
        assert seq > 0 and len(gid) == 16 and any(gid)
        gids.add(gid)
        seqs.append(seq)
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert ts == ns
        stamps.append(ns)
        assert list(msg.name) == list(h2.JOINTS)
        sent = by_ts.get(ns)
        if sent is not None:
            matched += 1
            np.testing.assert_allclose(msg.position, np.radians(list(sent)))
    assert matched > 0.8 * len(samples)
    assert (
        len(gids) == 1 and seqs == sorted(seqs) and seqs[-1] - seqs[0] == len(seqs) - 1
    )  # one publisher, no gaps
    periods = np.diff(stamps) / 1e6
    assert 9.0 < float(np.median(periods)) < 11.0  # 100 Hz from CAN timestamps


def test_cli_command_moves_joint_and_refusals_send_nothing(appliance, mbus, spawn) -> None:  # type: ignore[no-untyped-def]
    _cfg_path, cfg, procs = appliance
    wait_for(lambda: collect(mbus, 0.2, {h2.JOINT_ANGLES}), timeout=15)
    r = cli(cfg, "send", "position", "r_knee", "30")
    assert r.returncode == 5 and "nobody holds motion" in r.stderr, r.stderr
    hold(cfg, spawn)
    r = cli(cfg, "send", "position", "r_knee", "30")
    assert r.returncode == 0, r.stderr + procs["controller_manager"].output()
    assert r.stdout.startswith("ok held by controller operator.r_knee.position")
    wait_for(lambda: any(h2.decode(m).r_knee == 30 for m in collect(mbus, 0.1, {110})), timeout=5)

    refusals = [
        (["send", "position", "r_knee", "85"], "outside the limits 0..80"),
        (["send", "position", "r_knee", "101"], "outside 0..100"),
        (["send", "position", "r_elbow", "10"], "unknown joint 'r_elbow'"),
        (["send", "stiffness", "l_knee", "10", "120"], "120 is outside 0..100"),
        (["send", "limits", "--max", "0,0,30,0,0,0"], "MaxAngles.r_ankle: 30 is outside -20..20"),
        (["send", "torque", "all", "3"], "'all' joints is only for disabled or stopped"),
        # Issue 19 (4): limits that hold.
        (
            ["send", "limits", "--min=50,50,0,0,0,0", "--max=10,10,15,90,80,15"],
            "min 50 must be below max 10",
        ),
        (
            ["send", "limits", "--max=95,80,15,90,80,15"],
            "r_hip: limits -20..95 reach outside the configured -20..90",
        ),
        (["send", "torque", "r_knee", "21"], "r_knee torque 21 counts is above its cap 20"),
        (["send", "torque", "r_ankle", "-11"], "r_ankle torque -11 counts is above its cap 10"),
        (["send", "stiffness", "l_knee", "10", "60"], "l_knee stiffness 60 % is above its cap 50"),
    ]
    mbus.q.queue.clear()  # the held r_knee's set-points so far
    for args, expected in refusals:
        r = cli(cfg, *args)
        assert r.returncode == 5, (args, r.stderr)
        assert expected in r.stderr, (args, r.stderr)
    # The independent listener saw no command frame of the refusals: only the held r_knee's.
    assert {h2.decode(f) for f in collect(mbus, 0.5, {70, 75, 80, 85})} <= {
        h2.JointControl(2, 1, 30, 0)
    }
    r = cli(cfg, "send", "disable", "all")
    assert r.returncode == 0, r.stderr
    frames = [h2.decode(f) for f in collect(mbus, 0.5, {70})]
    disabled = [f for f in frames if f.mode == h2.MODES["disabled"]]
    assert sorted(f.motor for f in disabled) == [1, 2, 3, 4, 5, 6]
    assert frames[frames.index(disabled[-1]) + 1 :] == []  # nothing held after the disable
    # Stricter limits an operator sends bind every later command (configured r_knee max is 80).
    assert cli(cfg, "send", "limits", "--max", "90,60,15,90,80,15").returncode == 0
    r = cli(cfg, "send", "position", "r_knee", "70")
    assert r.returncode == 5 and "outside the limits 0..60" in r.stderr, r.stderr
    assert cli(cfg, "send", "torque", "r_knee", "20").returncode == 0  # at the cap: allowed


def test_negative_limit_lists_need_no_equals_sign(appliance, mbus) -> None:  # type: ignore[no-untyped-def]
    """Issue 19: `--min -10,0,...` (no `=`) is a value, not an unknown option."""
    _cfg_path, cfg, _procs = appliance
    wait_for(lambda: collect(mbus, 0.2, {h2.JOINT_ANGLES}), timeout=15)
    r = cli(cfg, "send", "limits", "--min", "-10,0,-20,-10,0,-20", "--max", "90,80,15,90,80,15")
    assert r.returncode == 0, r.stderr
    frames = {m.arbitration_id: h2.decode(m) for m in collect(mbus, 0.5, {h2.MIN_ANGLES})}
    assert list(frames[h2.MIN_ANGLES]) == [-10, 0, -20, -10, 0, -20]


def test_cli_echo_topics_hz(appliance, mbus) -> None:  # type: ignore[no-untyped-def]
    _cfg_path, cfg, _procs = appliance
    wait_for(lambda: collect(mbus, 0.2, {h2.JOINT_ANGLES}), timeout=15)
    r = cli(cfg, "echo", "joint_states", "--json", "-n", "3")
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    assert len(lines) == 3 and lines[0]["name"] == list(h2.JOINTS)
    assert "rad" not in r.stdout  # --json stays raw
    # Issue 19: the text view says the units (joint angles also in degrees, as commands take them)
    r = cli(cfg, "echo", "joint_states", "-n", "1")
    assert r.returncode == 0, r.stderr
    fields = dict(line.split(": ", 1) for line in r.stdout.splitlines() if ": " in line)
    assert fields["position"].endswith(" deg)") and " rad  ([" in fields["position"], r.stdout
    assert fields["effort"].endswith("] N·m"), r.stdout
    r = cli(cfg, "echo", "foot_switches", "-n", "1")
    assert r.returncode == 0, r.stderr
    assert "battery_volts: " in r.stdout and " V\n" in r.stdout, r.stdout
    assert "battery_raw: " in r.stdout and " counts\n" in r.stdout, r.stdout
    r = cli(cfg, "topics", "--listen", "1")
    assert "/h2/joint_states" in r.stdout and "sensor_msgs/msg/JointState" in r.stdout
    assert "/h2/foot_switches" in r.stdout
    r = cli(cfg, "echo", "no_such_topic", "--timeout", "1")
    assert r.returncode == 4 and "no messages on no_such_topic within 1 s" in r.stderr
    r = cli(cfg, "hz", "joint_states", "-n", "2")
    rates = [float(line.split()[1]) for line in r.stdout.splitlines()]
    assert rates and all(80 < x < 120 for x in rates), r.stdout


def test_cli_unreachable_is_an_error_not_a_hang(tmp_path: Path) -> None:
    t = time.monotonic()
    r = subprocess.run(
        [*EXOLINK, "send", "stream", "on", "--at", "tcp/127.0.0.1:9", "--timeout", "1"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert r.returncode == 4
    assert "no appliance answers at tcp/127.0.0.1:9" in r.stderr
    assert time.monotonic() - t < 15
    r = subprocess.run(
        [*EXOLINK, "echo", "x", "--at", "tcp/127.0.0.1:9", "--timeout", "1"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert r.returncode == 4 and "no appliance answers at tcp/127.0.0.1:9" in r.stderr


def test_reader_counts_gaps_and_malformed(write_config, spawn, group) -> None:  # type: ignore[no-untyped-def]
    cfg_path = write_config(nodes=NODES[:2])
    cfg = load(cfg_path)
    spawn("node", "run", "simulator", "-c", str(cfg_path), "--listen", cfg.zenoh.listen[0])
    spawn("node", "run", "h2_reader", "-c", str(cfg_path))
    s = connect(messaging.local_endpoint(cfg.zenoh))
    try:

        def frames_seen() -> int:
            try:
                return messaging.request(s, "exolink/sim/nodes/h2_reader/stats", timeout_s=3)[
                    "frames"
                ]["110"]
            except messaging.Unreachable:  # the reader's queryable is not declared yet
                return 0

        wait_for(lambda: frames_seen() > 20, timeout=20)
        messaging.request(s, "exolink/sim/sim/fault", {"fault": "silent", "duration_s": 0.2})
        time.sleep(0.4)  # one fault at a time
        messaging.request(s, "exolink/sim/sim/fault", {"fault": "malformed", "duration_s": 0.2})
        time.sleep(1.0)
        stats = messaging.request(s, "exolink/sim/nodes/h2_reader/stats", timeout_s=3)
        assert stats["missing"]["110"] >= 10  # ~20 periods silent
        assert stats["malformed"] >= 10
        # Issue 19: an angle outside the joint's mechanical range (r_ankle 90, range -20..20)
        # is counted as a fault, not passed off as a plain angle.
        bus = open_bus(cfg.can)
        bus.send(
            can.Message(
                arbitration_id=110, data=bytes([10, 20, 90, 10, 20, 0]), is_extended_id=False
            )
        )
        bus.shutdown()
        wait_for(
            lambda: messaging.request(s, "exolink/sim/nodes/h2_reader/stats")["out_of_range"] >= 1
        )
        r = messaging.request(s, "exolink/sim/sim/fault", {"fault": "meteor"})
        assert r == {
            "ok": False,
            "error": "unknown fault 'meteor' (valid: none, silent, malformed, flood)",
        }
    finally:
        s.close()


def test_a_reader_waking_every_fourth_cycle_still_publishes_every_sample_in_order(
    write_config, spawn, tmp_path
) -> None:  # type: ignore[no-untyped-def]
    """The board config's ``cycles_per_read: 4`` (canbus.Cadence): a quarter of the wake-ups
    and Zenoh bursts, and a subscriber in another process still gets every cycle's sample, in
    order, stamped 10 ms apart by the CAN frames."""
    nodes = [NODES[0], {**NODES[1], "params": {"cycles_per_read": 4}}]
    cfg_path = write_config(nodes=nodes)
    cfg = load(cfg_path)
    spawn("node", "run", "simulator", "-c", str(cfg_path), "--listen", cfg.zenoh.listen[0])
    spawn("node", "run", "h2_reader", "-c", str(cfg_path))
    stats_key = "exolink/sim/nodes/h2_reader/stats"
    s = connect(messaging.local_endpoint(cfg.zenoh))
    try:

        def stats() -> dict | None:
            try:
                return messaging.request(s, stats_key, timeout_s=3)
            except messaging.Unreachable:  # the reader's queryable is not declared yet
                return None

        wait_for(lambda: (st := stats()) and st["published_joint_states"] > 20, timeout=20)
        out = tmp_path / "samples.bin"
        sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(cfg_path), str(out), "3"])
        before = stats()
        sub.wait(15)
        after = stats()
    finally:
        s.close()
    assert before and after
    samples = read_samples(out)
    assert len(samples) > 200
    seqs = [int.from_bytes(att[0:8], "little", signed=True) for _p, att, _k in samples]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # every one, in order
    stamps = [int.from_bytes(att[8:16], "little", signed=True) for _p, att, _k in samples]
    assert 9.0 < float(np.median(np.diff(stamps))) / 1e6 < 11.0
    frames = after["receive"]["frames"] - before["receive"]["frames"]
    reads = after["receive"]["batches"] - before["receive"]["batches"]
    # Three frames a cycle: 12 a read at four cycles per read; a reader waking every cycle
    # reads 3. A host stall only makes reads bigger.
    assert reads > 0 and frames / reads >= 8, (frames, reads)


def test_foot_switches_go_out_on_change_and_as_a_refresh(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    """A change of the switches (or the battery count) is published on its own frame's time,
    an unchanged state only once per ``foot_switches_refresh_s``: on the board every Zenoh
    sample costs ~1 ms of the one core. No transition may be lost."""
    params = {"start_stream": False, "foot_switches_refresh_s": 0.3}
    cfg_path = write_config(nodes=[{"name": "h2_reader", "plugin": "h2_reader", "params": params}])
    cfg = load(cfg_path)
    hub = messaging.open_hub_session(cfg)
    sub, got = feet_subscriber(hub)
    spawn("node", "run", "h2_reader", "-c", str(cfg_path))

    def stats() -> dict | None:
        return reader_stats(hub)

    bus = open_bus(cfg.can)
    try:
        wait_for(lambda: stats() is not None, timeout=20)
        stream_feet(bus)
        wait_for(lambda: (st := stats()) and st["frames"]["130"] == len(FEET_STATES), timeout=10)
        time.sleep(0.5)
        st = stats()
    finally:
        bus.shutdown()
        sub.undeclare()
        hub.close()
    assert st is not None
    assert feet_runs(got) == FEET_RUNS  # every transition, in order, none invented
    assert st["foot_switch_changes"] == 4
    # Unchanged states: one refresh per 0.3 s at most (1.05 s of frames: ~4), not 100 a second.
    assert len(got) == st["published_foot_switches"] <= 5 + 4 + 2, got
    for (t0, s0, b0), (t1, s1, b1) in itertools.pairwise(got):
        if (s0, b0) == (s1, b1):
            assert t1 - t0 >= 0.3e9


def test_an_outbox_puts_a_reads_samples_together_in_order_only_when_flushed() -> None:
    """Zenoh batches only puts that come together (messaging.Outbox): a reader adds each
    cycle's samples as it decodes them and puts them all after the read."""
    from exolink import config

    cfg = config.parse(config.bundled("sim").read_text())
    s = zenoh.open(messaging.session_config(cfg.zenoh))
    try:
        m = messaging.Messaging(s, cfg)
        pub = m.publisher("outbox_probe", "std_msgs/msg/String", raw=True)
        got: list[tuple[bytes, int]] = []
        sub = s.declare_subscriber(
            pub.key,
            lambda x: got.append(
                (x.payload.to_bytes(), messaging.decode_attachment(x.attachment.to_bytes())[1])
            ),
        )
        out = messaging.Outbox()
        for i in range(3):
            out.add(pub, bytes([0, 1, 0, 0, 2, 0, 0, 0, 48 + i, 0]), 1000 + i)
        time.sleep(0.2)
        assert got == []
        out.flush()
        wait_for(lambda: len(got) == 3, timeout=5)
        assert [ns for _p, ns in got] == [1000, 1001, 1002]
        out.flush()  # empty: nothing again
        time.sleep(0.2)
        assert len(got) == 3
        sub.undeclare()
        pub.close()
    finally:
        s.close()
