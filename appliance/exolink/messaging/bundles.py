"""Bundles: a batch of one topic's messages in one Zenoh sample (see below for why)."""

from __future__ import annotations

import struct

from exolink.messaging.keys import mgmt_key

# --- bundles ---------------------------------------------------------------------------------
# A high-rate topic (joint_states, a MACCEPA board's state: 100 Hz each) reaches the recorder as
# one sample per batch of messages instead of one per message: on a slow core a Zenoh sample
# costs the publisher, the router and each subscriber a fixed amount however small it is
# (docs/performance.md, benchmarks/board/units.py), and the recorder takes every message of
# both topics through the router. The messages inside are the CDR bytes, sequence numbers and source
# times they have on the topic's own key, which a laptop still gets one by one.

BUNDLE_PATH = "bundle"
BUNDLE_MAGIC = b"EXB1"
_BUNDLE_HEAD = struct.Struct("<4sHB")  # magic, message count, GID length (then the GID)
_BUNDLE_ITEM = struct.Struct("<qqI")  # sequence number, source ns, CDR length (then the CDR)
MAX_BUNDLE = 4096


def bundle_key(device: str, data_key: str) -> str:
    """``exolink/<device>/bundle/<data key>``: outside the data key space on purpose, so a
    subscriber of data (a laptop's ``0/**``) never matches it, and no login but the
    appliance's may publish there (exolink.roles)."""
    return mgmt_key(device, BUNDLE_PATH, data_key)


def bundle_selector(device: str) -> str:
    return mgmt_key(device, BUNDLE_PATH, "**")


def bundled_data_key(device: str, key: str) -> str:
    """A bundle key -> the data key of its topic; ValueError for other keys."""
    prefix = mgmt_key(device, BUNDLE_PATH, "")
    if not key.startswith(prefix) or key == prefix:
        raise ValueError(f"not a bundle key of {device}: {key}")
    return key[len(prefix) :]


def encode_bundle(gid: bytes, items: list[tuple[int, int, bytes]]) -> bytes:
    """(sequence, source ns, CDR) messages of one publisher (its GID) as one payload."""
    if not 0 < len(items) <= MAX_BUNDLE:
        raise ValueError(f"a bundle holds 1 to {MAX_BUNDLE} messages, not {len(items)}")
    parts = [_BUNDLE_HEAD.pack(BUNDLE_MAGIC, len(items), len(gid)), gid]
    for seq, ns, payload in items:
        parts += (_BUNDLE_ITEM.pack(seq, ns, len(payload)), payload)
    return b"".join(parts)


def decode_bundle(raw: bytes) -> tuple[bytes, list[tuple[int, int, bytes]]]:
    """(GID, messages) of a bundle; ValueError naming what is wrong (anything may arrive)."""
    if len(raw) < _BUNDLE_HEAD.size:
        raise ValueError(f"bundle of {len(raw)} bytes is shorter than its header")
    magic, count, n = _BUNDLE_HEAD.unpack_from(raw)
    if magic != BUNDLE_MAGIC:
        raise ValueError(f"bundle magic {magic!r}, expected {BUNDLE_MAGIC!r}")
    if n not in (16, 24):
        raise ValueError(f"bundle GID of {n} bytes (16 or 24)")
    at = _BUNDLE_HEAD.size + n
    gid = bytes(raw[_BUNDLE_HEAD.size : at])
    items = []
    for i in range(count):
        if at + _BUNDLE_ITEM.size > len(raw):
            raise ValueError(f"bundle ends in message {i + 1} of {count}'s header")
        seq, ns, size = _BUNDLE_ITEM.unpack_from(raw, at)
        at += _BUNDLE_ITEM.size
        if at + size > len(raw):
            raise ValueError(f"bundle ends in message {i + 1} of {count} ({size} bytes)")
        items.append((seq, ns, bytes(raw[at : at + size])))
        at += size
    if at != len(raw) or not items:
        raise ValueError(f"bundle of {count} messages has {len(raw) - at} bytes left over")
    return gid, items
