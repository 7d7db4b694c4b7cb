"""Parked vehicles: standing boxes of the six vehicle classes beside the kerbs, off every driving lane.

A parked vehicle stands just outside an edge's sidewalk (or its road border where it has none),
parallel to the road, in a verge, lay-by or driveway; slots come one after another along each road
edge, and a candidate is kept only where its box (grown by ``CLEAR_M``) covers no road, sidewalk,
building, tree, pole, RSU or other parked vehicle on the layout's occupancy grid. Deterministic from
the scenario seed (its own random stream). SUMO never sees them: they are off its lanes.
"""

from __future__ import annotations

import math

import numpy as np

from cosim.scenario.model import ParkedSpec
from cosim.world import geom
from cosim.world.geom import Occupancy
from cosim.world.layout import CELL_M, GROUND_Z, _outer_right
from cosim.world.network import RoadNetwork
from cosim.world.types import ParkedVehicle, Prism
from cosim.world.vtypes import variants

KERB_GAP_M = 0.4  # [m] between the sidewalk's (or road's) outer border and the parked box
CLEAR_M = 0.3  # [m] kept free around every parked box
SLOT_GAP_M = 1.0  # [m] between consecutive slots along a kerb
MEAN_SLOT_M = 6.5  # [m] mean slot length (a car and its gap): slots per km of kerb = 1000 / MEAN_SLOT_M


def place_parked(
    net: RoadNetwork,
    prisms: list[Prism],
    bounds_m: tuple[float, float, float, float],
    spec: ParkedSpec,
    mix: dict[str, float],
    rng: np.random.Generator,
) -> list[ParkedVehicle]:
    """Parked vehicles at ``spec.density_veh_per_km`` of road edge (as many as fit), classes drawn by ``mix``."""
    if spec.density_veh_per_km <= 0:
        return []
    occupied = Occupancy(bounds_m, CELL_M)
    for p in prisms:
        if p.cls not in ("terrain", "lane_marking"):
            occupied.add(np.array(p.footprint))
    classes = sorted(mix)
    shares = np.array([mix[c] for c in classes], float)
    shares /= shares.sum()
    xmin, ymin, xmax, ymax = bounds_m
    out: list[ParkedVehicle] = []
    p_keep = min(1.0, spec.density_veh_per_km * MEAN_SLOT_M / 1000.0)  # slot by slot, for the density asked
    for edge in sorted(net.road_edges(), key=lambda e: e.edge_id):
        kerb = _outer_right(edge)
        length = geom.polyline_length(kerb)
        s = float(rng.uniform(2.0, 6.0))
        while s < length - 2.0:
            cls = classes[int(rng.choice(len(classes), p=shares))]
            of_class = variants()[cls]
            v = of_class[int(rng.integers(len(of_class)))]
            keep = rng.random() < p_keep
            mid = s + v.length_m / 2
            if mid + v.length_m / 2 > length - 2.0:
                break
            if keep:
                p = geom.point_at(kerb, mid)
                yaw = geom.direction_at(kerb, mid)
                off = KERB_GAP_M + v.width_m / 2  # to the right of the kerb line
                cx, cy = p[0] + off * math.sin(yaw), p[1] - off * math.cos(yaw)
                grown = geom.rect(cx, cy, v.length_m + 2 * CLEAR_M, v.width_m + 2 * CLEAR_M, yaw)
                inside = (grown[:, 0].min() > xmin and grown[:, 0].max() < xmax and grown[:, 1].min() > ymin
                          and grown[:, 1].max() < ymax)
                if inside and occupied.free(grown):
                    occupied.add(grown)
                    centre = (round(float(cx), 3), round(float(cy), 3), round(GROUND_Z + v.height_m / 2, 3))
                    out.append(ParkedVehicle(f"parked_{len(out):04d}", cls, v.type_id, centre,
                                             (v.length_m, v.width_m, v.height_m), round(float(yaw), 6)))
            s += v.length_m + SLOT_GAP_M
    return out
