"""Controller manager [thesis: the ros_control hardware interface]: the one writer of motion and
the home of the operator's intent (limits in force, who holds motion).

- ``node``: the node: its bus, its loop's turns, the writes a request asks for; the loop's two
  ways out are ``cycle_loop`` (read -> update -> write each H2 cycle) and ``on_timer``;
- ``api``: its requests: controllers, presence; ``commands``: the operator's one-off commands to
  the H2 and the MACCEPA boards (``exolink send``, ``exolink maccepa``);
- ``manager``: the controllers, their claims and switches, one cycle's outputs (no I/O), with
  ``loaded`` (loading and describing them), ``switching`` (switches at a cycle boundary),
  ``slots`` (what it holds and hands out), ``budget`` (an update judged: CPU, values) and
  ``boards`` (the MACCEPA boards' writes);
- ``bus_view``: what the node knows of the bus (frames decoded, the latest readings, stops);
- ``params``, ``frames``: the node's params; its frames, encoded once, and its reader's ids;
- ``intent``: the operator's limits (persisted) and presence;
- ``timed``: a trajectory's set-points handed to the kernel's timer (the broadcast manager);
- ``builtin``, ``maccepa``: the built-in controllers (joints; MACCEPA boards).
"""

from exolink.nodes.controller_manager.frames import drop_rules, one_socket
from exolink.nodes.controller_manager.node import ControllerManagerNode

__all__ = ["ControllerManagerNode", "drop_rules", "one_socket"]
