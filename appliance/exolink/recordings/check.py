"""What a recording file still holds: every CRC it carries checked, damage found and named.

The recorder writes a CRC of every chunk (its messages), of the data section (every record before
the summary: header, metadata, chunks, message indexes) and of the summary (the index and
statistics), as the MCAP format provides. ``check`` reads the whole file and checks all of them;
a damaged file is named by where (chunk, byte offset, log time range), never read as if whole.
The mcap library parses every record and checks chunk CRCs; what it does not do is written here:
the data-section and summary CRCs of a seeking reader, reading on past a damaged record (finding
the next record start: exolink.recordings.records), and naming the loss. ``exolink.recordings.readback`` (info, export, play, recover)
builds on it.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from exolink.recordings.records import (
    CHUNK,
    DATA_END,
    DATA_OPS,
    FOOTER,
    FOOTER_OP,
    HEAD,
    HEADER,
    MAX_CHUNK_BYTES,
    MCAP_MAGIC,
    MESSAGE_INDEX,
    crc_of,
    index_records,
    parse,
    read_at,
    resync,
)


class RecordingError(Exception):
    pass


def iso(ns: int) -> str:
    """A log time as UTC, to the millisecond (how losses and the CLI name times)."""
    return datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds")


# --- integrity: CRCs, damage, and where --------------------------------------------------------


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
        if read_at(f, 0, 8) != MCAP_MAGIC:
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
        footer_at = size - 8 - FOOTER.size
        if size < 8 + FOOTER.size + 8 or read_at(f, size - 8, 8) != MCAP_MAGIC:
            c.summary = "missing"
            return size
        raw = read_at(f, footer_at, FOOTER.size)
        op, length, start, offsets, crc = FOOTER.unpack(raw)
        if op != FOOTER_OP or length != 20 or start > footer_at or offsets > footer_at:
            c.summary = "damaged"
            c.losses.append(Loss(footer_at, FOOTER.size, "footer damaged", messages=0))
            return footer_at
        summary_at = start or footer_at
        if crc:
            actual = zlib.crc32(raw[:25], crc_of(f, summary_at, footer_at))
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
            head = read_at(f, pos, HEAD.size)
            if len(head) < HEAD.size:
                c.cut_off_at = pos
                break
            op, length = HEAD.unpack(head)
            end = pos + HEAD.size + length
            parsed = None
            if op in DATA_OPS and end <= self.limit:
                body = f.read(length)
                try:
                    parsed, used = parse(op, body)
                except Exception:
                    parsed = None
                if parsed is not None and used != length:  # the writer pads nothing
                    parsed = None
            if parsed is None:
                torn = op in DATA_OPS and end > self.check.size
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
            if op == DATA_END:
                self.data_end_at, self.data_crc = pos, parsed.data_section_crc
                break
            pos = end
        else:
            if c.summary == "missing" and self.data_end_at is None:
                c.cut_off_at = pos
        self._close_chunk()
        self._finish()

    def _record(self, pos: int, op: int, length: int, rec: Any) -> Iterator[Any]:
        if op == CHUNK:
            self._close_chunk()
            yield from self._chunk(pos, HEAD.size + length, rec)
        elif op == MESSAGE_INDEX:
            self._message_index(pos, HEAD.size + length, rec)
        else:
            self._close_chunk()
            if op not in (HEADER, DATA_END):
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
        return resync(self.f, pos + 1, self.limit)

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
        for offset, length in index_records(chunk_index):
            body = read_at(self.f, offset + HEAD.size, length - HEAD.size)
            n += len(parse(MESSAGE_INDEX, body)[0].records)
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
        elif crc_of(self.f, 0, self.data_end_at) == self.data_crc:
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
