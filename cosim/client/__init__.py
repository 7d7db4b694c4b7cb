"""Closed-loop clients: user code that joins an episode's lockstep, observes every tick and acts.

See :mod:`cosim.client.api` (``connect``, ``Client``, ``Observation``) and :mod:`cosim.actions`
(what may be asked of vehicles and drones); README section "Closing the loop".
"""

from cosim import actions
from cosim.client.api import Client, Observation, connect
from cosim.errors import ActionRejected

__all__ = ["ActionRejected", "Client", "Observation", "actions", "connect"]
