"""The one refusal type: a request refused for a reason its sender can act on.

Every part that refuses (a handler on the board, the watchdog's arm, the operator's limits, a
controller, an update, the clock, the laptop's view of a refused reply) raises ``Refused`` or a
subclass that says whose refusal it is. The text reaches the caller as it is: over Zenoh as the
reply's ``error`` (``exolink.messaging.rpc`` turns any ``Refused`` into one), on the command line
as ``refused: ...`` with exit code 5 (``exolink.errors``). So nothing translates one refusal into
another, and one ``except Refused`` catches them all. At the bottom of the layers: it imports
nothing.
"""

from __future__ import annotations


class Refused(Exception):
    """Refused, and why (the message is shown to the operator verbatim)."""
