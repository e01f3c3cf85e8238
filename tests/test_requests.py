"""The motion requests' schemas (exolink.control.requests): what the command line builds is what
the controller manager decodes, field for field, and what does not fit is refused by name."""

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
