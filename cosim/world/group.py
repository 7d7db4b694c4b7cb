"""The cooperative layout's group (``agents.layout: cooperative``): the connected vehicles depart together
on one shared route, so that they stay in each other's range for the episode.

One route (:func:`plan_group`) is drawn through the inner edges of the connected class's strongly connected
core, long enough that the group does not reach its end within the episode (warm-up included, at 1.2 times
the fastest speed limit of those edges: SUMO's drivers go up to about 20 % over the limit), so the traffic
adapter never extends it (extensions are drawn per vehicle and would split the group). The vehicles stand
one behind the other along its first edges, :data:`GAP_M` apart along the road, each on the suffix of the
route from its own edge; vehicle_0 leads the queue (events placed ``ahead_of: vehicle_0`` find open road,
the collaborators follow it). RSUs stand at the junctions the route
passes (:func:`route_junctions`), drones hover and patrol over them (cosim/drones/routes.py).

A map with no inner road long enough for that, or where the vehicles cannot be placed within
:data:`NEAR_M` of each other, is an input error: the group is never silently spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import sumolib

from cosim.errors import InputError
from cosim.scenario.model import Scenario
from cosim.world.routes import (
    END_CLEARANCE_M,
    MIN_LANE_M,
    PlannedVehicle,
    inner_edges,
    random_route,
    strong_core,
)
from cosim.world.vtypes import SUMO_VCLASS, variants

GAP_M = (25.0, 40.0)  # [m] along-road gap between one group member's front bumper and the next one's
NEAR_M = (20.0, 100.0)  # [m] each member departs within this straight-line distance of another member
SPEED_MARGIN = 1.2  # drivers' speed factor bound (SUMO's default speedFactor deviation is 0.1)
WARMUP_S = 4.0  # [s] SUMO time before episode t = 0 (cosim/traffic/sumo_sim.py: WARMUP_S)
TRIES = 40  # start edges tried before the map is declared too small for the group


@dataclass(frozen=True)
class GroupPlan:
    route: tuple[str, ...]  # edge ids of the shared route
    members: tuple[PlannedVehicle, ...]  # vehicle_0.. in id order
    junctions: tuple[str, ...]  # junction ids the route passes, in the order the group meets them


def route_junctions(net: sumolib.net.Net, route: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Junction ids at the ends of ``route``'s edges, first occurrence, in route order (the start
    edge's own start junction is behind the group and left out)."""
    out: list[str] = []
    for eid in route:
        j = net.getEdge(eid).getToNode().getID()
        if j not in out:
            out.append(j)
    return tuple(out)


def _slots(net: sumolib.net.Net, route: list[str]) -> list[tuple[float, str, float]]:
    """Per route edge: (route distance of the edge's start [m], edge id, edge length [m])."""
    out, s = [], 0.0
    for eid in route:
        e = net.getEdge(eid)
        out.append((s, eid, e.getLength()))
        s += e.getLength()
    return out


def _place_members(
    net: sumolib.net.Net, route: list[str], scenario: Scenario, rng: np.random.Generator
) -> list[PlannedVehicle] | None:
    """The group along ``route`` from its start, or None when a member finds no place within reach."""
    cls = scenario.agents.vehicles.vclass
    vclass = SUMO_VCLASS[cls]
    n = scenario.agents.vehicles.count
    of_class = variants()[cls]
    picked = [of_class[int(rng.integers(len(of_class)))] for _ in range(n)]
    slots = _slots(net, route)
    placed: list[tuple[int, str, int, float, np.ndarray]] = []  # route index, lane id, lane index, pos, xy
    s_next = 0.0
    for k in range(n):
        v = picked[k]
        found = None
        for idx, (s0, eid, length) in enumerate(slots):
            lo, hi = v.length_m + 2.0, length - END_CLEARANCE_M
            if hi <= lo or s0 + hi < s_next or length < MIN_LANE_M:
                continue
            pos = max(lo, s_next - s0)
            lanes = [ln for ln in net.getEdge(eid).getLanes() if ln.allows(vclass)]
            if not lanes:
                continue
            ln = lanes[int(rng.integers(len(lanes)))]
            pos = min(pos, ln.getLength() - END_CLEARANCE_M)
            if pos < lo:
                continue
            x, y = sumolib.geomhelper.positionAtShapeOffset(ln.getShape(), pos)
            found = (idx, ln.getID(), ln.getIndex(), pos, np.array([x, y]))
            break
        if found is None:
            return None
        if placed and not NEAR_M[0] <= min(float(np.linalg.norm(found[4] - p[4])) for p in placed) <= NEAR_M[1]:
            return None
        placed.append(found)
        s_next = slots[found[0]][0] + found[3] + float(rng.uniform(*GAP_M))
    # the first one placed is the last in the queue: vehicle_0 is the last placed, at the front
    members = [
        PlannedVehicle(f"vehicle_{n - 1 - k}", picked[k], lane_id, lane_index, round(pos, 2), tuple(route[idx:]))
        for k, (idx, lane_id, lane_index, pos, _xy) in enumerate(placed)
    ]
    return members[::-1]


def plan_group(net: sumolib.net.Net, scenario: Scenario, rng: np.random.Generator) -> GroupPlan | None:
    """The connected vehicles as one group on a shared route; None without connected vehicles.

    Raises :class:`InputError` when the map cannot hold the group (see the module doc)."""
    n = scenario.agents.vehicles.count
    if n == 0:
        return None
    cls = scenario.agents.vehicles.vclass
    vclass = SUMO_VCLASS[cls]
    core = strong_core(net, vclass)
    inner = [e for e in inner_edges(net, core) if net.getEdge(e).getLength() >= MIN_LANE_M] if core else []
    if not inner:
        raise InputError(f"agents.layout cooperative: the map has no inner road where a group of {n} connected "
                         f"vehicles of class {cls!r} can depart; use agents.layout: spread or a larger map")
    vmax = max(net.getEdge(e).getSpeed() for e in inner)
    need_m = (WARMUP_S + scenario.duration_s) * vmax * SPEED_MARGIN + n * NEAR_M[1]
    weights = np.array([net.getEdge(e).getLength() for e in inner])
    weights /= weights.sum()
    for _attempt in range(TRIES):
        start = inner[int(rng.choice(len(inner), p=weights))]
        route = [start]
        length = net.getEdge(start).getLength()
        for _leg in range(200):
            if length >= need_m:
                break
            more = random_route(net, route[-1], inner, vclass, rng)[1:]
            if not more:
                break
            route += more
            length += sum(net.getEdge(e).getLength() for e in more)
        if length < need_m:
            continue
        members = _place_members(net, route, scenario, rng)
        if members is not None:
            return GroupPlan(tuple(route), tuple(members), route_junctions(net, route))
    raise InputError(
        f"agents.layout cooperative: no place on the map holds a group of {n} connected vehicles "
        f"(each within {NEAR_M[0]:.0f}-{NEAR_M[1]:.0f} m of another on one route of {math.ceil(need_m)} m); "
        f"use agents.layout: spread, fewer vehicles or a larger map"
    )
