"""Reading recordings back: summary, CSV export, recovery after power loss, playback onto Zenoh.

Everything decodes with the schema stored in the file (rosbags parses the ros2msg text), so a
recording stays readable after the project's own message definitions change.
"""

from __future__ import annotations

import csv
import fnmatch
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

TRIGGER_SUFFIX = "/trigger"
JOINT_STATE = "sensor_msgs/msg/JointState"


class RecordingError(Exception):
    pass


@dataclass
class Info:
    path: str
    topics: dict[str, dict[str, Any]] = field(default_factory=dict)  # topic -> type, count
    start_ns: int = 0
    end_ns: int = 0
    messages: int = 0
    triggers: list[int] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9 if self.messages else 0.0


@cache
def _store_for(schema_name: str, schema_text: str) -> Any:
    """A rosbags typestore that knows this file's schema (and its embedded dependencies)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    types: dict[str, Any] = {}
    blocks = schema_text.split("=" * 80 + "\n")
    types.update(get_types_from_msg(blocks[0], schema_name))
    for block in blocks[1:]:
        head, _, body = block.partition("\n")
        name = head.removeprefix("MSG: ").strip()
        if "/msg/" not in name:
            pkg, _, n = name.partition("/")
            name = f"{pkg}/msg/{n}"
        types.update(get_types_from_msg(body, name))
    store.register(types)
    return store


def decode(schema: Any, data: bytes) -> Any:
    return _store_for(schema.name, schema.data.decode()).deserialize_cdr(data, schema.name)


def _open(path: str | Path) -> Any:
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file")
    return p.open("rb")


def iter_messages(
    path: str | Path, topics: list[str] | None = None
) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) in log-time order; a truncated file raises RecordingError."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    with _open(path) as f:
        try:
            reader = make_reader(f)
            yield from reader.iter_messages(topics=topics, log_time_order=True)
        except (McapError, EOFError, ValueError) as exc:
            raise RecordingError(
                f"{path}: not a complete MCAP file ({exc}); try `exolink recover`"
            ) from None


def info(path: str | Path) -> Info:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    out = Info(str(path))
    with _open(path) as f:
        try:
            reader = make_reader(f)
            summary = reader.get_summary()
            out.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except (McapError, EOFError, ValueError) as exc:
            raise RecordingError(
                f"{path}: not a complete MCAP file ({exc}); try `exolink recover`"
            ) from None
    if summary is None or summary.statistics is None:
        raise RecordingError(f"{path}: no summary section; try `exolink recover`")
    st = summary.statistics
    out.start_ns, out.end_ns, out.messages = (
        st.message_start_time,
        st.message_end_time,
        st.message_count,
    )
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        out.topics[ch.topic] = {
            "type": schema.name if schema else "?",
            "count": st.channel_message_counts.get(cid, 0),
        }
    trig = [t for t in out.topics if t.endswith(TRIGGER_SUFFIX)]
    if trig:
        out.triggers = [
            _stamp_ns(decode(s, m.data).stamp) for s, _c, m in iter_messages(path, trig)
        ]
    return out


def _stamp_ns(t: Any) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def message_time_ns(msg: Any, log_time: int) -> int:
    """The message's own stamp (CAN receive time) when it has one, else when it was logged."""
    h = getattr(msg, "header", None)
    if h is not None:
        return _stamp_ns(h.stamp)
    s = getattr(msg, "stamp", None)
    return _stamp_ns(s) if s is not None and hasattr(s, "sec") else log_time


def flatten(msg: Any, prefix: str = "") -> dict[str, Any]:
    """Scalar columns of a message; JointState gets one rad and one deg column per joint."""
    if type(msg).__name__ == "JointState" or getattr(msg, "__msgtype__", "") == JOINT_STATE:
        cols: dict[str, Any] = {}
        for i, name in enumerate(msg.name):
            if i < len(msg.position):
                cols[f"{name}_rad"] = float(msg.position[i])
                cols[f"{name}_deg"] = math.degrees(float(msg.position[i]))
            if i < len(msg.effort):
                cols[f"{name}_nm"] = float(msg.effort[i])
        return cols
    out: dict[str, Any] = {}
    for k in getattr(msg, "__dataclass_fields__", {}):
        if k == "__msgtype__":
            continue
        v = getattr(msg, k)
        key = f"{prefix}{k}"
        if k in ("header", "stamp") and hasattr(v, "__dataclass_fields__"):
            continue
        if hasattr(v, "__dataclass_fields__"):
            out.update(flatten(v, key + "."))
        elif hasattr(v, "tolist"):
            for i, x in enumerate(v.tolist()):
                out[f"{key}[{i}]"] = x
        elif isinstance(v, list):
            for i, x in enumerate(v):
                if hasattr(x, "__dataclass_fields__"):
                    out.update(flatten(x, f"{key}[{i}]."))
                else:
                    out[f"{key}[{i}]"] = x
        else:
            out[key] = v
    return out


def export_csv(path: str | Path, out_dir: str | Path) -> dict[str, int]:
    """One CSV per topic: absolute time, time since the last trigger (empty before the first)."""
    triggers = sorted(info(path).triggers)  # a bad input file stops here, before any output
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"cannot write CSV files into {out}: {exc.strerror}") from None
    writers: dict[str, tuple[Any, Any, list[str]]] = {}
    counts: dict[str, int] = {}
    ti = -1
    try:
        for schema, channel, m in iter_messages(path):
            msg = decode(schema, m.data)
            t = message_time_ns(msg, m.log_time)
            while ti + 1 < len(triggers) and triggers[ti + 1] <= t:
                ti += 1
            row = {
                "time_s": f"{t / 1e9:.9f}",
                "time_since_trigger_s": f"{(t - triggers[ti]) / 1e9:.9f}" if ti >= 0 else "",
            }
            row.update(flatten(msg))
            w = writers.get(channel.topic)
            if w is None:
                name = channel.topic.strip("/").replace("/", "__") + ".csv"
                fh = (out / name).open("w", newline="")
                fields = list(row)
                writer = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
                writer.writeheader()
                w = writers[channel.topic] = (fh, writer, fields)
            w[1].writerow(row)
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    finally:
        for fh, _w, _f in writers.values():
            fh.close()
    return counts


def recover(path: str | Path, out: str | Path) -> dict[str, int]:
    """Copy every complete record of a cut-off file into a new, finished MCAP file."""
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import Writer

    recovered, stopped = 0, ""
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    if Path(out).exists():
        raise RecordingError(f"{out} exists (a recording is never overwritten)")
    with _open(path) as f, Path(out).open("xb") as g:
        w = Writer(g)
        w.start(profile="ros2", library="exolink recover")
        try:
            for rec in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                if isinstance(rec, Schema) and rec.id not in schema_ids:
                    schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel) and rec.id not in channel_ids:
                    if rec.schema_id in schema_ids or rec.schema_id == 0:
                        channel_ids[rec.id] = w.register_channel(
                            rec.topic,
                            rec.message_encoding,
                            schema_ids.get(rec.schema_id, 0),
                            dict(rec.metadata),
                        )
                elif isinstance(rec, Message) and rec.channel_id in channel_ids:
                    w.add_message(
                        channel_ids[rec.channel_id],
                        rec.log_time,
                        rec.data,
                        rec.publish_time,
                        rec.sequence,
                    )
                    recovered += 1
                elif isinstance(rec, Metadata):
                    w.add_metadata(rec.name, dict(rec.metadata))
        except Exception as exc:  # the cut-off point: a torn record, a short chunk, a bad CRC
            stopped = f"{type(exc).__name__}: {exc}"
        w.add_metadata(
            "exolink.recovered",
            {"from": str(path), "messages": str(recovered), "stopped_at": stopped},
        )
        w.finish()
    return {"messages": recovered}


REPLAY_PREFIX = "replay"
# Never republished onto the live keys: what the supervisor and the motion nodes take as the
# appliance's own word. The watchdog's state (motion nodes arm on it), the pattern state (the
# supervisor watches its operator), node diagnostics and heartbeats, the supervisor's diagnostics
# and trigger edges. Matched on the end of the topic, whatever its namespace.
OWN_STATE_TOPICS = ("watchdog", "pattern_state", "trigger", "supervisor/*", "nodes/*/*")


def own_state(topic: str) -> bool:
    """Is this recorded topic (namespace included) one of OWN_STATE_TOPICS?"""
    parts = topic.strip("/").split("/")
    for pattern in OWN_STATE_TOPICS:
        tail = pattern.split("/")
        if len(parts) >= len(tail) and all(
            fnmatch.fnmatchcase(p, t) for p, t in zip(parts[-len(tail) :], tail, strict=True)
        ):
            return True
    return False


def replay_topic(topic: str, live: bool, prefix: str = REPLAY_PREFIX) -> str | None:
    """Where a recorded topic is republished: under ``prefix`` (default), or with ``live`` its
    own key, except the appliance's own state (None: not republished)."""
    topic = topic.strip("/")
    if live:
        return None if own_state(topic) else topic
    if not prefix.strip("/"):
        raise RecordingError("a replay prefix is needed (the live keys take --live)")
    return f"{prefix.strip('/')}/{topic}"


PLAY_SETTLE_S = 1.0  # how long a replay waits for subscribers to learn of its publishers


def _declare(
    session: Any, graph: Any, pubs: dict[str, Any], key: str, topic: str, typename: str
) -> Any:
    from exolink import messaging, rosgraph

    token = graph.declare(rosgraph.PUBLISHER, f"/{topic}", typename, key.rsplit("/", 1)[-1])
    pub = pubs[key] = messaging.Publisher(session, key, typename, True, token, graph)
    return pub


def _declare_all(
    session: Any,
    graph: Any,
    pubs: dict[str, Any],
    domain_id: int,
    targets: dict[str, str | None],
    recorded: dict[str, dict[str, Any]],
) -> None:
    """Every replayed topic's publisher before the first message, and a moment for those who
    discover topics from the graph (a recorder, ``ros2 bag record``) to subscribe: its first
    messages are not lost to them."""
    from exolink import messaging

    for source, topic in targets.items():
        typename = recorded.get(source, {}).get("type")
        if topic is not None and typename not in (None, "?"):
            _declare(
                session,
                graph,
                pubs,
                messaging.topic_key(domain_id, "", topic, typename),
                topic,
                typename,
            )
    if pubs:
        time.sleep(PLAY_SETTLE_S)


def play(
    session: Any,
    path: str | Path,
    rate: float = 1.0,
    loop: bool = False,
    topics: list[str] | None = None,
    domain_id: int = 0,
    stop: Any = None,
    live: bool = False,
    prefix: str = REPLAY_PREFIX,
) -> int:
    """Republish a recording onto Zenoh with the original timing / rate.

    By default under ``<prefix>/<recorded topic>`` (``0/replay/h2/joint_states/...``), where
    nothing on an appliance listens; with ``live`` under the original keys, minus the appliance's
    own state (OWN_STATE_TOPICS). Data keys only, never a management key; the replay is a ROS 2
    node (``exolink_play``) in the graph with a publisher token per topic, as ``ros2 bag play``
    is: a ROS 2 tool sees what it publishes, and a recorder (which learns topics from the graph)
    records it.
    """
    from exolink import messaging, rosgraph

    if not rate > 0:
        raise RecordingError(f"rate must be > 0, got {rate}")
    recorded = info(path).topics
    wanted = list(recorded) if topics is None else topics
    targets = {t: replay_topic(t, live, prefix) for t in wanted}
    topics = [t for t, target in targets.items() if target is not None]
    if not topics:
        return 0
    graph = rosgraph.RosNode(session, domain_id, "", "exolink_play")
    pubs: dict[str, Any] = {}
    sent = 0
    try:
        _declare_all(session, graph, pubs, domain_id, targets, recorded)
        while True:
            t0_log = t0_wall = None
            for schema, channel, m in iter_messages(path, topics):
                if stop is not None and stop.is_set():
                    return sent
                if t0_log is None:
                    t0_log, t0_wall = m.log_time, time.monotonic()
                due = t0_wall + (m.log_time - t0_log) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                topic = targets.get(channel.topic)
                if topic is None:  # iter_messages filters already: never on a live own-state key
                    continue
                key = messaging.topic_key(domain_id, "", topic, schema.name)
                pub = pubs.get(key) or _declare(session, graph, pubs, key, topic, schema.name)
                pub.put(m.data, m.publish_time)
                sent += 1
            if not loop:
                break
    finally:  # the graph shows the replay only while it runs
        for p in pubs.values():
            p.close()
        graph.close()
    return sent
