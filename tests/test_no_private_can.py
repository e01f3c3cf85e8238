"""No module of the appliance or its nodes reads a python-can private attribute: what the
appliance needs of a bus is python-can's public API or the sim bus's own (exolink.canbus.simbus).

Private names are every ``_name`` (not dunder) python-can's own source uses as an attribute or
defines in a class body. Flagged in our code: ``obj._name`` on anything but ``self``/``cls``,
``getattr(obj, "_name")``, and, in a class that subclasses a python-can class, ``self._name``
where the python-can bases use that name (overriding its documented hooks, such as
``_recv_internal``, is a definition, not a read)."""

from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

import can

ROOT = Path(__file__).resolve().parent.parent
NAMEDTUPLE = {"_asdict", "_replace", "_fields", "_make"}  # public API of a NamedTuple


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _names_in(tree: ast.AST) -> set[str]:
    names: set[str] = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Attribute) and _private(n.attr):
            names.add(n.attr)
        elif isinstance(n, ast.ClassDef):
            for b in n.body:
                if isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef):
                    targets = [b.name]
                elif isinstance(b, ast.Assign):
                    targets = [t.id for t in b.targets if isinstance(t, ast.Name)]
                elif isinstance(b, ast.AnnAssign) and isinstance(b.target, ast.Name):
                    targets = [b.target.id]
                else:
                    continue
                names.update(t for t in targets if _private(t))
    return names


def python_can_private_names() -> set[str]:
    root = Path(can.__file__).parent
    names: set[str] = set()
    for f in root.rglob("*.py"):
        names |= _names_in(ast.parse(f.read_text(encoding="utf-8")))
    return names - NAMEDTUPLE


def _class_private_names(cls: type) -> set[str]:
    """Private names python-can's classes in ``cls``'s MRO use (their source, their dict)."""
    names: set[str] = set()
    for k in cls.__mro__:
        if not k.__module__.startswith("can"):
            continue
        names |= {n for n in vars(k) if _private(n)}
        names |= _names_in(ast.parse(inspect.getsource(k)))
    return names


def _imports(tree: ast.Module) -> dict[str, tuple[str, str | None]]:
    """Local names bound to python-can: name -> (module, attribute in it or None for the
    module itself)."""
    out: dict[str, tuple[str, str | None]] = {}
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            for a in n.names:
                if a.name.split(".")[0] == "can":
                    out[a.asname or "can"] = (a.name if a.asname else "can", None)
        elif isinstance(n, ast.ImportFrom) and n.module and n.module.split(".")[0] == "can":
            for a in n.names:
                out[a.asname or a.name] = (n.module, a.name)
    return out


def _python_can_bases(
    node: ast.ClassDef, imported: dict[str, tuple[str, str | None]]
) -> list[type]:
    """The python-can classes among a class's bases (``can.X``, or a name imported from can)."""
    out = []
    for b in node.bases:
        head, *rest = ast.unparse(b).split(".")
        if head not in imported:
            continue
        module, attr = imported[head]
        obj: object = importlib.import_module(module)
        for part in ([attr] if attr else []) + rest:
            obj = getattr(obj, part)
        if isinstance(obj, type):
            out.append(obj)
    return out


def reads(path: Path, private: set[str], root: Path = ROOT) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: list[str] = []
    imported = _imports(tree)

    def where(n: ast.AST) -> str:
        return f"{path.relative_to(root)}:{getattr(n, 'lineno', 0)}"

    for n in ast.walk(tree):
        if isinstance(n, ast.Attribute) and n.attr in private:
            base = n.value
            if not (isinstance(base, ast.Name) and base.id in ("self", "cls")):
                found.append(f"{where(n)} {ast.unparse(n)}")
        elif (
            isinstance(n, ast.Call)
            and isinstance(n.func, ast.Name)
            and n.func.id in ("getattr", "setattr", "hasattr")
            and len(n.args) >= 2
            and isinstance(n.args[1], ast.Constant)
            and n.args[1].value in private
        ):
            found.append(f"{where(n)} {ast.unparse(n)}")
        elif isinstance(n, ast.ClassDef):
            inherited: set[str] = set()
            for b in _python_can_bases(n, imported):
                inherited |= _class_private_names(b)
            for m in ast.walk(n):
                if (
                    isinstance(m, ast.Attribute)
                    and m.attr in inherited
                    and isinstance(m.value, ast.Name)
                    and m.value.id in ("self", "cls")
                ):
                    found.append(f"{where(m)} {ast.unparse(m)} (python-can's, inherited)")
    return found


def test_no_python_can_private_attribute_is_read() -> None:
    private = python_can_private_names()
    assert {"_multicast", "_socket", "_send_destination", "_can_protocol"} <= private
    found = [
        hit
        for folder in ("appliance", "nodes")
        for path in sorted((ROOT / folder).rglob("*.py"))
        for hit in reads(path, private)
    ]
    assert found == []


def test_the_scan_sees_what_it_looks_for(tmp_path: Path) -> None:
    """The rule catches the reads this codebase once made, in each form."""
    src = tmp_path / "sample.py"
    src.write_text(
        "import can\n"
        "from can.interfaces.udp_multicast.bus import UdpMulticastBus\n"
        "def f(bus):\n"
        "    return bus._multicast._socket, getattr(bus, '_send_destination')\n"
        "class B(UdpMulticastBus):\n"
        "    def send(self, msg, timeout=None):\n"
        "        return self._multicast, self._can_protocol, self._mine\n"
        "class C(can.BusABC):\n"
        "    def _recv_internal(self, timeout):\n"
        "        return self._is_shutdown\n"
    )
    text = "\n".join(reads(src, python_can_private_names(), tmp_path))
    for expected in (
        "bus._multicast._socket",
        "bus._multicast",
        "getattr(bus, '_send_destination')",
        "self._multicast (python-can's, inherited)",
        "self._can_protocol (python-can's, inherited)",
        "self._is_shutdown (python-can's, inherited)",
    ):
        assert expected in text, text
    assert "_mine" not in text and "_recv_internal" not in text
