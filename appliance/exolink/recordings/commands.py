"""The one rule of what a recorded command is: the recorder marks each channel by it, and
``exolink play`` (exolink.recordings.playback) never republishes one: replayed onto the live
keys a command would move the exoskeleton again. A file can add commands to the rule, never
take one away (a file is not trusted to say a command topic is safe)."""

from __future__ import annotations

from functools import cache

from exolink import roles

# The recorder writes it into every channel's metadata ("true" or "false"); ``play`` holds back
# a channel marked "true" as well as any topic the rule below names: a file can add commands to
# the rule, never take one away (a file is not trusted to say a command topic is safe).
COMMAND_MARK = "exolink.command"
JOINT_COMMANDS_TOPIC = "joint_commands"  # the H2 sender's record of the joint commands it sent
COMMAND_PATH = "cmd"  # anything on a ``cmd`` path (``cmd/joint``, ``arm/cmd``)


@cache
def _command_names() -> tuple[tuple[str, ...], ...]:
    from exolink import messaging  # heavy: Zenoh; reading a file offline needs none

    names = (*roles.ROS2_TOPICS_IN, messaging.COMMANDS_TOPIC, JOINT_COMMANDS_TOPIC)
    return tuple(tuple(n.strip("/").split("/")) for n in names)


def command_topic(topic: str) -> bool:
    """The one rule of what a command topic is, whatever its namespace (matched on the end):
    the ROS 2 command topics the appliance takes (roles.ROS2_TOPICS_IN), the command log
    (messaging.COMMANDS_TOPIC), ``joint_commands``, and any topic on a ``cmd`` path."""
    parts = tuple(topic.strip("/").split("/"))
    if COMMAND_PATH in parts:
        return True
    return any(len(parts) >= len(n) and parts[-len(n) :] == n for n in _command_names())


def command_metadata(topic: str) -> dict[str, str]:
    """A channel's metadata as the recorder writes it: the mark, either way."""
    return {COMMAND_MARK: "true" if command_topic(topic) else "false"}


def is_command(topic: str, metadata: dict[str, str] | None = None) -> bool:
    """A recorded channel is a command if the rule says so or its file marks it so."""
    return command_topic(topic) or (metadata or {}).get(COMMAND_MARK) == "true"
