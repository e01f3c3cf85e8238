"""The motion requests the controller manager takes, one schema each.

The command line builds them (and the dashboard, through the command line's parser), so do the
ROS 2 service and topic and the pattern player; the manager's handlers decode each request once
(``decode``, exolink.wire.requests) and refuse what does not fit, naming the field. On the wire they stay plain JSON
objects whose ``kind`` names the request, so a laptop without exolink can send them too.
Unknown fields are refused rather than ignored: a misspelt ``stifness`` must not move a joint
with a stiffness nobody asked for. Range and unit checks stay with the codecs and the operator's
limits (exolink.protocol, exolink.limits): a schema says what a request is, not what is safe.
"""

from __future__ import annotations

from typing import Any

import msgspec

from exolink.wire.requests import Action, tags
from exolink.wire.requests import body as body  # the helpers every request type shares
from exolink.wire.requests import decode as decode
from exolink.wire.requests import tag_of as tag_of

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


# --- the gait pattern (``pattern``: the pattern player) ---------------------------------------


class PatternStart(Action, tag="start", frozen=True):
    """Play the selected joints' pattern (the caller's login holds it: its presence)."""


class PatternStop(Action, tag="stop", frozen=True):
    pass


class PatternPause(Action, tag="pause", frozen=True):
    pass


class PatternRestart(Action, tag="restart", frozen=True):
    """From the pattern's first point."""


class PatternStatus(Action, tag="status", forbid_unknown_fields=False, frozen=True):
    """A read: it takes any other field (nothing in it could be misread)."""


class PatternSpeed(Action, tag="speed", frozen=True):
    """A level 1..10 (the player says which it takes)."""

    speed: int


class PatternSelect(Action, tag="select", frozen=True):
    """The joints the pattern drives, by name (or motor number as text)."""

    joints: list[str]


class PatternDisable(Action, tag="disable", frozen=True):
    """These joints disabled now; the pattern goes on with the others."""

    joints: list[str]


class PatternLoad(Action, tag="load", frozen=True):
    """A pattern file: ``content`` uploaded from the laptop (named ``name``), or ``file`` in the
    board's pattern folder."""

    content: str | None = None
    name: str = "uploaded"
    file: str | None = None


Pattern = (
    PatternStart
    | PatternStop
    | PatternPause
    | PatternRestart
    | PatternStatus
    | PatternSpeed
    | PatternSelect
    | PatternDisable
    | PatternLoad
)


# --- the controllers (``controllers``: the controller manager) -------------------------------


class ControllersList(Action, tag="list", forbid_unknown_fields=False, frozen=True):
    """A read: it takes any other field (nothing in it could be misread)."""


class ControllerTypes(Action, tag="types", forbid_unknown_fields=False, frozen=True):
    """A read, as ``list``."""


class ControllerState(Action, tag="state", forbid_unknown_fields=False, frozen=True):
    """A read, as ``list``."""

    name: str


class Hold(Action, tag="hold", frozen=True):
    """Take or renew the hold on motion (``holder``: the client's own id; ``what``: shown to
    others; ``take_over``: from whoever holds it)."""

    holder: str
    what: str | None = None
    take_over: bool = False


class Release(Action, tag="release", frozen=True):
    holder: str


class Load(Action, tag="load", frozen=True):
    """A controller ``name`` of ``type`` with its ``params`` (checked by its type); ``replace``
    one of that name, ``activate`` it at the next cycle, within ``within_s`` of the request."""

    name: str
    type: str
    params: dict[str, Any] = {}
    activate: bool = False
    replace: bool = False
    budget_ms: Number | None = None
    # seconds in (0, 10]: the manager checks it with a message that names the range
    within_s: Any = None


class Unload(Action, tag="unload", frozen=True):
    name: str


class Activate(Action, tag="activate", frozen=True):
    names: list[str]


class Deactivate(Action, tag="deactivate", frozen=True):
    names: list[str]


class SwitchControllers(Action, tag="switch", frozen=True):
    """One switch at one cycle boundary: these activated, those deactivated, or neither."""

    activate: list[str] = []
    deactivate: list[str] = []


class ControllerCommand(Action, tag="command", forbid_unknown_fields=False, frozen=True):
    """A command to controller ``name``: the rest of the request is the controller's own, which
    its type checks (a forward command's ``values``, the gait's ``speed`` or ``index``)."""

    name: str


Controllers = (
    ControllersList
    | ControllerTypes
    | ControllerState
    | Hold
    | Release
    | Load
    | Unload
    | Activate
    | Deactivate
    | SwitchControllers
    | ControllerCommand
)


def kind_of(request: _Request) -> str:
    """The request's ``kind``: its class's tag."""
    return tag_of(request)


def kinds(union: Any) -> tuple[str, ...]:
    """The kinds a union of requests takes, in its order (what a refusal lists)."""
    return tags(union)
