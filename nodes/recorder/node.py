"""The recorder node (``Recorder``): its commands (``record``, ``recordings``), the writer loop
over the intake's batches (intake.py), the card's reserve, and its diagnostics; what each file
says of itself (metadata.py)."""

from __future__ import annotations

import contextlib
import errno
import json
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import yaml
from exolink.nodes.recorder.inbox import Inbox
from exolink.nodes.recorder.intake import Intake, Item
from exolink.nodes.recorder.mcapfile import McapFile
from exolink.nodes.recorder.metadata import file_metadata, receive_counters, receive_metadata
from exolink.nodes.recorder.params import RecorderParams, Stats

from exolink import messaging, roles
from exolink.loops import Every
from exolink.messaging import Refused, Unlogged
from exolink.node import Node
from exolink.recordings import requests as reqs
from exolink.recordings import store as recstore
from exolink.recordings.replies import Listing, RecordStatus, plain
from exolink.wire import cdr
from exolink.wire.replies import Reply
from exolink.wire.requests import decode, with_default

DIAGNOSTICS = messaging.DIAGNOSTICS_TYPE
# How often the loop takes what the inbox holds. Each take is a wake-up (~1 ms of the board's
# one core under TCG, benchmarks/board/units.py); the rings hold ~90 s of samples.
INTAKE_PERIOD_S = 0.1
# Take from the inbox in slices of wall time, not of messages, with beat() between them: sharing
# one core with nodes that are importing, 500 messages took the loop past its 0.5 s stall limit.
DRAIN_SLICE_S = 0.05
# A start or stop replies within this (under the CLI's 3 s default) even if the card is slow to
# open or close the file: the reply then says so ("stopping", or no file yet), which is true,
# instead of the CLI timing out.
REPLY_WAIT_S = 2.0
CARD_CHECK_S = 1.0  # how often the card's free space is read (one statvfs)


# What ``exolink params recorder --set`` may change while the node runs (apply_params).
RUNTIME_PARAMS = ("reserve_mb", "fetch_mb_s")


class Recorder(Node):
    Params = RecorderParams
    # SD cards pause writes for a second or more while they erase; fsync in the writer loop waits
    # them out. That is a slow card, not a hung recorder: the queue holds minutes of data.
    stall_s = 5.0

    def configure(self) -> None:
        self.dir = Path(self.params.directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.lock = threading.Lock()
        self.stats = Stats()
        self.state, self.error = "idle", ""
        self.labels: dict[str, str] = {}
        # when the loop next syncs the file, checks the card, publishes diagnostics (0: at once)
        self._next_sync = self._next_card = self._next_diag = 0.0
        self.file: McapFile | None = None
        self.index = 0
        self.session_stamp = ""
        self._receive_at_open: dict[str, dict[str, Any]] = {}
        self._pending = 0  # taken from the inbox, not yet written
        cfg = msgspec.to_builtins(self.ctx.config)
        cfg.pop("source", None)
        self.config_yaml = yaml.safe_dump(cfg, sort_keys=False)  # pure Python: not in the loop
        m = self.ctx.messaging
        selectors = [
            messaging.topic_selector(m.domain_id, m.namespace, t) for t in self.params.topics
        ]
        p = self.params
        # subscribed while recording (start_recording, _unsubscribe_if_idle)
        self.intake = Intake(self.ctx.session, m.device, m.domain_id, selectors, p.exclude, p.inbox)
        self.pub_diag = self.own(
            m.publisher(f"nodes/{self.name}/diagnostics", DIAGNOSTICS, raw=True)
        )
        self.writing: Path | None = None  # the file open (or being opened) for writing
        self._bytes = 0  # written in this recording by files already closed
        self.rate = recstore.Rate()
        self.store = recstore.Store(
            self.dir, lambda: self.writing, self._reserve_bytes(), self.params.fetch_mb_s * 1e6
        )
        self.card = self.store.card()
        self.own(m.serve("recordings", self.on_recordings, roles.by_action(roles.RECORDINGS)))
        self.own(m.serve("record", self.on_command, roles.status_or(roles.OPERATOR)))
        if self.params.autostart and self.card.free < self.card.reserve:
            # booted onto a full card: said at once, rather than a file opened to be closed
            self.state, self.error = "error", f"card full: {self._card_text()}; not recording"
            self.log.error("recording_not_started_card_full", **plain(self.card))
        elif self.params.autostart:
            self.start_recording(dict(self.params.labels))

    # --- intake (the node's loop, in batches: intake.py) -------------------------------------

    def _refused(self, inbox: Inbox) -> None:
        if inbox.refused != self.stats.refused_topics:
            with self.lock:
                self.stats.refused_topics = inbox.refused
                self.stats.refused_from = dict(inbox.refused_from)

    def _take(self, until: float) -> list[Item]:
        """What the inbox holds now (until the wall-time slice ends), counted in the stats."""
        got = self.intake.take(until, self.state in ("recording", "stopping"), self._refused)
        if got.items or got.gaps or got.duplicates or got.malformed:
            with self.lock:
                self.stats.received += len(got.items)
                self.stats.dropped += got.gaps
                self.stats.duplicates += got.duplicates
                self.stats.malformed += got.malformed
        return got.items

    def _unsubscribe_if_idle(self, at_shutdown: bool = False) -> None:
        """The loop, once a recording ended: unless a new one started meanwhile (at shutdown,
        whatever the state: the inbox is opened per recording, not owned). The inbox is
        detached under the lock and closed outside it."""
        with self.lock:
            if not at_shutdown and self.state in ("recording", "stopping"):
                return
            inbox = self.intake.detach()
        if inbox is not None:
            inbox.close()

    # --- commands -------------------------------------------------------------------------

    def on_command(self, req: dict[str, Any]) -> RecordStatus:
        cmd = decode(with_default(req, "status"), reqs.Record, "record action")
        if isinstance(cmd, reqs.RecordStart):
            if self.state == "recording":
                raise Refused(f"already recording to {self.file.path if self.file else '?'}")
            self.card = self.store.card()
            if self.card.free < self.card.reserve:
                raise Refused(
                    f"card full: {self._card_text()}; not recording (fetch the recordings: "
                    "exolink record sync DIR, then exolink record delete NAME)"
                )
            self.start_recording({**self.params.labels, **cmd.labels})
        elif isinstance(cmd, reqs.RecordStop):
            if self.state != "recording":
                raise Refused(f"not recording (state {self.state})")
            with self.lock:
                self.state = "stopping"
        deadline = time.monotonic() + REPLY_WAIT_S
        while self._settling() and time.monotonic() < deadline:
            time.sleep(0.01)
        return self.status()

    def _settling(self) -> bool:
        """Whether the writer thread has yet to act on the command: a start is answered once
        its first file is open (the operator begins the trial on the reply, and the readers'
        counters at the file's open are then from before it), a stop once the file is closed."""
        return self.state == "stopping" or (self.state == "recording" and self.file is None)

    def status(self) -> RecordStatus:
        with self.lock:  # the counters as one copy (Stats' fields are RecordStatus' own)
            counts = vars(self.stats).copy()
            counts["files"] = list(self.stats.files)
            counts["refused_from"] = dict(self.stats.refused_from)
        f, card = self.file, self.card
        size = f.size() if f else 0
        return RecordStatus(
            state=self.state,
            error=self.error,
            file=str(f.path) if f else None,
            size=size,
            labels=self.labels,
            queue=self._pending,
            **counts,
            bytes=self._bytes + size,  # this recording's files, all
            card=card,
            rate_bps=round(self.rate.last, 1),
            hours_left=recstore.hours_left(card.free, card.reserve, self.rate.last),
        )

    def on_recordings(self, req: dict[str, Any]) -> Reply | Unlogged:
        """A laptop's request about the files (roles.RECORDINGS says who may ask what)."""
        ask = decode(with_default(req, "list"), reqs.Recordings, "recordings action")
        try:
            if isinstance(ask, reqs.List):
                return Listing(self.store.entries(), self.card, self.state)
            if isinstance(ask, reqs.Stat):
                return self.store.stat(ask.name)
            if isinstance(ask, reqs.Fetch):
                # A chunk is a read, not a command: the command log (recorded) keeps the
                # ``stat`` that began the fetch, not one entry per MiB.
                return Unlogged(plain(self.store.chunk(ask.name, ask.offset, ask.length)))
            out = self.store.delete(ask.name)
            self.card = self.store.card()
            return out
        except recstore.StoreError as exc:
            raise Refused(str(exc)) from None
        except OSError as exc:
            raise Refused(
                f"{getattr(ask, 'name', 'recordings')!s:.80}: {exc.strerror or exc}"
            ) from None

    def _reserve_bytes(self, params: RecorderParams | None = None) -> int:
        return int((params or self.params).reserve_mb * 2**20)

    def apply_params(self, new: RecorderParams) -> None:
        """The reserve and the fetches' pace change at run time (the next second's card check
        applies the reserve: a recording under it stops cleanly); the rest shape the files
        and subscriptions, and need a restart."""
        kept = {k: getattr(self.params, k) for k in RUNTIME_PARAMS}
        fixed = msgspec.structs.replace(new, **kept)
        if fixed != self.params:
            raise Refused(
                f"{self.name}: only {', '.join(RUNTIME_PARAMS)} change at run time; "
                "set the others in the config and restart the node"
            )
        self.store.set_limits(self._reserve_bytes(new), new.fetch_mb_s * 1e6)

    def _card_text(self) -> str:
        c = self.card
        return (
            f"{c.free / 2**20:.2f} MiB free, under the {c.reserve / 2**20:g} MiB "
            "the recorder leaves on the card"
        )

    def _check_card(self) -> None:
        """Once a second: the card's space and the write rate; under the reserve, the
        recording stops cleanly (the writer loop: it owns the file)."""
        self.card = self.store.card()
        if self.state != "recording":
            return
        f = self.file
        self.rate.note(self._bytes + (f.size() if f is not None else 0))
        if self.card.free >= self.card.reserve:
            return
        self._write_all(self._take(float("inf")))
        path = str(f.path) if f is not None else None
        self._close()
        self.error = f"card full: {self._card_text()}; recording stopped, {path} closed"
        self.state = "error"
        self._unsubscribe_if_idle()
        self.log.error("recording_stopped_card_full", file=path, **plain(self.card))

    def start_recording(self, labels: dict[str, str]) -> None:
        with self.lock:
            self.stats = Stats()  # counters are per recording session
        self.intake.discard()  # nothing from before leaks into this session
        with self.lock:
            self.intake.open()
        self.labels = labels
        self.index = 0
        self._bytes = 0
        self.rate.reset()
        self.session_stamp = time.strftime("%Y%m%d-%H%M%S")
        self.error = ""
        self.state = "recording"  # the writer thread opens the first file
        self.log.info("recording_started", labels=labels)

    # --- writer thread --------------------------------------------------------------------

    def _open(self) -> None:
        label = "_".join(f"{v}" for v in self.labels.values())[:40].replace("/", "-")
        name = "_".join(
            x for x in (self.ctx.config.device, self.session_stamp, label, f"{self.index:03d}") if x
        )
        self._receive_at_open = receive_counters(self.ctx.session, self.ctx.messaging, self.log)
        path = self.dir / f"{name}.mcap"
        self.writing = path  # listed as being recorded from before it exists
        try:
            about = file_metadata(self.ctx.config, self.labels, self.index, self.config_yaml)
            self.file = McapFile(path, self.params, about)
        except BaseException:
            self.writing = None
            raise
        with self.lock:
            self.stats.files.append(str(self.file.path))
        self.log.info("recording_file", path=str(self.file.path))

    def _close(self) -> None:
        if self.file is None:
            return
        with self.lock:
            stats = {
                k: json.dumps(v) if isinstance(v, dict) else str(v)
                for k, v in vars(self.stats).items()
                if k != "files"
            }
        f, self.file = self.file, None
        try:
            at_close = receive_counters(self.ctx.session, self.ctx.messaging, self.log)
            f.close(stats, receive_metadata(self._receive_at_open, at_close))
            self._bytes += f.size_closed()
        finally:
            self.writing = None

    def _need_split(self) -> bool:
        f, p = self.file, self.params
        if f is None:
            return False
        by_size = p.split_size_mb and f.size() >= p.split_size_mb * 2**20
        by_time = p.split_duration_s and time.monotonic() - f.opened >= p.split_duration_s
        return bool(by_size or by_time)

    def _write(self, item: Item) -> None:
        assert self.file is not None
        topic, typename, data, log_ns, pub_ns, seq = item
        cid = self.file.channel(topic, typename)
        self.file.w.add_message(
            cid, log_time=log_ns, data=data, publish_time=pub_ns, sequence=seq & 0xFFFFFFFF
        )
        with self.lock:
            self.stats.written += 1

    def _fail(self, exc: OSError) -> None:
        """Disk full or gone: stop cleanly, keep what is on disk, say so loudly."""
        self.error = (
            "disk full" if exc.errno == errno.ENOSPC else f"write failed: {exc.strerror or exc}"
        )
        self.state = "error"
        self.log.error(
            "recording_failed", error=self.error, file=str(self.file.path) if self.file else None
        )
        if self.file is not None:
            with contextlib.suppress(Exception):
                self.file.f.close()
            self.file = None
        self.writing = None
        with self.lock:  # what can no longer be written is counted, not hidden
            self.stats.dropped += self._pending
        self._pending = 0
        self._diagnostics()

    def loop(self) -> Every:
        """Every INTAKE_PERIOD_S: the intake's batch written, then what is due (the file's
        sync, its split, the card's check, the diagnostics)."""
        return Every(INTAKE_PERIOD_S, self._tick)

    def _tick(self) -> None:
        stopping = self.state == "stopping"  # seen before the take: it holds all until now
        try:
            items = self._take(time.monotonic() + DRAIN_SLICE_S)
            if self.file is None and (items or self.state == "recording"):
                self._open()  # only while recording does the take keep anything
            self._write_all(items)
            now = time.monotonic()
            if self.file is not None and now >= self._next_sync:
                self._next_sync = now + self.params.fsync_interval_s
                self.file.sync()
            if self._need_split():
                self._close()
                self.index += 1
            if now >= self._next_card:
                self._next_card = now + CARD_CHECK_S
                self._check_card()
            if stopping:
                self._write_all(self._take(float("inf")))
                self._close()
                self.state = "idle"
                self._unsubscribe_if_idle()
                self.log.info(
                    "recording_stopped",
                    **{k: v for k, v in vars(self.stats).items() if k != "files"},
                )
        except OSError as exc:
            self._fail(exc)
            self._unsubscribe_if_idle()
        if time.monotonic() >= self._next_diag:
            self._next_diag = time.monotonic() + 1.0
            self._diagnostics()

    def _write_all(self, items: list[Item]) -> None:
        self._pending = len(items)
        for item in items:
            self._write(item)
            self._pending -= 1

    def _diagnostics(self) -> None:
        s = self.status()
        level = "error" if self.state == "error" else "warn" if s.dropped else "ok"
        now = time.time_ns()
        values: dict[str, Any] = {
            "state": s.state,
            "file": s.file,
            "size": s.size,
            "received": s.received,
            "written": s.written,
            "dropped": s.dropped,
            "queue": s.queue,
            "refused_topics": s.refused_topics,
        }
        # The card, for `exolink status` (the supervisor keeps card_* values: see its nodes)
        values.update({f"card_{k}": v for k, v in plain(s.card).items()})
        values["card_rate_bps"] = s.rate_bps
        values["card_hours_left"] = None if s.hours_left is None else round(s.hours_left, 2)
        payload = cdr.diagnostics(
            now,
            f"{self.name}/recording",
            messaging.LEVELS[level],
            self.error or self.state,
            "sd",
            values,
        )
        self.pub_diag.put(payload, now)

    def shutdown(self) -> None:
        if self.file is not None:
            try:  # what the inbox still holds goes into the file
                self._write_all(self._take(float("inf")))
                self._close()
            except OSError as exc:
                self.log.error("recording_close_failed", error=str(exc))
        self._unsubscribe_if_idle(at_shutdown=True)
