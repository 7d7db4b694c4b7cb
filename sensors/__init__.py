"""Ray-cast sensors and annotations (LiDAR, cameras, GNSS, IMU, BEV, visibility); see suite.py.

This folder installs as ``cosim.sensors`` (pyproject.toml ``package-dir``): import it as
``cosim.sensors`` from an installed cosim (``pip install -e .``), never as ``sensors`` or through ``PYTHONPATH=.``.
"""

from .suite import AgentFrames, SensorFrameSet, SensorSuite

__all__ = ["AgentFrames", "SensorFrameSet", "SensorSuite"]
