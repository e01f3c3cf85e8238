"""Gait pattern files: CSV with a header naming the six joints and a row of whole degrees per
set-point (the thesis' pattern format, a spreadsheet's export). Checked whole before anything
plays: the configured limits, the count, ASCII digits; errors name the file's line. Names from
the network open only files inside the patterns directory (``pattern_in``)."""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

from exolink.limits.joints import Limits
from exolink.protocol import ProtocolError, h2

MAX_POINTS = 10_000
WHOLE = re.compile(r"[+-]?[0-9]+")  # ASCII: int() also takes other scripts' digits


@dataclass(frozen=True)
class Pattern:
    """Validated set-points in whole degrees, [row][joint index 0..5]."""

    file: str
    points: list[list[int]]


def load_pattern(path: str, limits: Limits) -> Pattern:
    """A pattern file the board's own config names (the start-up pattern)."""
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ProtocolError(f"{path}: cannot read pattern: {exc.strerror or exc}") from None
    return parse_pattern(text, path, limits)


def pattern_in(directory: str, name: str) -> str:
    """A file name inside the patterns directory; anything else (a path out of it, a link out of
    it) is refused: a network request must not make the board read /etc/shadow."""
    base = Path(directory).resolve()
    if not name or "/" in name or name in (".", ".."):
        raise ProtocolError(f"pattern name {name!r}: give a file name in {base}, not a path")
    target = (base / name).resolve()
    if target.parent != base or not target.is_file():
        raise ProtocolError(f"no pattern {name!r} in {base}")
    return str(target)


def parse_pattern(text: str, source: str, limits: Limits) -> Pattern:
    """CSV with a header of joint names (all six), one row per set-point, whole degrees inside
    the configured limits (the manager checks the limits in force again at start). Errors name
    the line and what is wrong; a file that may not be a pattern (no six-joint header) never has
    its content shown, a pattern's bad value is (its first 16 characters)."""
    path = source
    # A byte-order mark (a spreadsheet's "CSV UTF-8") is not part of the first joint's name.
    rows = list(csv.reader(text.removeprefix("\ufeff").splitlines()))
    if not rows:
        raise ProtocolError(f"{path}: empty pattern file")
    header = [c.strip() for c in rows[0]]
    if sorted(header) != sorted(h2.JOINTS):
        raise ProtocolError(f"{path}:1: header must name the six joints {', '.join(h2.JOINTS)}")
    order = [header.index(j) for j in h2.JOINTS]
    body = [r for r in rows[1:] if any(c.strip() for c in r)]
    if not 2 <= len(body) <= MAX_POINTS:
        raise ProtocolError(f"{path}: a pattern needs 2..{MAX_POINTS} set-points, got {len(body)}")
    points = []
    for n, row in enumerate(body, start=2):
        if len(row) != 6:
            raise ProtocolError(f"{path}:{n}: expected 6 values, got {len(row)}")
        cells = [row[i].strip() for i in order]
        for j, cell in enumerate(cells):
            if not WHOLE.fullmatch(cell):
                ascii_only = "" if cell.isascii() else " in ASCII digits"
                raise ProtocolError(
                    f"{path}:{n}: values must be whole degrees{ascii_only} "
                    f"({h2.JOINTS[j]} {cell[:16]!r})"
                )
        vals = [int(c) for c in cells]
        for j, v in enumerate(vals):
            lo, hi = limits.min_angles[j], limits.max_angles[j]
            if not lo <= v <= hi:
                raise ProtocolError(
                    f"{path}:{n}: {h2.JOINTS[j]} {v} deg is outside the limits {lo}..{hi}"
                )
        points.append(vals)
    return Pattern(source, points)
