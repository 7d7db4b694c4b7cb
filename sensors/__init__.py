"""Ray-cast sensors and annotations (LiDAR, cameras, GNSS, IMU, BEV, visibility); see suite.py.

The suite is imported on first use, so that light submodules (the procedural assets, which the
traffic worker uses for the pedestrians' boxes) do not pull in Open3D and the renderer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .suite import AgentFrames, SensorFrameSet, SensorSuite

__all__ = ["AgentFrames", "SensorFrameSet", "SensorSuite"]


def __getattr__(name: str):
    if name in __all__:
        from . import suite

        return getattr(suite, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
