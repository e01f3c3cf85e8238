"""Recording files on this laptop: ``info``, ``export`` (CSV, C3D, OpenSim), ``recover`` and
``play`` (onto Zenoh)."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path
from typing import Any

from exolink import gaitlab, logs
from exolink.cli.errors import EXIT_CONFIG, EXIT_USAGE, fail
from exolink.cli.options import common, decimal, guard
from exolink.client import remote
from exolink.recordings.check import iso
from exolink.recordings.playback import COMMANDS, REPLAY_PREFIX, held_back, play
from exolink.recordings.readback import RecordingError, export_csv, info, recover


def _guard_file(func):
    """A file that is missing, unreadable or not writable is one line naming it."""

    def wrapped(args: argparse.Namespace) -> int:
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


@_guard_file
def cmd_info(args: argparse.Namespace) -> int:
    i = info(args.file)
    if args.json:
        sys.stdout.write(json.dumps({**vars(i), "duration_s": i.duration_s}, indent=2) + "\n")
        return 0
    sys.stdout.write(
        f"file      {i.path}\nstart     {iso(i.start_ns)}\nduration  {i.duration_s:.3f} s\n"
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
        f"triggers  {len(i.triggers)}" + "".join(f"\n  {iso(t)}" for t in i.triggers) + "\n"
    )
    sys.stdout.write(f"checked   {_checked(i.integrity)}\n")
    for topic, t in sorted(i.topics.items()):
        mark = "  command (never replayed)" if t["command"] else ""
        sys.stdout.write(f"  {topic:40} {t['type']:40} {t['count']:>8}{mark}\n")
    return 0


def _checked(integrity: dict[str, Any]) -> str:
    """What `info` verified, one line: chunks and CRCs."""
    parts = [f"{integrity['chunks']} chunks CRC ok"]
    if integrity["chunks_without_crc"]:
        parts.append(f"{integrity['chunks_without_crc']} chunks without a CRC (unverified)")
    parts.append(f"data section CRC {integrity['data_crc']}")
    parts.append(f"summary CRC {integrity['summary_crc']}")
    return ", ".join(parts)


@_guard_file
def cmd_export(args: argparse.Namespace) -> int:
    if not (args.csv or args.c3d or args.opensim or args.events):
        return fail(
            "export needs --csv DIR, --c3d FILE, --opensim DIR or --events FILE", EXIT_USAGE
        )
    if args.csv:
        for topic, n in sorted(export_csv(args.file, args.csv).items()):
            sys.stdout.write(f"{topic:40} {n:>8} rows\n")
    if args.c3d or args.opensim or args.events:
        _export_gaitlab(args)
    return 0


def _export_gaitlab(args: argparse.Namespace) -> None:
    """C3D, OpenSim and the events CSV (exolink.gaitlab); what was lost is said, never hidden."""

    logs.setup("export")  # the library's log lines on stderr, never mixed into this output
    if args.c3d:
        gaitlab.require_ezc3d()  # a missing extra is said before the file is read
    trial = gaitlab.build_trial(args.file, args.zero, args.debounce_ms / 1000)
    written = []
    if args.c3d:
        written.append(gaitlab.write_c3d(trial, args.c3d))
    if args.opensim:
        written += gaitlab.write_opensim(trial, args.opensim, args.opensim_model)
    events = args.events
    if events is None and args.c3d:
        events = str(Path(args.c3d).with_suffix("")) + "_events.csv"
    elif events is None:
        events = str(
            Path(args.opensim) / (Path(args.file).name.removesuffix(".mcap") + "_events.csv")
        )
    written.append(gaitlab.write_events_csv(trial, events))
    zero = "first trigger edge" if trial.zero == "first-trigger" else "first joint sample"
    if args.zero == "first-trigger" and trial.zero == "start":
        sys.stderr.write("no trigger edge in the recording: time zero is its first joint sample\n")
    kinds: dict[str, int] = {}
    for e in trial.events:
        kinds[f"{e.label} {e.context}"] = kinds.get(f"{e.label} {e.context}", 0) + 1
    sys.stdout.write(
        f"{trial.frames} frames at {trial.rate_hz:g} Hz, {len(trial.channels)} channels, "
        f"time zero at the {zero} ({iso(trial.zero_ns)})\n"
        f"resampling: {gaitlab.RESAMPLING}\n"
        f"events: " + (", ".join(f"{k} {n}" for k, n in sorted(kinds.items())) or "none") + "\n"
    )
    invalid = {c.label: c.invalid for c in trial.channels if c.invalid}
    lost = {k: v for k, v in trial.losses.items() if v}
    if invalid or lost:
        sys.stdout.write(
            "not measured (NaN in the export): "
            + (", ".join(f"{k} {v}" for k, v in invalid.items()) or "no samples")
            + "\nlosses: "
            + (", ".join(f"{k} {v}" for k, v in lost.items()) or "none")
            + "\n"
        )
    else:
        sys.stdout.write("nothing lost: every exported sample was measured\n")
    for path in written:
        sys.stdout.write(f"wrote {path}\n")


@_guard_file
def cmd_recover(args: argparse.Namespace) -> int:
    out = args.output or args.file.removesuffix(".mcap") + ".recovered.mcap"
    r = recover(args.file, out)
    for loss in r.losses:
        sys.stderr.write(f"lost: {loss.describe()}\n")
    if r.orphans:
        sys.stderr.write(f"lost: {r.orphans} messages of channels defined only in a lost chunk\n")
    if r.cut_off_at is not None:
        sys.stderr.write(f"the file ends at byte {r.cut_off_at} (cut off: never finished)\n")
    about = "~" if any(x.estimated for x in r.losses) else ""
    lost = f", lost {about}{r.lost_messages} messages" if r.lost_messages else ""
    sys.stdout.write(f"recovered {r.messages} messages ({r.chunks} chunks) into {out}{lost}\n")
    return 0


@_guard_file
@guard
def cmd_play(args: argparse.Namespace) -> int:
    recorded = info(args.file).topics  # a missing or broken file is said before connecting
    topics = (
        [t if t.startswith("/") else f"/{args.ns}/{t}" for t in args.topics]
        if args.topics
        else list(recorded)
    )
    held = _held_back(recorded, topics, args.live, args.loop)
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
    sys.stdout.write(f"played {n} messages onto {where}{held}\n")
    return 0


def _held_back(
    recorded: dict[str, dict[str, Any]], topics: list[str], live: bool, loop: bool
) -> str:
    """Says on stderr which topics play holds back and why, with their message counts; returns
    the totals for the closing line."""
    why: dict[str, list[tuple[str, int]]] = {}
    for t in topics:
        entry = recorded.get(t, {})
        reason = held_back(t, live, entry.get("command", False))
        if reason is not None:
            why.setdefault(reason, []).append((t, int(entry.get("count", 0))))
    totals = []
    for reason, items in why.items():
        head = (
            "held back (commands are never replayed, --live included)"
            if reason == COMMANDS
            else f"not replayed onto the live keys ({reason})"
        )
        listed = ", ".join(f"{t} ({n} messages)" for t, n in items)
        sys.stderr.write(f"{head}: {listed}\n")
        what = "command" if reason == COMMANDS else "own-state"
        totals.append(f"{sum(n for _t, n in items)} {what} messages ({len(items)} topics)")
    if not totals:
        return ""
    return f"; held back {' and '.join(totals)}" + (" each pass" if loop else "")


def register(sub: argparse._SubParsersAction) -> None:
    parent = common()
    p = sub.add_parser("info", help="topics, counts, duration and triggers of an MCAP file")
    p.add_argument("file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser(
        "export",
        help="export an MCAP file: one CSV per topic (--csv), or for the gait lab a C3D file "
        "(--c3d), OpenSim .mot/.sto (--opensim) and the gait events as CSV (--events)",
    )
    p.add_argument("file")
    p.add_argument("--csv", metavar="DIR", help="one CSV per topic into DIR")
    p.add_argument(
        "--c3d",
        metavar="FILE",
        help="joints, foot switches, battery and MACCEPA sensors as analog channels, gait and "
        "trigger events (needs the gaitlab extra: pip install 'exolink[gaitlab]')",
    )
    p.add_argument(
        "--opensim", metavar="DIR", help="<name>.mot of joint angles, <name>_torques.sto"
    )
    p.add_argument(
        "--events",
        metavar="FILE",
        help="the events as CSV (default: beside the C3D file, else in the OpenSim DIR)",
    )
    p.add_argument(
        "--zero",
        choices=["first-trigger", "start"],
        default="first-trigger",
        help="time zero: the first trigger edge (what came before is not exported; the "
        "start when there is none) or the first joint sample (default first-trigger)",
    )
    p.add_argument(
        "--debounce-ms",
        type=decimal,
        default=30.0,
        help="a foot contact change counts once it held this long (default 30)",
    )
    p.add_argument(
        "--opensim-model",
        choices=["rajagopal", "gait2392"],
        default="rajagopal",
        help="knee sign: flexion positive (rajagopal, as the H2) or negative (gait2392)",
    )
    p.set_defaults(func=cmd_export)

    p = sub.add_parser(
        "recover",
        help="rescue a recording cut off by power loss or damaged: copies what is intact into "
        "a new file and says what was lost",
    )
    p.add_argument("file")
    p.add_argument("-o", "--output")
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser(
        "play",
        parents=[parent],
        help=f"republish a recording onto Zenoh with its timing (under /{REPLAY_PREFIX}/ unless --live)",
    )
    p.add_argument("file")
    p.add_argument("--rate", type=decimal, default=1.0)
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
        "state (watchdog, pattern_state, trigger, node and supervisor diagnostics), and never "
        "a command topic (cmd/..., commands, joint_commands), with or without --live",
    )
    p.set_defaults(func=cmd_play)
