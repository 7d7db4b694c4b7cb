"""An in-process stand-in for :class:`~cosim.traffic.TrafficSim`: vehicles on straight lines, no SUMO.

Same interface (``step_to``, ``close``) for fast unit tests of the conductor. Every vehicle drives
east at a constant speed along its own row across the world's bounds; the connected vehicles
``vehicle_<i>`` come first, then background vehicles ``bg_<nnnn>`` cycling through the mix.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.protocol import VehicleState
from cosim.scenario.model import Scenario
from cosim.world.types import World
from cosim.world.vtypes import variants

ROW_SPACING_M = 6.0  # [m] between the rows the vehicles drive on
N_BACKGROUND = 6


class FakeTraffic:
    def __init__(self, scenario: Scenario, world: World, workdir: Path | None = None) -> None:
        rng = np.random.default_rng([scenario.seed, 20])
        xmin, ymin, xmax, ymax = world.bounds_m
        width = xmax - xmin
        classes = [scenario.agents.vehicles.vclass] * scenario.agents.vehicles.count
        mix = sorted(scenario.traffic.mix, key=lambda c: -scenario.traffic.mix[c])
        classes += [mix[k % len(mix)] for k in range(N_BACKGROUND)]
        ids = [f"vehicle_{i}" for i in range(scenario.agents.vehicles.count)]
        ids += [f"bg_{k:04d}" for k in range(N_BACKGROUND)]
        y0 = 0.5 * (ymin + ymax) - 0.5 * ROW_SPACING_M * (len(ids) - 1)
        self._vehicles = []
        for k, (vid, cls) in enumerate(zip(ids, classes, strict=True)):
            variant = variants()[cls][0]
            speed = min(
                variant.max_speed_mps,
                float(rng.uniform(5.0, 10.0)),
                0.8 * width / max(scenario.duration_s, 1.0),
            )
            x0 = xmin + 0.1 * width + float(rng.uniform(0.0, 10.0))
            self._vehicles.append((vid, cls, variant, x0, y0 + k * ROW_SPACING_M, speed))
        self._closed = False

    def step_to(self, t_ns: int) -> list[VehicleState]:
        t = t_ns * 1e-9
        out = []
        for vid, cls, v, x0, y, speed in self._vehicles:
            out.append(
                VehicleState(
                    sumo_id=vid,
                    cls=cls,
                    center_m=(x0 + speed * t, y, 0.5 * v.height_m),
                    size_m=(v.length_m, v.width_m, v.height_m),
                    yaw_rad=0.0,
                    pitch_rad=0.0,
                    speed_mps=speed,
                    velocity_mps=(speed, 0.0, 0.0),
                    accel_mps2=0.0,
                    yaw_rate_radps=0.0,
                    agent_id=vid if vid.startswith("vehicle_") else None,
                )
            )
        return sorted(out, key=lambda s: s.sumo_id)

    def close(self) -> None:
        self._closed = True
