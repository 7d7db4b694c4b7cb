"""The traffic worker's engine: libsumo behind the lockstep protocol."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

from cosim import protocol
from cosim.errors import CosimError
from cosim.scenario.model import Scenario
from cosim.workers.process import workdir_prefix
from cosim.world.types import World


class TrafficEngine:
    """Builds a :class:`cosim.traffic.TrafficSim` from the init request and steps it."""

    def __init__(self) -> None:
        self._sim: Any = None
        self._workdir = tempfile.TemporaryDirectory(prefix=workdir_prefix("traffic"))

    def init(self, request: protocol.InitRequest) -> dict[str, Any]:
        from cosim.traffic import TrafficSim

        if request.protocol != protocol.PROTOCOL_VERSION:
            raise CosimError(f"protocol {request.protocol} not supported (this worker speaks "
                             f"{protocol.PROTOCOL_VERSION})")
        scenario = Scenario.model_validate(request.scenario)
        world = World.from_wire(request.world)
        self._sim = TrafficSim(scenario, world, Path(self._workdir.name))
        return {"ready": True}

    def step(self, request: protocol.StepRequest) -> dict[str, Any]:
        if self._sim is None:
            raise CosimError("step before init")
        failed = [{"action": a, "error": err} for a in request.actions if (err := self._sim.command(a))]
        vehicles = self._sim.step_to(request.t_ns)
        return {"tick": request.tick, "t_ns": request.t_ns, "vehicles": vehicles, "failed": failed,
                "events": self._sim.events(), "signals": self._sim.signal_states()}

    def close(self) -> None:
        if self._sim is not None:
            self._sim.close()
            self._sim = None
        self._workdir.cleanup()
