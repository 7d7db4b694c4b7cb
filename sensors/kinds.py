"""Per-agent sensor kinds without rays of their own (GNSS; a new kind: one module), a registry by name.

A kind named ``<name>`` is
- its spec: a ``<name>`` field of :class:`cosim.scenario.model.RigSpec` (None: the rig has none);
- a module in ``sensors/`` that registers a :class:`SensorKind` with :func:`register_sensor_kind` and is
  listed at the bottom of this module (the built-in kinds register on import);
- its message: ``/<agent>/<name>`` in frame ``<agent>/<name>`` (at the agent's ``base_link``), from
  :attr:`SensorKind.message`; the suite renders it every tick after the LiDAR, in registration order;
- its entry in docs/episode_format.md (and the topic table of :mod:`cosim.io.format`).
"""

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


def render_kinds(rig: Any, ctx_of: Callable[[Any], SensorContext]) -> dict[str, Any]:
    """The frames of every registered kind the rig has (``ctx_of(spec)`` builds the context), in
    registration order."""
    return {name: kind.render(ctx_of(getattr(rig, name))) for name, kind in SENSOR_KINDS.items()
            if getattr(rig, name, None) is not None}


# Built-in kinds register themselves on import.
from . import gnss  # noqa: E402, F401
