"""Writes h2.dbc and maccepa.dbc from the protocol contract (shared/protocol/*.md) with cantools.

The DBC files are the data every tool reads (the codec, `cantools decode`, `cantools monitor`);
this script exists so the ten MACCEPA board copies are never edited by hand. A test checks the
committed files equal what it writes. Run: ``python -m exolink.protocol.make_dbc``.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

from cantools.database import Database
from cantools.database.can import Message, Node, Signal
from cantools.database.conversion import BaseConversion
from cantools.database.namedsignalvalue import NamedSignalValue

HERE = Path(__file__).parent
JOINTS = ("r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle")
# Mechanical ranges (degrees) from h2-can.md: also the bounds of the accepted-angle frames.
RANGES = {
    "r_hip": (-20, 100),
    "r_knee": (0, 100),
    "r_ankle": (-20, 20),
    "l_hip": (-20, 100),
    "l_knee": (0, 100),
    "l_ankle": (-20, 20),
}
# a signal's named values, as cantools types them
Choices = OrderedDict[int, str | NamedSignalValue]
MODES: Choices = OrderedDict(
    [(1, "position"), (2, "stiffness"), (3, "torque"), (4, "disabled"), (5, "stopped")]
)
CONTROLLERS: Choices = OrderedDict([(0, "position"), (1, "velocity")])
BOARDS = range(10)


def _sig(
    name: str,
    byte: int,
    bits: int = 8,
    signed: bool = False,
    minimum: float | None = None,
    maximum: float | None = None,
    unit: str | None = None,
    choices: Choices | None = None,
    is_float: bool = False,
    comment: str | None = None,
) -> Signal:
    return Signal(
        name,
        start=byte * 8,
        length=bits,
        byte_order="little_endian",
        is_signed=signed,
        conversion=BaseConversion.factory(scale=1, offset=0, choices=choices, is_float=is_float),
        minimum=minimum,
        maximum=maximum,
        unit=unit,
        comment=comment,
    )


def h2() -> Database:
    def joints(unit: str, lo: int = -128, hi: int = 127) -> list[Signal]:
        return [
            _sig(j, i, signed=True, minimum=lo, maximum=hi, unit=unit) for i, j in enumerate(JOINTS)
        ]

    def accepted() -> list[Signal]:
        return [
            _sig(j, i, signed=True, minimum=RANGES[j][0], maximum=RANGES[j][1], unit="deg")
            for i, j in enumerate(JOINTS)
        ]

    def msg(
        fid: int,
        name: str,
        signals: list[Signal],
        sender: str,
        cycle: int | None = None,
        comment: str = "",
    ) -> Message:
        return Message(fid, name, 6, signals, senders=[sender], cycle_time=cycle, comment=comment)

    messages = [
        msg(
            70,
            "JointControl",
            [
                _sig("motor", 0, minimum=1, maximum=6, comment="1 r_hip .. 6 l_ankle"),
                _sig("mode", 1, minimum=1, maximum=5, choices=MODES),
                _sig(
                    "setpoint",
                    2,
                    signed=True,
                    minimum=-128,
                    maximum=127,
                    comment="deg (position, stiffness) or torque counts (torque)",
                ),
                _sig("stiffness", 3, minimum=0, maximum=100, unit="%"),
            ],
            "host",
            comment="Joint control; bytes 5-6 reserved",
        ),
        msg(75, "MinAngles", accepted(), "host", comment="Minimum accepted position set-points"),
        msg(80, "MaxAngles", accepted(), "host", comment="Maximum accepted position set-points"),
        msg(
            85,
            "StreamControl",
            [_sig("start", 0, minimum=0, maximum=1)],
            "host",
            comment="1 start streaming ids 110/120/130, 0 stop",
        ),
        msg(110, "JointAngles", joints("deg"), "h2", 10),
        msg(120, "JointTorques", joints("Nm"), "h2", 10, comment="1 Nm per count by contract"),
        msg(
            130,
            "FootSwitches",
            [
                _sig("r_heel", 0),
                _sig("r_toe", 1),
                _sig("l_heel", 2),
                _sig("l_toe", 3),
                _sig("battery", 4, unit="count", comment="raw; pack 22.5 V nominal"),
            ],
            "h2",
            10,
            comment="0 open, non-zero pressed",
        ),
    ]
    return Database(messages=messages, nodes=[Node("host"), Node("h2")], version="1")


def maccepa() -> Database:
    messages: list[Message] = []
    for b in BOARDS:
        for base, name in ((10, "Kp"), (20, "Ki"), (30, "Kd"), (40, "Setpoint")):
            field = name.lower()
            messages.append(
                Message(
                    base + b,
                    f"{name}_B{b}",
                    5,
                    [
                        _sig(field, 0, bits=32, signed=True, is_float=True),
                        _sig("controller", 4, minimum=0, maximum=1, choices=CONTROLLERS),
                    ],
                    senders=["host"],
                )
            )
        messages.append(
            Message(
                80 + b,
                f"Duty_B{b}",
                8,
                [
                    _sig("duty", 0, bits=16, signed=True, minimum=0, maximum=100, unit="%"),
                    _sig(
                        "action",
                        6,
                        minimum=0,
                        maximum=1,
                        choices=OrderedDict([(0, "stop_control"), (1, "set_duty")]),
                    ),
                ],
                senders=["host"],
            )
        )
        messages.append(
            Message(
                50 + b,
                f"Sensors_B{b}",
                8,
                [
                    _sig("current", 0, 16, True, unit="mA"),
                    _sig("temperature", 2, 16, True, unit="degC"),
                    _sig("velocity", 4, 16, True, unit="rpm"),
                    _sig("load", 6, 16, True, unit="N"),
                ],
                senders=[f"board{b}"],
            )
        )
        messages.append(
            Message(
                60 + b,
                f"Positions_B{b}",
                8,
                [
                    _sig("link", 0, 16, True, unit="deg"),
                    _sig("lever", 2, 16, True, unit="deg"),
                    _sig("extra_position", 4, 16, True),
                    _sig("extra_sensor", 6, 16, True),
                ],
                senders=[f"board{b}"],
            )
        )
        messages.append(
            Message(
                70 + b,
                f"Controller_B{b}",
                8,
                [
                    _sig("setpoint", 0, 16, True),
                    _sig("actuation", 2, 16, True),
                    _sig("process_variable", 4, 16, True),
                ],
                senders=[f"board{b}"],
            )
        )
    messages.sort(key=lambda m: m.frame_id)
    nodes = [Node("host")] + [Node(f"board{b}") for b in BOARDS]
    return Database(messages=messages, nodes=nodes, version="1")


def render() -> dict[str, str]:
    """DBC text with Unix line endings (cantools writes CRLF)."""
    dbs = {"h2.dbc": h2(), "maccepa.dbc": maccepa()}
    return {name: db.as_dbc_string().replace("\r\n", "\n") for name, db in dbs.items()}


def main() -> None:
    for name, text in render().items():
        (HERE / name).write_text(text)


if __name__ == "__main__":
    main()
