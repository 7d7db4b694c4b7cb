"""The static world as plain data: what SUMO drives on, what the renderer meshes and what the
drones plan their altitude over. Built once per episode, deterministic from the scenario and seed.

All coordinates are in ``map`` (ENU, metres) and equal to the SUMO network's x/y.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

Point2 = tuple[float, float]


@dataclass(frozen=True, slots=True)
class Prism:
    """A vertical extrusion of a simple polygon: the one primitive of the static scene.

    ``footprint`` is counter-clockwise in map x/y [m] without a repeated last point; the solid spans
    ``z0_m`` to ``z1_m``. ``cls`` is a semantic class name from :mod:`cosim.classes`; ``instance_id``
    is 0 for stuff (road, terrain, vegetation...) and a unique id >= 1_000_000 for things that deserve
    one (buildings, poles).
    """

    cls: str
    footprint: tuple[Point2, ...]
    z0_m: float
    z1_m: float
    instance_id: int = 0


@dataclass(frozen=True, slots=True)
class Junction:
    junction_id: str
    position_m: Point2
    kind: str  # SUMO junction type (traffic_light, priority, ...)


@dataclass(frozen=True, slots=True)
class RsuSite:
    """A roadside unit: a pole at a junction; ``position_m`` is the sensor head (top of the pole)."""

    agent_id: str
    junction_id: str
    position_m: tuple[float, float, float]
    yaw_rad: float  # turns the head's four cameras onto the roads around the pole (cosim/world/rsu.py)
    height_m: float


@dataclass(frozen=True, slots=True)
class ParkedVehicle:
    """A parked vehicle: a standing box of one of the six vehicle classes (labelled with ``parked``)."""

    parked_id: str  # parked_<nnnn>
    cls: str
    type_id: str  # the variant (cosim.world.vtypes), for its look
    center_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class StaticLayout:
    prisms: tuple[Prism, ...]
    ground_z_m: float = 0.0

    def max_height_near(self, x: float, y: float, radius_m: float) -> float:
        """Highest top of any prism whose footprint's bounding box comes within ``radius_m`` of (x, y)."""
        top = self.ground_z_m
        for p in self.prisms:
            xs = [q[0] for q in p.footprint]
            ys = [q[1] for q in p.footprint]
            if min(xs) - radius_m <= x <= max(xs) + radius_m and min(ys) - radius_m <= y <= max(ys) + radius_m:
                top = max(top, p.z1_m)
        return top


@dataclass(frozen=True, slots=True)
class World:
    """One episode's world. Sent to workers inline (``to_wire``), attached to the episode."""

    map_kind: str
    net_xml: bytes
    routes_xml: bytes
    bounds_m: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    junctions: tuple[Junction, ...]
    rsus: tuple[RsuSite, ...]
    layout: StaticLayout
    geo_origin: tuple[float, float, float]  # lat [deg], lon [deg], alt [m] of map (0, 0, 0)
    parked: tuple[ParkedVehicle, ...] = ()
    #: cooperative layout: the junctions the connected vehicles' shared route passes, in the order the group
    #: meets them (cosim/world/group.py); empty for ``spread``
    group_junctions: tuple[str, ...] = ()

    def to_wire(self) -> dict[str, Any]:
        wire: dict[str, Any] = {
            "map_kind": self.map_kind,
            "net_xml": self.net_xml,
            "routes_xml": self.routes_xml,
            "bounds_m": list(self.bounds_m),
            "junctions": [[j.junction_id, list(j.position_m), j.kind] for j in self.junctions],
            "rsus": [[r.agent_id, r.junction_id, list(r.position_m), r.yaw_rad, r.height_m] for r in self.rsus],
            "prisms": [[p.cls, [list(q) for q in p.footprint], p.z0_m, p.z1_m, p.instance_id]
                       for p in self.layout.prisms],
            "ground_z_m": self.layout.ground_z_m,
            "geo_origin": list(self.geo_origin),
            "parked": [[p.parked_id, p.cls, p.type_id, list(p.center_m), list(p.size_m), p.yaw_rad]
                       for p in self.parked],
        }
        if self.group_junctions:  # only then: a spread world's wire (and episode) stays as it was
            wire["group_junctions"] = list(self.group_junctions)
        return wire

    @classmethod
    def from_wire(cls, d: dict[str, Any]) -> World:
        return cls(
            map_kind=d["map_kind"],
            net_xml=d["net_xml"],
            routes_xml=d["routes_xml"],
            bounds_m=tuple(d["bounds_m"]),
            junctions=tuple(Junction(j[0], tuple(j[1]), j[2]) for j in d["junctions"]),
            rsus=tuple(RsuSite(r[0], r[1], tuple(r[2]), r[3], r[4]) for r in d["rsus"]),
            layout=StaticLayout(
                tuple(Prism(p[0], tuple(tuple(q) for q in p[1]), p[2], p[3], p[4]) for p in d["prisms"]),
                d["ground_z_m"],
            ),
            geo_origin=tuple(d["geo_origin"]),
            parked=tuple(ParkedVehicle(p[0], p[1], p[2], tuple(p[3]), tuple(p[4]), p[5]) for p in d.get("parked", [])),
            group_junctions=tuple(d.get("group_junctions", ())),
        )
