"""Top items of a py-spy profile (``py-spy record --format raw``: collapsed stacks with counts).

``python -m benchmarks.board.profile FILE [--names JSON]`` prints, per process, its share of the
samples and the functions it spends them in: "self" (the innermost frame, where the CPU was) and
"total" (every frame on the stack, once per sample). py-spy's default leaves idle threads out, so
a process's samples over ``rate * seconds`` is roughly its CPU share.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import sys
from pathlib import Path
from typing import Any

_PROCESS = re.compile(r'^process (\d+):"?(.*?)"?$')
_THREAD = re.compile(r"^thread \((0x[0-9a-f]+)\)(?:: (.*))?$")
_LINE = re.compile(r"^(.*?) \((.*?)(?::\d+)?\)$")


def _frame(f: str) -> str:
    """``func (path/to/mod.py:123)`` -> ``func (mod.py)``: lines of one function together."""
    m = _LINE.match(f)
    if not m:
        return f
    func, path = m.groups()
    parts = path.split("/")
    short = "/".join(parts[-2:]) if parts[-1] == "__init__.py" else parts[-1]
    return f"{func} ({short})"


def summarize(
    text: str, names: dict[int, str] | None = None, top: int = 15
) -> dict[str, dict[str, Any]]:
    """``{process: {samples, threads: {name: n}, self: [[frame, n]...], total: [...]}}``."""
    out: dict[str, dict[str, Any]] = {}
    acc: dict[str, tuple[collections.Counter[str], ...]] = {}
    for line in text.splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        n = int(count)
        frames = stack.split(";")
        proc = "?"
        if frames and (m := _PROCESS.match(frames[0])):
            pid = int(m.group(1))
            proc = (names or {}).get(pid) or f"{pid} {m.group(2)[:40]}"
            frames = frames[1:]
        thread = "main"
        if frames and (m := _THREAD.match(frames[0])):
            thread = m.group(2) or m.group(1)
            frames = frames[1:]
        selfc, total, threads = acc.setdefault(
            proc, (collections.Counter(), collections.Counter(), collections.Counter())
        )
        threads[thread] += n
        if frames:
            short = [_frame(f) for f in frames]
            selfc[short[-1]] += n
            for f in set(short):
                total[f] += n
    for proc, (selfc, total, threads) in acc.items():
        samples = sum(threads.values())
        out[proc] = {
            "samples": samples,
            "threads": dict(threads.most_common()),
            "self": [[f, n] for f, n in selfc.most_common(top)],
            "total": [[f, n] for f, n in total.most_common(top)],
        }
    return out


def render(summary: dict[str, dict[str, Any]], expected: float | None = None) -> str:
    """``expected``: samples of one fully busy thread (rate x seconds), for a % column."""
    lines = []
    for proc, s in sorted(summary.items(), key=lambda kv: -kv[1]["samples"]):
        share = f" ({100 * s['samples'] / expected:.1f}% of one CPU)" if expected else ""
        lines.append(f"== {proc}: {s['samples']} samples{share}")
        lines.append("   threads: " + ", ".join(f"{t} {n}" for t, n in s["threads"].items()))
        for label in ("self", "total"):
            lines.append(f"   top {label}:")
            for f, n in s[label]:
                lines.append(f"     {100 * n / max(1, s['samples']):5.1f}%  {n:6d}  {f}")
    return "\n".join(lines)


def top_pstats(path: Path, top: int = 25) -> dict[str, Any]:
    """A cProfile file's functions by own time and by cumulative time (seconds, calls), and the
    profiled wall time: cProfile adds a cost per call, so small functions look dearer."""
    import pstats

    st = pstats.Stats(str(path))
    rows = [
        (f"{fn} ({Path(file).name}:{line})", cc, nc, tt, ct)
        for (file, line, fn), (cc, nc, tt, ct, _callers) in st.stats.items()  # type: ignore[attr-defined]
    ]

    def pick(i: int) -> list[list[Any]]:
        best = sorted(rows, key=lambda r: -r[i])[:top]
        return [[r[0], r[2], round(r[3], 4), round(r[4], 4)] for r in best]

    return {
        "total_s": round(st.total_tt, 3),  # type: ignore[attr-defined]
        "columns": ["function", "calls", "own_s", "cumulative_s"],
        "by_own": pick(3),
        "by_cumulative": pick(4),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("file")
    p.add_argument("--names", help='JSON {"pid": "name"}')
    p.add_argument("--expected", type=float, help="rate x seconds")
    p.add_argument("--top", type=int, default=15)
    args = p.parse_args()
    names = {int(k): v for k, v in json.loads(args.names).items()} if args.names else None
    print(render(summarize(Path(args.file).read_text(), names, args.top), args.expected))
    return 0


if __name__ == "__main__":
    sys.exit(main())
