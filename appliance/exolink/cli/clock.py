"""`exolink clock [sync]`: how far the board's clock is from this laptop's, and setting it.

A board at a site with no time server stamps its recordings with the wrong time; this laptop's
clock is the reference (exolink.board.clock). ``exolink status`` shows the same line.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from exolink.board import clock
from exolink.cli.options import common, guard
from exolink.client import Refused, Remote, remote
from exolink.wire import management
from exolink.wire.replies import ClockStatus, read
from exolink.wire.requests import body


def step_body(off: clock.Offset) -> dict[str, Any]:
    """The board's clock stepped to this laptop's (exolink.wire.management.Step)."""
    return body(management.Step(off.offset_s, off.error_s))


def offset(r: Remote) -> clock.Offset:
    return clock.measure(lambda: float(r.call("clock")["now"]))


def describe(status: ClockStatus, off: clock.Offset | None) -> str:
    """One line, then a warning line when the board's time cannot be trusted."""
    source = status.source
    if source == "laptop" and (step := status.last_step):
        source = f"set from a laptop by {step.by} at {step.at}"
    elif source == "unsynchronised":
        source = "UNSYNCHRONISED (no time server, not set from a laptop)"
    text = f"clock    {source}"
    if off is not None:
        text += (
            f"; board - this laptop {off.offset_s * 1e3:+.1f} ms (+- {off.error_s * 1e3:.1f} ms)"
        )
    text += "\n"
    warn = []
    if clock.unset(status):
        warn.append(
            "the board's clock is not synchronised: "
            + (
                "`exolink clock sync` sets it"
                if status.from_laptop
                else "give it a time server (clock.from_laptop is false)"
            )
        )
    if off is not None and off.off():
        warn.append(
            f"the board's clock is {abs(off.offset_s) * 1e3:.0f} ms off this laptop's "
            f"(over {clock.WARN_OFFSET_S * 1e3:g} ms): recordings will not line up"
        )
    return text + "".join(f"         WARNING: {w}\n" for w in warn)


def sync_at_arm(r: Remote) -> str:
    """The laptop's time, taken by a board that has no other (before the arm: steps are refused
    once armed). A line to show when it stepped or could not; "" when nothing was needed."""
    try:
        st = read(r.call("clock"), ClockStatus)
    except Refused:  # an older supervisor: it has no clock to set
        return ""
    if st.synchronised or not st.from_laptop:
        return ""
    off = offset(r)
    if st.source == "laptop" and not off.off():
        return ""
    try:
        r.call("clock", body=step_body(off))
    except Refused as exc:
        return f"clock    not set from this laptop: {exc}\n"
    return (
        f"clock    set from this laptop's (it was {off.offset_s * 1e3:+.0f} ms off; "
        "no time server)\n"
    )


@guard
def cmd_clock(args: argparse.Namespace) -> int:
    with remote(args) as r:
        off = offset(r)
        if args.action == "sync":
            r.call("clock", body=step_body(off))
            time.sleep(0.05)
            after = offset(r)
            sys.stdout.write(
                f"stepped the board's clock by {-off.offset_s * 1e3:+.1f} ms; now "
                f"{after.offset_s * 1e3:+.1f} ms (+- {after.error_s * 1e3:.1f} ms) from this laptop\n"
            )
            off = after
        sys.stdout.write(describe(read(r.call("clock"), ClockStatus), off))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "clock",
        parents=[common()],
        help="the board's clock against this laptop's; sync: set it (no time server, disarmed)",
    )
    p.add_argument("action", nargs="?", choices=["sync"])
    p.set_defaults(func=cmd_clock)
