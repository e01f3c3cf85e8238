"""What the recorder takes in, apart from what it writes: the inbox's samples (subscribed while
it records), each key parsed and matched against ``exclude`` once, bundles opened, and the
publishers' sequence gaps and duplicates counted (a sample may come twice: by its key and in
its bundle)."""

from __future__ import annotations

import contextlib
import fnmatch
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import zenoh
from exolink.nodes.recorder.inbox import Inbox

from exolink import messaging

Item = tuple[str, str, bytes, int, int, int]  # topic, type, CDR, log ns, publish ns, sequence
MAX_KEYS = 4096  # keys whose parse is cached (a flood of made-up keys clears it)
# A message numbered at most this far below its publisher's last is a duplicate (a topic taken
# both ways while its subscription moves to its bundles); further below, a new count (a forged
# sample with a huge number then costs a gap in the counters, never the messages after it).
DUPLICATE_WINDOW = 1000
TAKE_AT_LEAST = 64  # samples a take holds before it looks at its time slice


@dataclass
class Taken:
    """One take: the items to write (while recording) and what was counted on the way."""

    items: list[Item] = field(default_factory=list)
    gaps: int = 0  # sequence numbers never seen: samples lost before the recorder
    duplicates: int = 0
    malformed: int = 0  # bundles that did not decode


class Intake:
    """The inbox opens and is detached under the recorder's lock (its commands' threads and its
    loop both do); its samples are taken on the loop's thread only."""

    def __init__(
        self,
        session: zenoh.Session,
        device: str,
        domain_id: int,
        selectors: list[str],
        exclude: list[str],
        capacity: int,
    ) -> None:
        self._session, self._device, self._domain_id = session, device, domain_id
        self._selectors, self._exclude, self._capacity = selectors, exclude, capacity
        self.inbox: Inbox | None = None
        self._last_seq: dict[bytes, int] = {}  # publisher GID -> its last sequence number seen
        # key -> (topic, type, is a bundle), None for keys not recorded (the board's ~220
        # samples/s share a dozen keys)
        self._keys: dict[str, tuple[str, str, bool] | None] = {}

    def open(self) -> None:
        """Subscribed from now on."""
        if self.inbox is None:
            self.inbox = Inbox(
                self._session,
                self._device,
                self._domain_id,
                self._selectors,
                self.kept,
                self._capacity,
            )

    def detach(self) -> Inbox | None:
        """The inbox, no longer taken from: the caller closes it (outside the lock)."""
        inbox, self.inbox = self.inbox, None
        return inbox

    def samples(self, on_refused: Callable[[Inbox], None] | None = None) -> Iterator[Any]:
        """What the inbox holds now; with ``on_refused`` (the loop's take), topics the graph
        showed since the last take are subscribed first (on that thread only) and the refusals
        reported."""
        inbox = self.inbox
        if inbox is not None:
            if on_refused is not None:
                inbox.discover()
                on_refused(inbox)
            yield from inbox.samples()

    def take(self, until: float, recording: bool, on_refused: Callable[[Inbox], None]) -> Taken:
        """What the inbox holds now (until the wall-time slice ends), minus excluded topics;
        the publishers' sequence gaps are counted only while ``recording``."""
        out = Taken()
        items = out.items
        now = time.time_ns()
        keys, last_seq = self._keys, self._last_seq
        for sample in self.samples(on_refused):
            key = str(sample.key_expr)
            try:
                kept = keys[key]
            except KeyError:  # a key not seen before (once each)
                if len(keys) >= MAX_KEYS:  # anyone may publish: the cache stays bounded
                    keys.clear()
                kept = keys[key] = self._kept_sample_key(key)
            if kept is None:
                continue
            topic, typename, bundle = kept
            if bundle:
                try:
                    gid, messages = messaging.decode_bundle(sample.payload.to_bytes())
                except ValueError:
                    out.malformed += 1
                    continue
            else:
                seq, src, gid = 0, 0, b""
                att = sample.attachment
                if att is not None:
                    with contextlib.suppress(Exception):
                        seq, src, gid = messaging.decode_attachment(att.to_bytes())
                messages = [(seq, src, sample.payload.to_bytes())]
            for seq, src, data in messages:
                if gid:
                    last = last_seq.get(gid)
                    if last is not None and last - DUPLICATE_WINDOW < seq <= last:
                        out.duplicates += 1  # seen by the other way (its key and its bundle)
                        continue
                    if recording and last is not None and seq > last + 1:
                        out.gaps += seq - last - 1
                    last_seq[gid] = seq
                if recording:
                    items.append((topic, typename, data, now, src or now, seq))
            if len(items) >= TAKE_AT_LEAST and time.monotonic() >= until:
                break
        return out

    def discard(self) -> None:
        """A new recording: nothing queued before it, and sequence gaps counted from each
        publisher's first sample in it (the numbers published in the pause are no loss of this
        one)."""
        for _ in self.samples():
            pass
        self._last_seq.clear()

    def _kept_sample_key(self, key: str) -> tuple[str, str, bool] | None:
        """A sample key's (topic, type, is a bundle), None when it is not recorded."""
        try:
            key, bundle = messaging.bundled_data_key(self._device, key), True
        except ValueError:
            bundle = False
        kept = self.kept(key)
        if kept is None or (bundle and not (self.inbox is not None and self.inbox.wanted(key))):
            return None
        return (*kept, bundle)

    def kept(self, key: str) -> tuple[str, str] | None:
        """A data key's (topic, type), None if it is not one or ``exclude`` matches it."""
        try:
            topic, typename = messaging.parse_key(key)
        except ValueError:
            return None
        if any(fnmatch.fnmatchcase(topic, pat) for pat in self._exclude):
            return None
        return topic, typename
