"""Node discovery through the ``exolink.nodes`` entry-point group.

A third party adds a node by pip-installing a package that declares an entry point in this group;
nothing here needs editing (the python-can interface model).
"""

from __future__ import annotations

from functools import cache
from importlib.metadata import entry_points
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from exolink.node import Node

GROUP = "exolink.nodes"


class PluginError(LookupError):
    pass


@cache
def available() -> dict[str, str]:
    """Plugin name -> ``module:Class`` for every installed node."""
    return {ep.name: ep.value for ep in entry_points(group=GROUP)}


@cache
def find_node_class(plugin: str) -> type[Node]:
    """Import only the node that is asked for: other nodes' dependencies stay unloaded."""
    eps = [ep for ep in entry_points(group=GROUP) if ep.name == plugin]
    if not eps:
        names = ", ".join(sorted(available())) or "none installed"
        raise PluginError(f"unknown node plugin {plugin!r} (available: {names})")
    try:
        cls = eps[0].load()
    except Exception as exc:  # a broken third-party plugin must not look like a missing one
        raise PluginError(f"node plugin {plugin!r} failed to import: {exc}") from exc
    from exolink.node import Node

    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise PluginError(f"node plugin {plugin!r} ({eps[0].value}) is not an exolink Node")
    return cls


CONTROLLER_GROUP = "exolink.controllers"


def controller_types() -> dict[str, str]:
    """Controller type -> ``module:Class`` for every installed controller (not cached: a lab
    may pip-install one while the manager runs, and the next load should see it)."""
    return {ep.name: ep.value for ep in entry_points(group=CONTROLLER_GROUP)}


def find_controller_class(kind: str) -> type:
    """Import the controller type asked for; PluginError names what is installed."""
    eps = [ep for ep in entry_points(group=CONTROLLER_GROUP) if ep.name == kind]
    if not eps:
        names = ", ".join(sorted(controller_types())) or "none installed"
        raise PluginError(f"unknown controller type {kind!r} (available: {names})")
    try:
        cls = eps[0].load()
    except Exception as exc:
        raise PluginError(f"controller type {kind!r} failed to import: {exc}") from exc
    from exolink.controller import Controller

    if not (isinstance(cls, type) and issubclass(cls, Controller)):
        raise PluginError(f"controller type {kind!r} ({eps[0].value}) is not an exolink Controller")
    return cls
