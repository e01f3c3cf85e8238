"""The service types exolink serves, as rosbags field definitions and RIHS01 hashes.

Below both the message layer (exolink.messaging, whose typestore and hash table hold them) and
the services served over it (exolink.rosservices).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

# Standard services used as they are (std_srvs' definitions, unchanged since Humble).
STD_SRVS = {
    "std_srvs/srv/Trigger": ("", "bool success\nstring message\n"),
    "std_srvs/srv/SetBool": ("bool data\n", "bool success\nstring message\n"),
}


def srv_definitions(msg_dir: Path) -> dict[str, tuple[str, str]]:
    """Every service type exolink serves: std_srvs' and each ``<pkg>/srv/*.srv`` file."""
    out = dict(STD_SRVS)
    for path in sorted(msg_dir.glob("*/srv/*.srv")):
        request, _, response = path.read_text().partition("\n---\n")
        out[f"{path.parent.parent.name}/srv/{path.stem}"] = (request, response)
    return out


def _srv_names(x: Any) -> Any:
    """rosbags files every type under ``<pkg>/msg/``; a service's parts live under ``srv``."""
    if isinstance(x, str):
        return x.replace("/srv/msg/", "/srv/")
    if isinstance(x, tuple | list):
        return type(x)(_srv_names(i) for i in x)
    return x


def service_fielddefs(name: str, request: str, response: str) -> dict[str, Any]:
    """rosbags field definitions of a service as rosidl generates it: ``<T>_Request``,
    ``<T>_Response``, ``<T>_Event`` (service_msgs/ServiceEventInfo info, request and response
    as sequences of at most one) and ``<T>`` itself (request_message, response_message,
    event_message), the type whose RIHS01 hash rmw_zenoh puts into the key."""
    from rosbags.typesys import get_types_from_msg  # lazy: rosbags: the ROS 2 services only

    types: dict[str, Any] = {}
    types.update(get_types_from_msg(request, f"{name}_Request"))
    types.update(get_types_from_msg(response, f"{name}_Response"))
    event = (
        f"service_msgs/msg/ServiceEventInfo info\n{name}_Request[<=1] request\n"
        f"{name}_Response[<=1] response\n"
    )
    types.update(get_types_from_msg(event, f"{name}_Event"))
    whole = (
        f"{name}_Request request_message\n{name}_Response response_message\n"
        f"{name}_Event event_message\n"
    )
    types.update(get_types_from_msg(whole, name))
    return {_srv_names(k): _srv_names(v) for k, v in types.items()}


def service_hashes(store: Any, names: list[str]) -> dict[str, str]:
    """RIHS01 of each service type. rosbags' Jazzy store types ServiceEventInfo's client_gid as
    ``char[16]``, which rosidl maps to uint8 (a different id in the hashed description): with
    it, std_srvs/Trigger hashed to 50f8... instead of the eeff2c... Jazzy advertises. The hashes
    are taken in a copy of the store whose ServiceEventInfo says uint8[16]."""
    from rosbags.typesys import Stores, get_typestore  # lazy: rosbags: the ROS 2 services only

    fixed = get_typestore(Stores.EMPTY)
    defs = dict(store.fielddefs)
    info = "service_msgs/msg/ServiceEventInfo"
    consts, fields = defs[info]

    def uint8(desc: Any) -> Any:
        if isinstance(desc, tuple):
            return ("uint8", 0) if desc == ("char", 0) else tuple(uint8(d) for d in desc)
        return desc

    defs[info] = (consts, [(n, uint8(t)) for n, t in fields])
    fixed.register(defs)
    return {name: str(fixed.hash_rihs01(name)) for name in names}
