"""The drone worker's engine: the drone fleet (JSBSim / PyBullet) behind the lockstep protocol."""

from __future__ import annotations

from typing import Any

from cosim import protocol
from cosim.errors import CosimError
from cosim.scenario.model import Scenario
from cosim.world.types import World


class DroneEngine:
    """Builds a :class:`cosim.drones.DroneFleet` from the init request and steps it."""

    def __init__(self) -> None:
        self._fleet: Any = None

    def init(self, request: protocol.InitRequest) -> dict[str, Any]:
        from cosim.drones import DroneFleet

        if request.protocol != protocol.PROTOCOL_VERSION:
            raise CosimError(f"protocol {request.protocol} not supported (this worker speaks "
                             f"{protocol.PROTOCOL_VERSION})")
        self._fleet = DroneFleet(Scenario.model_validate(request.scenario), World.from_wire(request.world))
        return {"ready": True}

    def step(self, request: protocol.StepRequest) -> dict[str, Any]:
        if self._fleet is None:
            raise CosimError("step before init")
        failed = [{"action": a, "error": err} for a in request.actions if (err := self._fleet.command(a, request.tick))]
        drones = self._fleet.step_to(request.t_ns, request.tick, request.escort_targets)
        return {"tick": request.tick, "t_ns": request.t_ns, "drones": drones, "failed": failed}

    def close(self) -> None:
        if self._fleet is not None:
            self._fleet.close()
            self._fleet = None
