"""The static scene as prisms: road surface, markings, sidewalks, buildings, vegetation, poles, terrain.

Built once per episode from the road network and a random generator. Vertical layout [m]:
terrain top -0.02, road top 0.0, lane markings top 0.005, sidewalks top 0.12; everything else
stands on the terrain. Placement uses an occupancy grid so buildings never overlap roads,
sidewalks or each other, and tree canopies never hang over a road lane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.world import geom
from cosim.world.geom import Occupancy, Raster
from cosim.world.network import Edge, RoadNetwork
from cosim.world.types import Prism

ROAD_Z = (-0.10, 0.0)
MARKING_Z = (-0.05, 0.005)
SIDEWALK_Z = (-0.10, 0.12)
TERRAIN_Z = (-0.30, -0.02)
GROUND_Z = -0.02
CELL_M = 0.5  # [m] occupancy grid resolution
FIRST_INSTANCE_ID = 1_000_000


@dataclass(frozen=True)
class LayoutStyle:
    """How a kind of place looks. Ranges are (low, high) of uniform draws."""

    building_frontage_m: tuple[float, float]
    building_depth_m: tuple[float, float]
    building_height_m: tuple[float, float]
    building_setback_m: tuple[float, float]
    building_gap_m: tuple[float, float]
    building_probability: float  # chance that a frontage slot gets a building
    downtown_boost: float  # extra height factor at the map centre (0: none)
    infill_per_ha: float  # tries per hectare to fill block interiors with more buildings
    street_tree_spacing_m: float | None
    scatter_trees_per_ha: float  # trees scattered in free space
    hedges: bool
    fields: bool
    street_light_spacing_m: float | None
    dash_m: tuple[float, float]  # lane divider dash, gap
    edge_lines: bool
    stop_lines: bool


STYLES: dict[str, LayoutStyle] = {
    "urban": LayoutStyle(
        building_frontage_m=(14, 30),
        building_depth_m=(14, 24),
        building_height_m=(12, 36),
        building_setback_m=(1.0, 2.5),
        building_gap_m=(0.0, 2.0),
        building_probability=0.95,
        downtown_boost=1.2,
        infill_per_ha=25.0,
        street_tree_spacing_m=14.0,
        scatter_trees_per_ha=4.0,
        hedges=False,
        fields=False,
        street_light_spacing_m=30.0,
        dash_m=(3.0, 6.0),
        edge_lines=False,
        stop_lines=True,
    ),
    "suburban": LayoutStyle(
        building_frontage_m=(9, 13),
        building_depth_m=(8, 12),
        building_height_m=(5, 8.5),
        building_setback_m=(6.0, 10.0),
        building_gap_m=(7.0, 14.0),
        building_probability=0.85,
        downtown_boost=0.0,
        infill_per_ha=0.0,
        street_tree_spacing_m=None,
        scatter_trees_per_ha=25.0,
        hedges=True,
        fields=False,
        street_light_spacing_m=40.0,
        dash_m=(3.0, 6.0),
        edge_lines=True,
        stop_lines=True,
    ),
    "rural": LayoutStyle(
        building_frontage_m=(10, 24),
        building_depth_m=(8, 16),
        building_height_m=(4, 9),
        building_setback_m=(12.0, 30.0),
        building_gap_m=(30.0, 120.0),
        building_probability=0.25,
        downtown_boost=0.0,
        infill_per_ha=0.0,
        street_tree_spacing_m=None,
        scatter_trees_per_ha=10.0,
        hedges=False,
        fields=True,
        street_light_spacing_m=None,
        dash_m=(4.5, 9.0),
        edge_lines=True,
        stop_lines=False,
    ),
    "highway": LayoutStyle(
        building_frontage_m=(25, 50),
        building_depth_m=(18, 35),
        building_height_m=(7, 13),
        building_setback_m=(10.0, 20.0),
        building_gap_m=(15.0, 40.0),
        building_probability=0.5,
        downtown_boost=0.0,
        infill_per_ha=0.0,
        street_tree_spacing_m=None,
        scatter_trees_per_ha=8.0,
        hedges=False,
        fields=True,
        street_light_spacing_m=45.0,
        dash_m=(6.0, 12.0),
        edge_lines=True,
        stop_lines=False,
    ),
}


class _Ids:
    def __init__(self) -> None:
        self.next = FIRST_INSTANCE_ID

    def __call__(self) -> int:
        self.next += 1
        return self.next - 1


def prism(cls: str, poly: np.ndarray, z0: float, z1: float, instance_id: int = 0) -> Prism:
    p = geom.ccw(poly)
    return Prism(
        cls,
        tuple((round(float(x), 3), round(float(y), 3)) for x, y in p),
        round(z0, 3),
        round(z1, 3),
        instance_id,
    )


def edge_road_polygon(edge: Edge) -> np.ndarray | None:
    """CCW outline (N, 2) of an edge's road lanes (sidewalks excluded), or None."""
    road = sorted((ln for ln in edge.lanes if ln.is_road), key=lambda ln: ln.index)
    if not road:
        return None
    right = geom.offset_polyline(road[0].shape, -0.5 * road[0].width_m)
    left = geom.offset_polyline(road[-1].shape, 0.5 * road[-1].width_m)
    if len(right) != len(left):
        return geom.strip(road[0].shape, sum(ln.width_m for ln in road))
    return geom.ccw(np.concatenate([right, left[::-1]]))


def road_polygons(net: RoadNetwork) -> list[np.ndarray]:
    """Drivable surface: every non-internal edge's road lanes and every junction outline."""
    polys = [p for e in net.edges.values() if not e.internal and (p := edge_road_polygon(e)) is not None]
    polys += [geom.ccw(j.shape) for j in net.junctions.values() if len(j.shape) >= 3 and j.kind != "internal"]
    return [p for p in polys if len(p) >= 3 and geom.signed_area(p) > 0.01]


def road_raster(net: RoadNetwork, bounds_m: tuple[float, float, float, float], cell_m: float = CELL_M) -> Raster:
    """Occupancy grid of the drivable surface (lanes of non-internal edges, internal lanes, junctions)."""
    polys = road_polygons(net)
    polys += [geom.strip(ln.shape, ln.width_m) for ln in net.lanes(internal=True) if ln.is_road]
    return Raster.empty(bounds_m, cell_m).with_polygons(polys)


def _two_way(net: RoadNetwork) -> set[tuple[str, str]]:
    return {(e.from_node, e.to_node) for e in net.road_edges()}


def markings(net: RoadNetwork, style: LayoutStyle) -> list[Prism]:
    """Lane dividers (dashed), centre lines (solid, one per direction: a double line), edge and stop lines."""
    out: list[Prism] = []
    pairs = _two_way(net)
    dash, gap = style.dash_m
    for e in sorted(net.road_edges(), key=lambda e: e.edge_id):
        road = sorted((ln for ln in e.lanes if ln.is_road), key=lambda ln: ln.index)
        for a in road[:-1]:
            border = geom.offset_polyline(a.shape, 0.5 * a.width_m)
            length = geom.polyline_length(border)
            s = 1.0
            while s + dash < length - 1.0:
                out.append(prism("lane_marking", geom.strip(geom.resample(border, s, s + dash), 0.15), *MARKING_Z))
                s += dash + gap
        top = road[-1]
        if (e.to_node, e.from_node) in pairs or style.edge_lines:
            centre = geom.offset_polyline(top.shape, 0.5 * top.width_m - 0.15)
            out.append(prism("lane_marking", geom.strip(centre, 0.15), *MARKING_Z))
        if style.edge_lines:
            edge_line = geom.offset_polyline(road[0].shape, -0.5 * road[0].width_m + 0.2)
            out.append(prism("lane_marking", geom.strip(edge_line, 0.15), *MARKING_Z))
        to_j = net.junctions.get(e.to_node)
        if style.stop_lines and to_j is not None and to_j.kind == "traffic_light":
            for ln in road:
                length = ln.length_m
                if length < 5.0:
                    continue
                p = geom.point_at(ln.shape, length - 1.0)
                yaw = geom.direction_at(ln.shape, length - 1.0)
                out.append(prism("lane_marking", geom.rect(p[0], p[1], 0.4, ln.width_m - 0.2, yaw), *MARKING_Z))
    return out


def sidewalks(net: RoadNetwork) -> list[Prism]:
    return [
        prism("sidewalk", geom.strip(ln.shape, ln.width_m), *SIDEWALK_Z)
        for e in sorted(net.edges.values(), key=lambda e: e.edge_id)
        if not e.internal
        for ln in e.lanes
        if ln.is_sidewalk
    ]


def _outer_right(edge: Edge) -> np.ndarray:
    """Right border (N, 2) of an edge including its sidewalk."""
    ln = min(edge.lanes, key=lambda ln: ln.index)
    return geom.offset_polyline(ln.shape, -0.5 * ln.width_m)


def _road_right(edge: Edge) -> np.ndarray:
    ln = min((ln for ln in edge.lanes if ln.is_road), key=lambda ln: ln.index)
    return geom.offset_polyline(ln.shape, -0.5 * ln.width_m)


class _Builder:
    def __init__(
        self,
        net: RoadNetwork,
        kind: str,
        bounds: tuple[float, float, float, float],
        rng: np.random.Generator,
        extra_buildings: list[tuple[np.ndarray, float | None]],
    ) -> None:
        self.net, self.kind, self.bounds, self.rng = net, kind, bounds, rng
        self.style = STYLES.get(kind, STYLES["suburban"])
        self.ids = _Ids()
        self.prisms: list[Prism] = []
        self.road = road_raster(net, bounds)
        paved = [p for p in sidewalks(net)]
        self.paved = Occupancy(bounds, CELL_M)
        self.paved.add_mask(self.road)
        for p in paved:
            self.paved.add(np.array(p.footprint))
        self.solid = Occupancy(bounds, CELL_M)  # paved + margin + buildings + trees: what new things avoid
        self.solid.add_mask(self.paved.raster().dilated(0.5))
        self.canopy_block = Occupancy(bounds, CELL_M)  # road lanes + buildings: what canopies avoid
        self.canopy_block.add_mask(self.road)
        self.extra_buildings = extra_buildings
        self.centre = (0.5 * (bounds[0] + bounds[2]), 0.5 * (bounds[1] + bounds[3]))
        self.half = 0.5 * min(bounds[2] - bounds[0], bounds[3] - bounds[1])

    def inside(self, poly: np.ndarray, margin: float = 1.0) -> bool:
        xmin, ymin, xmax, ymax = self.bounds
        return bool(
            (poly[:, 0] >= xmin + margin).all()
            and (poly[:, 0] <= xmax - margin).all()
            and (poly[:, 1] >= ymin + margin).all()
            and (poly[:, 1] <= ymax - margin).all()
        )

    def add_building(self, poly: np.ndarray, height: float) -> None:
        self.prisms.append(prism("building", poly, GROUND_Z, height, self.ids()))
        self.solid.add(poly)
        self.canopy_block.add(poly)

    def add_tree(self, x: float, y: float, radius: float, height: float, on_sidewalk: bool = False) -> bool:
        """Trunk and crown; a sidewalk tree only keeps clear of road lanes and buildings."""
        canopy = geom.regular_polygon(x, y, radius, 8, 0.3)
        trunk = geom.rect(x, y, 0.4, 0.4, 0.0)
        if not self.inside(canopy, 0.0):
            return False
        if not (self.canopy_block if on_sidewalk else self.solid).free(trunk):
            return False
        if not self.canopy_block.free(canopy):
            return False
        crown_base = min(2.5, 0.35 * height)
        self.prisms.append(prism("vegetation", trunk, GROUND_Z, crown_base))
        self.prisms.append(prism("vegetation", canopy, crown_base, height))
        self.solid.add(geom.regular_polygon(x, y, max(0.8, 0.5 * radius), 8))
        return True

    # ---------------------------------------------------------------------------- buildings
    def frontage_buildings(self) -> None:
        st, rng = self.style, self.rng
        for e in sorted(self.net.road_edges(), key=lambda e: e.edge_id):
            base = _outer_right(e)
            length = geom.polyline_length(base)
            s = float(rng.uniform(0.0, st.building_gap_m[1]))
            while s < length:
                f = float(rng.uniform(*st.building_frontage_m))
                d = float(rng.uniform(*st.building_depth_m))
                gap = float(rng.uniform(*st.building_gap_m))
                if s + f > length:
                    break
                if rng.random() < st.building_probability:
                    setback = float(rng.uniform(*st.building_setback_m))
                    for attempt in range(3):  # step back and narrow down where the first try collides
                        if self._try_building(
                            base, s + 0.15 * attempt * f, f * (1 - 0.3 * attempt), d, setback + 2.0 * attempt
                        ):
                            break
                s += f + gap

    def _try_building(self, base: np.ndarray, s: float, f: float, d: float, setback: float) -> bool:
        st, rng = self.style, self.rng
        p = geom.point_at(base, s + 0.5 * f)
        yaw = geom.direction_at(base, s + 0.5 * f)
        nx, ny = math.sin(yaw), -math.cos(yaw)  # right of the driving direction
        off = setback + 0.5 * d
        poly = geom.rect(p[0] + off * nx, p[1] + off * ny, f, d, yaw)
        if not self.inside(poly) or not self.solid.free(poly):
            return False
        self.add_building(poly, round(self._height(p), 2))
        if st.hedges:
            hedge_off = 0.5 * setback
            hedge = geom.rect(p[0] + hedge_off * nx, p[1] + hedge_off * ny, 0.7 * f, 0.8, yaw)
            if self.solid.free(hedge):
                self.prisms.append(prism("vegetation", hedge, GROUND_Z, 1.2))
                self.solid.add(hedge)
            for _ in range(int(rng.integers(1, 3))):
                back = off + 0.5 * d + float(rng.uniform(3.0, 7.0))
                along = float(rng.uniform(-0.5 * f, 0.5 * f))
                self.add_tree(
                    p[0] + back * nx + along * math.cos(yaw),
                    p[1] + back * ny + along * math.sin(yaw),
                    float(rng.uniform(2.0, 3.5)),
                    float(rng.uniform(6.0, 11.0)),
                )
        if self.kind == "rural":  # a farm: a barn or two next to the house
            for _ in range(int(rng.integers(1, 3))):
                bf, bd = float(rng.uniform(15, 30)), float(rng.uniform(10, 18))
                along = (0.5 * f + 0.5 * bf + float(rng.uniform(4, 10))) * (1 if rng.random() < 0.5 else -1)
                back = off + float(rng.uniform(-3, 12))
                barn = geom.rect(
                    p[0] + back * nx + along * math.cos(yaw),
                    p[1] + back * ny + along * math.sin(yaw),
                    bf,
                    bd,
                    yaw + (math.pi / 2 if rng.random() < 0.3 else 0.0),
                )
                if self.inside(barn) and self.solid.free(barn):
                    self.add_building(barn, round(float(rng.uniform(5, 9)), 2))
        return True

    def infill_buildings(self) -> None:
        """More buildings inside the blocks, aligned with the nearest road, where there is room."""
        st, rng = self.style, self.rng
        xmin, ymin, xmax, ymax = self.bounds
        n = round(st.infill_per_ha * (xmax - xmin) * (ymax - ymin) / 1e4)
        if n == 0:
            return
        road_dirs = [
            (geom.direction_at(ln.shape, 0.5 * ln.length_m), geom.point_at(ln.shape, 0.5 * ln.length_m))
            for ln in self.net.lanes(internal=False)
            if ln.is_road
        ]
        mids = np.array([p for _, p in road_dirs])
        for _ in range(n):
            x, y = float(rng.uniform(xmin, xmax)), float(rng.uniform(ymin, ymax))
            yaw = road_dirs[int(np.argmin(np.linalg.norm(mids - [x, y], axis=1)))][0]
            f, d = float(rng.uniform(*st.building_frontage_m)), float(rng.uniform(*st.building_depth_m))
            poly = geom.rect(x, y, f, d, yaw)
            grown = geom.rect(x, y, f + 4.0, d + 4.0, yaw)  # keep courtyards and passages open
            if self.inside(poly) and self.solid.free(grown):
                self.add_building(poly, round(self._height(np.array([x, y])), 2))

    def _height(self, p: np.ndarray) -> float:
        st = self.style
        h = float(self.rng.uniform(*st.building_height_m))
        if st.downtown_boost:
            r = math.dist(p, self.centre) / max(self.half, 1.0)
            h *= 1.0 + st.downtown_boost * math.exp(-((r / 0.45) ** 2))
        return h

    def given_buildings(self) -> None:
        rng = self.rng
        for poly, height in self.extra_buildings:
            drawn = float(rng.uniform(6.0, 20.0))  # drawn for every outline, so heights do not shift
            if len(poly) < 3 or abs(geom.signed_area(poly)) < 4.0 or not self.inside(poly, 0.0):
                continue
            if not self.solid.free(poly):  # an outline over a road or sidewalk is left out
                continue
            self.add_building(geom.ccw(poly), round(height if height is not None else drawn, 2))

    # ---------------------------------------------------------------------------- vegetation
    def street_trees(self) -> None:
        spacing = self.style.street_tree_spacing_m
        if spacing is None:
            return
        for e in sorted(self.net.road_edges(), key=lambda e: e.edge_id):
            walk = [ln for ln in e.lanes if ln.is_sidewalk]
            if not walk:
                continue
            ln = walk[0]
            length = ln.length_m
            s = 8.0
            while s < length - 8.0:
                p = geom.point_at(ln.shape, s)
                yaw = geom.direction_at(ln.shape, s)
                # a planting pit at the sidewalk's outer third
                off = 0.2 * ln.width_m
                x, y = p[0] + off * math.sin(yaw), p[1] - off * math.cos(yaw)
                self.add_tree(x, y, float(self.rng.uniform(1.4, 2.0)), float(self.rng.uniform(7.0, 12.0)), True)
                s += spacing

    def scatter_trees(self) -> None:
        xmin, ymin, xmax, ymax = self.bounds
        area_ha = (xmax - xmin) * (ymax - ymin) / 1e4
        n = round(self.style.scatter_trees_per_ha * area_ha)
        for _ in range(n):
            x, y = float(self.rng.uniform(xmin, xmax)), float(self.rng.uniform(ymin, ymax))
            k = int(self.rng.integers(1, 5)) if self.kind in ("rural", "highway") else 1  # small copses
            for _ in range(k):
                self.add_tree(
                    x + float(self.rng.normal(0, 4)),
                    y + float(self.rng.normal(0, 4)),
                    float(self.rng.uniform(2.0, 4.0)),
                    float(self.rng.uniform(6.0, 15.0)),
                )

    def fields(self) -> None:
        if not self.style.fields:
            return
        xmin, ymin, xmax, ymax = self.bounds
        y = ymin + 2.0
        while y < ymax - 10:
            h = float(self.rng.uniform(30, 70))
            x = xmin + 2.0
            while x < xmax - 10:
                w = float(self.rng.uniform(30, 80))
                self._try_field(x, y, min(w, xmax - 2 - x), min(h, ymax - 2 - y))
                x += w
            y += h

    def _try_field(self, x: float, y: float, w: float, h: float) -> None:
        for shrink in (0.0, 0.25, 0.5):
            fx, fy = x + 2.0 + shrink * w * 0.5, y + 2.0 + shrink * h * 0.5
            fw, fh = (w - 4.0) * (1 - shrink), (h - 4.0) * (1 - shrink)
            if fw < 12 or fh < 12:
                return
            poly = geom.rect(fx + 0.5 * fw, fy + 0.5 * fh, fw, fh, 0.0)
            if self.solid.free(poly):
                crop = float(self.rng.choice([0.0, 0.4, 0.8, 1.2]))
                if crop > 0:  # ploughed fields stay bare terrain
                    self.prisms.append(prism("vegetation", poly, GROUND_Z, crop))
                self.solid.add(poly)
                return

    def median_hedges(self) -> None:
        """Shrubs along the left of one-way carriageways (the median of a dual carriageway), in 20 m pieces."""
        pairs = _two_way(self.net)
        for e in sorted(self.net.road_edges(), key=lambda e: e.edge_id):
            if (e.to_node, e.from_node) in pairs:
                continue
            top = max((ln for ln in e.lanes if ln.is_road), key=lambda ln: ln.index)
            line = geom.offset_polyline(top.shape, 0.5 * top.width_m + 3.0)
            length = geom.polyline_length(line)
            s = 5.0
            while s + 20.0 < length - 5.0:
                piece = geom.strip(geom.resample(line, s, s + 20.0), 1.2)
                if self.solid.free(piece):
                    self.prisms.append(prism("vegetation", piece, GROUND_Z, 1.3))
                    self.solid.add(piece)
                s += 21.0

    # ---------------------------------------------------------------------------- poles
    def street_lights(self) -> None:
        spacing = self.style.street_light_spacing_m
        if spacing is None:
            return
        for e in sorted(self.net.road_edges(), key=lambda e: e.edge_id):
            base = _road_right(e)
            length = geom.polyline_length(base)
            s = 0.5 * spacing
            while s < length - 5.0:
                p = geom.point_at(base, s)
                yaw = geom.direction_at(base, s)
                x, y = p[0] + 0.8 * math.sin(yaw), p[1] - 0.8 * math.cos(yaw)
                foot = geom.rect(x, y, 0.3, 0.3, yaw)
                if self.inside(foot, 0.0) and not self.road.lookup(foot).any() and self.canopy_block.free(foot):
                    self.prisms.append(prism("street_light", foot, GROUND_Z, 8.0, self.ids()))
                    arm = geom.rect(x - 0.9 * math.sin(yaw), y + 0.9 * math.cos(yaw), 0.25, 1.8, yaw)
                    self.prisms.append(prism("street_light", arm, 7.7, 8.0, self.ids()))
                    self.solid.add(foot)
                s += spacing

    def signal_poles(self) -> None:
        for e in sorted(self.net.road_edges(), key=lambda e: e.edge_id):
            j = self.net.junctions.get(e.to_node)
            if j is None or j.kind != "traffic_light":
                continue
            base = _road_right(e)
            length = geom.polyline_length(base)
            p = geom.point_at(base, length - 1.0)
            yaw = geom.direction_at(base, length - 1.0)
            x, y = p[0] + 0.6 * math.sin(yaw), p[1] - 0.6 * math.cos(yaw)
            foot = geom.rect(x, y, 0.25, 0.25, yaw)
            if not self.road.lookup(foot).any():
                self.prisms.append(prism("pole", foot, GROUND_Z, 4.5, self.ids()))
                self.solid.add(foot)

    def build(self) -> list[Prism]:
        xmin, ymin, xmax, ymax = self.bounds
        self.prisms.append(
            prism(
                "terrain",
                geom.rect(0.5 * (xmin + xmax), 0.5 * (ymin + ymax), xmax - xmin, ymax - ymin, 0.0),
                *TERRAIN_Z,
            )
        )
        for p in road_polygons(self.net):
            self.prisms.append(prism("road", p, *ROAD_Z))
        self.prisms += sidewalks(self.net)
        self.prisms += markings(self.net, self.style)
        self.signal_poles()
        self.street_lights()
        self.given_buildings()
        if not self.extra_buildings:
            self.frontage_buildings()
            self.infill_buildings()
        self.street_trees()
        if self.kind == "highway":
            self.median_hedges()
        self.fields()
        self.scatter_trees()
        return self.prisms


def build_layout(
    net: RoadNetwork,
    kind: str,
    bounds_m: tuple[float, float, float, float],
    rng: np.random.Generator,
    buildings: list[tuple[np.ndarray, float | None]] | None = None,
) -> tuple[list[Prism], Raster]:
    """Every static prism of the world and the road-surface raster used to place them."""
    b = _Builder(net, kind, bounds_m, rng, buildings or [])
    return b.build(), b.road
