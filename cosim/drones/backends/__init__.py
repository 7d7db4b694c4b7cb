"""Registry of drone dynamics backends: name -> class (see :class:`DynamicsBackend`)."""

from __future__ import annotations

from collections.abc import Callable

from cosim.drones.backends.base import DynamicsBackend
from cosim.errors import InputError

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


# Built-in backends register themselves on import.
from cosim.drones.backends import jsbsim_backend, pybullet_backend  # noqa: E402, F401

__all__ = ["DynamicsBackend", "backend_class", "backend_names", "register_backend"]
