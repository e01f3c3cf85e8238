"""The house's figures (issue: a house a newcomer can live in): files over 400 lines, import
cycles between modules, imports inside functions, ``type: ignore`` comments, modules that know
the H2 protocol, README lines. Read from the source (ast, grimp): no process is started, so
the figures are the same on any host."""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PRODUCT = ("appliance", "nodes")
LONG_FILE = 400
IGNORE = re.compile(r"#\s*type:\s*ignore(\[[^\]]*\])?")


def _files() -> list[Path]:
    return sorted(p for d in PRODUCT for p in (ROOT / d).rglob("*.py"))


def _rel(p: Path) -> str:
    return str(p.relative_to(ROOT))


def long_files() -> dict[str, int]:
    """Product files over LONG_FILE lines -> their lines, longest first."""
    sizes = {_rel(p): len(p.read_text().splitlines()) for p in _files()}
    return dict(sorted(((f, n) for f, n in sizes.items() if n > LONG_FILE), key=lambda x: -x[1]))


def imports_in_functions() -> dict[str, int]:
    """Import statements inside a function body, per file (heavy optional modules kept lazy
    are expected here; each should say why)."""
    out: dict[str, int] = {}
    for p in _files():
        tree = ast.parse(p.read_text())
        n = 0
        for fn in ast.walk(tree):
            if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                n += sum(
                    isinstance(x, ast.Import | ast.ImportFrom)
                    for stmt in fn.body
                    for x in ast.walk(stmt)
                    if not isinstance(x, ast.FunctionDef | ast.AsyncFunctionDef)
                )
        if n:
            out[_rel(p)] = n
    return out


def type_ignores() -> dict[str, int]:
    """``type: ignore`` comments in product code: all, and those that name no error code."""
    total = bare = 0
    for p in _files():
        for m in IGNORE.finditer(p.read_text()):
            total += 1
            bare += m.group(1) is None
    return {"total": total, "without_code": bare}


def import_cycles() -> list[list[str]]:
    """Groups of exolink modules that import each other (strongly connected, module level and
    TYPE_CHECKING imports included), from import-linter's graph (grimp) of the package laid out
    as installed (the Makefile's IMPORT_TREE: the editable install hides exolink.nodes)."""
    with tempfile.TemporaryDirectory() as tmp:
        pkg = Path(tmp) / "exolink"
        pkg.mkdir()
        for entry in (ROOT / "appliance").iterdir():
            (pkg / entry.name).symlink_to(entry)
        (pkg / "nodes").symlink_to(ROOT / "nodes")
        out = subprocess.run(
            [sys.executable, "-c", _GRAPH],
            env={**os.environ, "PYTHONPATH": tmp},
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    edges: dict[str, list[str]] = json.loads(out)
    return [sorted(c) for c in _sccs(sorted(edges), edges) if len(c) > 1]


# grimp is the dev tools' (import-linter); only this figure needs it, in a child process that
# finds the linked tree first.
_GRAPH = """
import json, grimp
g = grimp.build_graph("exolink", cache_dir=None)
print(json.dumps({m: sorted(g.find_modules_directly_imported_by(m)) for m in g.modules}))
"""


def _sccs(nodes: list[str], edges: dict[str, list[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components, iterative (no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    for root in nodes:
        if root in index:
            continue
        work = [(root, 0)]
        while work:
            v, i = work.pop()
            if i == 0:
                index[v] = low[v] = len(index)
                stack.append(v)
                on.add(v)
            succ = edges.get(v, [])
            if i < len(succ):
                work.append((v, i + 1))
                w = succ[i]
                if w not in index:
                    work.append((w, 0))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                out.append(comp)
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[v])
    return out


def h2_modules() -> list[str]:
    """Product modules that import the H2 protocol module (exolink.protocol.h2)."""
    pat = re.compile(r"from exolink\.protocol import [^\n]*\bh2\b|exolink\.protocol\.h2")
    return [_rel(p) for p in _files() if pat.search(p.read_text()) and "protocol" not in p.parts]


def run(quick: bool) -> dict[str, Any]:
    longs = long_files()
    lazy = imports_in_functions()
    cycles = import_cycles()
    h2 = h2_modules()
    return {
        "files_over_400": len(longs),
        "files_over_400_lines": longs,
        "import_cycles": len(cycles),
        "import_cycle_modules": cycles,
        "imports_in_functions": sum(lazy.values()),
        "type_ignore": type_ignores(),
        "modules_importing_h2": len(h2),
        "readme_lines": len((ROOT / "README.md").read_text().splitlines()),
    }
