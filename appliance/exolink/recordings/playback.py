"""``exolink play``: a recording republished onto Zenoh at its recorded pace, under a replay
prefix or (``live``) on its own keys, never a command (exolink.recordings.commands) and never
the appliance's own state onto the live keys. The file is checked whole first
(exolink.recordings.readback.info): a damaged file is refused, never half played."""

from __future__ import annotations

import fnmatch
import time
from pathlib import Path
from typing import Any

from exolink.recordings.check import RecordingError
from exolink.recordings.commands import command_topic
from exolink.recordings.readback import info, iter_messages
from exolink.wire import rosgraph

REPLAY_PREFIX = "replay"
# Never republished onto the live keys: what the supervisor and the motion nodes take as the
# appliance's own word. The watchdog's state (motion nodes arm on it), the pattern state (the
# supervisor watches its operator), node diagnostics and heartbeats, the supervisor's diagnostics
# and trigger edges. Matched on the end of the topic, whatever its namespace.
OWN_STATE_TOPICS = ("watchdog", "pattern_state", "trigger", "supervisor/*", "nodes/*/*")


def own_state(topic: str) -> bool:
    """Is this recorded topic (namespace included) one of OWN_STATE_TOPICS?"""
    parts = topic.strip("/").split("/")
    for pattern in OWN_STATE_TOPICS:
        tail = pattern.split("/")
        if len(parts) >= len(tail) and all(
            fnmatch.fnmatchcase(p, t) for p, t in zip(parts[-len(tail) :], tail, strict=True)
        ):
            return True
    return False


COMMANDS = "command"
OWN_STATE = "the appliance's own state"


def held_back(topic: str, live: bool, command: bool = False) -> str | None:
    """Why ``play`` does not republish a recorded topic (None: it does). A command (``command``:
    its file marks it so, or the rule says so) never, wherever it would go: replayed onto the
    live keys it would move the exoskeleton again; the appliance's own state not onto them."""
    if command or command_topic(topic):
        return COMMANDS
    if live and own_state(topic):
        return OWN_STATE
    return None


def replay_topic(
    topic: str, live: bool, prefix: str = REPLAY_PREFIX, command: bool = False
) -> str | None:
    """Where a recorded topic is republished: under ``prefix`` (default), or with ``live`` its
    own key; None for what is held back (``held_back``: commands, and the appliance's own state
    onto the live keys)."""
    topic = topic.strip("/")
    if held_back(topic, live, command) is not None:
        return None
    if live:
        return topic
    if not prefix.strip("/"):
        raise RecordingError("a replay prefix is needed (the live keys take --live)")
    return f"{prefix.strip('/')}/{topic}"


PLAY_SETTLE_S = 1.0  # how long a replay waits for subscribers to learn of its publishers


def _declare(
    session: Any, graph: Any, pubs: dict[str, Any], key: str, topic: str, typename: str
) -> Any:
    from exolink import messaging  # heavy: Zenoh; reading a file offline needs none

    token = graph.declare(rosgraph.PUBLISHER, f"/{topic}", typename, key.rsplit("/", 1)[-1])
    pub = pubs[key] = messaging.Publisher(session, key, typename, True, token, graph)
    return pub


def _declare_all(
    session: Any,
    graph: Any,
    pubs: dict[str, Any],
    domain_id: int,
    targets: dict[str, str | None],
    recorded: dict[str, dict[str, Any]],
) -> None:
    """Every replayed topic's publisher before the first message, and a moment for those who
    discover topics from the graph (a recorder, ``ros2 bag record``) to subscribe: its first
    messages are not lost to them."""
    from exolink import messaging  # heavy: Zenoh; reading a file offline needs none

    for source, topic in targets.items():
        typename = recorded.get(source, {}).get("type")
        if topic is not None and typename not in (None, "?"):
            _declare(
                session,
                graph,
                pubs,
                messaging.topic_key(domain_id, "", topic, typename),
                topic,
                typename,
            )
    if pubs:
        time.sleep(PLAY_SETTLE_S)


def play(
    session: Any,
    path: str | Path,
    rate: float = 1.0,
    loop: bool = False,
    topics: list[str] | None = None,
    domain_id: int = 0,
    stop: Any = None,
    live: bool = False,
    prefix: str = REPLAY_PREFIX,
) -> int:
    """Republish a recording onto Zenoh with the original timing / rate.

    By default under ``<prefix>/<recorded topic>`` (``0/replay/h2/joint_states/...``), where
    nothing on an appliance listens; with ``live`` under the original keys, minus the appliance's
    own state (OWN_STATE_TOPICS). Never a command topic (``held_back``), with or without
    ``live``. The whole file is checked first (``info``): nothing of a damaged one is sent.
    Data keys only, never a management key; the replay is a ROS 2 node (``exolink_play``) in
    the graph with a publisher token per topic, as ``ros2 bag play`` is: a ROS 2 tool sees what
    it publishes, and a recorder (which learns topics from the graph) records it.
    """
    from exolink import messaging  # heavy: Zenoh; reading a file offline needs none

    if not rate > 0:
        raise RecordingError(f"rate must be > 0, got {rate}")
    recorded = info(path).topics
    wanted = list(recorded) if topics is None else topics
    targets = {
        t: replay_topic(t, live, prefix, recorded.get(t, {}).get("command", False)) for t in wanted
    }
    topics = [t for t, target in targets.items() if target is not None]
    if not topics:
        return 0
    graph = rosgraph.RosNode(session, domain_id, "", "exolink_play")
    pubs: dict[str, Any] = {}
    sent = 0
    try:
        _declare_all(session, graph, pubs, domain_id, targets, recorded)
        while True:
            t0_log = t0_wall = None
            for schema, channel, m in iter_messages(path, topics):
                if stop is not None and stop.is_set():
                    return sent
                if t0_log is None:
                    t0_log, t0_wall = m.log_time, time.monotonic()
                due = t0_wall + (m.log_time - t0_log) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                topic = targets.get(channel.topic)
                if topic is None:  # iter_messages filters already: never on a live own-state key
                    continue
                key = messaging.topic_key(domain_id, "", topic, schema.name)
                pub = pubs.get(key) or _declare(session, graph, pubs, key, topic, schema.name)
                pub.put(m.data, m.publish_time)
                sent += 1
            if not loop:
                break
    finally:  # the graph shows the replay only while it runs
        for p in pubs.values():
            p.close()
        graph.close()
    return sent
