"""Parked vehicles: placed beside the kerbs, overlapping nothing (BEV polygons), labelled with `parked`."""

from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from cosim.scenario import load_scenario_data
from cosim.traffic.metrics import convex_overlap_area
from cosim.world.geom import rect

VEHICLE_CLASSES = {"car", "van", "truck", "bus", "motorcycle", "bicycle"}


def _box(p) -> np.ndarray:
    return rect(p.center_m[0], p.center_m[1], p.size_m[0], p.size_m[1], p.yaw_rad)


def _samples(p, step_m: float = 0.1) -> np.ndarray:
    """Points covering a parked box (grid and border) in map x, y."""
    length, w = p.size_m[0], p.size_m[1]
    u, v = np.meshgrid(np.linspace(-length / 2, length / 2, max(2, math.ceil(length / step_m) + 1)),
                       np.linspace(-w / 2, w / 2, max(2, math.ceil(w / step_m) + 1)))
    c, s = math.cos(p.yaw_rad), math.sin(p.yaw_rad)
    return np.stack([p.center_m[0] + c * u.ravel() - s * v.ravel(), p.center_m[1] + s * u.ravel() + c * v.ravel()], 1)


@pytest.fixture(scope="module", params=["urban", "suburban"])
def world(request, tmp_path_factory):
    from cosim.world import build_world

    loaded = load_scenario_data({"name": "p", "seed": 3, "map": {"kind": request.param, "size_m": 300},
                                 "parked": {"density_veh_per_km": 40}})
    return loaded, build_world(loaded, tmp_path_factory.mktemp("parked"))


@pytest.mark.integration
def test_parked_vehicles_overlap_nothing(world):
    from cosim.world.layout import road_polygons
    from cosim.world.network import read_network

    _, w = world
    parked = w.parked
    assert len(parked) >= 5, len(parked)  # not vacuous (the verges of suburban streets hold trees and hedges)
    assert {p.cls for p in parked} <= VEHICLE_CLASSES and len({p.cls for p in parked}) >= 3
    boxes = [_box(p) for p in parked]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            assert convex_overlap_area(boxes[i], boxes[j]) == 0.0, (parked[i].parked_id, parked[j].parked_id)
    solid = [np.array(pr.footprint) for pr in w.layout.prisms if pr.cls in ("sidewalk", "building", "pole", "rsu",
                                                                             "vegetation", "street_light")]
    solid += road_polygons(read_network(w.net_xml))
    paths = [MplPath(poly) for poly in solid]
    for p in parked:
        pts = _samples(p)
        for path, poly in zip(paths, solid, strict=True):
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            if (pts.max(axis=0) < lo).any() or (pts.min(axis=0) > hi).any():
                continue
            assert not path.contains_points(pts).any(), f"{p.parked_id} overlaps a {len(poly)}-gon at {lo}"


@pytest.mark.integration
def test_parked_placement_is_deterministic_and_off_by_default(world):
    """Placement again on the same layout with the same random stream gives the same vehicles; density 0
    (the default) places none. Parking has its own stream, so it never changes the layout."""
    from cosim.scenario.model import ParkedSpec, Scenario
    from cosim.world.build import STAGE_PARKED, stage_rng
    from cosim.world.network import read_network
    from cosim.world.parking import place_parked

    loaded, w = world
    sc = loaded.scenario
    net = read_network(w.net_xml)
    again = place_parked(net, list(w.layout.prisms), w.bounds_m, sc.parked, sc.traffic.mix,
                         stage_rng(sc.seed, STAGE_PARKED))
    assert tuple(again) == w.parked
    assert Scenario(name="x").parked == ParkedSpec() and ParkedSpec().density_veh_per_km == 0
    assert place_parked(net, list(w.layout.prisms), w.bounds_m, ParkedSpec(), sc.traffic.mix,
                        stage_rng(sc.seed, STAGE_PARKED)) == []
