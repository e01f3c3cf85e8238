"""Recording commands on the board: the recorder (``record start|stop|status``) and its card
(``record list|fetch|sync|delete``). A file on this laptop is exolink.cli.files'."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from exolink.cli.errors import EXIT_CONFIG, EXIT_USAGE, fail
from exolink.cli.options import Leaves, common, guard, integer
from exolink.client import Remote, remote
from exolink.recordings import fetching
from exolink.recordings import requests as reqs
from exolink.recordings.replies import Deleted, Listing, RecordStatus, read
from exolink.recordings.store import DEFAULT_CHUNK, RECORDING, StoreError
from exolink.wire.requests import body as request_body
from exolink.wire.requests import classes


def _labels(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"label {item!r} must be KEY=VALUE (e.g. --label subject=S01)")
        out[key] = value
    return out


def record_body(args: argparse.Namespace) -> dict[str, Any]:
    """The recorder request of a parsed `exolink record ...`; ValueError names a bad label."""
    if args.action == "start":
        return request_body(reqs.RecordStart(_labels(args.label or [])))
    return request_body(classes(reqs.Record)[args.action]())


@guard
def cmd_record(args: argparse.Namespace) -> int:
    try:
        body = record_body(args)
    except ValueError as exc:
        return fail(str(exc), EXIT_USAGE)
    with remote(args) as r:
        raw = r.call("record", body=body)
    raw.pop("ok", None)
    if getattr(args, "json", False):
        sys.stdout.write(json.dumps(raw) + "\n")
    else:
        s = read(raw, RecordStatus)
        err = f" ({s.error})" if s.error else ""
        sys.stdout.write(
            f"{s.state}{err}  file {s.file or '-'}  size {s.size / 2**20:.2f} MiB  "
            f"messages {s.written}/{s.received}  dropped {s.dropped}  files {len(s.files)}\n"
        )
        if s.refused_topics:
            sys.stdout.write(f"{_refused(s.refused_topics, s.refused_from)}\n")
    return 0


# A request of a fetch waits this long for its answer: 1 MiB takes ~0.2 s over 100 Mbit/s and
# the board paces what it serves (the recorder's fetch_mb_s, 1 MB/s: ~1 s a chunk, more while
# another laptop fetches too); a reply the router dropped is asked for again after this.
FETCH_TIMEOUT_S = 5.0


class _Asker:
    """Requests to the board's ``recordings`` (the recorder's), patient with the board's rate
    limit and lost replies (fetching.Patient); a refusal is the CLI's usual one. Its counts
    of what was asked again end each fetch's line: a slow fetch says why."""

    def __init__(self, r: Remote) -> None:
        r.timeout = max(r.timeout, FETCH_TIMEOUT_S)
        self.patient = fetching.Patient(lambda body: r.ask("recordings", body=body))

    def __call__(self, body: dict[str, Any]) -> dict[str, Any]:
        return self.patient(body)  # its refusals are the CLI's (exolink.refusal)

    def retried(self) -> str:
        """What this fetch asked again, or nothing."""
        p = self.patient
        if not (p.retried_lost or p.retried_rate):
            return ""
        return f"; asked again: {p.retried_lost} lost, {p.retried_rate} rate-limited"


def _mib(n: float) -> str:
    return f"{n / 2**20:.2f} MiB"


@guard
def cmd_record_list(args: argparse.Namespace) -> int:
    with remote(args) as r:
        raw = _Asker(r)(request_body(reqs.List()))
    if args.json:
        sys.stdout.write(json.dumps({"files": raw["files"], "card": raw["card"]}) + "\n")
        return 0
    s = read(raw, Listing)
    for f in s.files:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(f.mtime))
        sys.stdout.write(f"{f.name}  {_mib(f.size):>12}  {when}  {f.state}\n")
    c = s.card
    sys.stdout.write(
        f"{len(s.files)} files; card {_mib(c.free)} free of {_mib(c.total)} "
        f"(the recorder keeps {_mib(c.reserve)})\n"
    )
    return 0


def _fetch_one(ask: _Asker, name: str, dest: Path, chunk: int) -> None:
    ask.patient.retried_lost = ask.patient.retried_rate = 0
    f = fetching.fetch(ask, name, dest, chunk)
    if f.skipped:
        sys.stdout.write(f"{name}: already here, sha256 {f.sha256}\n")
        return
    resumed = f" (resumed at {_mib(f.resumed_at)})" if f.resumed_at else ""
    rate = (f.size - f.resumed_at) / 2**20 / f.seconds if f.seconds > 0 else 0.0
    sys.stdout.write(
        f"{name}: {_mib(f.size)} in {f.seconds:.1f} s ({rate:.1f} MiB/s){resumed}, "
        f"sha256 {f.sha256} checked{ask.retried()}\n"
    )


def _guard_store(func):
    """What the laptop found wrong with a fetch (a checksum, a name) is a refusal, one line."""

    def wrapped(args: argparse.Namespace) -> int:
        try:
            return int(func(args))
        except StoreError as exc:
            return fail(str(exc), EXIT_CONFIG)
        except OSError as exc:
            return fail(f"{exc.filename or args.dir}: {exc.strerror or exc}", EXIT_CONFIG)

    return wrapped


@_guard_store
@guard
def cmd_record_fetch(args: argparse.Namespace) -> int:
    dest = Path(args.dir)
    dest.mkdir(parents=True, exist_ok=True)
    with remote(args) as r:
        ask = _Asker(r)
        for name in args.names:
            _fetch_one(ask, name, dest, args.chunk)
    return 0


@_guard_store
@guard
def cmd_record_sync(args: argparse.Namespace) -> int:
    dest = Path(args.dir)
    dest.mkdir(parents=True, exist_ok=True)
    with remote(args) as r:
        ask = _Asker(r)
        listing = read(ask(request_body(reqs.List())), Listing).files
        lacking = fetching.missing(listing, dest)
        for name in lacking:
            _fetch_one(ask, name, dest, args.chunk)
    writing = [f.name for f in listing if f.state == RECORDING]
    note = f"; {writing[0]} is still being recorded (sync again once it stops)" if writing else ""
    sys.stdout.write(
        f"synced {len(lacking)} files into {dest}; {len(listing) - len(writing) - len(lacking)} "
        f"were already here{note}\n"
    )
    return 0


@guard
def cmd_record_delete(args: argparse.Namespace) -> int:
    with remote(args) as r:
        ask = _Asker(r)
        for name in args.names:
            d = read(ask(request_body(reqs.Delete(name))), Deleted)
            sys.stdout.write(f"deleted {d.name} ({_mib(d.size)}) from the board\n")
    return 0


def _refused(n: int, by: dict[str, int]) -> str:
    """The recorder's refused topics, one line: how many, and from which sessions (zids)."""
    who = ", ".join(f"{zid} {k}" for zid, k in sorted(by.items(), key=lambda kv: -kv[1]))
    return (
        f"refused {n} topics (graph tokens over the recorder's per-session or foreign limits; "
        f"the appliance's own topics have their own): {who}"
    )


def _chunk_option(q: argparse.ArgumentParser) -> None:
    q.add_argument(
        "--chunk",
        type=integer,
        default=DEFAULT_CHUNK,
        help=f"bytes per request (default {DEFAULT_CHUNK >> 10} KiB, at most 1 MiB: a slow "
        "link drops larger replies)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    parent = common()
    p = sub.add_parser("record", help="start / stop / status of the recorder on the board")
    s = Leaves(p.add_subparsers(dest="action", required=True), parent)
    q = s.add_parser("start", help="start [--label subject=S01 --label session=walk1]")
    q.add_argument("--label", action="append", metavar="KEY=VALUE")
    s.add_parser("stop")
    q = s.add_parser("status")
    q.add_argument("--json", action="store_true")
    q = s.add_parser("list", help="the recordings on the board's card (observer)")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_record_list)
    q = s.add_parser(
        "fetch",
        help="copy recordings to this laptop (operator): chunked, resumed from NAME.part, "
        "checked against the board's sha256",
    )
    q.add_argument("names", nargs="+", metavar="NAME")
    q.add_argument("-o", "--dir", default=".", help="where to put them (default: here)")
    _chunk_option(q)
    q.set_defaults(func=cmd_record_fetch)
    q = s.add_parser(
        "sync", help="fetch every finished recording DIR lacks (operator; the end of the day)"
    )
    q.add_argument("dir", metavar="DIR")
    _chunk_option(q)
    q.set_defaults(func=cmd_record_sync)
    q = s.add_parser("delete", help="delete recordings from the board's card (admin)")
    q.add_argument("names", nargs="+", metavar="NAME")
    q.set_defaults(func=cmd_record_delete)
    p.set_defaults(func=cmd_record)
