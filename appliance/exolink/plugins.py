"""Node discovery through the ``exolink.nodes`` entry-point group.

A third party adds a node by pip-installing a package that declares an entry point in this group;
nothing here needs editing (the python-can interface model).
"""

from __future__ import annotations

from functools import cache

from exolink.control.controller import Controller
from exolink.entrypoints import CONTROLLERS, NODES, PluginError, load, names
from exolink.node import Node

GROUP = NODES
CONTROLLER_GROUP = CONTROLLERS


@cache
def available() -> dict[str, str]:
    """Plugin name -> ``module:Class`` for every installed node."""
    return names(GROUP)


@cache
def find_node_class(plugin: str) -> type[Node]:
    """Import only the node that is asked for: other nodes' dependencies stay unloaded."""
    cls, where = load(GROUP, plugin, "node plugin", available)
    if not issubclass(cls, Node):
        raise PluginError(f"node plugin {plugin!r} ({where}) is not an exolink Node")
    return cls


def controller_types() -> dict[str, str]:
    """Controller type -> ``module:Class`` for every installed controller (not cached: a lab
    may pip-install one while the manager runs, and the next load should see it)."""
    return names(CONTROLLER_GROUP)


@cache
def find_controller_class(kind: str) -> type:
    """Import the controller type asked for; PluginError names what is installed.

    Cached, as find_node_class: the lookup reads every installed package's metadata, which
    was nearly all of a gait start's controller load on x86 (py-spy, 30 of 32 samples) and a
    burst of the manager's CPU at each start on the board. A PluginError is not cached, so a
    type a lab installs while the manager runs is still seen at its first load (a class
    already imported would not change with a reinstall anyway)."""
    cls, where = load(CONTROLLER_GROUP, kind, "controller type", controller_types)
    if not issubclass(cls, Controller):
        raise PluginError(f"controller type {kind!r} ({where}) is not an exolink Controller")
    return cls


__all__ = [
    "CONTROLLER_GROUP",
    "GROUP",
    "PluginError",
    "available",
    "controller_types",
    "find_controller_class",
    "find_node_class",
]
