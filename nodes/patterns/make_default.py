"""Writes normal_walking.csv: one step of normal walking, 51 set-points, whole degrees.

Smooth periodic joint curves shaped like healthy gait (hip -10..25 deg, knee 0..60 with the
loading-response bump, ankle -12..8), kept inside the H2 ranges. Run once; the CSV is the data.
"""

from __future__ import annotations

import math
from pathlib import Path

POINTS = 51


def hip(p: float) -> float:
    return 7.5 + 17.5 * math.cos(2 * math.pi * p)


def knee(p: float) -> float:
    swing = 60 * math.exp(-(((p - 0.72) / 0.12) ** 2))
    loading = 15 * math.exp(-(((p - 0.15) / 0.07) ** 2))
    return swing + loading


def ankle(p: float) -> float:
    return -2 + 8 * math.sin(2 * math.pi * (p - 0.1)) - 6 * math.exp(-(((p - 0.62) / 0.06) ** 2))


def rows() -> list[list[int]]:
    out = []
    for i in range(POINTS):
        p = i / POINTS
        q = (p + 0.5) % 1.0  # left leg half a cycle later
        out.append(
            [
                round(hip(p)),
                round(knee(p)),
                round(ankle(p)),
                round(hip(q)),
                round(knee(q)),
                round(ankle(q)),
            ]
        )
    return out


def main() -> None:
    lines = ["r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle"] + [",".join(map(str, r)) for r in rows()]
    (Path(__file__).parent / "normal_walking.csv").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
