"""Node discovery through the ``exolink.nodes`` entry-point group.

A third party adds a node by pip-installing a package that declares an entry point in this group;
nothing here needs editing (the python-can interface model).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from importlib.metadata import entry_points

from exolink.controller import Controller
from exolink.node import Node

GROUP = "exolink.nodes"


class PluginError(LookupError):
    pass


@cache
def available() -> dict[str, str]:
    """Plugin name -> ``module:Class`` for every installed node."""
    return {ep.name: ep.value for ep in entry_points(group=GROUP)}


def _load(
    group: str, name: str, what: str, names: Callable[[], dict[str, str]]
) -> tuple[type, str]:
    """The class entry point ``name`` of ``group`` names, imported; PluginError says what is
    installed when it is missing, and a broken third-party plugin must not look like a missing
    one. ``what`` is how errors call it ("node plugin", "controller type"). Returns the class and
    its ``module:Class``."""
    eps = [ep for ep in entry_points(group=group) if ep.name == name]
    if not eps:
        listed = ", ".join(sorted(names())) or "none installed"
        raise PluginError(f"unknown {what} {name!r} (available: {listed})")
    try:
        cls = eps[0].load()
    except Exception as exc:
        raise PluginError(f"{what} {name!r} failed to import: {exc}") from exc
    return cls, eps[0].value


@cache
def find_node_class(plugin: str) -> type[Node]:
    """Import only the node that is asked for: other nodes' dependencies stay unloaded."""
    cls, where = _load(GROUP, plugin, "node plugin", available)
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise PluginError(f"node plugin {plugin!r} ({where}) is not an exolink Node")
    return cls


CONTROLLER_GROUP = "exolink.controllers"


def controller_types() -> dict[str, str]:
    """Controller type -> ``module:Class`` for every installed controller (not cached: a lab
    may pip-install one while the manager runs, and the next load should see it)."""
    return {ep.name: ep.value for ep in entry_points(group=CONTROLLER_GROUP)}


def find_controller_class(kind: str) -> type:
    """Import the controller type asked for; PluginError names what is installed."""
    cls, where = _load(CONTROLLER_GROUP, kind, "controller type", controller_types)
    if not (isinstance(cls, type) and issubclass(cls, Controller)):
        raise PluginError(f"controller type {kind!r} ({where}) is not an exolink Controller")
    return cls
