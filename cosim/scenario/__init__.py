"""Scenario files: schema (:mod:`.model`) and loading with overlays and overrides (:mod:`.loader`)."""

from cosim.scenario.loader import LoadedScenario, find_scenario, load_scenario, load_scenario_data, shipped_scenarios
from cosim.scenario.model import Scenario

__all__ = ["LoadedScenario", "Scenario", "find_scenario", "load_scenario", "load_scenario_data", "shipped_scenarios"]
