"""Shared by the recipe checks (on the host) and the built-image checks (`make test-image-built`)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def debian_lock() -> dict[str, str]:
    """image/debian.lock as package -> version; a malformed line fails here, not as a wrong pin."""
    lines = (REPO / "image/debian.lock").read_text().splitlines()
    bad = [line for line in lines if not re.fullmatch(r"[a-z0-9][a-z0-9+.-]*=\S+", line)]
    assert bad == [], "not name=version"
    return dict(line.split("=", 1) for line in lines)
