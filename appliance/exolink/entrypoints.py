"""Classes found by name through entry points (``exolink.nodes``, ``exolink.controllers``):
imported only when asked for, so a process loads the plugins it uses and no other's
dependencies. The bottom of the house: the config reads a node's ``Params`` through it, and
``exolink.plugins`` adds the checks that need the node and controller base classes."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from importlib.metadata import entry_points

NODES = "exolink.nodes"
CONTROLLERS = "exolink.controllers"


class PluginError(LookupError):
    pass


def names(group: str) -> dict[str, str]:
    """Entry point name -> ``module:Class`` for everything installed in ``group``."""
    return {ep.name: ep.value for ep in entry_points(group=group)}


def load(
    group: str, name: str, what: str, listed: Callable[[], dict[str, str]] | None = None
) -> tuple[type, str]:
    """The class entry point ``name`` of ``group`` names, imported; PluginError says what is
    installed when it is missing, and a broken third-party plugin must not look like a missing
    one. ``what`` is how errors call it ("node plugin", "controller type"). Returns the class and
    its ``module:Class``."""
    eps = [ep for ep in entry_points(group=group) if ep.name == name]
    if not eps:
        known = ", ".join(sorted(listed() if listed else names(group))) or "none installed"
        raise PluginError(f"unknown {what} {name!r} (available: {known})")
    try:
        cls = eps[0].load()
    except Exception as exc:
        raise PluginError(f"{what} {name!r} failed to import: {exc}") from exc
    if not isinstance(cls, type):
        raise PluginError(f"{what} {name!r} ({eps[0].value}) is not a class")
    return cls, eps[0].value


@cache
def node_params_type(plugin: str) -> type:
    """The ``Params`` struct a node plugin declares (what its config ``params`` must be)."""
    cls, where = load(NODES, plugin, "node plugin")
    params = getattr(cls, "Params", None)
    if not isinstance(params, type):
        raise PluginError(f"node plugin {plugin!r} ({where}) declares no Params")
    return params
