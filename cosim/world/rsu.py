"""Roadside-unit sites: poles at the corners of busy inner junctions, cameras turned onto the roads.

Junctions on the map's outer ring (:data:`RING_M` of the bounds of all junctions, where the roads of a
generated town run on beyond the map and traffic enters and leaves) see half as many roads and no
buildings' worth of traffic behind them, so RSUs stand at inner junctions first: signalised before
unsignalised, more incoming lanes before fewer, spread over the inner area in farthest-point order from
the junction nearest the centre. The head's yaw turns the rig's four cameras (90 degrees apart) onto the
roads around the pole (:func:`road_yaw`), so that no camera stares at the building beside it.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from cosim.world.geom import Raster
from cosim.world.network import JunctionGeom
from cosim.world.types import RsuSite

log = logging.getLogger(__name__)

RING_M = 30.0  # [m] junctions this close to the bounds of all junctions are on the outer ring
VIEW_M = 40.0  # [m] how far out a camera's view is sampled for road when the head is turned
MAX_OFFSET_M = 20.0  # [m] farthest a pole stands from its junction centre (where the junction allows): the
# corner of two three-lane avenues with sidewalks is about 18 m from the centre
FAR_OFFSET_M = 40.0  # [m] search limit for junctions wider than that
POLE_CLEARANCE_M = 0.6  # [m] pole to road surface


def outer_ring(junctions: list[JunctionGeom]) -> set[str]:
    """Ids of the junctions within :data:`RING_M` of the bounds of all ``junctions``."""
    if not junctions:
        return set()
    xy = np.array([j.position_m for j in junctions])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    near = np.minimum(np.minimum(xy[:, 0] - lo[0], hi[0] - xy[:, 0]), np.minimum(xy[:, 1] - lo[1], hi[1] - xy[:, 1]))
    return {j.junction_id for j, d in zip(junctions, near, strict=True) if d <= RING_M}


def choose_junctions(
    junctions: list[JunctionGeom], degree: dict[str, int], count: int, centre: tuple[float, float],
    lanes_in: dict[str, int] | None = None,
) -> list[JunctionGeom]:
    """``count`` busy junctions spread over the town's inside: inner junctions (not on the
    :func:`outer_ring`) before outer ones, then signalised, then with three or more incoming roads
    (``degree``: incoming road edges per junction id), then more incoming lanes (``lanes_in``) first;
    of the best such group with ``count`` members, farthest-point order from the one nearest ``centre``.
    Repeats junctions when there are fewer than ``count``."""
    if not junctions or count <= 0:
        return []
    ring = outer_ring(junctions)
    lanes_in = lanes_in or {}

    def rank(j: JunctionGeom) -> tuple[int, int]:
        kind = 0 if j.kind == "traffic_light" else 1 if degree.get(j.junction_id, 0) >= 3 else 2
        return int(j.junction_id in ring), kind

    pool = sorted(junctions, key=lambda j: (rank(j), -lanes_in.get(j.junction_id, 0), j.junction_id))
    for level in sorted({rank(j) for j in pool}):
        n = sum(rank(j) <= level for j in pool)
        if n >= count:
            pool = pool[:n]
            break
    pts = np.array([j.position_m for j in pool])
    first = int(np.argmin(np.linalg.norm(pts - np.array(centre), axis=1)))
    chosen = [first]
    dist = np.linalg.norm(pts - pts[first], axis=1)
    while len(chosen) < min(count, len(pool)):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
    out = [pool[i] for i in chosen]
    k = 0
    while len(out) < count:
        out.append(out[k % len(chosen)])
        k += 1
    return out


def choose_on_route(
    junctions: list[JunctionGeom], degree: dict[str, int], count: int, centre: tuple[float, float],
    route: tuple[str, ...], lanes_in: dict[str, int] | None = None,
) -> list[JunctionGeom]:
    """``count`` junctions for the cooperative layout: of the first ``2 * count`` junctions of ``junctions``
    on the group's ``route`` (junction ids in the order the group meets them), the best by
    :func:`choose_junctions`'s rank (inner, then signalised, then three or more incoming roads), in route
    order; where the route has fewer, the other junctions nearest the route's fill up."""
    if count <= 0:
        return []
    by_id = {j.junction_id: j for j in junctions}
    on = [by_id[i] for i in route if i in by_id][: 2 * count]
    ring = outer_ring(junctions)

    def rank(j: JunctionGeom) -> tuple[int, int]:
        kind = 0 if j.kind == "traffic_light" else 1 if degree.get(j.junction_id, 0) >= 3 else 2
        return int(j.junction_id in ring), kind

    best = sorted(range(len(on)), key=lambda i: (rank(on[i]), i))[:count]
    out = [on[i] for i in sorted(best)]
    if len(out) < count:
        rest = [j for j in junctions if j not in out]
        if not out or not rest:
            return out + choose_junctions(rest or out, degree, count - len(out), centre, lanes_in)
        pts = np.array([j.position_m for j in out])

        def near(j: JunctionGeom) -> tuple[float, tuple[int, int], str]:
            return round(float(np.min(np.linalg.norm(pts - np.array(j.position_m), axis=1))), 3), rank(j), j.junction_id

        out += sorted(rest, key=near)[: count - len(out)]
        k = 0
        while len(out) < count:  # fewer junctions than RSUs: a second pole at a junction, as choose_junctions does
            out.append(out[k])
            k += 1
    return out


def road_yaw(pole_xy: tuple[float, float], road: Raster, fallback: float) -> float:
    """Head yaw [rad] that turns the rig's four cameras (yaw + k 90 degrees) onto the roads around
    ``pole_xy``: of yaws 3 degrees apart, the one whose cameras see the most road surface, sampled in
    each camera's view (5 directions over 80 degrees, 6 to :data:`VIEW_M` m out), counting each
    camera's share by its square root so that every camera gets some road; ties go to the yaw nearest
    ``fallback``."""
    yaws = np.radians(np.arange(0.0, 360.0, 3.0))
    spread = np.radians(np.array([-40.0, -20.0, 0.0, 20.0, 40.0]))
    reach = np.array([6.0, 10.0, 15.0, 20.0, 30.0, VIEW_M])
    best, best_score = fallback, -1.0
    for yaw in sorted(yaws, key=lambda y: abs(math.remainder(y - fallback, 2 * math.pi))):
        score = 0.0
        for k in range(4):
            a = yaw + k * math.pi / 2 + spread
            pts = np.array([(pole_xy[0] + r * math.cos(t), pole_xy[1] + r * math.sin(t)) for t in a for r in reach])
            score += math.sqrt(float(road.lookup(pts).mean()))
        if score > best_score + 1e-9:
            best, best_score = float(yaw), score
    return math.atan2(math.sin(best), math.cos(best))


def _spot(
    j: JunctionGeom, tries: tuple[tuple[Raster, float, float], ...], used: list[tuple[float, float]], phase: float
) -> tuple[float, float] | None:
    """The nearest point around junction ``j`` that is free in a raster of ``tries`` (raster, spacing to
    ``used`` poles [m], reach [m]), scanning rings 0.5 m apart in 16 directions from angle ``phase``."""
    jx, jy = j.position_m
    for clear, spacing, reach in tries:
        for r in np.arange(4.0, reach + 0.01, 0.5):
            for a in phase + np.arange(16) * (math.pi / 8):
                p = (jx + r * math.cos(a), jy + r * math.sin(a))
                if not clear.lookup(np.array([p]))[0] and all(math.dist(p, u) >= spacing for u in used):
                    return p
    return None


def place_rsus(
    junctions: list[JunctionGeom],
    degree: dict[str, int],
    count: int,
    height_range_m: tuple[float, float],
    road: Raster,
    centre: tuple[float, float],
    rng: np.random.Generator,
    lanes_in: dict[str, int] | None = None,
    route: tuple[str, ...] = (),
) -> list[RsuSite]:
    """RSU sites ``rsu_0..``: a pole off the road surface within :data:`MAX_OFFSET_M` of its junction,
    at junctions :func:`choose_junctions` picks (``lanes_in``: incoming lanes per junction id), the head
    turned by :func:`road_yaw` onto the roads around it. With a group ``route`` (junction ids, cooperative
    layout) the junctions are :func:`choose_on_route`'s.

    Junctions wider than that all around (two multi-lane avenues crossing) are only used when there
    are not enough others; their pole then stands at the nearest spot off the road, with a warning.
    """
    sites: list[RsuSite] = []
    blocked = road.dilated(POLE_CLEARANCE_M)
    near = ((blocked, 3.0, MAX_OFFSET_M), (road, 1.0, MAX_OFFSET_M))
    feasible = [j for j in junctions if _spot(j, near, [], 0.0) is not None]
    pool = feasible if len(feasible) >= min(count, len(junctions)) else junctions
    used: list[tuple[float, float]] = []
    chosen = (choose_on_route(pool, degree, count, centre, route, lanes_in) if route
              else choose_junctions(pool, degree, count, centre, lanes_in))
    for i, j in enumerate(chosen):
        jx, jy = j.position_m
        phase = float(rng.uniform(0, 2 * math.pi))
        best = _spot(j, (*near, (road, 1.0, FAR_OFFSET_M)), used, phase)
        if best is None:
            best = (jx + MAX_OFFSET_M * math.cos(phase), jy + MAX_OFFSET_M * math.sin(phase))
        if math.dist(best, (jx, jy)) > MAX_OFFSET_M + 1e-6:
            log.warning(
                "rsu_%d stands %.1f m from junction %s: nothing closer is off the road",
                i,
                math.dist(best, (jx, jy)),
                j.junction_id,
            )
        used.append(best)
        h = round(float(rng.uniform(*height_range_m)), 3)
        x, y = round(float(best[0]), 3), round(float(best[1]), 3)
        yaw = road_yaw((x, y), road, math.atan2(jy - y, jx - x))
        sites.append(RsuSite(f"rsu_{i}", j.junction_id, (x, y, h), yaw, h))
    return sites
