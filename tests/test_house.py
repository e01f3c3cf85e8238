"""The house rules the linters cannot see (tools/imports.py): an import inside a function is a
heavy or optional module loaded on demand, and says so where it stands."""

from __future__ import annotations

from tools import imports


def test_every_import_inside_a_function_gives_its_reason() -> None:
    unexplained = imports.unexplained_lazy(imports.modules())
    assert unexplained == [], (
        "imports inside functions without a reason (a comment on the line, or above its block; "
        f"a dodged cycle is a layer to fix instead): {unexplained}"
    )
