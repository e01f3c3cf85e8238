"""Who may do what on the network: the one place roles, logins and Zenoh's access control meet.

A board with logins (a usrpwd dictionary in its Zenoh config) runs its router with Zenoh's own
access control, default deny. Each laptop login is named after its role. Every management query
ends with the caller's login (``exolink/<device>/<path>/<login>``) and the ACL lets a login
query only keys ending in its own name, so a handler reads a caller's identity from the key and
Zenoh has already proven it. What a role may do is then decided here (``allows``), per request.

- ``observer``: data, status, e-stop, the list of recordings on the card.
- ``operator``: also arm and disarm, hold motion (presence), joint commands, patterns,
  recording and fetching recordings, trigger, setting the board's clock from the laptop's
  (exolink.board.clock).
- ``admin``: also node start/stop/restart, params, logs, simulator faults, deleting recordings.
- ``exolink``: the appliance's own processes (the login in /etc/exolink/zenoh.json5, readable by
  the service only); they declare queryables and publish data, which no laptop login may.

No laptop login may put data (except under ``<domain>/replay/``, where ``exolink play`` puts a
recording, and the operator on the ROS 2 command topics in ``ROS2_TOPICS_IN``, which go through
the same validation as the CLI's commands) or declare queryables: a forged ``watchdog`` state or joint state would otherwise
reach the nodes that act on them. An appliance without logins (``make sim``, a
closed lab network) enforces nothing: any key suffix is believed.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

OBSERVER, OPERATOR, ADMIN = "observer", "operator", "admin"
ROLES = (OBSERVER, OPERATOR, ADMIN)
APPLIANCE_USER = "exolink"
# A caller without a login (open appliance) speaks as admin: nothing is enforced there anyway.
ANONYMOUS_USER = ADMIN
_RANK = {OBSERVER: 0, OPERATOR: 1, ADMIN: 2, APPLIANCE_USER: 3}

# ROS 2 services the supervisor serves (exolink.supervisor.ros2api) and the role each needs;
# topics a ROS 2 node may publish to the appliance. A ROS 2 client cannot add its login to a
# key, so the router's access control decides: each login may query exactly these.
ROS2_SERVICES: dict[str, str] = {
    "estop": OBSERVER,
    "arm": OPERATOR,
    "disarm": OPERATOR,
    "record": OPERATOR,
    "pattern/stop": OPERATOR,
    "pattern/pause": OPERATOR,
    "joint_command": OPERATOR,
    "node_control": ADMIN,
}
ROS2_TOPICS_IN: dict[str, str] = {"cmd/joint": OPERATOR}
ROS_GRAPH = "@ros2_lv/{domain}/**"

ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


# The largest request each login may send, refused before it is parsed (exolink.messaging.serve)
# and never quoted back. An observer asks for status and may e-stop: a few hundred bytes. An
# operator uploads a gait pattern (pattern_player: CSV text up to 1 MiB, JSON-escaped: ~1 byte
# more per row) and an admin sets params: 2 MiB. The appliance's own processes hand whole
# trajectories to the controller manager (10,000 rows of JSON numbers, ~1 MB): 4 MiB. The
# router takes no message above the largest (messaging.MAX_MESSAGE_BYTES).
MAX_REQUEST_BYTES: dict[str, int] = {
    OBSERVER: 4 << 10,
    OPERATOR: 2 << 20,
    ADMIN: 2 << 20,
    APPLIANCE_USER: 4 << 20,
}


def known(user: str) -> bool:
    """A login this appliance has (a key may end in anything)."""
    return user in _RANK


class Forbidden(Exception):
    """A caller's role does not allow the request; the text names both."""


def check(user: str, needed: str, what: str) -> None:
    """Raise Forbidden unless login ``user`` holds role ``needed`` (or a higher one)."""
    if user not in _RANK:
        raise Forbidden(f"unknown caller {user!r} (logins: {', '.join(ROLES)})")
    if _RANK[user] < _RANK[needed]:
        raise Forbidden(f"{what} needs the {needed} role; this login is {user}")


def status_or(role: str) -> Callable[[dict[str, Any]], str]:
    """Needs of a key whose ``status`` action (the default) is a read and the rest commands."""

    def needs(request: dict[str, Any]) -> str:
        return OBSERVER if request.get("action", "status") in ("status", None) else role

    return needs


# What each request to the recorder's ``recordings`` key needs: an observer sees what is on the
# card, an operator copies it to a laptop (the data of a subject: more than status), only an
# admin deletes. An action not listed needs admin (the handler then says it is unknown).
RECORDINGS: dict[str, str] = {
    "list": OBSERVER,
    "stat": OPERATOR,
    "fetch": OPERATOR,
    "delete": ADMIN,
}


def by_action(table: dict[str, str], default: str = ADMIN) -> Callable[[dict[str, Any]], str]:
    """Needs of a key whose actions each need their own role (``table``; ``list`` the default
    action)."""

    def needs(request: dict[str, Any]) -> str:
        return table.get(str(request.get("action", "list")), default)

    return needs


def _rule(rid: str, messages: list[str], flows: list[str], keys: list[str]) -> dict[str, Any]:
    return {
        "id": rid,
        "messages": messages,
        "flows": flows,
        "permission": "allow",
        "key_exprs": keys,
    }


def access_control(domain_id: int, namespace: str = "h2") -> dict[str, Any]:
    """Zenoh's ``access_control`` section for the supervisor's router."""
    data = [f"{domain_id}/**"]
    bundles = [f"exolink/*/bundle/{domain_id}/**"]  # messaging.bundle_key of a data key
    graph = [ROS_GRAPH.format(domain=domain_id)]

    def ros_keys(names: dict[str, str], role: str) -> list[str]:
        """Keys of the ROS 2 services or topics a role may use (any type and hash)."""
        ns = namespace.strip("/")
        return [f"{domain_id}/{ns}/{n}/*/*" for n, r in names.items() if _RANK[role] >= _RANK[r]]

    rules = [
        # ``**`` matches no verbatim chunk (``@ros2_lv``): the graph is named as well
        _rule("appliance", ALL_MESSAGES, ["ingress", "egress"], ["**", *graph]),
        # Data and presence, for every login (egress: what the router sends the laptop).
        _rule("read data", ["declare_subscriber"], ["ingress"], data),
        _rule("receive data", ["put", "delete"], ["egress"], data),
        _rule(
            "see nodes",
            ["liveliness_query", "declare_liveliness_subscriber"],
            ["ingress"],
            ["exolink/*/nodes/*/alive"],
        ),
        _rule(
            "node tokens",
            ["liveliness_token", "reply"],
            ["egress"],
            ["exolink/*/nodes/*/alive"],
        ),
        # `exolink play` (operator and up) republishes a recording under replay/, never live keys.
        _rule("replay", ["put", "delete"], ["ingress"], [f"{domain_id}/replay/**"]),
        # The ROS 2 graph (rmw_zenoh): every login reads it and declares its own node and
        # entity tokens (a ROS 2 tool's session is a node too). Tokens carry no data.
        _rule(
            "ros graph",
            ["liveliness_token", "liveliness_query", "declare_liveliness_subscriber"],
            ["ingress"],
            graph,
        ),
        _rule("see ros graph", ["liveliness_token", "reply"], ["egress"], graph),
        # A bundled topic's batches (exolink.messaging bundle_key): the same data as its key,
        # one sample per batch, for a laptop client (messaging.MessageSubscription). Only the
        # appliance puts there.
        _rule(
            "read bundles",
            ["declare_subscriber", "liveliness_query", "declare_liveliness_subscriber"],
            ["ingress"],
            bundles,
        ),
        _rule("receive bundles", ["put", "liveliness_token", "reply"], ["egress"], bundles),
        _rule("logs", ["declare_subscriber"], ["ingress"], ["exolink/*/log/*"]),
        _rule("receive logs", ["put"], ["egress"], ["exolink/*/log/*"]),
    ]
    policies = [{"id": "appliance", "rules": ["appliance"], "subjects": [APPLIANCE_USER]}]
    for role in ROLES:
        own = [f"exolink/*/**/{role}"]
        rules += [
            _rule(f"{role} queries", ["query"], ["ingress"], own),
            _rule(f"{role} replies", ["reply"], ["egress"], own),
        ]
        services, topics = ros_keys(ROS2_SERVICES, role), ros_keys(ROS2_TOPICS_IN, role)
        rules += [
            _rule(f"{role} ros2 calls", ["query"], ["ingress"], services),
            # A ROS 2 client queries ALL_COMPLETE: it sends only where it was told a complete
            # queryable is, so the router must announce the service (egress, not ingress).
            _rule(f"{role} ros2 answers", ["reply", "declare_queryable"], ["egress"], services),
        ]
        granted = [f"{role} queries", f"{role} replies", "read data", "receive data"]
        granted += ["read bundles", "receive bundles"]
        granted += ["see nodes", "node tokens", "ros graph", "see ros graph"]
        granted += [f"{role} ros2 calls", f"{role} ros2 answers"]
        if topics:  # put, and the appliance's subscription announced (a publisher sends
            # only where the router said a subscriber is)
            rules += [
                _rule(f"{role} ros2 topics", ["put"], ["ingress"], topics),
                _rule(f"{role} ros2 readers", ["declare_subscriber"], ["egress"], topics),
            ]
            granted += [f"{role} ros2 topics", f"{role} ros2 readers"]
        if _RANK[role] >= _RANK[OPERATOR]:
            granted += ["replay"]
        if role == ADMIN:
            granted += ["logs", "receive logs"]
        policies.append({"id": role, "rules": granted, "subjects": [role]})
    subjects = [{"id": u, "usernames": [u]} for u in (APPLIANCE_USER, *ROLES)]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def enforced(usrpwd: dict[str, Any] | None) -> bool:
    """A router config with a login dictionary enforces roles (the board); without, it's open."""
    return bool(usrpwd and usrpwd.get("dictionary_file"))
