"""The management requests, one schema each: the supervisor's routes (exolink.supervisor.api),
a node's params, the timing monitor's query, the simulator's faults and the software update.

The command line, the dashboard (through the command line's parser), the ROS 2 services and the
appliance's own nodes build them; the supervisor's handlers decode each request once
(exolink.wire.requests) and refuse what does not fit, naming the field. ``action`` names the
request; a request without one asks for the route's status. The e-stop is the exception to
every rule here: the supervisor acts on ``"action": "estop"`` before decoding anything, and its
schema takes any other field, so nothing a client adds can keep it from stopping.
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec

from exolink.wire.requests import Action, action_of
from exolink.wire.requests import convert as convert  # the untagged requests' decode

# --- the watchdog (``watchdog``) ------------------------------------------------------------


class Arm(Action, tag="arm", frozen=True):
    """Allow motion (refused while anything blocks it: the supervisor lists what)."""


class Disarm(Action, tag="disarm", frozen=True):
    """No motion from now on, without a trip."""


class Estop(Action, tag="estop", forbid_unknown_fields=False, frozen=True):
    """Trip now: every login's, whatever else the request holds (its detail names the login
    Zenoh proved, never a name in the request)."""


class Trip(Action, tag="trip", frozen=True):
    """A trip with a reason of its own: the appliance's nodes only (the motion holder lost)."""

    reason: str = ""
    detail: str = ""


Watchdog = Arm | Disarm | Estop | Trip


# --- nodes (``control``, ``logs``) ----------------------------------------------------------


class _NodeAction(Action, frozen=True):
    node: str


class Start(_NodeAction, tag="start", frozen=True):
    pass


class Stop(_NodeAction, tag="stop", frozen=True):
    """A critical node stopped is a trip (arming waits for it to beat again)."""


class Restart(_NodeAction, tag="restart", frozen=True):
    pass


NodeControl = Start | Stop | Restart


class Logs(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True, frozen=True):
    """A node's last ``lines`` journal lines."""

    node: str
    lines: Annotated[int, msgspec.Meta(ge=1)] = 50


# --- the trigger and the board's clock (``trigger``, ``clock``) ------------------------------


class Fire(Action, tag="fire", frozen=True):
    """A pulse on the trigger output (an EMG unit's start)."""


Trigger = Fire


class Step(Action, tag="step", frozen=True):
    """Step the board's clock by ``offset_s`` (an operator laptop's, measured with ``error_s``);
    exolink.board.clock refuses it while armed or synchronised."""

    offset_s: float
    error_s: float


Clock = Step


# --- software updates (``update``: exolink.board.update) --------------------------------------


class Begin(Action, tag="begin", frozen=True):
    """A bundle of ``size`` bytes whose SHA-256 is ``sha256`` follows in chunks (``name``: for
    the journal, cut to 120 characters)."""

    size: Annotated[int, msgspec.Meta(ge=1)]
    sha256: Annotated[str, msgspec.Meta(pattern="^[0-9a-f]{64}$")]
    name: str = "bundle.raucb"


class Chunk(Action, tag="chunk", frozen=True):
    """The bundle's next bytes, base64 in ``data``, from ``offset`` (the bytes received so far)."""

    offset: Annotated[int, msgspec.Meta(ge=0)]
    data: str


class Commit(Action, tag="commit", frozen=True):
    """Every byte in: check the hash and hand the bundle to the root agent (a reboot follows)."""


class Abort(Action, tag="abort", frozen=True):
    """Drop the upload under way."""


Update = Begin | Chunk | Commit | Abort


# --- any node (``nodes/<name>/params``) and the observers' own -------------------------------


class SetParam(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    key: str
    value: Any


class Params(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True, frozen=True):
    """A node's params (``set``: one changed first, if the node allows it at run time)."""

    set: SetParam | None = None


class Timing(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True, frozen=True):
    """The timing monitor's figures for frame ``id`` (only those ``dlc`` long with first byte
    ``byte0``, if given): over the next ``seconds`` from now (0: what it holds), or with ``past``
    the ``seconds`` before the question, answered at once; against ``expected_ms`` (None: the
    mean period). The monitor answers one question at a time: two windows of 60 s asked at once
    took 120 s, so the bench's second one timed out (J66); asked with ``past`` after the window,
    neither holds up the other."""

    id: int
    seconds: float = 0.0
    byte0: int | None = None
    dlc: int | None = None
    expected_ms: float | None = None
    past: bool = False


class Fault(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True, frozen=True):
    """The simulator's H2 misbehaving for ``duration_s`` (silent, malformed, ...)."""

    fault: str
    duration_s: float = 1.0


def status_asked(req: Any) -> bool:
    """No ``action`` (or ``status``): the route's status, whatever else the request holds."""
    return isinstance(req, dict) and action_of(req) in (None, "status")
