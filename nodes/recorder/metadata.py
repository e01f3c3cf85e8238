"""What each recording says of itself beside its messages: the device, the software, the
operator's labels, which clock stamped it, the config it ran with, and every bus reader's
receive counters at its open and close (frames dropped or late while it was written), so a
file read years later says how it was made and whether anything is missing."""

from __future__ import annotations

import time
from typing import Any

import msgspec

from exolink import __version__, roles
from exolink.board import clock
from exolink.config import ApplianceConfig
from exolink.wire.replies import NodeStats

RECEIVE_QUERY_S = 0.5  # the readers' receive counters, asked when a file opens and closes
RECEIVE_DELTAS = ("dropped", "late", "frames")  # counters also given for the file alone


def file_metadata(
    cfg: ApplianceConfig, labels: dict[str, str], index: int, config_yaml: str
) -> dict[str, dict[str, str]]:
    """The MCAP metadata records a file opens with."""
    return {
        "exolink": {
            "device": cfg.device,
            "software_version": __version__,
            "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "file_index": str(index),
        },
        "exolink.labels": dict(labels),
        # which clock stamped this file (a board with no time server: exolink.board.clock)
        "exolink.board.clock": clock.recorded(cfg.state_dir),
        "exolink.config": {"yaml": config_yaml},
    }


def receive_counters(session: Any, msg: Any, log: Any) -> dict[str, dict[str, Any]]:
    """Every bus reader's receive counters now (node -> FrameReader.counters())."""
    out: dict[str, dict[str, Any]] = {}
    # Every node's stats queryable, asked as the appliance's own login (see exolink.roles).
    key = msg.mgmt("nodes", "*", "stats", roles.APPLIANCE_USER)
    try:
        for reply in session.get(key, payload=b"{}", timeout=RECEIVE_QUERY_S):
            if reply.ok is None:
                continue
            try:
                stats = msgspec.json.decode(reply.ok.payload.to_bytes(), type=NodeStats)
            except msgspec.DecodeError:  # not a node's stats: nothing to say of it
                continue
            if stats.receive is not None:
                out[stats.node] = stats.receive
    except Exception as exc:  # the file is written either way; the gap is said in it
        log.warning("receive_counters_unavailable", error=str(exc))
    return out


def receive_metadata(
    at_open: dict[str, dict[str, Any]], at_close: dict[str, dict[str, Any]]
) -> dict[str, str]:
    """``<node>.<counter>``: since the reader started; ``<node>.<counter>_in_file``: between
    this file's open and close (absent if the reader restarted or did not answer at open)."""
    meta: dict[str, str] = {}
    for node, now in sorted(at_close.items()):
        meta.update({f"{node}.{k}": str(v) for k, v in now.items()})
        before = at_open.get(node, {})
        for k in RECEIVE_DELTAS:
            a, b = before.get(k), now.get(k)
            if isinstance(a, int) and isinstance(b, int) and b >= a:
                meta[f"{node}.{k}_in_file"] = str(b - a)
    for node in sorted(set(at_open) - set(at_close)):
        meta[f"{node}.error"] = "no answer when the file was closed"
    return meta
