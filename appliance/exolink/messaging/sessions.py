"""Zenoh sessions: the router's QoS and limits, client and node configs, runtimes, logins."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator, MutableMapping
from pathlib import Path

import zenoh

from exolink import roles
from exolink.config import ApplianceConfig, ConfigError, ZenohConfig

CLIENT_CONNECT_TIMEOUT_MS = 3000


class Unreachable(Exception):
    """Nothing answered: a session that could not connect, a query without a reply."""


# --- sessions --------------------------------------------------------------------------------

# What the router does to every message it receives: a put, delete or query may wait for room
# in a transmit queue at most Zenoh's wait_before_drop (1 ms; 50 ms for the rest of a fragmented
# one), never wait_before_close (5 s). A query's replies travel with its QoS (Zenoh 1.10: "to
# avoid priority inversion"; a reply's own cannot be overwritten), so a client that asks with
# congestion control Block and then stops reading made every reply to it block the router, and
# with it every e-stop and the watchdog's word to the nodes, until Zenoh closed that client 5 s
# later. Dropped instead, a reply nobody reads costs nothing; one a client wanted and lost to a
# full queue ends its query without an answer (its own timeout says so).
# Queries (and so their replies) go in a queue of their own, ahead of the data stream: behind
# the data on a saturated core, requests to the recorder (which takes every topic) and chunks
# back to a laptop (behind its joint_states) were all dropped. A request's rate is bounded per
# login (roles, messaging.serve).
ROUTER_QOS = [
    {
        "id": "nothing_blocks_the_router",
        "messages": ["put", "delete"],
        "flows": ["ingress"],
        "overwrite": {"congestion_control": "drop"},
    },
    {
        "id": "requests_ahead_of_data",
        "messages": ["query"],
        "flows": ["ingress"],
        "overwrite": {"congestion_control": "drop", "priority": "interactive_high"},
    },
]
# Batches (64 KiB each, allocated when used) a session may queue for requests and replies
# toward one peer: Zenoh's default is 2, and a recording's chunk (a 64 KiB chunk is ~88 KB of
# JSON, two batches) then fits only into an empty queue; behind a slow link or a starved
# router its second fragment waited past max_wait_before_drop_fragments and was dropped.
REPLY_QUEUE_BATCHES = 8
# The most the router takes in one message (transport/link/rx/max_message_size): the largest
# request any login may send (roles.MAX_REQUEST_BYTES) and room for its framing. Zenoh's own
# default, 1 GiB, let any client make the router hold that much while it reassembled it.
MAX_MESSAGE_BYTES = max(roles.MAX_REQUEST_BYTES.values()) + (64 << 10)


def session_config(
    zcfg: ZenohConfig,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    mode: str = "peer",
) -> zenoh.Config:
    """Multicast scouting off unless configured, no scouting delay (fast node restarts).

    The supervisor's hub session is a router (as rmw_zenoh's zenohd) and nodes and laptops are
    clients of it: measured with Zenoh 1.10, a router does not forward between two peers that
    cannot reach each other directly, and nodes should not open ports of their own.
    """
    try:
        cfg = zenoh.Config.from_file(zcfg.config_file) if zcfg.config_file else zenoh.Config()
    except zenoh.ZError as exc:
        raise ConfigError(f"{zcfg.config_file}: not a valid Zenoh config: {exc}") from None
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(zcfg.multicast_scouting))
    cfg.insert_json5("scouting/delay", "0")
    # Zenoh 1.x maps a 16 MiB shared-memory pool in each session and copies any message over
    # 3 KiB into it (status replies, logs): 8 MB of the supervisor's PSS on x86, touched for
    # nothing (every exolink sample is far smaller and goes over TCP). Off unless a config
    # file turns it on.
    if not (zcfg.config_file and "shared_memory" in Path(zcfg.config_file).read_text()):
        cfg.insert_json5("transport/shared_memory/enabled", "false")
    cfg.insert_json5("transport/link/tx/queue/size/interactive_high", str(REPLY_QUEUE_BATCHES))
    cfg.insert_json5("listen/endpoints", json.dumps(listen if listen is not None else []))
    cfg.insert_json5("connect/endpoints", json.dumps(connect if connect is not None else []))
    if mode == "client":
        cfg.insert_json5(
            "connect/timeout_ms",
            json.dumps({"router": -1, "peer": -1, "client": CLIENT_CONNECT_TIMEOUT_MS}),
        )
    if mode == "router":
        cfg.insert_json5("qos/network", json.dumps(ROUTER_QOS))
        cfg.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
    if mode == "router" and roles.enforced(json.loads(cfg.get_json("transport/auth/usrpwd"))):
        acl = roles.access_control(zcfg.domain_id, zcfg.namespace)
        cfg.insert_json5("access_control", json.dumps(acl))
    return cfg


ZENOH_RUNTIME = "ZENOH_RUNTIME"  # read by Zenoh once, when a process first opens a session


def _runtime_setting(threads: int, own_tx: bool = False) -> str:
    """Every Zenoh runtime handed to ``threads`` app workers; ``own_tx``: but transmission."""
    names = ("rx", "acc", "net") if own_tx else ("rx", "tx", "acc", "net")
    handover = ", ".join(f"{n}: (handover: app)" for n in names)
    tx = ", tx: (worker_threads: 1)" if own_tx else ""
    return f"({handover}, app: (worker_threads: {threads}){tx})"


def zenoh_runtime(zcfg: ZenohConfig, env: MutableMapping[str, str] = os.environ) -> str | None:
    """Set the process's Zenoh runtimes from ``zenoh.threads`` before any session exists;
    processes started afterwards (the zygote, nodes) inherit it. An operator's own
    ZENOH_RUNTIME is left as it is. Returns the setting in force.

    Why: Zenoh 1.x runs rx (2 threads), tx, accept, net and app runtimes; a sample crosses
    several of them in each process. On one core each hand-over is a thread wake-up, and a
    wake-up costs about a millisecond of the emulated board's CPU (docs/performance.md). Handlers that query
    another node from inside a queryable (the sender handing a position to the manager) still
    answer with one thread (tests/test_zenoh_runtime.py). The router is the exception
    (``router_runtime``)."""
    if zcfg.threads is not None and ZENOH_RUNTIME not in env:
        env[ZENOH_RUNTIME] = _runtime_setting(zcfg.threads)
    return env.get(ZENOH_RUNTIME)


ROUTER_TX_ENV = "EXOLINK_ROUTER_TX"  # "app": no transmit thread of its own (experiments only)


@contextlib.contextmanager
def router_runtime(
    zcfg: ZenohConfig, env: MutableMapping[str, str] = os.environ
) -> Iterator[str | None]:
    """While the router's session opens (its process's first), the runtimes of ``zenoh.threads``
    with transmission on a thread of its own; afterwards the environment is the nodes' again.

    Why: a router forwards a message on the thread that received it, and pushing it into the
    next link's transmit queue blocks until that queue has room; with transmission handed to
    the same single thread, nothing empties the queue. A message larger than the queue (2
    batches of 64 KB per priority) then stalled every client for 5 s (Zenoh's
    ``wait_before_close``) and Zenoh closed the next hop's link: a 100 KB query to a node was
    lost, an e-stop behind it 5 s late. Two app workers do not help (the blocked worker's
    transmit task stays queued on it). Nodes keep one thread: their large pushes (replies,
    commands) come from Python threads, never from Zenoh's own."""
    setting = env.get(ZENOH_RUNTIME)
    ours = zcfg.threads is not None and setting == _runtime_setting(zcfg.threads)
    if env.get(ROUTER_TX_ENV) == "app":  # measuring the thread's cost (bench-board --guest-env)
        ours = False
    if ours:
        env[ZENOH_RUNTIME] = _runtime_setting(zcfg.threads or 1, own_tx=True)
    try:
        yield env.get(ZENOH_RUNTIME)
    finally:
        if ours and setting is not None:
            env[ZENOH_RUNTIME] = setting


def login(cfg: zenoh.Config) -> str:
    """The login a session's management queries end with (see roles)."""
    return json.loads(cfg.get_json("transport/auth/usrpwd/user")) or roles.ANONYMOUS_USER


def open_session(cfg: zenoh.Config, what: str) -> zenoh.Session:
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as exc:
        raise Unreachable(f"{what}: {str(exc).split(' at ')[0]}") from None


def local_endpoint(zcfg: ZenohConfig) -> str:
    """Where a process on the board reaches the supervisor: its first listen port, on loopback."""
    if not zcfg.listen:
        raise ValueError("zenoh.listen is empty: nodes have no supervisor endpoint to reach")
    proto, _, addr = zcfg.listen[0].partition("/")
    port = addr.rsplit(":", 1)[-1]
    return f"{proto}/127.0.0.1:{port}"


def open_node_session(cfg: ApplianceConfig) -> zenoh.Session:
    """A node's client session, with the appliance's own login when the board has logins."""
    endpoint = local_endpoint(cfg.zenoh)
    zcfg = session_config(cfg.zenoh, connect=[endpoint], mode="client")
    return open_session(zcfg, f"supervisor's Zenoh router at {endpoint}")


def open_hub_session(cfg: ApplianceConfig) -> zenoh.Session:
    """The supervisor's (or a standalone run's) session: listens where laptops connect."""
    zcfg = session_config(
        cfg.zenoh, listen=cfg.zenoh.listen, connect=cfg.zenoh.connect, mode="router"
    )
    with router_runtime(cfg.zenoh):
        return open_session(zcfg, f"listening on {', '.join(cfg.zenoh.listen)}")


def open_client_session(
    endpoint: str, config_file: str | None = None, handshake_s: float | None = None
) -> zenoh.Session:
    """A laptop tool's session to one appliance (config_file: the login file the board wrote
    for a role; without one, an open appliance is assumed). Its queries end with client_login.
    ``handshake_s``: how long the connect and Zenoh's open handshake may take (default 3 s and
    Zenoh's 10 s); a board whose CPU is saturated answers the handshake later than that."""
    zcfg = _client_config(endpoint, config_file)
    if handshake_s is not None:
        ms = int(handshake_s * 1000)
        zcfg.insert_json5(
            "connect/timeout_ms", json.dumps({"router": -1, "peer": -1, "client": ms})
        )
        zcfg.insert_json5("transport/unicast/open_timeout", json.dumps(ms))
    hint = f" as {login(zcfg)} (is the login file this board's?)" if config_file else ""
    return open_session(zcfg, f"no appliance answers at {endpoint}{hint}")


def client_login(config_file: str | None) -> str:
    return login(_client_config("tcp/127.0.0.1:0", config_file))


def _client_config(endpoint: str, config_file: str | None) -> zenoh.Config:
    if config_file and not os.path.isfile(config_file):
        raise ConfigError(f"{config_file}: Zenoh config file not found")
    base = ZenohConfig(listen=[], config_file=config_file)
    return session_config(base, connect=[endpoint], mode="client")
