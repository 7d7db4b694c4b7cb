"""Escort tracking error measured from an episode's labels (``/labels/objects`` payloads)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from cosim.scenario.model import EscortDrone, Scenario


def escort_errors(labels: Iterable[dict[str, Any]], scenario: Scenario) -> dict[str, list[float]]:
    """Per escorting drone, the horizontal distance [m] to its commanded offset point at every tick.

    The offset point is the target vehicle's box centre plus ``offset_m`` (forward, left) in its body frame.
    """
    escorts = {f"drone_{i}": d for i, d in enumerate(scenario.agents.drones) if isinstance(d, EscortDrone)}
    errors: dict[str, list[float]] = {k: [] for k in escorts}
    for payload in labels:
        by_agent = {o["agent_id"]: o for o in payload["objects"] if o["agent_id"]}
        for drone_id, spec in escorts.items():
            car, drone = by_agent.get(spec.target), by_agent.get(drone_id)
            if car is None or drone is None:
                continue
            x, y, z, w = car["rotation"]
            yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
            fwd, left = spec.offset_m
            gx = car["center_m"][0] + fwd * math.cos(yaw) - left * math.sin(yaw)
            gy = car["center_m"][1] + fwd * math.sin(yaw) + left * math.cos(yaw)
            errors[drone_id].append(math.hypot(drone["center_m"][0] - gx, drone["center_m"][1] - gy))
    return errors


def rms(values: list[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values)) if values else float("nan")
