"""Which objects each agent sees: LiDAR returns and pixels per camera for every actor (track id).

Counts come straight from the instance channels of the agent's own frames, so they agree with the
data exactly. Static instances (ids >= 1_000_000) and 0 are not objects and are not counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATIC_INSTANCE_MIN = 1_000_000


@dataclass(frozen=True)
class ObjectVisibility:
    track_id: int
    lidar_points: int
    pixels: dict[str, int]  # camera name -> pixel count

    @property
    def visible(self) -> bool:
        return self.lidar_points > 0 or any(v > 0 for v in self.pixels.values())


@dataclass(frozen=True)
class VisibilityFrame:
    agent_id: str
    objects: tuple[ObjectVisibility, ...]  # sorted by track id; only objects seen at least once


def instance_counts(instance: np.ndarray) -> dict[int, int]:
    """Pixels (or points) per track id in an instance array (static instances and 0 left out)."""
    ids = instance.ravel()
    ids = ids[(ids > 0) & (ids < STATIC_INSTANCE_MIN)]
    if ids.size == 0:
        return {}
    c = np.bincount(ids.astype(np.int64))
    nz = np.nonzero(c)[0]
    return {int(i): int(c[i]) for i in nz}


def render_visibility(agent_id: str, lidar_instance: np.ndarray | None,
                      camera_instance: dict[str, np.ndarray | dict[int, int]]) -> VisibilityFrame:
    """``lidar_instance`` (N,) and ``camera_instance`` name -> (H, W) instance array of one agent, or that
    array's :func:`instance_counts` (a suite that let go of the array counted it as the camera rendered)."""
    lid = instance_counts(lidar_instance) if lidar_instance is not None else {}
    cams = {name: img if isinstance(img, dict) else instance_counts(img) for name, img in camera_instance.items()}
    tracks = sorted(set(lid) | {t for c in cams.values() for t in c})
    objs = tuple(
        ObjectVisibility(t, lid.get(t, 0), {name: c.get(t, 0) for name, c in cams.items()}) for t in tracks
    )
    return VisibilityFrame(agent_id, objs)
