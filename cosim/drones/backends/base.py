"""The narrow adapter every drone dynamics engine sits behind.

A backend owns one rigid body: the airframe, its 4 lagged rotors and the air around it. It speaks
cosim frames and SI units only (map ENU, body FLU, metres, newtons); any engine-specific units or
frames are converted inside the adapter module and nowhere else. The registry of backends by name
(:func:`register_backend`, :func:`backend_class`) is here too; :mod:`cosim.drones.backends` imports the built-in ones.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import ClassVar

import numpy as np

from cosim.drones.airframe import Airframe, RotorBank
from cosim.drones.control import BodyState
from cosim.errors import InputError
from cosim.world.types import World


class DynamicsBackend(ABC):
    """One drone's flight dynamics, stepped at a fixed ``dt_s``."""

    name: ClassVar[str]

    def __init__(self, frame: Airframe, dt_s: float, world: World):
        self.frame = frame
        self.dt_s = dt_s
        self.world = world
        self.rotors = RotorBank.hovering(frame, dt_s)

    @abstractmethod
    def reset(self, position_m: np.ndarray, yaw_rad: float, velocity_mps: np.ndarray | None = None) -> None:
        """Place the drone at ``position_m`` (3,) map ENU [m], level, moving at ``velocity_mps`` (3,) map
        ENU [m/s] (None: at rest), not turning, rotors at hover thrust."""

    @abstractmethod
    def step(self, rotor_command_n: np.ndarray, wind_mps: np.ndarray) -> None:
        """Advance ``dt_s``: rotors lag toward ``rotor_command_n`` (4,) [N]; the air moves at
        ``wind_mps`` (3,) ENU [m/s]."""

    @abstractmethod
    def state(self) -> BodyState:
        """The body's state after the last step (or reset)."""

    def contact(self) -> str | None:
        """What the engine saw the body touch during the last step (None: nothing, or not modelled)."""
        return None

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the engine."""


# ------------------------------------------------------------------------------------- registry

_REGISTRY: dict[str, type[DynamicsBackend]] = {}


def register_backend(name: str) -> Callable[[type[DynamicsBackend]], type[DynamicsBackend]]:
    """Class decorator adding a backend under ``name``; a second registration of a name is an error."""

    def add(cls: type[DynamicsBackend]) -> type[DynamicsBackend]:
        if name in _REGISTRY:
            raise ValueError(f"drone dynamics backend {name!r} is already registered ({_REGISTRY[name].__name__})")
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return add


def backend_class(name: str) -> type[DynamicsBackend]:
    """The backend class registered as ``name``; an unknown name is an error listing the known ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY))
        raise InputError(f"unknown drone dynamics backend {name!r}; known backends: {known}") from None


def backend_names() -> list[str]:
    return sorted(_REGISTRY)
