"""Measure a traffic episode against the physical acceptance checks, without the conductor.

``python -m benchmarks.traffic_acceptance [--kinds urban suburban rural highway] [--seed 0] [--duration 60]``
builds each world, runs :class:`~cosim.traffic.TrafficSim` tick by tick and prints one JSON line per
kind: classes seen, share of box centres on the road surface, worst bird's-eye overlap, connected
vehicles missing, RSU distances to their junctions, class shares (of the vehicles seen and of the
boxes over all ticks), vehicles entering and leaving per minute, vehicles on the road (first, least,
most), teleports and collisions.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from cosim.scenario.loader import LoadedScenario
from cosim.traffic.metrics import max_pairwise_overlap


def episode_metrics(loaded: LoadedScenario, workdir: Path) -> dict[str, Any]:
    """Run ``loaded`` for its whole duration and measure every tick (see the module docstring)."""
    from cosim.traffic.sumo_sim import TrafficSim
    from cosim.world import build_world
    from cosim.world.layout import road_raster
    from cosim.world.network import read_network

    sc = loaded.scenario
    world = build_world(loaded, workdir / "world")
    road = road_raster(read_network(world.net_xml), world.bounds_m, 0.25)
    connected = {f"vehicle_{i}" for i in range(sc.agents.vehicles.count)}
    on = total = missing = 0
    worst, worst_at = 0.0, None
    vehicles: dict[str, str] = {}
    boxes: Counter[str] = Counter()
    on_road: list[int] = []
    sim = TrafficSim(sc, world, workdir / "sumo")
    try:
        for k in range(sc.n_ticks):
            states = sim.step_to(k * sc.tick_ns)
            pts = np.array([s.center_m[:2] for s in states]).reshape(-1, 2)
            on += int(road.lookup(pts).sum())
            total += len(pts)
            overlap, pair = max_pairwise_overlap(states)
            if overlap > worst:
                worst, worst_at = overlap, {"tick": k, "pair": list(pair or ())}
            missing += len(connected - {s.sumo_id for s in states})
            vehicles.update({s.sumo_id: s.cls for s in states})
            boxes.update(s.cls for s in states)
            on_road.append(len(states))
            if k == 0:
                entered0, left0 = sim.entered, sim.left
        teleports, collisions = sim.teleports, sim.collisions
        minutes = (sc.n_ticks - 1) * sc.tick_ns / 60e9
        entered, left = sim.entered - entered0, sim.left - left0
    finally:
        sim.close()
    junctions = {j.junction_id: j.position_m for j in world.junctions}
    counts = Counter(vehicles.values())
    return {
        "kind": sc.map.kind,
        "seed": sc.seed,
        "ticks": sc.n_ticks,
        "vehicles": len(vehicles),
        "classes_missing": sorted(c for c, share in sc.traffic.mix.items() if share > 0 and c not in counts),
        "on_road": on / max(total, 1),
        "worst_overlap_m2": worst,
        "worst_overlap_at": worst_at,
        "connected_missing_ticks": missing,
        "rsu_junction_dist_m": [round(math.dist(r.position_m[:2], junctions[r.junction_id]), 2) for r in world.rsus],
        "class_share": {c: round(counts[c] / max(len(vehicles), 1), 3) for c in sorted(sc.traffic.mix)},
        "class_share_of_boxes": {c: round(boxes[c] / max(sum(boxes.values()), 1), 3) for c in sorted(sc.traffic.mix)},
        "class_share_wanted": {c: round(v, 3) for c, v in sorted(sc.traffic.mix.items())},
        "entered_per_min": round(entered / max(minutes, 1e-9), 1),
        "left_per_min": round(left / max(minutes, 1e-9), 1),
        "on_road_first_min_max": [on_road[0], min(on_road), max(on_road)],
        "teleports": teleports,
        "collisions": collisions,
    }


def main(argv: list[str] | None = None) -> None:
    from cosim.scenario import load_scenario_data

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", nargs="+", default=["urban", "suburban", "rural", "highway"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=60.0, help="episode length [s]")
    ap.add_argument("--size", type=float, default=400.0, help="map.size_m")
    ap.add_argument("--density", type=float, default=None, help="traffic.density_veh_per_km")
    args = ap.parse_args(argv)
    for kind in args.kinds:
        data: dict[str, Any] = {
            "name": f"accept_{kind}",
            "seed": args.seed,
            "duration_s": args.duration,
            "map": {"kind": kind, "size_m": args.size},
        }
        if args.density is not None:
            data["traffic"] = {"density_veh_per_km": args.density}
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(episode_metrics(load_scenario_data(data), Path(tmp))))


if __name__ == "__main__":
    main()
