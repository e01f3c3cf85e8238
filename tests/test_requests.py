"""The requests' schemas (exolink.control.requests, exolink.wire.management,
exolink.recordings.requests): what the command line builds is what the handler decodes, field
for field, and what does not fit is refused by name."""

from __future__ import annotations

import re

import pytest

from exolink.cli.motion import maccepa_body
from exolink.cli.parser import build_parser
from exolink.cli.remote import h2_body
from exolink.control import requests
from exolink.refusal import Refused


def _h2(argv: list[str]) -> requests.H2Command:
    body = h2_body(build_parser().parse_args(["send", *argv]))
    cmd: requests.H2Command = requests.decode(body, requests.H2Command, "command kind")
    assert requests.body(cmd) == body  # the same object on both sides
    return cmd


def test_the_command_lines_requests_decode_as_sent() -> None:
    assert _h2(["position", "r_knee", "30"]) == requests.Joint("r_knee", "position", 30, 0)
    assert _h2(["torque", "r_knee", "5"]) == requests.Joint("r_knee", "torque", 5)
    assert _h2(["disable", "all"]) == requests.Joint("all", "disabled")
    assert _h2(["limits", "--reset"]) == requests.Limits(reset=True)
    assert _h2(["stream", "off"]) == requests.Stream(False)
    body = maccepa_body(build_parser().parse_args(["maccepa", "0", "gains", "--kp", "2"]))
    gains = requests.decode(body, requests.MaccepaCommand, "MACCEPA command")
    assert gains == requests.Gains(0, kp=2, controller="position")


@pytest.mark.parametrize(
    ("body", "error"),
    [
        ({"kind": "joint", "joint": "r_knee", "mode": "torque", "setpoint": True}, "`$.setpoint`"),
        ({"kind": "joint", "joint": 3, "mode": "position"}, "got `int` - at `$.joint`"),
        ({"kind": "limits", "min": "1,2,3"}, "at `$.min`"),
        ({"kind": "joint", "joint": "r_knee", "mode": "position", "by": "x"}, "field `by`"),
        ({"joint": "r_knee"}, "unknown command kind None (joint, limits, stream)"),
    ],
)
def test_what_does_not_fit_is_refused_by_name(body: dict[str, object], error: str) -> None:
    with pytest.raises(Refused, match=re.escape(error)):
        requests.decode(body, requests.H2Command, "command kind")


def test_management_bodies_the_cli_builds_decode_to_the_same_request() -> None:
    """The command line's (and the dashboard's) management bodies are the schemas the
    supervisor decodes (exolink.wire.management)."""
    from exolink.board.clock import Offset
    from exolink.cli.clock import step_body
    from exolink.cli.remote import control_body, trigger_body, watchdog_body
    from exolink.wire import management
    from exolink.wire.requests import decode

    for action in ("start", "stop", "restart"):
        cmd = decode(control_body(action, "recorder"), management.NodeControl, "node action")
        assert (type(cmd).__name__.lower(), cmd.node) == (action, "recorder")
    for action in ("arm", "disarm", "estop"):
        assert watchdog_body(action) == {"action": action}
        decode(watchdog_body(action), management.Watchdog, "watchdog action")
    assert decode(trigger_body(True), management.Trigger, "trigger action") == management.Fire()
    assert management.status_asked(trigger_body(False))
    step = decode(step_body(Offset(0.25, 0.002)), management.Clock, "clock action")
    assert (step.offset_s, step.error_s) == (0.25, 0.002)


def test_pattern_and_record_bodies_the_cli_builds_decode_to_the_same_request(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`exolink pattern ...` and `exolink record ...` build the schemas the pattern player and
    the recorder decode; a field of the wrong type or an unknown one is refused by name."""
    from argparse import Namespace

    from exolink.cli.motion import pattern_body
    from exolink.cli.recordings import record_body
    from exolink.recordings import requests as reqs
    from exolink.wire.requests import decode

    csv = tmp_path / "walk.csv"
    csv.write_text("a,b\n")
    cases = [
        (Namespace(action="speed", level=7), requests.PatternSpeed(7)),
        (
            Namespace(action="select", joints=["r_hip", "l_knee"]),
            requests.PatternSelect(["r_hip", "l_knee"]),
        ),
        (
            Namespace(action="load", file=str(csv)),
            requests.PatternLoad(content="a,b\n", name="walk.csv"),
        ),
        (Namespace(action="load", file="normal"), requests.PatternLoad(file="normal")),
        (Namespace(action="start"), requests.PatternStart()),
    ]
    for args, want in cases:
        assert decode(pattern_body(args), requests.Pattern, "pattern action") == want
    start = record_body(Namespace(action="start", label=["subject=S01"]))
    assert decode(start, reqs.Record, "record action") == reqs.RecordStart({"subject": "S01"})
    for body, err in [
        ({"action": "speed", "speed": "10"}, "`$.speed`"),
        ({"action": "speed", "speed": True}, "`$.speed`"),
        ({"action": "select", "joints": "r_hip"}, "`$.joints`"),
        ({"action": "start", "now": 1}, "`now`"),
        ({"action": "walk"}, "unknown pattern action 'walk' (start, stop, pause"),
    ]:
        with pytest.raises(Refused, match=re.escape(err)):
            decode(body, requests.Pattern, "pattern action")
    for body, err in [
        ({"action": "start", "labels": {"subject": 1}}, "`$.labels"),
        ({"action": "fetch", "name": "a.mcap", "offset": "0", "length": 10}, "`$.offset`"),
        ({"action": "delete"}, "missing required field `name`"),
    ]:
        union = reqs.Record if body["action"] == "start" else reqs.Recordings
        with pytest.raises(Refused, match=re.escape(err)):
            decode(body, union, "request")
