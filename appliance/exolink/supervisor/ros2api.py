"""What a ROS 2 user calls and publishes, served by the supervisor next to the JSON API.

Services (under the appliance's namespace, e.g. ``/h2/arm``), each the JSON API's handler:

==================  ==============================  =======================================
service             type                            JSON API (role the ACL asks for)
==================  ==============================  =======================================
``estop``           std_srvs/srv/Trigger            watchdog estop (observer)
``arm``             std_srvs/srv/Trigger            watchdog arm (operator)
``disarm``          std_srvs/srv/Trigger            watchdog disarm (operator)
``record``          std_srvs/srv/SetBool            record start (true) / stop (operator)
``pattern/stop``    std_srvs/srv/Trigger            pattern stop (operator)
``pattern/pause``   std_srvs/srv/Trigger            pattern pause (operator)
``joint_command``   exolink_msgs/srv/SendJointCommand  h2 command, kind joint (operator)
``node_control``    exolink_msgs/srv/NodeControl    node start/stop/restart (admin)
==================  ==============================  =======================================

Pattern *start* is not offered: the CLI's start holds a liveliness token so the watchdog trips
when the laptop vanishes, and a ROS 2 service call has no such presence.

Topic in: ``cmd/joint`` (exolink_msgs/msg/JointCommand; mode 1..5, set-point and stiffness as
the frame carries them): each message is the joint command above, refused the same way (the
refusal goes to the log: a topic has no reply).

The routing lives here, in one process that already holds rosbags; nodes stay light.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Any

import structlog

from exolink import logs, messaging, roles, rosservices
from exolink.control import requests
from exolink.protocol import h2
from exolink.recordings import requests as reqs
from exolink.wire import management
from exolink.wire.requests import body as request_body

TRIGGER, SET_BOOL = "std_srvs/srv/Trigger", "std_srvs/srv/SetBool"
JOINT_SRV, NODE_SRV = "exolink_msgs/srv/SendJointCommand", "exolink_msgs/srv/NodeControl"
JOINT_TOPIC, JOINT_TYPE = "cmd/joint", "exolink_msgs/msg/JointCommand"

# Who may call / publish what: exolink.roles, where Zenoh's access control is written.
SERVICE_ROLES, TOPIC_ROLES = roles.ROS2_SERVICES, roles.ROS2_TOPICS_IN

_log = structlog.get_logger("exolink.ros2")


class Ros2Api:
    """Declares the services and the input subscription on the supervisor's session."""

    def __init__(self, sup: Any) -> None:
        self.sup, self.msg = sup, sup.msg
        self.workers = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ros2")
        self._joints_lock = threading.Lock()
        self.joints_pending = self.joints_dropped = 0
        wd = sup.api.watchdog
        routes: dict[str, tuple[str, Callable[[Any], dict[str, Any]]]] = {
            "estop": (TRIGGER, self._local(wd, lambda _r: request_body(management.Estop()))),
            "arm": (TRIGGER, self._local(wd, lambda _r: request_body(management.Arm()))),
            "disarm": (TRIGGER, self._local(wd, lambda _r: request_body(management.Disarm()))),
            "record": (
                SET_BOOL,
                self._remote(
                    ("record",),
                    lambda r: request_body(reqs.RecordStart() if r.data else reqs.RecordStop()),
                ),
            ),
            "pattern/stop": (
                TRIGGER,
                self._remote(("pattern",), lambda _r: requests.body(requests.PatternStop())),
            ),
            "pattern/pause": (
                TRIGGER,
                self._remote(("pattern",), lambda _r: requests.body(requests.PatternPause())),
            ),
            "joint_command": (JOINT_SRV, self._remote(("h2", "command"), _joint_request)),
            "node_control": (
                NODE_SRV,
                self._local(sup.api.control, lambda r: {"action": r.action, "node": r.node}),
            ),
        }
        self.services = [
            rosservices.ServiceServer(
                self.msg, name, srv, handler, self.workers, urgent=name == "estop"
            )
            for name, (srv, handler) in routes.items()
        ]
        self.sub = self.msg.subscribe(JOINT_TOPIC, JOINT_TYPE, self._on_joint)

    def _logged(self, key: str, request: dict[str, Any], reply: dict[str, Any]) -> None:
        self.msg.log_command(rosservices.ROS2_USER, key, request, reply)

    def _local(
        self, handler: Callable[..., Any], to_json: Callable[[Any], dict[str, Any]]
    ) -> Callable[[Any], dict[str, Any]]:
        caller = messaging.Caller(rosservices.ROS2_USER)  # the router's ACL chose who may call
        local = partial(handler, caller=caller) if messaging.takes_caller(handler) else handler

        def call(request: Any) -> dict[str, Any]:
            body = to_json(request)
            reply = rosservices.run_json(local, body)
            self._logged(self.msg.mgmt("ros2"), body, reply)
            return rosservices.outcome(reply, _summary)

        return call

    def _remote(
        self, path: tuple[str, ...], to_json: Callable[[Any], dict[str, Any]]
    ) -> Callable[[Any], dict[str, Any]]:
        def call(request: Any) -> dict[str, Any]:
            try:
                body = to_json(request)
            except ValueError as exc:
                return {"success": False, "message": str(exc)}
            reply = rosservices.run_json(lambda b: self.msg.request(*path, body=b), body)
            self._logged(self.msg.mgmt(*path), body, reply)
            return rosservices.outcome(reply, _summary)

        return call

    def _on_joint(self, msg: Any, meta: Any) -> None:
        """At most rosservices.MAX_PENDING commands wait; a flood's excess is dropped, counted
        and logged rarely (a topic has no reply to refuse with)."""
        with self._joints_lock:
            full = self.joints_pending >= rosservices.MAX_PENDING
            self.joints_pending += not full
            self.joints_dropped += full
            dropped = self.joints_dropped
        if full:
            if logs.rarely(dropped):
                _log.warning("ros2_joint_commands_dropped", count=dropped)
            return
        request = _joint_request(msg, numeric_mode=True)
        self.workers.submit(self._joint_from_topic, request, meta.gid.hex())

    def _joint_from_topic(self, body: dict[str, Any], gid: str) -> None:
        try:
            reply = rosservices.run_json(lambda b: self.msg.request("h2", "command", body=b), body)
            self._logged(self.msg.key(JOINT_TOPIC, JOINT_TYPE), {**body, "publisher": gid}, reply)
            if not reply.get("ok"):
                _log.warning("ros2_joint_command_refused", error=reply.get("error"), publisher=gid)
        finally:
            with self._joints_lock:
                self.joints_pending -= 1

    def close(self) -> None:
        for s in self.services:
            s.close()
        self.sub.undeclare()
        self.workers.shutdown(wait=False, cancel_futures=True)


def _joint_request(r: Any, numeric_mode: bool = False) -> dict[str, Any]:
    mode = h2.MODE_NAMES.get(int(r.mode), str(r.mode)) if numeric_mode else str(r.mode)
    return requests.body(requests.Joint(str(r.joint), mode, int(r.setpoint), int(r.stiffness)))


def _summary(reply: dict[str, Any]) -> str:
    """The one line a ROS 2 caller sees on success (the watchdog's state, a node's, ...)."""
    if "state" in reply:
        why = f" ({reply['reason']})" if reply.get("reason") else ""
        return f"{reply['state']}{why}"
    if "node" in reply and isinstance(reply["node"], dict):
        n = reply["node"]
        return f"{n.get('name', '')} {n.get('state', '')}".strip()
    return "ok"
