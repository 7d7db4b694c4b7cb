"""Pictures of a world from above: static layout, RSU sites and a tick of vehicles.

``python -m benchmarks.world_plot OUT.png --kind urban [--seed 0] [--size 400] [--t 20]`` builds the world,
runs the traffic to ``t`` seconds and draws it (used for docs/img/map_<kind>.png).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection
from matplotlib.patches import Polygon

from cosim.classes import SEMANTIC_COLOURS
from cosim.protocol import VehicleState
from cosim.world.types import World

#: Draw order (later on top) and the height that separates low from tall vegetation.
ORDER = (
    "terrain",
    "vegetation_low",
    "road",
    "sidewalk",
    "lane_marking",
    "building",
    "vegetation",
    "pole",
    "street_light",
    "rsu",
)
COLOURS = {
    **{k: tuple(c / 255 for c in v) for k, v in SEMANTIC_COLOURS.items()},
    "terrain": (0.80, 0.86, 0.70),
    "vegetation_low": (0.72, 0.80, 0.45),
    "road": (0.35, 0.35, 0.38),
    "sidewalk": (0.78, 0.74, 0.72),
    "vegetation": (0.25, 0.50, 0.20),
}


def draw_world(world: World, vehicles: list[VehicleState], path: Path, title: str = "", dpi: int = 110,
               overlay: Callable[[Axes], None] | None = None) -> None:
    """Write a top view of ``world`` with ``vehicles`` to ``path`` (PNG); ``overlay`` draws more on the axes."""
    from cosim.traffic.metrics import bev_corners

    xmin, ymin, xmax, ymax = world.bounds_m
    span = max(xmax - xmin, ymax - ymin)
    fig, ax = plt.subplots(figsize=(8, 8 * (ymax - ymin) / (xmax - xmin) + 0.3))
    groups: dict[str, list] = {k: [] for k in ORDER}
    heights: list[float] = []
    for p in world.layout.prisms:
        key = p.cls
        if p.cls == "vegetation" and p.z1_m < 1.5:
            key = "vegetation_low"
        groups.setdefault(key, []).append(p.footprint)
        if key == "building":
            heights.append(p.z1_m)
    for key in ORDER:
        polys = groups.get(key, [])
        if not polys:
            continue
        if key == "building":
            top = max(heights)
            shade = [(0.55 - 0.35 * h / top,) * 3 for h in heights]
            ax.add_collection(PolyCollection(polys, facecolors=shade, edgecolors=(0.1, 0.1, 0.1), linewidths=0.3))
        else:
            ax.add_collection(PolyCollection(polys, facecolors=COLOURS.get(key, (1, 0, 1)), edgecolors="none"))
    for r in world.rsus:
        ax.plot(r.position_m[0], r.position_m[1], marker="^", color="gold", markeredgecolor="k", markersize=9)
        ax.annotate(r.agent_id, r.position_m[:2], xytext=(4, 4), textcoords="offset points", fontsize=7)
    for s in vehicles:
        colour = tuple(c / 255 for c in SEMANTIC_COLOURS[s.cls])
        edge = "red" if s.agent_id else "white"
        ax.add_patch(
            Polygon(
                bev_corners(s),
                closed=True,
                facecolor=colour,
                edgecolor=edge,
                linewidth=1.2 if s.agent_id else 0.3,
            )
        )
        if s.agent_id:
            ax.annotate(
                s.agent_id,
                s.center_m[:2],
                xytext=(4, -8),
                textcoords="offset points",
                fontsize=7,
                color="red",
            )
    if overlay is not None:
        overlay(ax)
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(title or f"{world.map_kind}: {len(vehicles)} vehicles, {len(world.rsus)} RSUs ({span:.0f} m)")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    from cosim.scenario import load_scenario_data
    from cosim.traffic import TrafficSim
    from cosim.world import build_world

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("out", type=Path)
    ap.add_argument("--kind", default="urban")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=float, default=400.0)
    ap.add_argument("--t", type=float, default=20.0, help="episode time of the vehicles drawn [s]")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    loaded = load_scenario_data(
        {
            "name": f"map_{args.kind}",
            "seed": args.seed,
            "duration_s": max(args.t, 1.0),
            "map": {"kind": args.kind, "size_m": args.size},
        }
    )
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(loaded, Path(tmp))
        sim = TrafficSim(loaded.scenario, world, Path(tmp) / "sumo")
        try:
            states = sim.step_to(round(args.t * 1e9 / loaded.scenario.tick_ns) * loaded.scenario.tick_ns)
        finally:
            sim.close()
    draw_world(world, states, args.out, title=f"{args.kind} (seed {args.seed}, t = {args.t:g} s)")


if __name__ == "__main__":
    main()
