"""Recording commands: control the recorder on the board; read, export, recover and play files."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from datetime import UTC, datetime
from typing import Any

from exolink.cli.errors import EXIT_CONFIG, EXIT_USAGE, fail
from exolink.cli.remote import _decimal, _guard, _Leaves, common, remote
from exolink.recording import REPLAY_PREFIX


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
    body: dict[str, Any] = {"action": args.action}
    if args.action == "start":
        body["labels"] = _labels(args.label or [])
    return body


@_guard
def cmd_record(args: argparse.Namespace) -> int:
    try:
        body = record_body(args)
    except ValueError as exc:
        return fail(str(exc), EXIT_USAGE)
    with remote(args) as r:
        s = r.call("record", body=body)
    s.pop("ok", None)
    if getattr(args, "json", False):
        sys.stdout.write(json.dumps(s) + "\n")
    else:
        err = f" ({s['error']})" if s.get("error") else ""
        sys.stdout.write(
            f"{s['state']}{err}  file {s['file'] or '-'}  size {s['size'] / 2**20:.2f} MiB  "
            f"messages {s['written']}/{s['received']}  dropped {s['dropped']}  files {len(s['files'])}\n"
        )
    return 0


def _guard_file(func):  # type: ignore[no-untyped-def]
    """A file that is missing, unreadable or not writable is one line naming it."""

    def wrapped(args: argparse.Namespace) -> int:
        from exolink.recording import RecordingError

        try:
            return int(func(args))
        except RecordingError as exc:
            return fail(str(exc), EXIT_CONFIG)
        except BrokenPipeError:  # stdout's reader left (`| head`): main() ends quietly
            raise
        except OSError as exc:
            where = exc.filename if exc.filename is not None else getattr(args, "file", "")
            return fail(f"{where}: {exc.strerror or exc}", EXIT_CONFIG)

    return wrapped


def _iso(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds")


@_guard_file
def cmd_info(args: argparse.Namespace) -> int:
    from exolink.recording import info

    i = info(args.file)
    if args.json:
        sys.stdout.write(json.dumps({**vars(i), "duration_s": i.duration_s}, indent=2) + "\n")
        return 0
    sys.stdout.write(
        f"file      {i.path}\nstart     {_iso(i.start_ns)}\nduration  {i.duration_s:.3f} s\n"
        f"messages  {i.messages}\n"
    )
    for k, v in i.metadata.get("exolink.labels", {}).items():
        sys.stdout.write(f"label     {k}={v}\n")
    stats = i.metadata.get("exolink.stats")
    if stats:
        sys.stdout.write(
            f"recorder  received {stats.get('received')} written {stats.get('written')} dropped {stats.get('dropped')}\n"
        )
    sys.stdout.write(
        f"triggers  {len(i.triggers)}" + "".join(f"\n  {_iso(t)}" for t in i.triggers) + "\n"
    )
    for topic, t in sorted(i.topics.items()):
        sys.stdout.write(f"  {topic:40} {t['type']:40} {t['count']:>8}\n")
    return 0


@_guard_file
def cmd_export(args: argparse.Namespace) -> int:
    from exolink.recording import export_csv

    for topic, n in sorted(export_csv(args.file, args.csv).items()):
        sys.stdout.write(f"{topic:40} {n:>8} rows\n")
    return 0


@_guard_file
def cmd_recover(args: argparse.Namespace) -> int:
    from exolink.recording import recover

    out = args.output or args.file.removesuffix(".mcap") + ".recovered.mcap"
    r = recover(args.file, out)
    sys.stdout.write(f"recovered {r['messages']} messages into {out}\n")
    return 0


@_guard_file
@_guard
def cmd_play(args: argparse.Namespace) -> int:
    from exolink.recording import info, play, replay_topic

    recorded = info(args.file).topics  # a missing or broken file is said before connecting
    topics = (
        [t if t.startswith("/") else f"/{args.ns}/{t}" for t in args.topics]
        if args.topics
        else list(recorded)
    )
    held = [t for t in topics if replay_topic(t, args.live, args.prefix) is None]
    if held:
        sys.stderr.write(
            f"not replayed onto the live keys (the appliance's own state): {', '.join(held)}\n"
        )
    where = "the live keys" if args.live else f"/{args.prefix.strip('/')}/..."
    stop = threading.Event()
    with remote(args) as r:
        try:
            n = play(
                r.session,
                args.file,
                args.rate,
                args.loop,
                topics,
                args.domain,
                stop,
                live=args.live,
                prefix=args.prefix,
            )
        except KeyboardInterrupt:
            stop.set()
            return 130
    sys.stdout.write(f"played {n} messages onto {where}\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parent = common()
    p = sub.add_parser("record", help="start / stop / status of the recorder on the board")
    s = _Leaves(p.add_subparsers(dest="action", required=True), parent)
    q = s.add_parser("start", help="start [--label subject=S01 --label session=walk1]")
    q.add_argument("--label", action="append", metavar="KEY=VALUE")
    s.add_parser("stop")
    q = s.add_parser("status")
    q.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("info", help="topics, counts, duration and triggers of an MCAP file")
    p.add_argument("file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("export", help="export an MCAP file to one CSV per topic")
    p.add_argument("file")
    p.add_argument("--csv", required=True, metavar="DIR")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("recover", help="rescue a recording cut off by power loss")
    p.add_argument("file")
    p.add_argument("-o", "--output")
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser(
        "play",
        parents=[parent],
        help=f"republish a recording onto Zenoh with its timing (under /{REPLAY_PREFIX}/ unless --live)",
    )
    p.add_argument("file")
    p.add_argument("--rate", type=_decimal, default=1.0)
    p.add_argument("--loop", action="store_true")
    p.add_argument("--topics", nargs="+")
    p.add_argument(
        "--prefix",
        default=REPLAY_PREFIX,
        help=f"republish under PREFIX/<recorded topic> (default {REPLAY_PREFIX}: "
        f"`exolink echo /{REPLAY_PREFIX}/h2/joint_states`)",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="republish onto the recorded (live) topics instead; never the appliance's own "
        "state (watchdog, pattern_state, trigger, node and supervisor diagnostics)",
    )
    p.set_defaults(func=cmd_play)
