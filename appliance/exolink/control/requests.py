"""The motion requests the controller manager takes, one schema each.

The command line builds them (and the dashboard, through the command line's parser), so do the
ROS 2 service and topic and the pattern player; the manager's handlers decode each request once
(``decode``) and refuse what does not fit, naming the field. On the wire they stay plain JSON
objects whose ``kind`` names the request, so a laptop without exolink can send them too.
Unknown fields are refused rather than ignored: a misspelt ``stifness`` must not move a joint
with a stiffness nobody asked for. Range and unit checks stay with the codecs and the operator's
limits (exolink.protocol, exolink.limits): a schema says what a request is, not what is safe.
"""

from __future__ import annotations

from typing import Any, get_args

import msgspec

from exolink.refusal import Refused

# A number as the client sent it: an int stays an int (the codecs name a value as it came,
# "duty cycle 150", not "150.0").
Number = int | float


class _Request(
    msgspec.Struct, tag_field="kind", forbid_unknown_fields=True, omit_defaults=True, frozen=True
):
    pass


# --- the H2 (``h2/command``) ----------------------------------------------------------------


class Joint(_Request, tag="joint", frozen=True):  # frozen again: mypy reads each class alone
    """Joint control: ``joint`` by name (or ``all``, for disabled and stopped only), ``mode`` by
    name (position, stiffness, torque, disabled, stopped) or the protocol's number."""

    joint: str
    mode: str | int
    setpoint: Number | None = None
    stiffness: Number | None = None


class Limits(_Request, tag="limits", frozen=True):
    """The operator's accepted angles: six each (in the joints' order, or by joint name), only
    narrower than the config's; ``reset``: back to the config's."""

    min: list[Number] | dict[str, Number] | None = None
    max: list[Number] | dict[str, Number] | None = None
    reset: bool = False


class Stream(_Request, tag="stream", frozen=True):
    """The H2's data stream on or off."""

    on: bool


H2Command = Joint | Limits | Stream


# --- a MACCEPA board (``maccepa``) ------------------------------------------------------------


class Gains(_Request, tag="gains", frozen=True):
    board: int
    kp: Number | None = None
    ki: Number | None = None
    kd: Number | None = None
    # the board's own controller (position / velocity, or 0 / 1); none: the one it runs
    controller: str | int | None = None


class Setpoint(_Request, tag="setpoint", frozen=True):
    board: int
    value: Number
    controller: str | int | None = None


class Duty(_Request, tag="duty", frozen=True):
    board: int
    value: Number


class Stop(_Request, tag="stop", frozen=True):
    board: int


MaccepaCommand = Gains | Setpoint | Duty | Stop


def kind_of(request: _Request) -> str:
    """The request's ``kind``: its class's tag."""
    return str(request.__struct_config__.tag)


def kinds(union: Any) -> tuple[str, ...]:
    """The kinds a union of requests takes, in its order (what a refusal lists)."""
    return tuple(str(cls.__struct_config__.tag) for cls in get_args(union))


def decode(req: dict[str, Any], union: Any, what: str) -> Any:
    """``req`` as one of the requests in ``union``, or Refused naming what is wrong (an unknown
    kind with the known ones, a field by its path)."""
    known = kinds(union)
    if req.get("kind") not in known:
        raise Refused(f"unknown {what} {req.get('kind')!r} ({', '.join(known)})")
    try:
        return msgspec.convert(req, union, strict=True)
    except msgspec.ValidationError as exc:
        raise Refused(f"{what} {req['kind']}: {exc}") from None


def body(request: _Request) -> dict[str, Any]:
    """The JSON object a request travels as."""
    out: dict[str, Any] = msgspec.to_builtins(request)
    return out
