"""The ray-backend seam: the engines that find where rays meet triangle meshes.

A backend is an object with four operations (:class:`RayBackend`), each over plain numpy arrays:

- ``build(vertices, triangles, quality)`` -> an opaque scene handle, or None for an empty mesh
  (``vertices`` (V, 3) float32 [m], ``triangles`` (T, 3) uint32). ``quality`` is a :data:`QUALITIES`
  hint: ``high`` for the episode's static world (built once, cast against all episode long),
  ``medium`` for a tick's actors, ``low`` for the short-lived scenes of the actors moved to a LiDAR
  firing's time. A backend may ignore it;
- ``closest(scene, rays)`` -> ``t`` (N,) float32 in units of each direction's length (inf on a miss)
  and the triangle index (N,) int32 (-1 on a miss), for ``rays`` (N, 6) float32 [origin, direction];
- ``occluded(scene, rays)`` -> (N,) bool: whether each ray meets any triangle at all (t in (0, inf));
- ``name``.

"Build actors at a time" is ``build`` of the actors' vertices moved by their velocity (see
:class:`cosim.sensors.scene.TickScene`): a backend needs no notion of time. A backend may also offer
``instances(prototypes, translations, offsets)``: one scene of scenes it built (one per actor, at the
tick), each translated by its row of ``translations`` (N, 3) [m], whose hits report ``offsets[i]`` plus the
triangle's index in prototype ``i``; the actors at each LiDAR time bin are then made of instances instead of
a new BVH of the moved mesh (``embree``: 8 builds of every actor per tick become one; the same triangles,
distances to float32 rounding, tests/test_ray_backends.py).

Backends are a registry (:data:`RAY_BACKENDS`, :func:`ray_backend`); the scenario key
``sensors.ray_backend`` chooses one (docs/architecture.md, "Ray backends"): ``embree`` (the default,
:mod:`cosim.sensors.ray_embree`) and ``open3d`` (the reference, :mod:`cosim.sensors.ray_open3d`).
Triangle ids of the two agree on all but a tiny share of rays (edges shared by two triangles);
whatever a backend hits, the labels are those of the triangle it hit.
"""

from __future__ import annotations

import importlib
from typing import Any, Literal, Protocol

import numpy as np

from cosim.errors import InputError
from cosim.registry import Registry

Quality = Literal["low", "medium", "high"]
QUALITIES: tuple[Quality, ...] = ("low", "medium", "high")


class RayBackend(Protocol):
    name: str

    def build(self, vertices: np.ndarray, triangles: np.ndarray, quality: Quality) -> Any | None: ...

    def closest(self, scene: Any | None, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def occluded(self, scene: Any | None, rays: np.ndarray) -> np.ndarray: ...


#: name -> module that registers it on import (backends load their engine only when chosen)
_MODULES = {"embree": "cosim.sensors.ray_embree", "open3d": "cosim.sensors.ray_open3d"}
RAY_BACKENDS: Registry[RayBackend] = Registry("ray backend")
DEFAULT_BACKEND = "embree"


def ray_backend(name: str = DEFAULT_BACKEND) -> RayBackend:
    """The backend registered as ``name`` (importing its module on first use); an unknown name is an
    :class:`~cosim.errors.InputError` listing the known ones (the built-in ones too, imported or not)."""
    if name not in RAY_BACKENDS:
        if name not in _MODULES:
            raise InputError(f"unknown {RAY_BACKENDS.what} {name!r}; known: {', '.join(backend_names())}")
        importlib.import_module(_MODULES[name])
    return RAY_BACKENDS.get(name)


def backend_names() -> list[str]:
    """Every backend name: the built-in ones and any registered since."""
    return sorted(set(_MODULES) | set(RAY_BACKENDS.names()))


def misses(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``closest`` of ``n`` rays in an empty scene."""
    return np.full(n, np.inf, np.float32), np.full(n, -1, np.int32)


class Built:
    """A scene built by a backend: its handle and the backend's two queries on it."""

    __slots__ = ("backend", "handle")

    def __init__(self, backend: RayBackend, handle: Any):
        self.backend, self.handle = backend, handle

    def closest(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.backend.closest(self.handle, rays)

    def occluded(self, rays: np.ndarray) -> np.ndarray:
        return self.backend.occluded(self.handle, rays)


def build(backend: RayBackend, vertices: np.ndarray, triangles: np.ndarray, quality: Quality) -> Built | None:
    """``backend``'s scene of the mesh, or None when it has no triangles."""
    if len(triangles) == 0:
        return None
    return Built(backend, backend.build(vertices, triangles, quality))
