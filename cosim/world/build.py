"""build_world: scenario -> World (network, routes, static layout, RSU sites, geo origin).

Deterministic: every stage draws from its own generator seeded by (scenario seed, stage), so a
change in one stage (say, more trees) does not move the vehicles.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cosim.preflight import map_file
from cosim.world import geom
from cosim.world.clutter import place_clutter
from cosim.world.group import plan_group
from cosim.world.layout import GROUND_Z, build_layout, prism
from cosim.world.netgen import MapRequest, NetworkResult, generate_network
from cosim.world.network import read_network
from cosim.world.parking import place_parked
from cosim.world.routes import plan_vehicles, read_sumolib, routes_xml
from cosim.world.rsu import place_rsus
from cosim.world.signals import plan_signals
from cosim.world.types import Junction, StaticLayout, World

if TYPE_CHECKING:
    from cosim.scenario.loader import LoadedScenario

log = logging.getLogger(__name__)

STAGE_NET, STAGE_LAYOUT, STAGE_RSU, STAGE_ROUTES, STAGE_PARKED, STAGE_SIGNALS, STAGE_GROUP = 1, 2, 3, 4, 5, 6, 7
STAGE_CLUTTER = 8
MARGIN_M = {"urban": 30.0, "suburban": 30.0}  # [m] scenery beyond the outermost road; others 20
RSU_POLE_M = 0.35  # [m] side of an RSU pole


def stage_rng(seed: int, stage: int) -> np.random.Generator:
    return np.random.default_rng([seed, stage])


def build_world(loaded: LoadedScenario, workdir: Path) -> World:
    """Build the episode's world; map files (kind net/osm) are resolved against the scenario folder."""
    sc = loaded.scenario
    spec = sc.map
    file = map_file(loaded)
    workdir = Path(workdir) / "map"
    result = generate_network(
        MapRequest(spec.kind, spec.size_m, spec.lanes, file, workdir, sc.pedestrians.density_per_km > 0),
        stage_rng(sc.seed, STAGE_NET),
    )
    result = NetworkResult(plan_signals(result.net_xml, sc.traffic.signals, stage_rng(sc.seed, STAGE_SIGNALS)),
                           result.buildings)
    net = read_network(result.net_xml, f"map.file {file}" if file is not None else f"the generated {spec.kind} network")
    margin = MARGIN_M.get(spec.kind, 20.0)
    xmin, ymin, xmax, ymax = net.bounds_m
    if spec.kind not in ("net", "osm"):  # the generated square, even where no road reaches its edge
        xmin, ymin, xmax, ymax = min(xmin, 0.0), min(ymin, 0.0), max(xmax, spec.size_m), max(ymax, spec.size_m)
    bounds = (
        round(xmin - margin, 3),
        round(ymin - margin, 3),
        round(xmax + margin, 3),
        round(ymax + margin, 3),
    )

    prisms, road = build_layout(net, spec.kind, bounds, stage_rng(sc.seed, STAGE_LAYOUT), result.buildings)
    junctions = net.real_junctions() or [j for j in net.junctions.values() if j.kind != "internal"]
    junctions = sorted(junctions, key=lambda j: j.junction_id)
    centre = (0.5 * (xmin + xmax), 0.5 * (ymin + ymax))
    degree: dict[str, int] = {}
    lanes_in: dict[str, int] = {}
    for e in net.road_edges():
        degree[e.to_node] = degree.get(e.to_node, 0) + 1
        lanes_in[e.to_node] = lanes_in.get(e.to_node, 0) + sum(ln.is_road for ln in e.lanes)
    sumo_net = read_sumolib(result.net_xml)
    group = plan_group(sumo_net, sc, stage_rng(sc.seed, STAGE_GROUP)) if sc.agents.layout == "cooperative" else None
    rsus = place_rsus(
        junctions, degree, sc.agents.rsus.count, sc.agents.rsus.height_m, road, centre, stage_rng(sc.seed, STAGE_RSU),
        lanes_in, group.junctions if group is not None else (),
    )
    next_id = max((p.instance_id for p in prisms), default=999_999) + 1
    for k, r in enumerate(rsus):
        foot = geom.rect(r.position_m[0], r.position_m[1], RSU_POLE_M, RSU_POLE_M, r.yaw_rad)
        prisms.append(prism("rsu", foot, GROUND_Z, r.height_m, next_id + k))
    # roadside clutter (map.clutter, cosim/world/clutter.py), before the parked vehicles, which keep clear of it
    prisms += place_clutter(net, prisms, bounds, spec.clutter, stage_rng(sc.seed, STAGE_CLUTTER),
                            next_id + len(rsus))

    parked = place_parked(net, prisms, bounds, sc.parked, sc.traffic.mix, stage_rng(sc.seed, STAGE_PARKED))
    planned = plan_vehicles(sumo_net, sc, net.road_length_km(), stage_rng(sc.seed, STAGE_ROUTES),
                            group.members if group is not None else None)
    geo = (sc.geo_origin.lat_deg, sc.geo_origin.lon_deg, sc.geo_origin.alt_m)
    if spec.kind in ("net", "osm") and net.geo_origin is not None:
        geo = (net.geo_origin[0], net.geo_origin[1], sc.geo_origin.alt_m)
    log.info(
        "world %s: %.2f km of road, %d junctions, %d prisms, %d vehicles, %d RSUs",
        spec.kind,
        net.road_length_km(),
        len(junctions),
        len(prisms),
        len(planned),
        len(rsus),
    )
    return World(
        map_kind=spec.kind,
        net_xml=result.net_xml,
        routes_xml=routes_xml(planned),
        bounds_m=bounds,
        junctions=tuple(
            Junction(j.junction_id, (round(j.position_m[0], 3), round(j.position_m[1], 3)), j.kind) for j in junctions
        ),
        rsus=tuple(rsus),
        layout=StaticLayout(tuple(prisms), 0.0),
        geo_origin=geo,
        parked=tuple(parked),
        group_junctions=group.junctions if group is not None else (),
    )
