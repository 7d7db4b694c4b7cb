"""The sensor-kind seam's types and registry (:mod:`cosim.sensors.kinds` is its face: import the registry from
there, where the built-in kinds have registered): a kind module imports :func:`register_sensor_kind` from
here."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cosim.registry import Registry
from cosim.snapshot import AgentState
from cosim.world.types import World


@dataclass(frozen=True)
class SensorContext:
    """What a kind's render sees: the agent at this tick, the rig's spec of the kind, the world, the random
    generator of the agent's sensors (draw a fixed number of values per tick: determinism) and whether
    noise is on."""

    agent: AgentState
    spec: Any
    world: World
    rng: np.random.Generator
    noise: bool
    t_ns: int


@dataclass(frozen=True)
class SensorKind:
    """``render(ctx) -> frame``; ``message(agent_id, frame, t_ns)`` -> the protobuf message (or a
    ``(schema name, JSON schema, payload)`` triple for a JSON message) the episode writer writes."""

    name: str
    render: Callable[[SensorContext], Any]
    message: Callable[[str, Any, int], Any]


#: Sensor kinds by name: a duplicate name is an error, an unknown one lists the known ones.
SENSOR_KINDS: Registry[SensorKind] = Registry("sensor kind")


def register_sensor_kind(kind: SensorKind) -> SensorKind:
    return SENSOR_KINDS.add(kind.name, kind)
