"""What every typed request shares: a msgspec tagged union per route, decoded once by its handler.

On the wire a request stays a plain JSON object (a laptop without exolink can send one), whose
tag field names which request it is (``kind`` for motion, ``action`` for management). Decoding
refuses what does not fit and names it: an unknown tag with the known ones, a field by its path.
Unknown fields are refused rather than ignored where a request acts (a misspelt field must not
be silently dropped), not in a read (a list, a status: nothing in it could be misread), and
never in an e-stop (nothing may keep it from stopping).
"""

from __future__ import annotations

from typing import Any, get_args

import msgspec

from exolink.refusal import Refused


class Action(
    msgspec.Struct, tag_field="action", forbid_unknown_fields=True, omit_defaults=True, frozen=True
):
    """The base of every request ``action`` names (the management routes, the pattern player,
    the controllers, the recorder); a read subclasses it with ``forbid_unknown_fields=False``."""


def action_of(req: Any, default: str | None = None) -> Any:
    """A request's ``action`` as it came (``default`` without one), before it is decoded: for
    who may ask it and which thread answers it. None for a request that is not an object."""
    return req.get("action", default) if isinstance(req, dict) else None


def with_default(req: Any, action: str) -> Any:
    """A request without ``action`` as one for ``action`` (the route's default)."""
    if isinstance(req, dict) and "action" not in req:
        return {**req, "action": action}
    return req


def tag_of(request: msgspec.Struct) -> str:
    """The request's tag (its ``kind`` or ``action``): its class's."""
    return str(request.__struct_config__.tag)


def classes(union: Any) -> dict[str, Any]:
    """The union's request classes by tag, in its order: a request built from its tag."""
    return {str(cls.__struct_config__.tag): cls for cls in get_args(union) or (union,)}


def tags(union: Any) -> tuple[str, ...]:
    """The tags a union of requests takes, in its order (what a refusal lists)."""
    return tuple(classes(union))


def tag_field(union: Any) -> str:
    """The field that names the request (``kind``, ``action``)."""
    first = (get_args(union) or (union,))[0]
    return str(first.__struct_config__.tag_field)


def decode(req: dict[str, Any], union: Any, what: str) -> Any:
    """``req`` as one of the requests in ``union``, or Refused naming what is wrong."""
    field, known = tag_field(union), tags(union)
    if not isinstance(req, dict):
        raise Refused(f"a {what} is a JSON object, got {type(req).__name__}")
    tag = req.get(field)
    if tag not in known:
        raise Refused(f"unknown {what} {tag!r} ({', '.join(known)})")
    try:
        return msgspec.convert(req, union, strict=True)
    except msgspec.ValidationError as exc:
        raise Refused(f"{what} {tag}: {exc}") from None


def convert(req: Any, cls: type[msgspec.Struct], what: str) -> Any:
    """``req`` as ``cls`` (a request without a tag), or Refused naming the field."""
    try:
        return msgspec.convert(req, cls, strict=True)
    except msgspec.ValidationError as exc:
        raise Refused(f"{what}: {exc}") from None


def body(request: msgspec.Struct) -> dict[str, Any]:
    """The JSON object a request travels as."""
    out: dict[str, Any] = msgspec.to_builtins(request)
    return out
