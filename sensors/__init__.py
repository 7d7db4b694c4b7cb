"""Ray-cast sensors and annotations (LiDAR, cameras, GNSS, IMU, BEV, visibility); see suite.py."""

from .suite import AgentFrames, SensorFrameSet, SensorSuite

__all__ = ["AgentFrames", "SensorFrameSet", "SensorSuite"]
