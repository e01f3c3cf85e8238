"""Damaged recordings: one flipped byte in a real recording (a sim appliance's recorder wrote it)
is found by `info`, `export` and `play` (an error naming where, no traceback, nothing written or
sent), and `recover` copies the rest, skipping the damage and saying what it lost. Every
recovered file is read back with the mcap library's plain reader: nothing in it differs from
the original. Offsets come from the original file's own index (the mcap reader's summary)."""

from __future__ import annotations

import random
import struct
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from benchmarks.harness import (
    EXOLINK,
    TEST_GROUPS,
    Appliance,
    Spawner,
    free_port,
    group,
    sim_config,
    wait_for,
)

FOOTER = 1 + 8 + 8 + 8 + 4  # opcode, length, summary start, summary offset start, CRC
CHUNK_HEAD = 1 + 8 + 8 + 8 + 8 + 4 + 4 + 4 + 8  # ... "zstd", then the compressed records


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """~3 s of a sim appliance (joint states, foot switches, diagnostics, a trigger edge) in
    small zstd chunks (4 KiB: a dozen of them), labelled, as the recorder writes it."""
    d = tmp_path_factory.mktemp("damage")
    params = {"directory": str(d / "rec"), "chunk_size": 4096, "fsync_interval_s": 0.5}
    nodes = [
        {"name": "simulator", "plugin": "simulator"},
        {"name": "h2_reader", "plugin": "h2_reader"},
        {"name": "recorder", "plugin": "recorder", "params": params},
    ]
    cfg = sim_config(d / "appliance.yaml", group(TEST_GROUPS), nodes)
    spawn = Spawner(d)
    try:
        app = Appliance(cfg, spawn)
        assert app.cli("record", "start", "--label", "subject=S01").returncode == 0
        time.sleep(1)
        assert app.cli("trigger", "fire").returncode == 0
        time.sleep(2)
        assert app.cli("record", "stop").returncode == 0
        wait_for(lambda: "idle" in app.cli("record", "status").stdout, timeout=15)
    finally:
        spawn.close()
    [path] = sorted((d / "rec").glob("*.mcap"))
    yield path


def messages(path: Path) -> list[tuple[str, int, bytes]]:
    """Every message as the mcap library's plain reader gives it: (topic, log time, bytes)."""
    with path.open("rb") as f:
        return [(c.topic, m.log_time, m.data) for _s, c, m in make_reader(f).iter_messages()]


def layout(path: Path) -> dict[str, int]:
    """Offsets of the parts to damage, from the file's own summary and footer."""
    size = path.stat().st_size
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
        f.seek(size - 8 - FOOTER)
        footer = next(StreamReader(f, skip_magic=True).records)
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 6, len(chunks)
    c2, c3, c4 = chunks[2], chunks[3], chunks[4]
    [labels] = [m for m in summary.metadata_indexes if m.name == "exolink.labels"]
    first_index = min(c2.message_index_offsets.values())
    return {
        "chunk 2": 2,
        "chunk 3": 3,
        "chunk 4": 4,
        # the zstd frame's header: the chunk does not decompress
        "zstd frame header": c2.chunk_start_offset + CHUNK_HEAD + 1,
        # the middle of the compressed records: a CRC mismatch (or no decompression)
        "compressed records": c3.chunk_start_offset + c3.chunk_length // 2,
        # the chunk record's length field: the reader must find the next record itself
        "chunk length": c4.chunk_start_offset + 6,
        # the top byte of a message index entry's log time (after opcode, length, channel id,
        # entries length, then 8 bytes of time)
        "message index": first_index + 9 + 2 + 4 + 7,
        # the label's value ("S01"): still valid text, so only the data section's CRC tells
        "labels metadata": labels.offset + labels.length - 2,
        "summary": footer.summary_start + (size - 8 - FOOTER - footer.summary_start) // 2,
        "footer": size - 8 - FOOTER + 12,
    }


# case -> (what the error must name, which chunk loses its messages (None: no message lost))
CASES: dict[str, tuple[str, str | None]] = {
    "zstd frame header": ("chunk 2 at", "chunk 2"),
    "compressed records": ("chunk 3 at", "chunk 3"),
    "chunk length": ("chunk 4 at", "chunk 4"),
    "message index": ("message index", None),
    "labels metadata": ("data section CRC mismatch", None),
    "summary": ("summary", None),
    "footer": ("footer damaged", None),
}


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*EXOLINK, *args], capture_output=True, text=True, timeout=60)


@pytest.fixture
def damaged(recording: Path, tmp_path: Path) -> Callable[[str], Path]:
    def make(case: str) -> Path:
        raw = bytearray(recording.read_bytes())
        raw[layout(recording)[case]] ^= 0x55
        out = tmp_path / "damaged.mcap"
        out.write_bytes(raw)
        return out

    return make


@pytest.mark.parametrize("case", list(CASES))
def test_one_flipped_byte_is_an_error_or_a_stated_loss(  # type: ignore[no-untyped-def]
    case: str, recording: Path, damaged, tmp_path: Path
) -> None:
    where, lost_chunk = CASES[case]
    original = messages(recording)
    path = damaged(case)
    # info, export and play: one line naming the damage, exit 3, nothing written or sent
    for cmd in (
        ["info", str(path)],
        ["export", str(path), "--csv", str(tmp_path / "csv")],
        ["play", str(path), "--at", f"tcp/127.0.0.1:{free_port()}"],
    ):
        r = run(*cmd)
        assert r.returncode == 3, (cmd, r.stdout, r.stderr)
        assert "Traceback" not in r.stderr and len(r.stderr.splitlines()) == 1, r.stderr
        assert r.stderr.startswith(f"exolink: {path}: ") and where in r.stderr, r.stderr
        assert "exolink recover" in r.stderr
    assert not list((tmp_path / "csv").glob("*.csv"))
    # recover: the rest, with the loss stated, and read back by the plain reader
    out = tmp_path / "recovered.mcap"
    r = run("recover", str(path), "-o", str(out))
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert f"lost: {lost_chunk} at" in r.stderr if lost_chunk else "no message lost" in r.stderr
    got = messages(out)
    assert set(got) <= set(original)  # nothing altered, nothing invented
    assert f"recovered {len(got)} messages" in r.stdout
    if lost_chunk is None:
        assert len(got) == len(original), r.stdout
    else:  # the lost chunk's messages, counted from its message index: exactly
        lost = len(original) - len(got)
        assert lost > 0 and f"lost {lost} messages" in r.stdout, (r.stdout, r.stderr)
    r = run("info", str(out))  # a finished file whose every CRC checks out
    assert r.returncode == 0 and "data section CRC checked, summary CRC checked" in r.stdout
    assert "/h2/joint_states" in r.stdout


def test_chunk_numbers_and_times_name_the_loss(recording: Path, damaged) -> None:  # type: ignore[no-untyped-def]
    """The error names the chunk, its byte range and its log times, and those are the lost
    messages' times in the original."""
    path = damaged("compressed records")
    r = run("info", str(path))
    original = messages(recording)
    with recording.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    c3 = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[3]
    start, end = c3.chunk_start_offset, c3.chunk_start_offset + c3.chunk_length
    assert f"chunk 3 at {start}..{end}" in r.stderr
    from exolink.recordings.check import iso

    assert f"log time {iso(c3.message_start_time)} .. {iso(c3.message_end_time)}" in r.stderr
    inside = [m for m in original if c3.message_start_time <= m[1] <= c3.message_end_time]
    assert inside


def test_not_an_mcap_file(tmp_path: Path, recording: Path) -> None:
    """Random bytes, and random bytes behind MCAP's magic: a clear error, exit 3, and recover
    leaves no file behind."""
    rnd = random.Random(7)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(rnd.randbytes(100_000))
    for cmd in (["info"], ["export", "--csv", str(tmp_path / "csv")], ["recover"]):
        r = run(cmd[0], str(junk), *cmd[1:])
        assert r.returncode == 3 and "not an MCAP file" in r.stderr, r
    assert not (tmp_path / "junk.recovered.mcap").exists()
    magic = tmp_path / "magic.mcap"
    magic.write_bytes(recording.read_bytes()[:8] + rnd.randbytes(100_000))
    r = run("recover", str(magic))
    assert r.returncode == 3 and "nothing recoverable" in r.stderr, r
    assert not (tmp_path / "magic.recovered.mcap").exists()


def test_the_recorder_writes_every_crc(recording: Path) -> None:
    """Chunk CRCs, the data section's and the summary's: all non-zero in what it wrote."""
    raw = recording.read_bytes()
    with recording.open("rb") as f:
        records = list(StreamReader(f, emit_chunks=True, validate_crcs=True).records)
    chunks = [r for r in records if type(r).__name__ == "Chunk"]
    [data_end] = [r for r in records if type(r).__name__ == "DataEnd"]
    [footer] = [r for r in records if type(r).__name__ == "Footer"]
    assert chunks and all(c.uncompressed_crc for c in chunks)
    assert data_end.data_section_crc and footer.summary_crc
    assert struct.unpack_from("<I", raw, len(raw) - 8 - 4)[0] == footer.summary_crc
