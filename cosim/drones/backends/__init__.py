"""Drone dynamics backends: name -> class (see :class:`DynamicsBackend`). The registry lives in
:mod:`cosim.drones.backends.base`, where a backend module imports :func:`register_backend` from; this face imports
the built-in backends, so that they have registered whenever the package is imported."""

from __future__ import annotations

from cosim.drones.backends import jsbsim_backend, pybullet_backend  # noqa: F401 (they register themselves)
from cosim.drones.backends.base import DynamicsBackend, backend_class, backend_names, register_backend

__all__ = ["DynamicsBackend", "backend_class", "backend_names", "register_backend"]
