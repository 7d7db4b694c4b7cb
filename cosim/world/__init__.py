"""The static world: road network, initial traffic, scene layout and RSU sites (:func:`build_world`)."""

from cosim.world.build import build_world
from cosim.world.types import Junction, Prism, RsuSite, StaticLayout, World

__all__ = ["Junction", "Prism", "RsuSite", "StaticLayout", "World", "build_world"]
