"""Roadside clutter (``map.clutter: kitti``): the things a real residential street has beyond its kerb.

KITTI's residential and town streets are lined, behind the parked cars, by walls, fences, hedges and
bushes at the property line, poles, bollards and signs, vegetation of several heights, ground that rises
beyond the kerb, and houses close to the road. cosim's generated towns have the houses and street trees
but little else; this module adds the rest, along the right side of every road edge (both sides of a
two-way street):

- a **property line** :data:`PROPERTY_OFFSET_M` beyond the edge's outer border (sidewalk or road), behind
  the strip parked vehicles stand in (cosim/world/parking.py puts their boxes, grown by their clearance,
  within 2.8 m of that border), cut into runs of :data:`RUN_M`, each a low wall, a fence, a hedge, a row
  of bushes or open (the shares :data:`RUN_SHARES`);
- **street furniture** on the property line between runs: poles, bollards, signs (a post and a plate);
- **vegetation of several heights** behind it (shrubs and small trees);
- **raised ground**: banks of terrain 0.2-1.2 m high behind some runs (the road, sidewalk and parking
  strip stay level: the ground rises beyond them);
- **houses close to the road**: extra houses :data:`HOUSE_SETBACK_M` from the border where the frontage
  has room.

Classes (cosim/classes.py, unchanged): walls and fences are ``building`` (solid man-made structures, as
Cityscapes' and KITTI-360's wall and fence fold into construction), hedges, bushes and trees
``vegetation``, poles and bollards ``pole``, sign plates ``traffic_sign``, banks ``terrain``. Every piece
keeps clear of road lanes, sidewalks and whatever the layout already placed (its occupancy grid), so no
clutter stands in a driving lane, on a sidewalk or in a parked vehicle's box; moving road users keep to
lanes and sidewalks, so no clutter meets an actor's box. Deterministic from the scenario seed (its own
random stream); with ``map.clutter: none`` (the default) nothing here runs and worlds keep their bytes.
"""

from __future__ import annotations

import math

import numpy as np

from cosim.world import geom
from cosim.world.geom import Occupancy
from cosim.world.layout import CELL_M, GROUND_Z, _outer_right, prism, road_raster
from cosim.world.network import RoadNetwork
from cosim.world.types import Prism

CLUTTER_KINDS = ("none", "kitti")
#: [m] from an edge's outer border (sidewalk or road) to the property line: parked boxes, grown by their
#: clearance, stay within 2.8 m of it, and the occupancy grid's 0.5 m cells must leave them that strip
PROPERTY_OFFSET_M = 3.6
RUN_M = (4.0, 14.0)  # [m] length of one run along the property line
#: what a run is: wall, fence, hedge, bushes, open (shares)
RUN_SHARES = {"wall": 0.2, "fence": 0.2, "hedge": 0.3, "bushes": 0.15, "open": 0.15}
FURNITURE_PROBABILITY = 0.5  # chance of a pole, bollard or sign between two runs
BANK_PROBABILITY = 0.3  # chance that the ground behind a run rises
HOUSE_SETBACK_M = (4.5, 6.5)  # [m] from the border to a close house's front
HOUSE_SIZE_M = ((8.0, 12.0), (7.0, 10.0), (5.0, 8.0))  # frontage, depth, height ranges


def place_clutter(net: RoadNetwork, prisms: list[Prism], bounds_m: tuple[float, float, float, float], kind: str,
                  rng: np.random.Generator, first_id: int) -> list[Prism]:
    """The clutter prisms of ``kind`` (``kitti``; ``none``: nothing) for a world whose layout is ``prisms``;
    instance ids from ``first_id`` up (one per piece)."""
    if kind == "none":
        return []
    b = _Clutter(net, prisms, bounds_m, rng, first_id)
    for e in sorted(net.road_edges(), key=lambda e: e.edge_id):
        b.edge(_outer_right(e))
    return b.out


class _Clutter:
    def __init__(self, net: RoadNetwork, prisms: list[Prism], bounds_m, rng: np.random.Generator, first_id: int):
        self.rng, self.bounds, self.next_id = rng, bounds_m, first_id
        self.solid = Occupancy(bounds_m, CELL_M)
        self.solid.add_mask(road_raster(net, bounds_m).dilated(0.5))
        for p in prisms:
            if p.cls not in ("terrain", "lane_marking"):
                self.solid.add(np.array(p.footprint))
        self.out: list[Prism] = []

    def _inside(self, poly: np.ndarray) -> bool:
        xmin, ymin, xmax, ymax = self.bounds
        return bool(poly[:, 0].min() > xmin + 1 and poly[:, 0].max() < xmax - 1 and poly[:, 1].min() > ymin + 1
                    and poly[:, 1].max() < ymax - 1)

    def _put(self, parts: list[tuple[str, np.ndarray, float, float]], keep_out: np.ndarray | None = None) -> bool:
        """Add ``parts`` (class, footprint, z0, z1) as one piece where ``keep_out`` (default: every footprint)
        is free; each part of a thing its own instance id (vegetation and terrain are stuff: 0)."""
        zone = [keep_out] if keep_out is not None else [p[1] for p in parts]
        if not all(self._inside(z) and self.solid.free(z) for z in zone):
            return False
        for cls, poly, z0, z1 in parts:
            stuff = cls in ("vegetation", "terrain")
            self.out.append(prism(cls, poly, z0, round(z1, 2), 0 if stuff else self.next_id))
            self.next_id += 0 if stuff else 1
        for z in zone:
            self.solid.add(z)
        return True

    def edge(self, border: np.ndarray) -> None:
        rng = self.rng
        line = geom.offset_polyline(border, -PROPERTY_OFFSET_M)
        length = geom.polyline_length(line)
        kinds = list(RUN_SHARES)
        shares = np.array([RUN_SHARES[k] for k in kinds])
        s = float(rng.uniform(1.0, 4.0))
        while s < length - 3.0:
            run = min(float(rng.uniform(*RUN_M)), length - 2.0 - s)
            what = kinds[int(rng.choice(len(kinds), p=shares))]
            u = rng.random(6)  # drawn for every run, so one piece's fate does not shift the others
            if run > 1.0:
                self._run(what, geom.resample(line, s, s + run), u)
                if u[4] < BANK_PROBABILITY:
                    self._bank(geom.offset_polyline(geom.resample(line, s, s + run), -1.6), u[5])
            gap_s = s + run + 0.6
            if rng.random() < FURNITURE_PROBABILITY and gap_s < length - 1.0:
                self._furniture(geom.point_at(line, gap_s), geom.direction_at(line, gap_s), rng.random(2))
            s += run + 1.2
        self._houses(border, length)

    def _run(self, what: str, piece: np.ndarray, u: np.ndarray) -> None:
        if what == "wall":
            self._put([("building", geom.strip(piece, 0.25), GROUND_Z, 0.6 + 1.4 * u[0])])
        elif what == "fence":
            self._put([("building", geom.strip(piece, 0.06), GROUND_Z, 1.0 + 0.8 * u[0])],
                      geom.strip(piece, 0.3))
        elif what == "hedge":
            width = 0.6 + 0.6 * u[1]
            self._put([("vegetation", geom.strip(geom.offset_polyline(piece, -0.5 * width), width), GROUND_Z,
                        0.8 + 1.4 * u[0])])
        elif what == "bushes":
            n = max(1, int(geom.polyline_length(piece) / 2.5))
            for k in range(n):
                along = (k + 0.5) * geom.polyline_length(piece) / n
                p, yaw = geom.point_at(piece, along), geom.direction_at(piece, along)
                r = 0.4 + 0.6 * ((u[0] + 0.37 * k) % 1.0)
                x, y = p[0] + r * math.sin(yaw), p[1] - r * math.cos(yaw)  # behind the line
                self._put([("vegetation", geom.regular_polygon(x, y, r, 8, 0.3 * k), GROUND_Z,
                            0.5 + 1.3 * ((u[1] + 0.61 * k) % 1.0))])
        # behind the line: a shrub or small tree of its own height (vegetation of several heights)
        if u[2] < 0.5:
            p = geom.point_at(piece, 0.5 * geom.polyline_length(piece))
            yaw = geom.direction_at(piece, 0.5 * geom.polyline_length(piece))
            back = 2.0 + 1.5 * u[3]
            x, y = p[0] + back * math.sin(yaw), p[1] - back * math.cos(yaw)
            if u[3] < 0.5:  # a shrub 1-3 m
                self._put([("vegetation", geom.regular_polygon(x, y, 0.8 + u[1], 8), GROUND_Z, 1.0 + 2.0 * u[0])])
            else:  # a small tree: trunk and crown 3-6 m
                h = 3.0 + 3.0 * u[0]
                crown = geom.regular_polygon(x, y, 1.0 + 0.8 * u[1], 8, 0.3)
                self._put([("vegetation", geom.rect(x, y, 0.25, 0.25, yaw), GROUND_Z, 0.4 * h),
                           ("vegetation", crown, 0.4 * h, h)], crown)

    def _bank(self, line: np.ndarray, u: float) -> None:
        """Ground rising behind the property line: a terrain bank 0.2-1.2 m high, 2.5 m deep."""
        self._put([("terrain", geom.strip(line, 2.5), GROUND_Z, 0.2 + 1.0 * u)])

    def _furniture(self, p: np.ndarray, yaw: float, u: np.ndarray) -> None:
        x, y = float(p[0]), float(p[1])
        if u[0] < 0.4:  # a pole (telegraph, lamp without its arm) 4-8 m
            self._put([("pole", geom.rect(x, y, 0.22, 0.22, yaw), GROUND_Z, 4.0 + 4.0 * u[1])])
        elif u[0] < 0.7:  # a bollard 0.8-1.1 m
            self._put([("pole", geom.rect(x, y, 0.2, 0.2, yaw), GROUND_Z, 0.8 + 0.3 * u[1])])
        else:  # a sign: a post and its plate facing the road
            top = 2.2 + 0.6 * u[1]
            plate = geom.rect(x, y, 0.6, 0.04, yaw)
            self._put([("pole", geom.rect(x, y, 0.08, 0.08, yaw), GROUND_Z, top),
                       ("traffic_sign", plate, top, top + 0.6)], geom.rect(x, y, 0.7, 0.3, yaw))

    def _houses(self, border: np.ndarray, length: float) -> None:
        """Houses close to the road where the frontage (and the clutter so far) leaves room."""
        rng = self.rng
        s = float(rng.uniform(2.0, 8.0))
        while s < length - 6.0:
            f, d, h = (float(rng.uniform(*r)) for r in HOUSE_SIZE_M)
            setback = float(rng.uniform(*HOUSE_SETBACK_M))
            if s + f > length - 2.0:
                break
            p = geom.point_at(border, s + 0.5 * f)
            yaw = geom.direction_at(border, s + 0.5 * f)
            off = setback + 0.5 * d
            poly = geom.rect(p[0] + off * math.sin(yaw), p[1] - off * math.cos(yaw), f, d, yaw)
            self._put([("building", poly, GROUND_Z, h)])
            s += f + float(rng.uniform(3.0, 8.0))
