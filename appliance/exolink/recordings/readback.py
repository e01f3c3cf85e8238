"""Reading recordings back: summary, CSV export, recovery after power loss, playback onto Zenoh.

Everything decodes with the schema stored in the file (rosbags parses the ros2msg text), so a
recording stays readable after the project's own message definitions change.

Nothing is read on trust: ``info``, ``export`` and ``play`` check every CRC of the file first
(``exolink.recordings.check``): a damaged file is a RecordingError naming where, never data that differs
from what was recorded; ``recover`` keeps what is intact and says what it lost.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from exolink.recordings.check import Loss, RecordingError, Walk, _open, check, verify
from exolink.recordings.commands import is_command

TRIGGER_SUFFIX = "/trigger"
JOINT_STATE = "sensor_msgs/msg/JointState"


@dataclass
class Info:
    path: str
    topics: dict[str, dict[str, Any]] = field(default_factory=dict)  # topic -> type, count, command
    start_ns: int = 0
    end_ns: int = 0
    messages: int = 0
    triggers: list[int] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    integrity: dict[str, Any] = field(default_factory=dict)  # what was checked (Check)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9 if self.messages else 0.0


@cache
def _store_for(schema_name: str, schema_text: str) -> Any:
    """A rosbags typestore that knows this file's schema (and its embedded dependencies)."""
    # lazy: rosbags: only when a file is decoded
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


def _unreadable(path: str | Path, exc: Exception) -> str:
    """The error for a file the reader failed on: the damage ``check`` finds, named."""
    c = check(path)
    if c.losses or not c.complete:
        return c.problem()
    return f"{path}: unreadable ({type(exc).__name__}: {exc}); try `exolink recover`"


def iter_messages(
    path: str | Path, topics: list[str] | None = None
) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) in log-time order, each chunk's CRC checked as it is read
    (the mcap reader's own check). Damage, or a file cut off, raises RecordingError naming
    where; callers that must not act on half a file call ``verify`` (or ``info``) first."""
    from mcap.reader import make_reader  # lazy: mcap's reader: only when a file is read

    with _open(path) as f:
        try:
            reader = make_reader(f, validate_crcs=True)
            yield from reader.iter_messages(topics=topics, log_time_order=True)
        except RecordingError:
            raise
        except Exception as exc:  # the reader's, the decompressor's or a parse error
            raise RecordingError(_unreadable(path, exc)) from None


def info(path: str | Path) -> Info:
    """Topics, counts, times, triggers and metadata, after the whole file checked out
    (``verify``: every chunk's, the data section's and the summary's CRC)."""
    from mcap.reader import make_reader  # lazy: mcap's reader: only when a file is read

    checked = verify(path)
    out = Info(str(path))
    out.integrity = {
        "chunks": checked.chunks,
        "chunks_without_crc": checked.unchecked,
        "data_crc": checked.data_crc,
        "summary_crc": checked.summary,
    }
    with _open(path) as f:
        try:
            reader = make_reader(f)
            summary = reader.get_summary()
            out.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except Exception as exc:
            raise RecordingError(_unreadable(path, exc)) from None
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
            "command": is_command(ch.topic, ch.metadata),
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
    """One CSV per topic: absolute time, time since the last trigger (empty before the first).
    The whole file is checked first (``info``): a damaged one is refused before any output, and
    one that changes under the export takes back the CSV files it began."""
    triggers = sorted(info(path).triggers)
    return write_csv(iter_messages(path), triggers, out_dir)


def write_csv(
    messages: Iterator[tuple[Any, Any, Any]], triggers: list[int], out_dir: str | Path
) -> dict[str, int]:
    """The writing half of ``export_csv`` ((schema, channel, message) in log-time order in; a
    CSV per topic out, all taken back if reading fails midway). Apart so that the benchmark can
    price the checks: the same writing fed by a reader that checks nothing."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"cannot write CSV files into {out}: {exc.strerror}") from None
    writers: dict[str, tuple[Any, Any, list[str]]] = {}
    counts: dict[str, int] = {}
    ti = -1
    done = False
    try:
        for schema, channel, m in messages:
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
        done = True
    finally:
        for fh, _w, _f in writers.values():
            fh.close()
            if not done:
                Path(fh.name).unlink(missing_ok=True)
    return counts


class _Copier:
    """Writes the intact records of a walk into a new file: a message's channel (and schema) is
    registered when its first message comes, from the intact chunks or the checked summary."""

    def __init__(self, w: Any, summary: Any) -> None:
        self.w = w
        self.schemas: dict[int, Any] = dict(summary.schemas) if summary else {}
        self.channels: dict[int, Any] = dict(summary.channels) if summary else {}
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.messages = 0
        self.orphans = 0  # messages whose channel was defined in a lost chunk only

    def add(self, rec: Any) -> None:
        # lazy: mcap's records: only when a file is recovered
        from mcap.records import Channel, Message, Metadata, Schema

        if isinstance(rec, Schema):
            self.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self.channels[rec.id] = rec
        elif isinstance(rec, Message):
            cid = self._channel(rec.channel_id)
            if cid is None:
                self.orphans += 1
                return
            self.w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
            self.messages += 1
        elif isinstance(rec, Metadata):
            self.w.add_metadata(rec.name, dict(rec.metadata))

    def _channel(self, old: int) -> int | None:
        if old in self.channel_ids:
            return self.channel_ids[old]
        ch = self.channels.get(old)
        if ch is None:
            return None
        sid = 0
        if ch.schema_id:
            schema = self.schemas.get(ch.schema_id)
            if schema is None:
                return None
            if schema.id not in self.schema_ids:
                self.schema_ids[schema.id] = self.w.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            sid = self.schema_ids[schema.id]
        cid = self.w.register_channel(ch.topic, ch.message_encoding, sid, dict(ch.metadata))
        self.channel_ids[old] = cid
        return cid


@dataclass
class Recovered:
    """What ``recover`` saved and what it could not."""

    messages: int
    chunks: int
    losses: list[Loss]
    orphans: int  # intact messages of a channel defined only in a lost chunk
    cut_off_at: int | None

    @property
    def lost_messages(self) -> int:
        return sum(x.messages or 0 for x in self.losses) + self.orphans


def recover(path: str | Path, out: str | Path) -> Recovered:
    """Copy every intact record of a cut-off or damaged file into a new, finished MCAP file.

    A damaged chunk is skipped and the copy goes on with the next intact one; what was lost
    (chunks, byte offsets, log time ranges, messages counted or estimated) is returned and
    written into the new file's ``exolink.recovered`` metadata. Not an MCAP file, or nothing
    intact in it: RecordingError, and no output file."""
    from mcap.writer import Writer  # lazy: mcap's writer: only when a file is recovered

    target = Path(out)
    if target.exists():
        raise RecordingError(f"{out} exists (a recording is never overwritten)")
    with _open(path) as f:
        walk = Walk(f, path, keep=True)
        try:
            with target.open("xb") as g:
                w = Writer(g, enable_data_crcs=True)
                w.start(profile="ros2", library="exolink recover")
                copier = _Copier(w, walk.summary)
                for rec in walk:
                    copier.add(rec)
                c = walk.check
                done = Recovered(copier.messages, c.chunks, c.losses, copier.orphans, c.cut_off_at)
                if done.messages == 0 and c.losses:
                    raise RecordingError(f"{path}: nothing recoverable: {c.problem()}")
                w.add_metadata("exolink.recovered", _recovered_metadata(path, done))
                w.finish()
        except BaseException:
            target.unlink(missing_ok=True)  # nothing half-done
            raise
    return done


def _recovered_metadata(path: str | Path, r: Recovered) -> dict[str, str]:
    return {
        "from": str(path),
        "messages": str(r.messages),
        "chunks": str(r.chunks),
        "lost_messages": str(r.lost_messages),
        "losses": "; ".join(x.describe() for x in r.losses),
        "orphans": str(r.orphans),
        "cut_off_at": "" if r.cut_off_at is None else str(r.cut_off_at),
    }
