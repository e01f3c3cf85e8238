"""Zenoh key expressions: a topic's data key as rmw_zenoh forms it, selectors, and the
management keys ``exolink/<device>/...``."""

from __future__ import annotations

from exolink.messaging.types import dds_name, type_hash
from exolink.wire import rosgraph


def topic_key(
    domain_id: int, namespace: str, topic: str, typename: str, distro: str = "jazzy"
) -> str:
    """The only place a data key expression is built (Humble's rmw_zenoh has no type hashes)."""
    path = "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)
    th = rosgraph.HUMBLE_TYPE_HASH if distro == "humble" else type_hash(typename)
    return f"{domain_id}/{path}/{dds_name(typename)}/{th}"


def topic_selector(domain_id: int, namespace: str, topic: str = "**") -> str:
    """Selector matching a topic of any type (for subscribers that discover types from keys)."""
    path = "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)
    return f"{domain_id}/{path}/*/*" if topic != "**" else f"{domain_id}/{path}"


def parse_key(key: str) -> tuple[str, str]:
    """A data key -> (topic path incl. namespace, typename); ValueError for other keys."""
    parts = key.split("/")
    hashed = parts[-1].startswith("RIHS01_") or parts[-1] == rosgraph.HUMBLE_TYPE_HASH
    if len(parts) < 4 or not hashed or "::dds_::" not in parts[-2]:
        raise ValueError(f"not a data key: {key}")
    pkg, kind, _, name = parts[-2].split("::")
    return "/".join(parts[1:-2]), f"{pkg}/{kind}/{name.rstrip('_')}"


def mgmt_key(device: str, *path: str) -> str:
    """The only place a management key expression is built."""
    return "/".join(("exolink", device, *path))


def data_key_of(entity: rosgraph.Entity) -> str:
    """The data key a graph publisher or subscription (its token) uses."""
    return f"{entity.domain_id}/{entity.topic.strip('/')}/{entity.type}/{entity.type_hash}"
