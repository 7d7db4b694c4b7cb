"""Scenario files: schema (:mod:`.model`) and loading with overlays and overrides (:mod:`.loader`).

The names are looked up on first use (PEP 562): a worker that only reads a :class:`Scenario` sent to it imports
the schema alone, not the loader and its YAML stack (about 0.2 CPU-s a process on these machines)."""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cosim.scenario.loader import (
        LoadedScenario,
        find_scenario,
        load_scenario,
        load_scenario_data,
        shipped_scenarios,
    )
    from cosim.scenario.model import Scenario

_HOME = {"LoadedScenario": "loader", "find_scenario": "loader", "load_scenario": "loader",
         "load_scenario_data": "loader", "shipped_scenarios": "loader", "Scenario": "model"}

__all__ = ["LoadedScenario", "Scenario", "find_scenario", "load_scenario", "load_scenario_data", "shipped_scenarios"]


def __getattr__(name: str) -> Any:
    if name not in _HOME:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{_HOME[name]}"), name)
    globals()[name] = value
    return value
