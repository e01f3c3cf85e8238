"""The MCAP file writer: one recording file, as the recorder's writer loop writes it."""

from __future__ import annotations

import os
import time
from pathlib import Path

from exolink.nodes.recorder.params import RecorderParams
from mcap.writer import CompressionType, Writer  # here, not on first file: see McapFile

from exolink import __version__, messaging
from exolink.recordings import commands


class McapFile:
    """One open MCAP file with its schemas and channels registered on first use.

    Each channel's metadata marks whether its topic is a command (``exolink.command``: "true" or
    "false", by exolink.recordings.commands.command_topic): ``exolink play`` never republishes a command.

    Nothing here may import: the writer loop opens files, and an import on it (mcap and its
    compressors took seconds under emulation) stalls its heartbeat until the supervisor kills it.
    """

    def __init__(self, path: Path, p: RecorderParams, metadata: dict[str, dict[str, str]]) -> None:
        comp = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }
        self.path = path
        self.f = path.open("xb")  # never overwrite a recording
        # CRCs of every chunk, of the data section and of the summary: readers tell a damaged
        # file from a good one (exolink.recordings.check), at one crc32 pass over what is written.
        self.w = Writer(
            self.f,
            chunk_size=p.chunk_size,
            compression=comp[p.compression],
            enable_crcs=True,
            enable_data_crcs=True,
        )
        self.w.start(profile="ros2", library=f"exolink {__version__}")
        for name, data in metadata.items():
            self.w.add_metadata(name, data)
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.opened = time.monotonic()

    def channel(self, topic: str, typename: str) -> int:
        cid = self.channels.get(topic)
        if cid is None:
            sid = self.schemas.get(typename)
            if sid is None:
                text = messaging.msgdef(typename)
                sid = self.schemas[typename] = self.w.register_schema(
                    typename, "ros2msg", text.encode()
                )
            name = f"/{topic}"
            cid = self.channels[topic] = self.w.register_channel(
                name, "cdr", sid, commands.command_metadata(name)
            )
        return cid

    def sync(self) -> None:
        self.w.flush()
        os.fsync(self.f.fileno())

    def size(self) -> int:
        return self.f.tell()

    def close(self, stats: dict[str, str], receive: dict[str, str] | None = None) -> None:
        self.w.add_metadata("exolink.stats", stats)
        self.w.add_metadata("exolink.receive", receive or {})
        self.w.finish()
        self.f.flush()
        os.fsync(self.f.fileno())
        self.f.close()

    def size_closed(self) -> int:
        return os.stat(self.path).st_size
