"""The recorder's requests, one schema each: ``record`` (start, stop, status) and ``recordings``
(list, stat, fetch, delete).

The command line, the dashboard and the ROS 2 service build them; the recorder decodes each
once (exolink.wire.requests) and refuses what does not fit, naming the field. A request without
``action`` asks ``record`` for its status and ``recordings`` for the list. The store keeps its
own checks of names, offsets and lengths (exolink.recordings.store): it is the card's boundary
whoever calls it.
"""

from __future__ import annotations

from exolink.wire.requests import Action


class RecordStart(Action, tag="start", frozen=True):
    """A new recording; ``labels`` go into its metadata beside the config's."""

    labels: dict[str, str] = {}


class RecordStop(Action, tag="stop", frozen=True):
    pass


class RecordStatus(Action, tag="status", forbid_unknown_fields=False, frozen=True):
    """A read: it takes any other field (nothing in it could be misread)."""


Record = RecordStart | RecordStop | RecordStatus


class List(Action, tag="list", forbid_unknown_fields=False, frozen=True):
    """A read, as ``record status``."""


class Stat(Action, tag="stat", frozen=True):
    """A closed file's size and sha256 (None while it is computed)."""

    name: str


class Fetch(Action, tag="fetch", frozen=True):
    """``length`` bytes at ``offset`` of a closed file, base64."""

    name: str
    offset: int
    length: int


class Delete(Action, tag="delete", frozen=True):
    name: str


Recordings = List | Stat | Fetch | Delete
