"""Run the benchmark suite: ``python -m benchmarks [--quick] [--only NAME] [--out FILE]``."""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from importlib import import_module
from typing import Any

SUITES = [
    "codec",
    "simulator",
    "reader",
    "flood",
    "supervisor",
    "pattern",
    "recorder",
    "controllers",
    "command",
    "presence",
    "ros2",
    "dashboard",
    "netsafety",
    "gaitlab",
    "fetch",
    "house",
]


def flatten(prefix: str, data: Any, out: list[tuple[str, str]]) -> None:
    if isinstance(data, dict):
        for k, v in data.items():
            flatten(f"{prefix}.{k}" if prefix else k, v, out)
    elif isinstance(data, list):
        out.append(
            (prefix, json.dumps(data) if len(json.dumps(data)) < 80 else f"[{len(data)} items]")
        )
    else:
        out.append((prefix, str(data)))


def main() -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks")
    p.add_argument("--quick", action="store_true", help="shorter runs")
    p.add_argument("--only", action="append", choices=SUITES)
    p.add_argument("--out", default="bench-results.json")
    args = p.parse_args()
    results: dict[str, Any] = {
        "machine": {
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "arch": platform.machine(),
            "load1": round(os.getloadavg()[0], 2),
        },
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    for name in args.only or SUITES:
        t = time.monotonic()
        sys.stderr.write(f"bench {name} ...\n")
        results[name] = import_module(f"benchmarks.bench_{name}").run(args.quick)
        results[name]["wall_s"] = round(time.monotonic() - t, 1)
    rows: list[tuple[str, str]] = []
    flatten("", results, rows)
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        sys.stdout.write(f"{k:<{width}}  {v}\n")
    with open(args.out, "w") as f:
        json.dump(results, f, indent=2)
    sys.stdout.write(f"written {args.out}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
