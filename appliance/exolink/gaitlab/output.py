"""Output files written atomically: under a temporary name beside the target, renamed into
place (nothing half-written is left under the target's name)."""

from __future__ import annotations

import os
from pathlib import Path

from exolink.recordings.check import RecordingError


def _partial(out: Path) -> Path:
    """Where a file is written before it takes its name: nothing half-written is left there."""
    return out.with_name(f".{out.stem}.partial{out.suffix}")


def _parent(out: Path) -> None:
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"cannot write into {out.parent}: {exc.strerror}") from None


def _replace(tmp: Path, out: Path) -> None:
    os.replace(tmp, out)
