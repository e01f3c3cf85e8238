"""The house's figures: files over 400 lines, import cycles between modules and imports inside
functions (tools/imports.py), ``type: ignore`` comments, modules that know the H2 protocol,
README lines. Read from the source: no process is started, so the figures are the same on any
host."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from tools import imports

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


def type_ignores() -> dict[str, int]:
    """``type: ignore`` comments in product code: all, and those that name no error code."""
    total = bare = 0
    for p in _files():
        for m in IGNORE.finditer(p.read_text()):
            total += 1
            bare += m.group(1) is None
    return {"total": total, "without_code": bare}


def h2_modules() -> list[str]:
    """Product modules that import the H2 protocol module (exolink.protocol.h2)."""
    pat = re.compile(r"from exolink\.protocol import [^\n]*\bh2\b|exolink\.protocol\.h2")
    return [_rel(p) for p in _files() if pat.search(p.read_text()) and "protocol" not in p.parts]


def run(quick: bool) -> dict[str, Any]:
    longs = long_files()
    known = imports.modules()
    edges = imports.imports(known)
    cycles = imports.cycles(edges, with_functions=False)
    h2 = h2_modules()
    return {
        "files_over_400": len(longs),
        "files_over_400_lines": longs,
        # module-level imports (TYPE_CHECKING ones apart), and with function-level ones too
        "import_cycles": len(cycles),
        "import_cycle_modules": cycles,
        "import_cycles_with_functions": len(imports.cycles(edges, with_functions=True)),
        "imports_in_functions": imports.all_lazy(known),
        "imports_in_functions_without_reason": len(imports.unexplained_lazy(known)),
        "type_ignore": type_ignores(),
        "modules_importing_h2": len(h2),
        "readme_lines": len((ROOT / "README.md").read_text().splitlines()),
    }
