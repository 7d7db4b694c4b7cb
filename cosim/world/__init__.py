"""The static world: road network, initial traffic, scene layout and RSU sites (:func:`build_world`).

:func:`build_world` is looked up on first use (PEP 562): the workers, which receive a built world, import the
world's types alone, not the builders (layout, clutter, parking, ...)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from cosim.world.types import Junction, Prism, RsuSite, StaticLayout, World

if TYPE_CHECKING:
    from cosim.world.build import build_world

__all__ = ["Junction", "Prism", "RsuSite", "StaticLayout", "World", "build_world"]


def __getattr__(name: str) -> Any:
    if name != "build_world":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from cosim.world.build import build_world

    globals()[name] = build_world
    return build_world
