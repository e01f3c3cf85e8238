"""Recording on simulated hardware, read back by independent readers: mcap's own reader for the
container, and rosbags (with the schema stored in the file) for the CDR payloads."""

from __future__ import annotations

import csv
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from benchmarks.harness import EXOLINK, Appliance, collect, motion_nodes, wait_for
from exolink import messaging
from exolink.board import clock
from exolink.protocol import h2
from exolink.recordings.readback import RecordingError, export_csv, info
from exolink.wire import rosgraph

JS_KEY = messaging.topic_key(0, "h2", "joint_states", "sensor_msgs/msg/JointState")


def nodes(directory: Path, reader: dict | None = None, **params: object) -> list[dict]:
    return [
        {"name": "simulator", "plugin": "simulator"},
        {"name": "h2_reader", "plugin": "h2_reader", "params": reader or {}},
        {
            "name": "recorder",
            "plugin": "recorder",
            "params": {"directory": str(directory), **params},
        },
    ]


def rosbags_decode(path: Path, topic: str) -> list[tuple[bytes, object]]:
    """Independent of exolink: mcap reader + a rosbags typestore built from the file's schema."""
    out = []
    with path.open("rb") as f:
        for schema, channel, m in make_reader(f).iter_messages(topics=[topic]):
            store = get_typestore(Stores.ROS2_JAZZY)
            text = schema.data.decode().split("=" * 80)[0]
            store.register(get_types_from_msg(text, schema.name))
            out.append((m.data, store.deserialize_cdr(m.data, schema.name)))
            assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
    return out


def reader_out(app: Appliance) -> dict:
    """The h2 reader's joint_states publisher: messages, put one by one, bundles."""
    s = messaging.open_client_session(app.at)
    try:
        stats = messaging.request(s, "exolink/sim/nodes/h2_reader/stats", timeout_s=3)
    finally:
        s.close()
    return dict(stats["joint_states_out"])


def recordings(d: Path) -> list[Path]:
    return sorted(d.glob("*.mcap"))


def test_walking_session_recorded_exactly(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The board's reader (a read every 4 cycles) bundles joint_states for the recorder while a
    laptop gets each message on the topic's key: the file holds exactly what the laptop got."""
    rec_dir = tmp_path / "rec"
    cfg = nodes(rec_dir, {"cycles_per_read": 4}, compression="lz4", chunk_size=65536)
    app = Appliance(write_config(nodes=cfg), spawn)
    s = messaging.open_client_session(app.at)
    published: dict[int, bytes] = {}
    sub = s.declare_subscriber(
        JS_KEY,
        lambda x: published.__setitem__(
            messaging.decode_attachment(x.attachment.to_bytes())[1], x.payload.to_bytes()
        ),
    )
    try:
        r = app.cli("record", "start", "--label", "subject=S01", "--label", "session=walk")
        assert r.returncode == 0, r.stderr
        assert app.cli("trigger", "fire").returncode == 0
        time.sleep(3)
        r = app.cli("record", "stop")
        assert r.returncode == 0 and "idle" in r.stdout
    finally:
        sub.undeclare()
        s.close()
    [path] = recordings(rec_dir)
    status = json.loads(app.cli("record", "status", "--json").stdout)
    assert status["bytes"] == path.stat().st_size  # what this recording wrote, its one file
    rows = rosbags_decode(path, "/h2/joint_states")
    assert len(rows) > 250
    stamps = []
    for data, msg in rows:
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert published.get(ns) == data  # byte-identical to what went over Zenoh
        stamps.append(ns)
    window = [t for t in published if stamps[0] <= t <= stamps[-1]]
    assert len(window) == len(rows)  # nothing published in the window is missing
    i = info(path)
    assert i.topics["/h2/joint_states"]["count"] == len(rows)
    assert len(i.triggers) == 1 and stamps[0] <= i.triggers[0] <= stamps[-1]
    assert i.metadata["exolink.labels"] == {"subject": "S01", "session": "walk"}
    # which clock stamped it, as the kernel says (this host: no laptop ever steps its clock)
    synced = clock.kernel().synchronised
    assert i.metadata["exolink.board.clock"]["synchronised"] == str(synced).lower()
    assert i.metadata["exolink.board.clock"]["source"] == (
        "time server" if synced else "unsynchronised"
    )
    assert (
        i.metadata["exolink"]["device"] == "sim"
        and "device: sim" in i.metadata["exolink.config"]["yaml"]
    )
    st = i.metadata["exolink.stats"]
    assert (
        st["dropped"] == "0" and st["received"] == st["written"]
    )  # every counted message is in the file
    out_js = reader_out(app)
    assert out_js["bundles"] > 0 and out_js["sent"] > 0  # bundles for the recorder, singles for us
    # CSV export matches the decoded values, with time relative to the trigger
    out = tmp_path / "csv"
    counts = export_csv(path, out)
    assert counts["/h2/joint_states"] == len(rows)
    with (out / "h2__joint_states.csv").open() as f:
        table = list(csv.DictReader(f))
    by_time = {round(float(r["time_s"]) * 1e9): r for r in table}
    for _data, msg in rows[::25]:
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        row = min(by_time.items(), key=lambda kv: abs(kv[0] - ns))[1]
        assert float(row["r_knee_rad"]) == pytest.approx(msg.position[1])
        assert float(row["r_knee_deg"]) == pytest.approx(msg.position[1] * 57.29577951308232)
        expect_rel = (ns - i.triggers[0]) / 1e9
        assert (row["time_since_trigger_s"] == "") == (ns < i.triggers[0])
        if ns >= i.triggers[0]:
            assert float(row["time_since_trigger_s"]) == pytest.approx(expect_rel, abs=1e-6)
    r = subprocess.run([*EXOLINK, "info", str(path)], capture_output=True, text=True)
    assert "triggers  1" in r.stdout and "/h2/joint_states" in r.stdout


def test_kill9_leaves_a_recoverable_file(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    rec_dir = tmp_path / "rec"
    app = Appliance(write_config(nodes=nodes(rec_dir, fsync_interval_s=0.5, autostart=True)), spawn)
    time.sleep(3)
    os.kill(app.node("recorder")["pid"], signal.SIGKILL)
    killed_at = time.time_ns()
    time.sleep(0.5)
    first = recordings(rec_dir)[0]
    with pytest.raises(RecordingError, match="try `exolink recover`"):
        info(first)
    out = tmp_path / "recovered.mcap"
    r = subprocess.run(
        [*EXOLINK, "recover", str(first), "-o", str(out)], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    i = info(out)
    js = i.topics["/h2/joint_states"]["count"]
    # everything up to the last fsync (0.5 s) survives: ~100/s for ~3 s, minus at most ~0.6 s
    assert js >= 200
    assert i.end_ns <= killed_at
    assert rosbags_decode(out, "/h2/joint_states")[-1][1].name[0] == "r_hip"


def slow_card(in_node, seconds: float) -> None:  # type: ignore[no-untyped-def]
    """An SD card that pauses while it erases: each os.fsync in the recorder sleeps first."""
    in_node(
        "recorder",
        f"""
import os, time
_fsync = os.fsync
def fsync(fd):
    time.sleep({seconds})
    _fsync(fd)
os.fsync = fsync
""",
    )


def test_slow_card_does_not_get_the_recorder_killed(  # type: ignore[no-untyped-def]
    write_config, spawn, tmp_path, in_node
) -> None:
    """SD cards pause for seconds while they erase blocks; the writer loop blocks in fsync then.
    Such a pause cannot be made on this machine's disk, so the recorder process gets one: a
    sitecustomize makes each os.fsync sleep 2 s first. The recorder must keep beating (it is
    not hung) and keep every message."""
    slow_card(in_node, 2.0)
    rec_dir = tmp_path / "rec"
    app = Appliance(write_config(nodes=nodes(rec_dir, fsync_interval_s=0.5, autostart=True)), spawn)
    time.sleep(7)  # three slow syncs at least
    r = app.cli("record", "stop")  # replies "stopping" while the card closes the file
    assert r.returncode == 0 and ("idle" in r.stdout or "stopping" in r.stdout), r
    wait_for(lambda: "idle" in app.cli("record", "status").stdout, timeout=15)
    rec = app.node("recorder")
    assert rec["restarts"] == 0 and rec["state"] == "running", rec
    assert "node_hung_killed" not in app.proc.output()
    [path] = recordings(rec_dir)
    st = info(path).metadata["exolink.stats"]
    assert st["dropped"] == "0" and st["received"] == st["written"]
    assert info(path).topics["/h2/joint_states"]["count"] > 400


def test_samples_that_did_not_fit_the_inbox_are_counted_as_dropped(  # type: ignore[no-untyped-def]
    write_config, spawn, tmp_path, in_node
) -> None:
    """The recorder's loop takes its inbox (Zenoh ring channels) in batches; when the card
    stalls longer than the inbox holds, the ring lets the oldest go. Each publisher numbers its
    samples, so the file's sequence gaps are exactly what the recorder says it dropped. A slow card (fsync
    sleeps 1 s, as above) and an inbox of 32 samples make it happen."""
    slow_card(in_node, 1.0)
    rec_dir = tmp_path / "rec"
    app = Appliance(
        write_config(nodes=nodes(rec_dir, fsync_interval_s=0.3, autostart=True, inbox=32)), spawn
    )
    time.sleep(4)
    assert app.cli("record", "stop").returncode == 0
    wait_for(lambda: "idle" in app.cli("record", "status").stdout, timeout=15)
    [path] = recordings(rec_dir)
    st = info(path).metadata["exolink.stats"]
    seqs: dict[int, list[int]] = {}
    with open(path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            seqs.setdefault(channel.id, []).append(message.sequence)
    gaps = sum(b - a - 1 for s in seqs.values() for a, b in itertools.pairwise(s))
    assert int(st["dropped"]) == gaps > 0
    assert st["received"] == st["written"]


def test_a_second_recording_counts_no_drops_for_the_pause_between(  # type: ignore[no-untyped-def]
    write_config, spawn, tmp_path
) -> None:
    """Between recordings the recorder takes nothing, so the publishers' sequence numbers
    move on without it: what was published in the pause is not a loss of the next file.
    Idle, it is not even subscribed: seen as the Zenoh matching status of a publisher (in the
    ROS graph, where the recorder learns its topics) on a key only the recorder takes."""
    rec_dir = tmp_path / "rec"
    app = Appliance(write_config(nodes=nodes(rec_dir)), spawn)
    s = messaging.open_client_session(app.at)
    key = messaging.topic_key(0, "h2", "probe", "std_msgs/msg/String")
    graph = rosgraph.RosNode(s, 0, "h2", "probe")
    graph.declare(rosgraph.PUBLISHER, "/h2/probe", "std_msgs/msg/String", key.rsplit("/", 1)[-1])
    probe = s.declare_publisher(key)
    try:
        assert not probe.matching_status.matching
        for _ in range(2):
            assert app.cli("record", "start").returncode == 0
            wait_for(lambda: probe.matching_status.matching, timeout=10)
            time.sleep(1.5)
            assert app.cli("record", "stop").returncode == 0
            wait_for(lambda: "idle" in app.cli("record", "status").stdout, timeout=15)
            wait_for(lambda: not probe.matching_status.matching, timeout=10)
            time.sleep(1.0)  # the pause: ~100 joint_states the recorder does not take
    finally:
        s.close()
    first, second = recordings(rec_dir)
    for path in (first, second):
        st = info(path).metadata["exolink.stats"]
        assert st["dropped"] == "0" and st["received"] == st["written"], (path.name, st)
        assert info(path).topics["/h2/joint_states"]["count"] > 50


@pytest.fixture
def tiny_disk(tmp_path: Path):  # type: ignore[no-untyped-def]
    d = tmp_path / "tiny"
    d.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(d)], capture_output=True, text=True
    )
    if r.returncode != 0:
        pytest.skip(
            f"cannot mount a small tmpfs here (needs root / CAP_SYS_ADMIN): {r.stderr.strip()}"
        )
    yield d
    subprocess.run(["umount", "-l", str(d)], check=False)


def test_disk_full_stops_cleanly_and_keeps_earlier_files(write_config, spawn, tiny_disk) -> None:  # type: ignore[no-untyped-def]
    params = {
        "autostart": True,
        "compression": "none",
        "split_size_mb": 0.15,
        "fsync_interval_s": 0.2,
        "reserve_mb": 0,  # the last resort: no reserve, the card really fills (ENOSPC)
    }
    app = Appliance(write_config(nodes=nodes(tiny_disk, **params)), spawn)
    wait_for(lambda: "disk full" in app.cli("record", "status").stdout, timeout=60)
    st = app.cli("record", "status", "--json")
    assert '"state": "error"' in st.stdout
    files = recordings(tiny_disk)
    assert len(files) >= 2
    for f in files[:-1]:  # every finished file is intact
        assert info(f).topics["/h2/joint_states"]["count"] > 0
    wait_for(lambda: app.node("recorder")["health"] == "error: disk full", timeout=5)
    assert app.node("recorder")["state"] == "running"  # the node lives on; nothing else is affected
    assert "error: disk full" in app.cli("status").stdout


def test_play_then_rerecord_gives_identical_messages(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    src_dir, dst_dir = tmp_path / "src", tmp_path / "dst"
    app = Appliance(write_config(nodes=nodes(src_dir)), spawn)
    assert app.cli("record", "start").returncode == 0
    time.sleep(2)
    assert app.cli("record", "stop").returncode == 0
    [src] = recordings(src_dir)
    app.proc.stop()
    # a second appliance with only a recorder: nothing else publishes joint states there
    other = Appliance(
        write_config(
            nodes=[
                {"name": "recorder", "plugin": "recorder", "params": {"directory": str(dst_dir)}}
            ]
        ),
        spawn,
    )
    assert other.cli("record", "start").returncode == 0
    r = subprocess.run(
        [
            *EXOLINK,
            "play",
            str(src),
            "--rate",
            "4",
            "--topics",
            "joint_states",
            "foot_switches",
            "--live",
            "--at",
            other.at,
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    time.sleep(0.5)
    assert other.cli("record", "stop").returncode == 0
    [dst] = recordings(dst_dir)
    for topic in ("/h2/joint_states", "/h2/foot_switches"):
        a = [d for d, _ in rosbags_decode(src, topic)]
        b = [d for d, _ in rosbags_decode(dst, topic)]
        # foot switches go out on change and once a second (h2_reader), joint states every cycle
        assert a == b and len(a) > (100 if topic == "/h2/joint_states" else 0)


def test_bad_files_and_commands(tmp_path, write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file")
    r = subprocess.run([*EXOLINK, "info", str(junk)], capture_output=True, text=True)
    assert r.returncode == 3 and "not an MCAP file" in r.stderr
    r = subprocess.run(
        [*EXOLINK, "info", str(tmp_path / "missing.mcap")], capture_output=True, text=True
    )
    assert r.returncode == 3 and "no such file" in r.stderr
    app = Appliance(write_config(nodes=nodes(tmp_path / "rec")), spawn)
    r = app.cli("record", "stop")
    assert r.returncode == 5 and "not recording" in r.stderr
    assert app.cli("record", "start").returncode == 0
    r = app.cli("record", "start")
    assert r.returncode == 5 and "already recording" in r.stderr


COLD_RECORDER = """
import json, sys, threading, time
from exolink.config import load
from exolink.runtime import NodeRunner
from exolink.nodes.recorder import Recorder

class Watched(Recorder):
    def configure(self):
        super().configure()
        self.after_configure = set(sys.modules)

runner = NodeRunner(Watched, load(sys.argv[1]), "recorder")
t = threading.Thread(target=runner.run)
t.start()
def recorded():
    stats = getattr(runner.node, "stats", None)  # set by configure, on the runner's thread
    return stats is not None and stats.files and stats.written > 50

deadline = time.monotonic() + 30
while time.monotonic() < deadline and not recorded():
    time.sleep(0.05)
runner.stop.set()
t.join(10)
print(json.dumps({"written": runner.node.stats.written,
                  "imported": sorted(set(sys.modules) - runner.node.after_configure)}))
"""


def test_recorder_imports_nothing_once_running(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The writer loop must not stall: under emulation the board's recorder imported mcap and
    its compressors on opening the first file, went silent for seconds and was killed on every
    restart. A cold process (nothing imported yet) records and the loop imports no module."""
    rec_dir = tmp_path / "rec"
    node_list = nodes(rec_dir, autostart=True)
    node_list[-1]["enabled"] = False  # the supervisor knows it; this test runs it cold, itself
    cfg = write_config(nodes=node_list)
    app = Appliance(cfg, spawn, wait_nodes=False)
    wait_for(lambda: app.node("h2_reader")["heartbeat_age_s"] is not None, timeout=20)
    r = subprocess.run(
        [sys.executable, "-c", COLD_RECORDER, str(cfg)], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.splitlines()[-1])
    assert out["written"] > 50, r.stderr
    assert out["imported"] == [], out["imported"]
    assert len(recordings(rec_dir)) == 1


def test_a_bundled_topic_reaches_the_recorder_once(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """With no one else subscribed, the reader puts no joint_states one by one: the recorder
    takes them from the bundles alone (messaging.bundle_key), each message with its own
    sequence number and stamp, none twice. A malformed bundle (anyone on an open appliance may
    put one) is counted and skipped; the recording goes on."""
    rec_dir = tmp_path / "rec"
    app = Appliance(write_config(nodes=nodes(rec_dir, {"cycles_per_read": 5})), spawn)
    assert app.cli("record", "start").returncode == 0
    s = messaging.open_client_session(app.at)
    try:
        time.sleep(2)
        junk = messaging.bundle_key("sim", JS_KEY)
        s.put(junk, b"EXB1 not a bundle")
        time.sleep(1)
    finally:
        s.close()
    out_js = reader_out(app)
    assert out_js["sent"] == 0 and out_js["bundles"] > 0
    wait_for(lambda: json.loads(app.cli("record", "status", "--json").stdout)["malformed"] == 1)
    assert app.cli("record", "stop").returncode == 0
    wait_for(lambda: "idle" in app.cli("record", "status").stdout, timeout=15)
    [path] = recordings(rec_dir)
    st = info(path).metadata["exolink.stats"]
    assert st["dropped"] == "0" and st["duplicates"] == "0" and st["malformed"] == "1"
    with open(path, "rb") as f:
        seqs = [
            m.sequence for _s, c, m in make_reader(f).iter_messages() if "joint_states" in c.topic
        ]
    assert len(seqs) > 150 and seqs == list(range(seqs[0], seqs[0] + len(seqs)))


# --- play never replays a command ----------------------------------------------------------------

CONTROL_NODES = motion_nodes(deadline_ms=300, h2_timeout_ms=300)
JOINT_COMMAND = "exolink_msgs/msg/JointCommand"


def publish_joint_commands(at: str, setpoints: list[int]) -> None:
    """A ROS 2 node on a laptop publishing r_knee position commands on /h2/cmd/joint, as
    rmw_zenoh does (a graph token, then CDR samples with attachments)."""
    s = messaging.open_client_session(at)
    key = messaging.topic_key(0, "h2", "cmd/joint", JOINT_COMMAND)
    graph = rosgraph.RosNode(s, 0, "", "teleop")
    token = graph.declare(rosgraph.PUBLISHER, "/h2/cmd/joint", JOINT_COMMAND, key.split("/")[-1])
    pub = messaging.Publisher(s, key, JOINT_COMMAND, False, token, graph)
    cls = messaging.msg_class(JOINT_COMMAND)
    try:
        time.sleep(1.0)  # the recorder learns the topic from the graph
        for sp in setpoints:
            ns = time.time_ns()
            cmd = cls(messaging.header(ns), "r_knee", 1, sp, 0, "teleop")
            pub.publish(cmd, ns)
            time.sleep(0.2)
        time.sleep(0.5)
    finally:
        pub.close()
        graph.close()
        s.close()


def test_play_live_never_replays_commands_onto_an_armed_appliance(  # type: ignore[no-untyped-def]
    write_config, spawn, tmp_path, mbus
) -> None:
    """A recording holding ROS 2 joint commands (and the command log), replayed with --live
    onto an armed appliance: the exoskeleton must not move. The CLI says what it held back;
    the appliance logs no command and no position frame goes on the bus."""
    src_dir = tmp_path / "src"
    rec = {"name": "recorder", "plugin": "recorder", "params": {"directory": str(src_dir)}}
    app = Appliance(write_config(nodes=[rec]), spawn)  # its supervisor takes /h2/cmd/joint
    assert app.cli("record", "start").returncode == 0
    publish_joint_commands(app.at, [10, 13, 16, 19, 22, 25])
    assert app.cli("record", "stop").returncode == 0
    wait_for(lambda: "idle" in app.cli("record", "status").stdout, timeout=15)
    app.proc.stop()
    [src] = recordings(src_dir)
    i = info(src)
    assert i.topics["/h2/cmd/joint"]["count"] == 6 and i.topics["/h2/cmd/joint"]["command"]
    assert i.topics["/h2/commands"]["command"] and not i.topics["/h2/watchdog"]["command"]
    with src.open("rb") as f:  # the recorder's mark, read by the plain mcap reader
        marks = {c.topic: c.metadata for c in make_reader(f).get_summary().channels.values()}
    assert marks["/h2/cmd/joint"] == {"exolink.command": "true"}
    assert marks["/h2/commands"] == {"exolink.command": "true"}
    assert marks["/h2/watchdog"] == {"exolink.command": "false"}

    live = Appliance(write_config(nodes=CONTROL_NODES), spawn)
    live.arm_and_hold()  # armed and held: a replayed command would move the knee
    s = messaging.open_client_session(live.at)
    logged: list[dict] = []
    log = s.declare_subscriber(
        messaging.topic_selector(0, "h2", "commands"),
        lambda x: logged.append(json.loads(x.payload.to_bytes()[8:-1])),
    )
    try:
        while mbus.recv(timeout=0) is not None:  # what the bus carried before: not ours
            pass
        r = subprocess.run(
            [*EXOLINK, "play", str(src), "--live", "--rate", "2", "--at", live.at],
            capture_output=True,
            text=True,
            timeout=60,
        )
        frames = collect(mbus, 1.0, {70})
    finally:
        log.undeclare()
        s.close()
    assert r.returncode == 0, r.stderr
    assert "held back (commands are never replayed, --live included)" in r.stderr
    assert "/h2/cmd/joint (6 messages)" in r.stderr and "/h2/commands (" in r.stderr
    assert "held back " in r.stdout and " command messages (2 topics)" in r.stdout
    knee = h2.motor_id("r_knee")
    moved = [
        f
        for f in (h2.decode(m) for m in frames)
        if isinstance(f, h2.JointControl) and f.motor == knee and f.mode == h2.MODES["position"]
    ]
    assert moved == []
    assert [e for e in logged if e.get("by") == "ros2"] == []
    assert live.status()["watchdog"]["state"] == "armed"


def test_a_file_marks_commands_the_rule_does_not_know(tmp_path: Path) -> None:
    """A file (another tool's, or one from a later version) may mark more topics as commands:
    play holds those back too. A file without marks (an older recording) gets the built-in
    rule; no mark takes a command topic off it."""
    from mcap.writer import Writer

    from exolink.recordings.playback import held_back, replay_topic

    path = tmp_path / "marked.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data\n")
        for topic, meta in (
            ("/h2/setpoints", {"exolink.command": "true"}),
            ("/h2/cmd/joint", {"exolink.command": "false"}),  # a file cannot unmark one
            ("/h2/commands", {}),  # unmarked (an older recording): the rule
            ("/h2/status_text", {}),
        ):
            cid = w.register_channel(topic, "cdr", sid, meta)
            w.add_message(cid, 1, b"\0\1\0\0\1\0\0\0\0", 1)
        w.finish()
    topics = info(path).topics
    commands = {t for t, v in topics.items() if v["command"]}
    assert commands == {"/h2/setpoints", "/h2/cmd/joint", "/h2/commands"}
    for t in commands:
        assert held_back(t, live=True, command=True) == "command"
        assert replay_topic(t, live=False, command=topics[t]["command"]) is None
    assert replay_topic("/h2/status_text", live=True) == "h2/status_text"
    for t in ("/h2/cmd/joint", "/x/cmd/vel/y", "/h2/joint_commands", "/replay/h2/commands"):
        assert replay_topic(t, live=False) is None and replay_topic(t, live=True) is None, t


# --- graph tokens from elsewhere never crowd out the appliance's topics --------------------------


def fake_publishers(session, n: int, tag: str) -> rosgraph.RosNode:  # type: ignore[no-untyped-def]
    """A ROS node with ``n`` publisher tokens on this session, for topics nobody publishes
    (``/h2/<tag><i>``): what any login may declare (roles: "ros graph"). Its tokens live as
    long as it does."""
    node = rosgraph.RosNode(session, 0, "h2", "fake")
    for i in range(n):
        topic = f"/h2/{tag}{i}"
        node.declare(rosgraph.PUBLISHER, topic, "std_msgs/msg/String", "RIHS01_" + "0" * 64)
    return node


def test_fake_graph_tokens_do_not_crowd_out_the_appliance(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Two laptop sessions declare 300 and 100 fake publisher tokens; after a recorder restart
    the next recording still holds every topic of the appliance, each laptop session got at
    most 64 topics and both together 128, and the refusals are counted in `record status`
    (and --json) and in the file. (400 in all: from ~500 tokens on, this Zenoh's router no
    longer keeps up: declaring 800 took ~25 s on this machine, with the old recorder too.)"""
    rec_dir = tmp_path / "rec"
    app = Appliance(write_config(nodes=nodes(rec_dir)), spawn)
    a, b = messaging.open_client_session(app.at), messaging.open_client_session(app.at)
    try:
        fakes = [fake_publishers(a, 300, "a"), fake_publishers(b, 100, "b")]
        time.sleep(0.5)
        assert app.cli("restart", "recorder").returncode == 0
        wait_for(lambda: app.node("recorder")["heartbeat_age_s"] is not None, timeout=20)
        assert app.cli("record", "start").returncode == 0
        time.sleep(3)
        assert app.cli("record", "stop").returncode == 0
        wait_for(lambda: "idle" in app.cli("record", "status").stdout, timeout=15)
        status = json.loads(app.cli("record", "status", "--json").stdout)
        text = app.cli("record", "status").stdout
    finally:
        for node in fakes:
            node.close()
        a.close()
        b.close()
    za, zb = str(a.zid()), str(b.zid())
    assert status["refused_topics"] == 300 + 100 - 128
    assert status["refused_from"] == {za: 300 - 64, zb: 100 - 64}
    assert f"refused {400 - 128} topics" in text and za in text
    [path] = recordings(rec_dir)
    i = info(path)
    for topic in (
        "/h2/joint_states",
        "/h2/foot_switches",
        "/h2/watchdog",
        "/h2/supervisor/diagnostics",
        "/h2/nodes/h2_reader/diagnostics",
    ):
        assert i.topics.get(topic, {}).get("count", 0) > 0, topic
    st = i.metadata["exolink.stats"]
    assert st["refused_topics"] == str(400 - 128)
    assert json.loads(st["refused_from"]) == {za: 236, zb: 36}
