"""Per-agent sensor kinds without rays of their own (GNSS; a new kind: one module), a registry by name.

A kind named ``<name>`` is
- its spec: a ``<name>`` field of :class:`cosim.scenario.model.RigSpec` (None: the rig has none);
- a module in ``sensors/`` that registers a :class:`SensorKind` with :func:`register_sensor_kind` (from
  :mod:`cosim.sensors.sensor_kind`, the seam's types and registry) and is imported here (the built-in kinds
  register on import, so whoever reads :data:`SENSOR_KINDS` from this module sees them all);
- its message: ``/<agent>/<name>`` in frame ``<agent>/<name>`` (at the agent's ``base_link``), from
  :attr:`SensorKind.message`; the suite renders it every tick after the LiDAR, in registration order;
- its entry in docs/episode_format.md (and the topic table of :mod:`cosim.io.format`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from . import gnss  # noqa: F401 (the built-in kinds register themselves on import)
from .sensor_kind import SENSOR_KINDS, SensorContext, SensorKind, register_sensor_kind

__all__ = ["SENSOR_KINDS", "SensorContext", "SensorKind", "register_sensor_kind", "render_kinds"]


def render_kinds(rig: Any, ctx_of: Callable[[Any], SensorContext]) -> dict[str, Any]:
    """The frames of every registered kind the rig has (``ctx_of(spec)`` builds the context), in
    registration order."""
    return {name: kind.render(ctx_of(getattr(rig, name))) for name, kind in SENSOR_KINDS.items()
            if getattr(rig, name, None) is not None}
