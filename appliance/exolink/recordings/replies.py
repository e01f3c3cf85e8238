"""The recorder's replies, one schema each: what it answers on ``record`` (its state) and on
``recordings`` (the files: list, stat, chunk, delete), and what a laptop reads back (``read``:
exolink.recordings.fetching, the CLI, the dashboard)."""

from __future__ import annotations

from exolink.wire.replies import Reply, plain, read

__all__ = ["plain", "read"]


class Card(Reply):
    """The recordings' card, in bytes: what a non-root writer may still use, and the reserve
    under which the recorder stops."""

    total: int
    free: int
    reserve: int


class FileEntry(Reply):
    """One file as the board lists it."""

    name: str
    size: int
    mtime: float  # s since the epoch
    state: str  # recording | closed
    sha256: str | None  # None until computed (closed files only)


class FileStat(FileEntry):
    """A closed file before a fetch: its checksum, or how far the board is computing it."""

    hashed: int = 0  # bytes hashed so far (its size once ``sha256`` is there)


class Listing(Reply):
    files: list[FileEntry]
    card: Card
    state: str  # the recorder's: idle | recording | stopping | error


class Chunk(Reply):
    """``size`` bytes of a closed file at ``offset``, base64 in ``data``; ``size``: the whole
    file's, so a fetch sees a file that changed under it."""

    name: str
    offset: int
    size: int
    data: str


class Deleted(Reply):
    name: str
    size: int


class RecordStatus(Reply):
    """``exolink record status``: the recording, what it received and wrote, and the card."""

    state: str
    error: str
    file: str | None  # the file being written
    size: int  # of that file
    labels: dict[str, str]
    queue: int  # messages waiting for the writer
    received: int
    written: int
    dropped: int
    duplicates: int
    malformed: int
    refused_topics: int
    refused_from: dict[str, int]
    files: list[str]  # this recording's files
    bytes: int  # all of them
    card: Card
    rate_bps: float
    hours_left: float | None  # None: no write rate yet
