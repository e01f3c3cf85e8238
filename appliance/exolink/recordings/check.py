"""What a recording file still holds: every CRC it carries checked, damage found and named.

The recorder writes a CRC of every chunk (its messages), of the data section (every record before
the summary: header, metadata, chunks, message indexes) and of the summary (the index and
statistics), as the MCAP format provides. ``check`` reads the whole file and checks all of them;
a damaged file is named by where (chunk, byte offset, log time range), never read as if whole.
The mcap library parses every record and checks chunk CRCs; what it does not do is written here:
the data-section and summary CRCs of a seeking reader, reading on past a damaged record (finding
the next record start), and naming the loss. ``exolink.recordings.readback`` (info, export, play, recover)
builds on it.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any


class RecordingError(Exception):
    pass


def iso(ns: int) -> str:
    """A log time as UTC, to the millisecond (how losses and the CLI name times)."""
    return datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds")


# --- integrity: CRCs, damage, and where --------------------------------------------------------

MCAP_MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")  # every record: opcode, length of what follows
_FOOTER = struct.Struct("<BQQQI")  # opcode, length 20, summary start, summary offset start, CRC
# Opcodes (the MCAP spec, mcap.opcode) of the records a file's data section holds.
_HEADER, _FOOTER_OP, _SCHEMA, _CHANNEL, _MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
_CHUNK, _MESSAGE_INDEX, _ATTACHMENT, _METADATA, _DATA_END = 0x06, 0x07, 0x09, 0x0C, 0x0F
_DATA_OPS = frozenset(
    {
        _HEADER,
        _SCHEMA,
        _CHANNEL,
        _MESSAGE,
        _CHUNK,
        _MESSAGE_INDEX,
        _ATTACHMENT,
        _METADATA,
        _DATA_END,
    }
)
# A chunk header's uncompressed size past this is damage (the recorder's chunks are <= 64 MiB):
# believed, it would have the decompressor allocate whatever a flipped bit says.
MAX_CHUNK_BYTES = 1 << 30
_BLOCK = 1 << 20


@dataclass
class Loss:
    """A stretch of a file that cannot be read or trusted: where, why, and what it held (as far
    as the file still says: the summary's chunk index, the chunk's message index, or its
    neighbours' times)."""

    offset: int
    length: int
    what: str
    chunk: int | None = None  # the chunk's number in the file (0 = first), when known
    start_ns: int | None = None
    end_ns: int | None = None
    messages: int | None = None
    estimated: bool = False  # messages: estimated from the chunk's size, not counted

    def describe(self) -> str:
        where = f"chunk {self.chunk} at" if self.chunk is not None else "bytes"
        where += f" {self.offset}..{self.offset + self.length}"
        if self.start_ns is not None and self.end_ns is not None:
            where += f", log time {iso(self.start_ns)} .. {iso(self.end_ns)}"
        elif self.start_ns is not None:
            where += f", log time after {iso(self.start_ns)}"
        if self.messages == 0:
            where += ", no message lost"
        elif self.messages is not None:
            n = self.messages
            where += f", {'~' if self.estimated else ''}{n} message{'s' if n != 1 else ''}"
        return f"{where}: {self.what}"


@dataclass
class Check:
    """What reading a whole file found: chunks whose CRC held, what is damaged, how it ends."""

    path: str
    size: int = 0
    chunks: int = 0  # chunks read whole, CRC matched
    unchecked: int = 0  # chunks written without a CRC (other writers): read, not verifiable
    losses: list[Loss] = field(default_factory=list)
    cut_off_at: int | None = None  # a file that never finished (power loss) ends here
    summary: str = "missing"  # checked | no crc | missing | damaged
    data_crc: str = "missing"  # checked | not written | missing | mismatch

    @property
    def complete(self) -> bool:
        return self.cut_off_at is None and self.summary in ("checked", "no crc")

    def problem(self) -> str:
        """One line for an error: the damage found (first few), or how the file ends."""
        if self.losses:
            shown = "; ".join(x.describe() for x in self.losses[:3])
            more = f"; and {len(self.losses) - 3} more" if len(self.losses) > 3 else ""
            return (
                f"{self.path}: damaged ({shown}{more}); "
                "`exolink recover` copies what is intact into a new file and says what was lost"
            )
        if self.cut_off_at is not None:
            return (
                f"{self.path}: not a complete MCAP file (it ends at byte {self.cut_off_at} "
                "inside its data: cut off, e.g. by power loss); try `exolink recover`"
            )
        return f"{self.path}: not a complete MCAP file (no summary section); try `exolink recover`"


@dataclass
class _Chunk:
    """A chunk as the walk met it (good or lost), until its message indexes have been read."""

    no: int
    offset: int
    length: int
    start_ns: int
    end_ns: int
    usize: int
    records: list[Any]  # its schemas, channels, messages (when the walk keeps them)
    loss: Loss | None = None
    indexed: int = 0  # messages its message indexes list
    indexed_times: tuple[int, int] | None = None  # the first and last log time they list


def _read_at(f: IO[bytes], offset: int, n: int) -> bytes:
    f.seek(offset)
    return f.read(n)


def _parse(op: int, body: bytes) -> tuple[Any, int]:
    """A record's body -> (mcap record, bytes it used), with the mcap library's record classes."""
    from mcap.data_stream import ReadDataStream  # lazy: mcap's readers: only when a file is checked
    from mcap.records import (
        Attachment,
        Channel,
        Chunk,
        DataEnd,
        Header,
        Message,
        MessageIndex,
        Metadata,
        Schema,
    )

    readers: dict[int, Any] = {
        _HEADER: Header.read,
        _SCHEMA: Schema.read,
        _CHANNEL: Channel.read,
        _MESSAGE: lambda s: Message.read(s, len(body)),
        _CHUNK: Chunk.read,
        _MESSAGE_INDEX: MessageIndex.read,
        _ATTACHMENT: Attachment.read,
        _METADATA: Metadata.read,
        _DATA_END: DataEnd.read,
    }
    stream = ReadDataStream(io.BytesIO(body))
    return readers[op](stream), stream.count


def _chunk_plausible(head: bytes) -> bool:
    """Could a chunk record start here (opcode, length, then its fields, all consistent)?"""
    if len(head) < 9 + 36 or head[0] != _CHUNK:
        return False
    (length,) = struct.unpack_from("<Q", head, 1)
    start, end, usize, _crc, clen = struct.unpack_from("<QQQII", head, 9)
    if clen not in (0, 3, 4) or len(head) < 9 + 36 + clen + 8 or start > end:
        return False
    comp = head[45 : 45 + clen]
    if comp not in (b"", b"lz4", b"zstd") or usize > MAX_CHUNK_BYTES:
        return False
    (dlen,) = struct.unpack_from("<Q", head, 45 + clen)
    return length == 36 + clen + 8 + dlen


def _metadata_plausible(head: bytes) -> bool:
    if len(head) < 9 + 8 or head[0] != _METADATA:
        return False
    (length,) = struct.unpack_from("<Q", head, 1)
    (nlen,) = struct.unpack_from("<I", head, 9)
    if nlen > 1024 or len(head) < 9 + 4 + nlen + 4:
        return False
    try:
        head[13 : 13 + nlen].decode()
    except UnicodeDecodeError:
        return False
    (mlen,) = struct.unpack_from("<I", head, 13 + nlen)
    return length == 4 + nlen + 4 + mlen


def _resync(f: IO[bytes], start: int, end: int) -> int | None:
    """The next offset in [start, end) where a chunk or metadata record plausibly starts (the
    records a damaged stretch is skipped to), or a DataEnd record right before the summary."""
    pos = start
    while pos < end:
        f.seek(pos)
        block = f.read(min(_BLOCK, end - pos) + 256)  # + the next candidate's header
        found = [
            i
            for op in (_CHUNK, _METADATA, _DATA_END)
            for i in _find_all(block, op)
            if pos + i < end
        ]
        for i in sorted(found):
            head = block[i : i + 256]
            if len(head) < 256 and pos + i + len(head) < end:
                head = _read_at(f, pos + i, 256)
            fits = len(head) >= 9 and pos + i + 9 + struct.unpack_from("<Q", head, 1)[0] <= end
            if fits and (_chunk_plausible(head) or _metadata_plausible(head)):
                return pos + i
            if head[:1] == bytes([_DATA_END]) and head[1:9] == struct.pack("<Q", 4):
                return pos + i
        pos += _BLOCK
    return None


def _find_all(block: bytes, op: int) -> Iterator[int]:
    needle = bytes([op])
    i = block.find(needle)
    while i >= 0:
        yield i
        i = block.find(needle, i + 1)


class Walk:
    """One pass over a file, record by record, in file order (the mcap library parses each).

    Iterating yields each intact record outside the chunks and, with ``keep``, every record of
    each intact chunk (schemas, channels, messages), plus a Loss for each stretch it could not
    read or trust; ``check`` holds the totals once it is done. A damaged record is skipped: to
    the next record when only a chunk's content is bad (its length still holds), else to the
    next chunk or metadata record the summary lists (when its CRC holds) or, without one, the
    next place such a record plausibly starts. The summary names chunks and their log times;
    the message indexes after each chunk count its messages.
    """

    def __init__(self, f: IO[bytes], path: str | Path, keep: bool) -> None:
        self.f, self.keep = f, keep
        f.seek(0, 2)
        self.check = Check(str(path), size=f.tell())
        if _read_at(f, 0, 8) != MCAP_MAGIC:
            raise RecordingError(
                f"{path}: not an MCAP file (it does not start with MCAP's magic bytes)"
            )
        self.summary: Any = None  # mcap Summary, when its CRC held
        self.limit = self._read_footer()
        self.chunk_at: dict[int, Any] = {}  # offset -> ChunkIndex (a checked summary's)
        if self.summary is not None:
            self.chunk_at = {c.chunk_start_offset: c for c in self.summary.chunk_indexes}
        self.numbers = {off: i for i, off in enumerate(sorted(self.chunk_at))}
        self.seen_chunks = 0
        self.current: _Chunk | None = None  # the last chunk, until its message indexes are read
        self.last_good_end: int | None = None  # log time where the last intact chunk ended
        self.unplaced: list[Loss] = []  # losses waiting for the next intact chunk's start time
        self.good_bytes = self.good_messages = 0  # intact chunks: sizes and indexed messages
        self.data_end_at: int | None = None
        self.data_crc = 0

    # --- footer and summary ---------------------------------------------------------------

    def _read_footer(self) -> int:
        """Checks the footer and the summary's CRC; returns where the data section ends at the
        latest (the summary's start when it can be believed, else the footer or the file end)."""
        c, f, size = self.check, self.f, self.check.size
        footer_at = size - 8 - _FOOTER.size
        if size < 8 + _FOOTER.size + 8 or _read_at(f, size - 8, 8) != MCAP_MAGIC:
            c.summary = "missing"
            return size
        raw = _read_at(f, footer_at, _FOOTER.size)
        op, length, start, offsets, crc = _FOOTER.unpack(raw)
        if op != _FOOTER_OP or length != 20 or start > footer_at or offsets > footer_at:
            c.summary = "damaged"
            c.losses.append(Loss(footer_at, _FOOTER.size, "footer damaged", messages=0))
            return footer_at
        summary_at = start or footer_at
        if crc:
            actual = zlib.crc32(raw[:25], _crc_of(f, summary_at, footer_at))
            if actual != crc:
                c.summary = "damaged"
                what = "summary (index and statistics) damaged: CRC mismatch"
                c.losses.append(Loss(summary_at, size - summary_at, what, messages=0))
                return footer_at
        c.summary = "checked" if crc else "no crc"
        if start:
            # lazy: mcap's readers: only when a file is checked
            from mcap.reader import SeekingReader

            try:
                f.seek(0)
                self.summary = SeekingReader(f).get_summary()
            except Exception as exc:  # CRC held: the writer wrote something unreadable
                c.summary = "damaged"
                what = f"summary does not parse ({type(exc).__name__}: {exc})"
                c.losses.append(Loss(summary_at, size - summary_at, what, messages=0))
                return footer_at
        return summary_at

    # --- the data section ------------------------------------------------------------------

    def __iter__(self) -> Iterator[Any]:
        f, c = self.f, self.check
        pos = 8
        while pos < self.limit:
            head = _read_at(f, pos, _HEAD.size)
            if len(head) < _HEAD.size:
                c.cut_off_at = pos
                break
            op, length = _HEAD.unpack(head)
            end = pos + _HEAD.size + length
            parsed = None
            if op in _DATA_OPS and end <= self.limit:
                body = f.read(length)
                try:
                    parsed, used = _parse(op, body)
                except Exception:
                    parsed = None
                if parsed is not None and used != length:  # the writer pads nothing
                    parsed = None
            if parsed is None:
                torn = op in _DATA_OPS and end > self.check.size
                nxt = self._skip_to(pos)
                if nxt is None and torn and c.summary == "missing":
                    c.cut_off_at = pos  # power loss: the last record was never finished
                    break
                stop = self.limit if nxt is None else nxt
                self._close_chunk()
                self._lose(self._stretch(Loss(pos, stop - pos, "unreadable records (skipped)")))
                if nxt is None:
                    break
                pos = nxt
                continue
            yield from self._record(pos, op, length, parsed)
            if op == _DATA_END:
                self.data_end_at, self.data_crc = pos, parsed.data_section_crc
                break
            pos = end
        else:
            if c.summary == "missing" and self.data_end_at is None:
                c.cut_off_at = pos
        self._close_chunk()
        self._finish()

    def _record(self, pos: int, op: int, length: int, rec: Any) -> Iterator[Any]:
        if op == _CHUNK:
            self._close_chunk()
            yield from self._chunk(pos, _HEAD.size + length, rec)
        elif op == _MESSAGE_INDEX:
            self._message_index(pos, _HEAD.size + length, rec)
        else:
            self._close_chunk()
            if op not in (_HEADER, _DATA_END):
                yield rec

    def _chunk(self, pos: int, length: int, rec: Any) -> Iterator[Any]:
        # lazy: mcap's readers: only when a file is checked
        from mcap.stream_reader import CRCValidationError, breakup_chunk, get_chunk_data_stream

        no = self.numbers.get(pos, self.seen_chunks)
        self.seen_chunks += 1
        cur = self.current = _Chunk(
            no, pos, length, rec.message_start_time, rec.message_end_time, rec.uncompressed_size, []
        )
        what = ""
        try:
            if rec.uncompressed_size > MAX_CHUNK_BYTES:
                what = f"chunk header damaged (says {rec.uncompressed_size} bytes)"
            elif self.keep:
                cur.records = breakup_chunk(rec, validate_crc=True)
            else:
                get_chunk_data_stream(rec, validate_crc=True)
        except CRCValidationError:
            what = "CRC mismatch: its content differs from what was written"
        except Exception as exc:  # a decompressor's or a record's error: damage all the same
            what = f"does not decompress or parse ({type(exc).__name__}: {exc})"
        if what:
            cur.records = []
            cur.loss = Loss(pos, length, what, chunk=no)
            return
        if rec.uncompressed_crc:
            self.check.chunks += 1
        else:
            self.check.unchecked += 1
        yield from cur.records

    def _message_index(self, pos: int, length: int, rec: Any) -> None:
        """Counts the messages of the chunk before (and, for a lost one, spans their times);
        an index that cannot belong to an intact chunk (times outside the chunk's, offsets past
        its end) is damage of its own, the chunk's messages intact."""
        cur, entries = self.current, rec.records
        if cur is None:
            self._lose(Loss(pos, length, "message index without its chunk", messages=0))
            return
        if cur.loss is None and not all(
            cur.start_ns <= t <= cur.end_ns and off < cur.usize for t, off in entries
        ):
            what = "message index damaged (the chunk's messages are intact; recover rebuilds it)"
            loss = Loss(pos, length, what, cur.no, cur.start_ns, cur.end_ns, messages=0)
            self._lose(loss)
            return
        cur.indexed += len(entries)
        if entries:
            times = [t for t, _ in entries]
            first, last = cur.indexed_times or (min(times), max(times))
            cur.indexed_times = (min(first, *times), max(last, *times))

    def _close_chunk(self) -> None:
        cur, self.current = self.current, None
        if cur is None:
            return
        if cur.loss is None:
            self.good_bytes += cur.length
            self.good_messages += cur.indexed
            for loss in self.unplaced:  # a loss's time: up to where this chunk starts
                loss.end_ns = cur.start_ns
            self.unplaced = []
            self.last_good_end = cur.end_ns
            return
        # Its log times from the checked summary, else its message index, else its own header
        # (which no CRC covers, but which is damaged less often than its larger content).
        loss, index = cur.loss, self.chunk_at.get(cur.offset)
        if index is not None:
            loss.start_ns, loss.end_ns = index.message_start_time, index.message_end_time
        elif cur.indexed_times is not None:
            loss.start_ns, loss.end_ns = cur.indexed_times
        elif cur.start_ns <= cur.end_ns:
            loss.start_ns, loss.end_ns = cur.start_ns, cur.end_ns
        if cur.indexed:
            loss.messages = cur.indexed
        self._lose(loss)

    def _skip_to(self, pos: int) -> int | None:
        """Where reading goes on after a record at ``pos`` that cannot be read: the next chunk
        or metadata record the checked summary lists, else the next place one plausibly
        starts."""
        if self.summary is not None:
            known = [o for o in self.chunk_at if o > pos]
            known += [m.offset for m in self.summary.metadata_indexes if m.offset > pos]
            return min(known, default=None)
        return _resync(self.f, pos + 1, self.limit)

    def _stretch(self, loss: Loss) -> Loss:
        """A skipped stretch named by the checked summary: its chunks, their log times, and
        their messages as their message indexes (where those still read) count them."""
        if self.summary is None:
            return loss
        end = loss.offset + loss.length
        inside = [c for o, c in self.chunk_at.items() if loss.offset <= o < end]
        if not inside:  # then no message: the summary lists every chunk
            names = [m.name for m in self.summary.metadata_indexes if loss.offset <= m.offset < end]
            loss.what = (
                f"metadata {', '.join(names)} unreadable"
                if names
                else "message index records unreadable (their chunk's messages are intact)"
            )
            loss.messages = 0
            return loss
        loss.chunk = min(self.numbers[c.chunk_start_offset] for c in inside)
        loss.start_ns = min(c.message_start_time for c in inside)
        loss.end_ns = max(c.message_end_time for c in inside)
        if len(inside) > 1:
            loss.what += f": {len(inside)} chunks"
        try:
            loss.messages = sum(self._indexed(c) for c in inside)
        except Exception:  # their indexes are in the damaged stretch too: estimated instead
            loss.messages = None
        return loss

    def _indexed(self, chunk_index: Any) -> int:
        """Messages a chunk's message index records list (read where the summary says)."""
        n = 0
        for offset, length in _index_records(chunk_index):
            body = _read_at(self.f, offset + _HEAD.size, length - _HEAD.size)
            n += len(_parse(_MESSAGE_INDEX, body)[0].records)
        return n

    def _lose(self, loss: Loss) -> None:
        if loss.start_ns is None and loss.messages != 0:
            loss.start_ns = self.last_good_end
            self.unplaced.append(loss)
        self.check.losses.append(loss)

    def _finish(self) -> None:
        """Estimates what uncounted losses held (bytes per message of the intact chunks) and
        checks the data section's CRC, which covers what no chunk CRC does."""
        c = self.check
        per_message = self.good_bytes / self.good_messages if self.good_messages else 0
        for loss in c.losses:
            if loss.messages is None and per_message:
                loss.messages, loss.estimated = round(loss.length / per_message), True
        if self.data_end_at is None:
            c.data_crc = "missing"
        elif not self.data_crc:
            c.data_crc = "not written"
        elif _crc_of(self.f, 0, self.data_end_at) == self.data_crc:
            c.data_crc = "checked"
        else:
            c.data_crc = "mismatch"
            if not any(x.offset < self.data_end_at for x in c.losses):
                what = (
                    "data section CRC mismatch: a record outside the messages (file header, "
                    "metadata: labels, stats, config; or a chunk's bookkeeping) differs from "
                    "what was written; every chunk's messages check out"
                )
                c.losses.append(Loss(8, self.data_end_at - 8, what, messages=0))


def _index_records(chunk_index: Any) -> Iterator[tuple[int, int]]:
    """(offset, length) of each message index record of a chunk, from its ChunkIndex."""
    offsets = sorted(chunk_index.message_index_offsets.values())
    if offsets:
        ends = [*offsets[1:], offsets[0] + chunk_index.message_index_length]
        yield from ((o, e - o) for o, e in zip(offsets, ends, strict=True))


def _crc_of(f: IO[bytes], start: int, end: int, crc: int = 0) -> int:
    f.seek(start)
    left = end - start
    while left > 0:
        block = f.read(min(_BLOCK, left))
        if not block:
            break
        crc = zlib.crc32(block, crc)
        left -= len(block)
    return crc


def check(path: str | Path) -> Check:
    """Read the whole file and check every CRC it carries; nothing raised for damage (see
    Check.losses), only for what is not an MCAP file at all."""
    with _open(path) as f:
        walk = Walk(f, path, keep=False)
        for _ in walk:
            pass
    return walk.check


def verify(path: str | Path) -> Check:
    """``check``, and a RecordingError naming the damage (or the cut-off) unless all is well."""
    c = check(path)
    if c.losses or not c.complete:
        raise RecordingError(c.problem())
    return c


def _open(path: str | Path) -> Any:
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file")
    return p.open("rb")
