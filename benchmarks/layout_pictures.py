"""Pictures of the two agent layouts (docs/evaluation.md, "Collaboration"): one shipped scenario's world from
above with ``agents.layout: spread`` and ``cooperative``, the connected vehicles at episode t = 0, the RSUs,
the hover points and patrol loops the drones fly, and the group's junctions.

    nice -n 10 .venv/bin/python -m benchmarks.layout_pictures docs/img [--scenario town_urban_day_clear]

writes ``layout_spread.png`` and ``layout_cooperative.png`` into the folder (about 10 s on 2 cores).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.world_plot import draw_world
from cosim.drones.routes import hover_point, lane_paths, patrol_loop, road_graph
from cosim.scenario import load_scenario
from cosim.scenario.model import HoverDrone, PatrolDrone


def picture(scenario: str, layout: str, out: Path) -> Path:
    from cosim.traffic import TrafficSim
    from cosim.world import build_world

    loaded = load_scenario(scenario, [f"agents.layout={layout}"])
    sc = loaded.scenario
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(loaded, Path(tmp))
        sim = TrafficSim(sc, world, Path(tmp) / "sumo")
        try:
            states = sim.step_to(0)
        finally:
            sim.close()
    roads, lanes, taken = road_graph(world.net_xml), lane_paths(world.net_xml), set()
    hovers, loops = [], []
    counts = {"hover": 0, "patrol": 0}
    for d in sc.agents.drones:
        if isinstance(d, HoverDrone):
            hovers.append(np.array(d.point) if d.point is not None else hover_point(world, counts["hover"]))
            counts["hover"] += 1
        elif isinstance(d, PatrolDrone):
            loops.append(np.array(d.waypoints)[:, :2] if d.waypoints is not None else
                         patrol_loop(world, counts["patrol"], d.loop_length_m, roads, taken, lanes))
            counts["patrol"] += 1
    pos = {j.junction_id: j.position_m for j in world.junctions}
    group = np.array([pos[j] for j in world.group_junctions if j in pos][:6])

    def overlay(ax) -> None:
        if len(group):
            ax.plot(group[:, 0], group[:, 1], "o", mfc="none", mec="orange", ms=16, mew=2,
                    label="group's junctions (first 6)")
        for k, loop in enumerate(loops):
            xy = np.vstack([loop, loop[:1]])
            ax.plot(xy[:, 0], xy[:, 1], "-", color="deepskyblue", lw=2, label="patrol loop" if k == 0 else None)
        for k, p in enumerate(hovers):
            ax.plot(p[0], p[1], "*", color="magenta", mec="k", ms=16, label="hover point" if k == 0 else None)
        ax.plot([], [], "^", color="gold", mec="k", label="RSU")
        ax.plot([], [], "s", mfc="none", mec="red", label="connected vehicle")
        ax.legend(loc="lower left", fontsize=8, framealpha=0.9)

    path = out / f"layout_{layout}.png"
    draw_world(world, states, path, overlay=overlay,
               title=f"{sc.name}, agents.layout: {layout} (t = 0)", dpi=80)
    return path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("out", type=Path)
    ap.add_argument("--scenario", default="town_urban_day_clear")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    for layout in ("spread", "cooperative"):
        print(picture(args.scenario, layout, args.out))


if __name__ == "__main__":
    main()
