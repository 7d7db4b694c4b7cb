"""Drone flight dynamics (JSBSim or PyBullet behind one adapter), shared guidance and control, and the
hover / patrol / escort strategies. The drone worker wraps :class:`DroneFleet`."""

from cosim.drones.backends import backend_class, backend_names, register_backend
from cosim.drones.fleet import DroneFleet

__all__ = ["DroneFleet", "backend_class", "backend_names", "register_backend"]
