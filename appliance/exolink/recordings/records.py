"""MCAP at the level of its records: the opcodes of a data section, a record's body parsed
with the mcap library's own classes, whether a record plausibly starts at an offset (to read
on past damage), and CRCs over a stretch of the file. ``exolink.recordings.check`` walks a
file with these and names what is lost."""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from typing import IO, Any

MCAP_MAGIC = b"\x89MCAP0\r\n"
HEAD = struct.Struct("<BQ")  # every record: opcode, length of what follows
FOOTER = struct.Struct("<BQQQI")  # opcode, length 20, summary start, summary offset start, CRC
# Opcodes (the MCAP spec, mcap.opcode) of the records a file's data section holds.
HEADER, FOOTER_OP, SCHEMA, CHANNEL, MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
CHUNK, MESSAGE_INDEX, ATTACHMENT, METADATA, DATA_END = 0x06, 0x07, 0x09, 0x0C, 0x0F
DATA_OPS = frozenset(
    {
        HEADER,
        SCHEMA,
        CHANNEL,
        MESSAGE,
        CHUNK,
        MESSAGE_INDEX,
        ATTACHMENT,
        METADATA,
        DATA_END,
    }
)
# A chunk header's uncompressed size past this is damage (the recorder's chunks are <= 64 MiB):
# believed, it would have the decompressor allocate whatever a flipped bit says.
MAX_CHUNK_BYTES = 1 << 30
BLOCK = 1 << 20


def read_at(f: IO[bytes], offset: int, n: int) -> bytes:
    f.seek(offset)
    return f.read(n)


def parse(op: int, body: bytes) -> tuple[Any, int]:
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
        HEADER: Header.read,
        SCHEMA: Schema.read,
        CHANNEL: Channel.read,
        MESSAGE: lambda s: Message.read(s, len(body)),
        CHUNK: Chunk.read,
        MESSAGE_INDEX: MessageIndex.read,
        ATTACHMENT: Attachment.read,
        METADATA: Metadata.read,
        DATA_END: DataEnd.read,
    }
    stream = ReadDataStream(io.BytesIO(body))
    return readers[op](stream), stream.count


def chunk_plausible(head: bytes) -> bool:
    """Could a chunk record start here (opcode, length, then its fields, all consistent)?"""
    if len(head) < 9 + 36 or head[0] != CHUNK:
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


def metadata_plausible(head: bytes) -> bool:
    if len(head) < 9 + 8 or head[0] != METADATA:
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


def resync(f: IO[bytes], start: int, end: int) -> int | None:
    """The next offset in [start, end) where a chunk or metadata record plausibly starts (the
    records a damaged stretch is skipped to), or a DataEnd record right before the summary."""
    pos = start
    while pos < end:
        f.seek(pos)
        block = f.read(min(BLOCK, end - pos) + 256)  # + the next candidate's header
        found = [
            i for op in (CHUNK, METADATA, DATA_END) for i in find_all(block, op) if pos + i < end
        ]
        for i in sorted(found):
            head = block[i : i + 256]
            if len(head) < 256 and pos + i + len(head) < end:
                head = read_at(f, pos + i, 256)
            fits = len(head) >= 9 and pos + i + 9 + struct.unpack_from("<Q", head, 1)[0] <= end
            if fits and (chunk_plausible(head) or metadata_plausible(head)):
                return pos + i
            if head[:1] == bytes([DATA_END]) and head[1:9] == struct.pack("<Q", 4):
                return pos + i
        pos += BLOCK
    return None


def find_all(block: bytes, op: int) -> Iterator[int]:
    needle = bytes([op])
    i = block.find(needle)
    while i >= 0:
        yield i
        i = block.find(needle, i + 1)


def index_records(chunk_index: Any) -> Iterator[tuple[int, int]]:
    """(offset, length) of each message index record of a chunk, from its ChunkIndex."""
    offsets = sorted(chunk_index.message_index_offsets.values())
    if offsets:
        ends = [*offsets[1:], offsets[0] + chunk_index.message_index_length]
        yield from ((o, e - o) for o, e in zip(offsets, ends, strict=True))


def crc_of(f: IO[bytes], start: int, end: int, crc: int = 0) -> int:
    f.seek(start)
    left = end - start
    while left > 0:
        block = f.read(min(BLOCK, left))
        if not block:
            break
        crc = zlib.crc32(block, crc)
        left -= len(block)
    return crc
