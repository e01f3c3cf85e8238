"""Units of the published messages' fields, for people reading `exolink echo`: the one table.

The DBC files give the units on the bus (appliance/exolink/protocol/*.dbc); these are the units after the
nodes' conversions: h2_reader publishes joint angles in rad (ROS' convention) and torques in N·m
(`torque_nm_per_count`); a JointCommand carries the frame's set-point, whose unit is its mode's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from exolink.protocol import h2

Unit = str | Callable[[dict[str, Any]], str | None]


def _setpoint(msg: dict[str, Any]) -> str | None:
    mode = h2.MODE_NAMES.get(msg.get("mode", 0))
    return {"position": "deg", "stiffness": "deg", "torque": "counts"}.get(mode or "")


UNITS: dict[str, dict[str, Unit]] = {
    "sensor_msgs/msg/JointState": {"position": "rad", "velocity": "rad/s", "effort": "N·m"},
    "exolink_msgs/msg/FootSwitches": {"battery_raw": "counts", "battery_volts": "V"},
    "exolink_msgs/msg/JointCommand": {"setpoint": _setpoint, "stiffness": "%"},
    "exolink_msgs/msg/MaccepaState": {
        "current_ma": "mA",
        "temperature_c": "°C",
        "velocity_rpm": "rpm",
        "load_n": "N",
        "link_deg": "deg",
        "lever_deg": "deg",
    },
    "exolink_msgs/msg/PatternState": {"period_ms": "ms"},
}


def unit(typename: str, field: str, msg: dict[str, Any]) -> str | None:
    """The unit of a top-level field of a message (given as plain data), None if it has none."""
    u = UNITS.get(typename, {}).get(field)
    return u(msg) if callable(u) else u


def degrees(value: Any) -> Any:
    """rad -> deg, for a number or a list of them (what an operator types is degrees)."""
    if isinstance(value, list):
        return [degrees(v) for v in value]
    return round(math.degrees(value), 2) if isinstance(value, float | int) else value
