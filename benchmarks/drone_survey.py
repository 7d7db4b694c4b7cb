"""Fly a scenario's drones over its built world, escorts following real SUMO traffic, without the
conductor: the separation between drones and how close patrols stay to the lanes.

    python -m benchmarks.drone_survey [SCENARIO ...] [--duration 60]

prints one JSON line per scenario (default: every shipped one): the smallest distance between two
drones with the pair and tick, and each patrol drone's median horizontal distance to the nearest
lane centre line. Escort targets reach the fleet one tick late, as in ``cosim run``
(:func:`cosim.runner.run_episode`); worlds and traffic are shared between scenarios that build the
same world.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cosim.assemble import escort_targets_of
from cosim.drones.fleet import DroneFleet
from cosim.protocol import DroneState, VehicleState
from cosim.scenario.loader import LoadedScenario, load_scenario
from cosim.scenario.model import EscortDrone
from cosim.world.routes import read_sumolib
from cosim.world.types import World

log = logging.getLogger(__name__)

SCENARIOS_DIR = Path(__file__).resolve().parents[1] / "scenarios"


@dataclass
class FleetFlight:
    states: list[list[DroneState]]  # per tick (index 0: t = 0), per drone
    min_separation_m: float  # smallest centre distance between two drones at any physics step
    closest: tuple[float, str, str, int] | None  # at the ticks: distance, pair, tick


def world_key(loaded: LoadedScenario) -> str:
    """What the built world depends on (two scenarios with the same key build the same world)."""
    sc = loaded.scenario
    a = sc.agents
    parts = {"map": sc.map.model_dump(), "seed": sc.seed, "traffic": sc.traffic.model_dump(),
             "vehicles": a.vehicles.model_dump(), "rsus": a.rsus.model_dump()}
    return json.dumps(parts, sort_keys=True)


def flight_key(loaded: LoadedScenario) -> str:
    """What a fleet's flight depends on besides the world: scenarios with the same key fly the same."""
    sc = loaded.scenario
    env = sc.environment
    parts = {"world": world_key(loaded), "agents": sc.agents.model_dump(), "wind": [env.wind_mps, env.gust_mps],
             "ticks": [sc.tick_hz, sc.n_ticks]}
    return json.dumps(parts, sort_keys=True)


def connected_traffic(loaded: LoadedScenario, world: World, workdir: Path, n_ticks: int) -> list[list[VehicleState]]:
    """The connected vehicles' states at ticks 0 .. n_ticks - 1 from real SUMO (libsumo, this process)."""
    from cosim.traffic.sumo_sim import TrafficSim

    sc = loaded.scenario
    sim = TrafficSim(sc, world, workdir)
    try:
        return [[v for v in sim.step_to(k * sc.tick_ns, pedestrians=False) if v.agent_id] for k in range(n_ticks)]
    finally:
        sim.close()


def fly(loaded: LoadedScenario, world: World, vehicles: list[list[VehicleState]]) -> FleetFlight:
    """Fly the scenario's fleet for ``len(vehicles)`` ticks; escorts get their vehicle one tick late."""
    sc = loaded.scenario
    escorts = {f"drone_{i}": d.target for i, d in enumerate(sc.agents.drones) if isinstance(d, EscortDrone)}
    fleet = DroneFleet(sc, world)
    states: list[list[DroneState]] = []
    closest = None
    try:
        for k in range(len(vehicles)):
            ticks_ago = vehicles[max(k - 1, 0)]
            states.append(fleet.step_to(k * sc.tick_ns, k, escort_targets_of(ticks_ago, escorts)))
            pos = np.array([s.position_m for s in states[-1]])
            for i in range(len(pos)):
                for j in range(i + 1, len(pos)):
                    d = float(np.linalg.norm(pos[i] - pos[j]))
                    if closest is None or d < closest[0]:
                        closest = (round(d, 2), states[-1][i].agent_id, states[-1][j].agent_id, k)
        return FleetFlight(states, fleet.min_separation_m, closest)
    finally:
        fleet.close()


def lane_distance_m(points_xy: np.ndarray, net_xml: bytes) -> np.ndarray:
    """(N,) horizontal distance [m] from each point (N, 2) to the nearest centre line of a drivable lane."""
    net = read_sumolib(net_xml)
    shapes = [np.array(ln.getShape())[:, :2] for e in net.getEdges() if e.getFunction() != "internal"
              for ln in e.getLanes() if ln.allows("passenger")]
    a = np.concatenate([s[:-1] for s in shapes])
    b = np.concatenate([s[1:] for s in shapes])
    ab = b - a
    len2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    out = np.empty(len(points_xy))
    for k, p in enumerate(np.asarray(points_xy, dtype=np.float64)):
        u = np.clip(np.einsum("ij,ij->i", p - a, ab) / len2, 0.0, 1.0)
        q = a + u[:, None] * ab - p
        out[k] = float(np.sqrt(np.min(np.einsum("ij,ij->i", q, q))))
    return out


class Survey:
    """Builds worlds and runs traffic once per distinct world; flies any number of scenarios over them."""

    def __init__(self, workdir: Path):
        self.workdir = Path(workdir)
        self._worlds: dict[str, tuple[World, list[list[VehicleState]]]] = {}
        self._flights: dict[str, dict[str, Any]] = {}

    def world_and_traffic(self, loaded: LoadedScenario) -> tuple[World, list[list[VehicleState]]]:
        from cosim.world.build import build_world

        key = world_key(loaded)
        n = loaded.scenario.n_ticks
        if key not in self._worlds or len(self._worlds[key][1]) < n:
            sub = self.workdir / f"w{len(self._worlds)}"
            world = self._worlds[key][0] if key in self._worlds else build_world(loaded, sub / "world")
            needs = any(isinstance(d, EscortDrone) for d in loaded.scenario.agents.drones)
            vehicles = connected_traffic(loaded, world, sub / "sumo", n) if needs else [[] for _ in range(n)]
            self._worlds[key] = (world, vehicles)
        world, vehicles = self._worlds[key]
        return world, vehicles[:n]

    def measure(self, loaded: LoadedScenario) -> dict[str, Any]:
        """Separation and patrol lane distances of one scenario (a flight already measured for a scenario
        with the same :func:`flight_key`, weather or lighting aside, is not flown again)."""
        key = flight_key(loaded)
        if key not in self._flights:
            self._flights[key] = self._measure(loaded)
        return {"scenario": loaded.scenario.name, **self._flights[key]}

    def _measure(self, loaded: LoadedScenario) -> dict[str, Any]:
        world, vehicles = self.world_and_traffic(loaded)
        flight = fly(loaded, world, vehicles)
        patrol: dict[str, float] = {}
        for i, d in enumerate(loaded.scenario.agents.drones):
            if d.strategy == "patrol":
                xy = np.array([tick[i].position_m[:2] for tick in flight.states])
                patrol[f"drone_{i}"] = round(float(np.median(lane_distance_m(xy, world.net_xml))), 2)
        return {
            "map": loaded.scenario.map.kind,
            "separation_m": loaded.scenario.agents.drone_separation_m,
            "min_distance_m": round(flight.min_separation_m, 2),
            "closest_at_ticks": flight.closest,
            "start_z_m": [round(s.position_m[2], 1) for s in flight.states[0]],
            "patrol_median_lane_distance_m": patrol,
        }


def shipped_scenarios() -> list[Path]:
    return sorted(SCENARIOS_DIR.glob("*.yaml"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenarios", nargs="*", help="scenario files or shipped names (default: every shipped one)")
    ap.add_argument("--duration", type=float, default=60.0, help="flight time [s]")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, as in cosim run")
    args = ap.parse_args(argv)
    paths = [Path(s) if s.endswith(".yaml") else SCENARIOS_DIR / f"{s}.yaml" for s in args.scenarios]
    with tempfile.TemporaryDirectory(prefix="cosim-survey-") as tmp:
        survey = Survey(Path(tmp))
        for path in paths or shipped_scenarios():
            loaded = load_scenario(path, [f"duration_s={args.duration:g}", "sensors.enabled=false", *args.set])
            print(json.dumps(survey.measure(loaded)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
