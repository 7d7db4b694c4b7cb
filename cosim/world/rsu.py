"""Roadside-unit sites: poles at junction corners, heads facing the junction centre."""

from __future__ import annotations

import logging
import math

import numpy as np

from cosim.world.geom import Raster
from cosim.world.network import JunctionGeom
from cosim.world.types import RsuSite

log = logging.getLogger(__name__)

MAX_OFFSET_M = 14.0  # [m] farthest a pole stands from its junction centre (where the junction allows)
FAR_OFFSET_M = 40.0  # [m] search limit for junctions wider than that
POLE_CLEARANCE_M = 0.6  # [m] pole to road surface


def choose_junctions(
    junctions: list[JunctionGeom], degree: dict[str, int], count: int, centre: tuple[float, float]
) -> list[JunctionGeom]:
    """``count`` junctions spread over the map (farthest-point order from the one nearest ``centre``),
    preferring signalised junctions, then junctions with three or more incoming roads (``degree``:
    incoming road edges per junction id). Repeats junctions when there are fewer than ``count``."""
    if not junctions or count <= 0:
        return []

    def rank(j: JunctionGeom) -> int:
        return 0 if j.kind == "traffic_light" else 1 if degree.get(j.junction_id, 0) >= 3 else 2

    pool = sorted(junctions, key=lambda j: (rank(j), j.junction_id))
    for level in (0, 1):
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
) -> list[RsuSite]:
    """RSU sites ``rsu_0..``: a pole off the road surface within :data:`MAX_OFFSET_M` of its junction.

    Junctions wider than that all around (two multi-lane avenues crossing) are only used when there
    are not enough others; their pole then stands at the nearest spot off the road, with a warning.
    """
    sites: list[RsuSite] = []
    blocked = road.dilated(POLE_CLEARANCE_M)
    near = ((blocked, 3.0, MAX_OFFSET_M), (road, 1.0, MAX_OFFSET_M))
    feasible = [j for j in junctions if _spot(j, near, [], 0.0) is not None]
    pool = feasible if len(feasible) >= min(count, len(junctions)) else junctions
    used: list[tuple[float, float]] = []
    for i, j in enumerate(choose_junctions(pool, degree, count, centre)):
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
        yaw = math.atan2(jy - y, jx - x)
        sites.append(RsuSite(f"rsu_{i}", j.junction_id, (x, y, h), yaw, h))
    return sites
