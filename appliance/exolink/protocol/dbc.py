"""DBC files compiled into struct layouts for the hot path.

cantools parses the DBC (the single source of truth); each frame becomes one ``struct.Struct`` so
decoding a frame is a single ``unpack`` (about 0.3 us on a desktop core, against ~20 us for a
cantools decode). Parsing costs ~200 ms of cantools import, too much for a node that must restart
fast on a 1 GHz Cortex-A8, so the compiled layout is cached as JSON keyed by the DBC's hash.
Only byte-aligned little-endian 8/16/32-bit integers and float32 are supported: that covers both
protocols, and anything else is refused with a clear error rather than decoded wrongly.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Protocol

import structlog

HERE = Path(__file__).parent
_FORMAT_VERSION = 1
_INT_FMT = {
    (8, True): "b",
    (8, False): "B",
    (16, True): "h",
    (16, False): "H",
    (32, True): "i",
    (32, False): "I",
}


class Received(Protocol):
    """What a decoder reads of a frame: a python-can Message, or the reader's lighter
    ``canbus.Frame`` (the hot path makes no Message per frame)."""

    @property
    def arbitration_id(self) -> int: ...
    @property
    def data(self) -> bytes | bytearray: ...
    @property
    def is_extended_id(self) -> bool: ...
    @property
    def is_remote_frame(self) -> bool: ...


class ProtocolError(ValueError):
    """A frame or value that cannot be encoded; the message names the signal and the bound."""


@dataclass(frozen=True, slots=True)
class SignalSpec:
    name: str
    byte: int
    fmt: str
    scale: float
    offset: float
    minimum: float
    maximum: float
    choices: dict[int, str]


@dataclass(frozen=True, slots=True)
class FrameSpec:
    frame_id: int
    name: str
    dlc: int
    signals: tuple[SignalSpec, ...]
    struct: struct.Struct
    scaled: tuple[int, ...]  # indices of signals whose raw value needs scale/offset

    def decode(self, data: bytes | bytearray) -> tuple[Any, ...]:
        """Raw unpack and scaling; the caller has checked the length."""
        raw = self.struct.unpack(data)
        if not self.scaled:
            return raw
        out = list(raw)
        for i in self.scaled:
            s = self.signals[i]
            out[i] = raw[i] * s.scale + s.offset
        return tuple(out)

    def pack_whole(self, values: tuple[int, ...]) -> bytes:
        """Whole raw values of an unscaled frame, checked against the DBC's bounds and packed:
        ``encode`` for a hot path (the controller manager's planned set-points: a few
        comparisons, not ``check``'s conversions). Anything else goes through ``encode``, which
        names what is wrong."""
        if len(values) == len(self.signals) and not self.scaled:
            for v, s in zip(values, self.signals, strict=True):
                if type(v) is not int or not s.minimum <= v <= s.maximum:
                    break
            else:
                return self.struct.pack(*values)
        return self.encode(values)

    def encode(self, values: tuple[float, ...] | list[float]) -> bytes:
        """Check every value against the DBC's bounds before packing: no half-valid frame."""
        return self.struct.pack(*self.check(values))

    def check(self, values: tuple[float, ...] | list[float]) -> list[int | float]:
        """The raw values of a frame, each checked against the DBC's bounds (ProtocolError
        names the signal): what ``encode`` packs, for a command checked before it is sent."""
        if len(values) != len(self.signals):
            raise ProtocolError(
                f"{self.name}: expected {len(self.signals)} values, got {len(values)}"
            )
        raw: list[int | float] = []
        for v, s in zip(values, self.signals, strict=True):
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ProtocolError(f"{self.name}.{s.name}: expected a number, got {v!r}")
            if not math.isfinite(v):
                raise ProtocolError(f"{self.name}.{s.name}: {v} is not a finite number")
            if not s.minimum <= v <= s.maximum:
                raise ProtocolError(
                    f"{self.name}.{s.name}: {v} is outside {_fmt(s.minimum)}..{_fmt(s.maximum)}"
                )
            r = (v - s.offset) / s.scale
            if s.fmt != "f":
                if r != int(r):
                    raise ProtocolError(
                        f"{self.name}.{s.name}: {v} is not a multiple of {_fmt(s.scale)}"
                    )
                r = int(r)
            raw.append(r)
        return raw

    def pack(self, values: tuple[float, ...] | list[float]) -> bytes:
        """Values a model computed and bounded itself (the simulator's boards): scaled and
        packed without ``encode``'s check of each value against the DBC, a fifth of its cost
        (the simulator builds six frames every 10 ms); struct still refuses a value that does
        not fit its signal's type. Anything from outside goes through ``encode``."""
        if not self.scaled:
            return self.struct.pack(*values)
        raw: list[int | float] = list(values)
        for i in self.scaled:
            s = self.signals[i]
            r = (raw[i] - s.offset) / s.scale
            raw[i] = r if s.fmt == "f" else round(r)
        return self.struct.pack(*raw)


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


@dataclass(frozen=True)
class Layout:
    source: str
    by_id: dict[int, FrameSpec]
    by_name: dict[str, FrameSpec]

    def frame(self, name: str) -> FrameSpec:
        try:
            return self.by_name[name]
        except KeyError:
            raise ProtocolError(f"{self.source}: no frame named {name!r}") from None


def _compile_with_cantools(path: Path) -> list[dict[str, Any]]:
    import cantools  # lazy: cantools only to compile a DBC (make dbc); nodes read the tables

    db = cantools.database.load_file(str(path), strict=True)
    if not isinstance(db, cantools.database.can.Database):
        raise TypeError(f"{path}: not a CAN database")
    frames = []
    for m in db.messages:
        signals = []
        for s in sorted(m.signals, key=lambda s: s.start):
            if s.byte_order != "little_endian" or s.start % 8 or s.length not in (8, 16, 32):
                raise ProtocolError(
                    f"{path.name}: {m.name}.{s.name}: only byte-aligned little-endian "
                    "8/16/32-bit signals are supported"
                )
            fmt = "f" if s.is_float else _INT_FMT[(s.length, s.is_signed)]
            if s.is_float and s.length != 32:
                raise ProtocolError(f"{path.name}: {m.name}.{s.name}: only float32 is supported")
            lo, hi = _raw_bounds(fmt)
            scale, offset = float(s.scale), float(s.offset)
            signals.append(
                {
                    "name": s.name,
                    "byte": s.start // 8,
                    "fmt": fmt,
                    "scale": scale,
                    "offset": offset,
                    "minimum": float(s.minimum) if s.minimum is not None else lo * scale + offset,
                    "maximum": float(s.maximum) if s.maximum is not None else hi * scale + offset,
                    "choices": {int(k): str(v) for k, v in (s.choices or {}).items()},
                }
            )
        frames.append({"frame_id": m.frame_id, "name": m.name, "dlc": m.length, "signals": signals})
    return frames


def _raw_bounds(fmt: str) -> tuple[float, float]:
    if fmt == "f":
        return -3.4028234663852886e38, 3.4028234663852886e38
    bits = struct.calcsize(fmt) * 8
    if fmt.islower():
        return -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    return 0, 2**bits - 1


def _build(path: Path, frames: list[dict[str, Any]]) -> Layout:
    by_id: dict[int, FrameSpec] = {}
    for f in frames:
        sigs = tuple(SignalSpec(**s) for s in f["signals"])
        fmt, pos = "<", 0
        for s in sigs:
            if s.byte < pos:
                raise ProtocolError(f"{path.name}: {f['name']}.{s.name} overlaps another signal")
            fmt += "x" * (s.byte - pos) + s.fmt
            pos = s.byte + struct.calcsize("<" + s.fmt)
        if pos > f["dlc"]:
            raise ProtocolError(f"{path.name}: {f['name']} signals exceed its length {f['dlc']}")
        fmt += "x" * (f["dlc"] - pos)
        scaled = tuple(i for i, s in enumerate(sigs) if s.scale != 1.0 or s.offset != 0.0)
        spec = FrameSpec(f["frame_id"], f["name"], f["dlc"], sigs, struct.Struct(fmt), scaled)
        by_id[spec.frame_id] = spec
    return Layout(path.name, by_id, {s.name: s for s in by_id.values()})


def _cache_dir() -> Path:
    root = os.environ.get("EXOLINK_CACHE") or os.environ.get("XDG_CACHE_HOME")
    return Path(root) / "exolink" if root else Path.home() / ".cache" / "exolink"


@cache
def load(path: str | Path) -> Layout:
    """The compiled layout of a DBC file, from the cache when the file is unchanged."""
    p = Path(path)
    digest = hashlib.sha256(p.read_bytes()).hexdigest()[:24]
    cached = _cache_dir() / f"{p.stem}-{digest}-v{_FORMAT_VERSION}.json"
    try:
        frames = json.loads(cached.read_text())
    except (OSError, ValueError):
        frames = _compile_with_cantools(p)
        try:
            cached.parent.mkdir(parents=True, exist_ok=True)
            tmp = cached.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps(frames))
            tmp.replace(cached)
        except OSError as exc:  # a read-only home only costs start-up time
            structlog.get_logger().warning("dbc_cache_unwritable", path=str(cached), error=str(exc))
    return _build(p, frames)


def bundled(name: str) -> Path:
    """Path of a DBC shipped inside the package (``h2`` or ``maccepa``)."""
    return HERE / f"{name}.dbc"
