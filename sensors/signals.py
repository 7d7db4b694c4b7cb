"""The traffic lights' static mesh (geometry: :mod:`cosim.sensors.assets.signals`)."""

from __future__ import annotations

import numpy as np

from cosim.classes import semantic_id

from .assets.signals import SignalParts
from .meshes import TriMesh


def signal_mesh(parts: SignalParts) -> TriMesh:
    """The :class:`cosim.sensors.meshes.TriMesh` of ``parts``: heads and lamps of class ``traffic_light``,
    poles and arms ``pole``."""
    t = len(parts.triangles)
    return TriMesh(parts.vertices, parts.triangles,
                   np.where(parts.pole, semantic_id("pole"), semantic_id("traffic_light")).astype(np.uint8),
                   parts.instance, parts.albedo, parts.reflectivity, np.zeros(t, np.float32),
                   np.arange(t, dtype=np.int64) // 2)
