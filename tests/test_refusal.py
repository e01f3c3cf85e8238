"""One refusal type: every exception class of the appliance and its nodes that refuses a request
is ``exolink.refusal.Refused`` or a subclass, so the RPC layer, the CLI's exit code 5 and the
dashboard each catch it once and nothing translates one refusal into another."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest
import zenoh

from benchmarks.harness import free_port
from exolink import errors, messaging
from exolink.config import ZenohConfig
from exolink.refusal import Refused

ROOT = Path(__file__).resolve().parent.parent
SOURCES = [*(ROOT / "appliance/exolink").rglob("*.py"), *(ROOT / "nodes").rglob("*.py")]


def _module(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    parts = ["exolink", *parts[2:]] if parts[0] == "appliance" else ["exolink", *parts]
    return ".".join(p for p in parts if p != "__init__")


def _refusal_classes() -> list[tuple[str, str]]:
    """(module, class) of every class whose name says it refuses."""
    found = []
    for path in SOURCES:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and "Refused" in node.name:
                found.append((_module(path), node.name))
    return found


def test_every_refusal_is_the_one_type() -> None:
    classes = _refusal_classes()
    names = {c for _m, c in classes}
    assert {"Refused", "ArmRefused", "IntentRefused", "ManagerRefused", "UpdateRefused"} <= names
    for module, name in classes:
        cls = getattr(importlib.import_module(module), name)
        assert issubclass(cls, Refused), f"{module}.{name} is not an exolink.refusal.Refused"


def test_the_laptops_and_the_handlers_refusal_are_the_same_class() -> None:
    from exolink import client
    from exolink.control import controller
    from exolink.recordings import fetching

    assert client.Refused is messaging.Refused is controller.Refused is fetching.Refused is Refused


def test_a_refusal_from_deep_in_a_handler_is_an_error_reply_verbatim() -> None:
    """Over a real Zenoh query: a subclass raised by a part the handler calls (here the
    intent's) is the reply's error as it was raised, not re-wrapped; a bug is not a refusal."""
    from exolink.nodes.controller_manager.intent import IntentRefused

    def handler(req: dict[str, object]) -> dict[str, object]:
        if req.get("bug"):
            raise KeyError("x")
        raise IntentRefused("angles outside the operator's limits: r_knee 95 > 90")

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(
        messaging.session_config(ZenohConfig(listen=[endpoint]), listen=[endpoint], mode="peer")
    )
    try:
        served = messaging.serve(session, "exolink/t/refusal", handler)
        try:
            key = "exolink/t/refusal"  # request() adds the login
            reply = messaging.request(session, key, {"action": "x"}, 5.0)
            assert reply == {
                "ok": False,
                "error": "angles outside the operator's limits: r_knee 95 > 90",
            }
            bug = messaging.request(session, key, {"bug": True}, 5.0)
            assert bug["ok"] is False and bug["error"].startswith("internal error: KeyError")
        finally:
            served.undeclare()
    finally:
        session.close()


def test_the_command_line_ends_a_refusal_with_exit_5(capsys: pytest.CaptureFixture[str]) -> None:
    from exolink.supervisor.watchdog import ArmRefused

    def command(_args: object) -> int:
        raise ArmRefused("not armed: h2_reader is not running")

    assert errors.run_guarded(command, None) == errors.EXIT_REFUSED  # type: ignore[arg-type]
    assert "refused: not armed: h2_reader is not running" in capsys.readouterr().err
