"""Measure exolink's import structure: cycles among module-level imports, and imports in functions.

A cycle among module-level imports makes import order matter and hides which layer a module
belongs to; an import inside a function is either a heavy optional module loaded on demand or a
cycle dodged. `python tools/imports.py` prints both so they can be re-measured after a change
(`lint-imports` checks the layers; this counts what the contracts cannot see).
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# The package's folders as pyproject.toml maps them (package-dir).
PACKAGES = {"exolink": ROOT / "appliance" / "exolink", "exolink.nodes": ROOT / "nodes"}


@dataclass(frozen=True)
class Import:
    source: str
    target: str
    line: int
    in_function: bool


def modules() -> dict[str, Path]:
    """Every exolink module and its file."""
    found: dict[str, Path] = {}
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join([package, *parts])
            if package == "exolink" and parts[:1] == ["nodes"]:
                continue
            found[name] = path
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _walk(node: ast.AST, in_function: bool) -> Iterator[tuple[ast.AST, bool]]:
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.If) and _is_type_checking(child):
            continue  # never runs: no edge at import time
        inner = in_function or isinstance(
            child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda
        )
        yield child, inner
        yield from _walk(child, inner)


def _is_dunder_import(node: ast.Call) -> bool:
    """`__import__("exolink.x")`: an import spelled so a reader (and import-linter) misses it."""
    return (
        isinstance(node.func, ast.Name)
        and node.func.id == "__import__"
        and bool(node.args)
        and isinstance(node.args[0], ast.Constant)
    )


def _resolve(name: str, known: dict[str, Path]) -> str | None:
    """The longest known module that `name` is or lies in."""
    while name:
        if name in known:
            return name
        name = name.rpartition(".")[0]
    return None


def imports(known: dict[str, Path]) -> list[Import]:
    """Every import of an exolink module by an exolink module."""
    found: list[Import] = []
    for module, path in known.items():
        is_package = path.name == "__init__.py"
        for node, in_function in _walk(ast.parse(path.read_text(), str(path)), False):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = module.split(".")
                    drop = node.level - 1 if is_package else node.level
                    anchor = anchor[: len(anchor) - drop]
                    base = ".".join([*anchor, base]) if base else ".".join(anchor)
                targets = [f"{base}.{alias.name}" for alias in node.names]
            elif isinstance(node, ast.Call) and _is_dunder_import(node):
                assert isinstance(node.args[0], ast.Constant)
                targets = [str(node.args[0].value)]
            for target in targets:
                resolved = _resolve(target, known)
                if resolved and resolved != module:
                    found.append(Import(module, resolved, node.lineno, in_function))
    return found


def cycles(edges: list[Import], *, with_functions: bool) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    graph: dict[str, set[str]] = {}
    for edge in edges:
        if with_functions or not edge.in_function:
            graph.setdefault(edge.source, set()).add(edge.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def main() -> int:
    known = modules()
    edges = imports(known)
    for label, with_functions in (("module-level", False), ("with function-level", True)):
        found = cycles(edges, with_functions=with_functions)
        sys.stdout.write(f"cycles ({label} imports): {len(found)}\n")
        for component in found:
            sys.stdout.write("  " + " ".join(component) + "\n")
    lazy = sorted({(edge.source, edge.line, edge.target) for edge in edges if edge.in_function})
    statements = len({(source, line) for source, line, _ in lazy})
    sys.stdout.write(f"function-level imports of exolink modules: {statements}\n")
    if "-v" in sys.argv:
        for source, line, target in lazy:
            sys.stdout.write(f"  {source}:{line} -> {target}\n")
    sys.stdout.write(f"function-level imports (all): {all_lazy(known)}\n")
    return 0


def all_lazy(known: dict[str, Path]) -> int:
    """Import statements (and ``__import__`` calls) inside functions, of any module."""
    count = 0
    for path in known.values():
        for node, in_function in _walk(ast.parse(path.read_text(), str(path)), False):
            count += in_function and isinstance(node, ast.Import | ast.ImportFrom)
            count += in_function and isinstance(node, ast.Call) and _is_dunder_import(node)
    return count


def unexplained_lazy(known: dict[str, Path]) -> list[tuple[str, int]]:
    """Imports inside functions that give no reason: no comment on the statement, nor on the
    line just above it or its block of imports (a heavy optional module says why it is loaded
    on demand; a dodged cycle is a layer to fix)."""
    found = []
    for module, path in known.items():
        lines = path.read_text().splitlines()
        for node, in_function in _walk(ast.parse("\n".join(lines), str(path)), False):
            if not (in_function and isinstance(node, ast.Import | ast.ImportFrom)):
                continue
            end = node.end_lineno or node.lineno
            if any("#" in ln for ln in lines[node.lineno - 1 : end]):
                continue
            above = node.lineno - 2
            while above >= 0 and "#" not in lines[above]:
                if not lines[above].lstrip().startswith(("import ", "from ")):
                    break
                above -= 1
            if above >= 0 and "#" in lines[above]:
                continue
            found.append((module, node.lineno))
    return sorted(found)


if __name__ == "__main__":
    raise SystemExit(main())
