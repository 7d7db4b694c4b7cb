"""A SUMO network read into plain arrays: lanes, edges and junctions with their shapes.

Everything downstream of the network generators (routes, layout, RSU sites, pictures) reads this,
not SUMO's XML, so it can be tested on small hand-made networks.
"""

from __future__ import annotations

import logging
import re
import tempfile
import xml.sax
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sumolib

from cosim.errors import InputError
from cosim.world import geom

log = logging.getLogger(__name__)

#: SUMO vClasses that count as motor or cycle traffic (a lane allowing one of them is a road lane).
VEHICLE_VCLASSES = ("passenger", "delivery", "truck", "bus", "motorcycle", "bicycle")


@dataclass(frozen=True)
class Lane:
    lane_id: str
    edge_id: str
    index: int  # 0 = rightmost
    width_m: float
    speed_mps: float
    shape: np.ndarray  # (N, 2) centre line in map x/y [m], in driving direction
    allowed: frozenset[str]  # SUMO vClasses allowed
    internal: bool

    @property
    def is_road(self) -> bool:
        return any(c in self.allowed for c in VEHICLE_VCLASSES)

    @property
    def is_sidewalk(self) -> bool:
        return self.allowed == frozenset({"pedestrian"})

    @property
    def length_m(self) -> float:
        return geom.polyline_length(self.shape)


@dataclass(frozen=True)
class Edge:
    edge_id: str
    from_node: str
    to_node: str
    lanes: tuple[Lane, ...]
    internal: bool


@dataclass(frozen=True)
class JunctionGeom:
    junction_id: str
    position_m: tuple[float, float]
    kind: str
    shape: np.ndarray  # (N, 2) outline, possibly empty


@dataclass(frozen=True)
class RoadNetwork:
    edges: dict[str, Edge]
    junctions: dict[str, JunctionGeom]
    bounds_m: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax of the network
    geo_origin: tuple[float, float] | None  # lat, lon of map (0, 0) when geo-referenced

    def lanes(self, *, internal: bool | None = None) -> list[Lane]:
        return [ln for e in self.edges.values() for ln in e.lanes if internal is None or ln.internal == internal]

    def road_edges(self) -> list[Edge]:
        """Non-internal edges that carry vehicles."""
        return [e for e in self.edges.values() if not e.internal and any(ln.is_road for ln in e.lanes)]

    def road_length_km(self) -> float:
        """Length of road [km]: a two-way road (edge pair in opposite directions) counts once."""
        total = 0.0
        roads = self.road_edges()
        pairs = {(e.from_node, e.to_node) for e in roads}
        for e in roads:
            length = max(ln.length_m for ln in e.lanes if ln.is_road)
            total += 0.5 * length if (e.to_node, e.from_node) in pairs else length
        return total / 1000.0

    def real_junctions(self) -> list[JunctionGeom]:
        """Junctions where roads meet (no internal or dead-end nodes)."""
        return [j for j in self.junctions.values() if j.kind not in ("internal", "dead_end")]


_LOCATION = re.compile(rb"<location\s([^>]*)/?>")
_ATTR = re.compile(rb'(\w+)="([^"]*)"')


def geo_origin_of(net_xml: bytes) -> tuple[float, float] | None:
    """(lat, lon) [deg] of map (0, 0) for a geo-referenced network, else None.

    Interpolates linearly between the network's projected (``convBoundary``) and geographic
    (``origBoundary``) bounds: over a town-sized map the projection is linear to well under a metre,
    and no projection library is needed.
    """
    m = _LOCATION.search(net_xml[:20000])
    if m is None:
        return None
    attrs = {k.decode(): v.decode() for k, v in _ATTR.findall(m.group(1))}
    if attrs.get("projParameter", "!") == "!" or "origBoundary" not in attrs or "convBoundary" not in attrs:
        return None
    lon0, lat0, lon1, lat1 = (float(v) for v in attrs["origBoundary"].split(","))
    x0, y0, x1, y1 = (float(v) for v in attrs["convBoundary"].split(","))
    if x1 <= x0 or y1 <= y0:
        return None
    lon = lon0 + (0.0 - x0) / (x1 - x0) * (lon1 - lon0)
    lat = lat0 + (0.0 - y0) / (y1 - y0) * (lat1 - lat0)
    return (lat, lon)


def _problem(exc: Exception) -> str:
    """What is wrong with a network file, from the exception sumolib raised reading it."""
    if isinstance(exc, xml.sax.SAXParseException):
        return f"not well-formed XML at line {exc.getLineNumber()}: {exc.getMessage()}"
    if isinstance(exc, KeyError):
        return f"an element lacks the required attribute {exc.args[0]!r}"
    return f"{type(exc).__name__}: {exc}"


def read_network(net_xml: bytes, source: str = "the SUMO network") -> RoadNetwork:
    """Parse a SUMO .net.xml; raises InputError naming ``source`` and the problem when it is not a usable network."""
    head = net_xml[:20000]
    m = _LOCATION.search(head)
    if b"<net" in head and (m is None or b"convBoundary" not in m.group(1)):
        raise InputError(f"{source}: not a usable SUMO network: no <location convBoundary=...> element near its "
                         "start (netconvert writes one into every network)")
    try:
        return _read_network(net_xml)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from None
    except Exception as exc:  # sumolib raises plain exceptions (KeyError, IndexError, SAX errors) on bad files
        raise InputError(f"{source}: not a usable SUMO network: {_problem(exc)}") from None


def _read_network(net_xml: bytes) -> RoadNetwork:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.net.xml"
        path.write_bytes(net_xml)
        net = sumolib.net.readNet(str(path), withInternal=True, withPedestrianConnections=False)
    edges: dict[str, Edge] = {}
    for e in net.getEdges(withInternal=True):
        eid = e.getID()
        internal = eid.startswith(":")
        lanes = []
        for ln in e.getLanes():
            shape = np.array([p[:2] for p in ln.getShape()], dtype=np.float64)
            if len(shape) < 2:
                continue
            allowed = frozenset(ln.getPermissions())
            lanes.append(
                Lane(
                    ln.getID(),
                    eid,
                    ln.getIndex(),
                    float(ln.getWidth()),
                    float(ln.getSpeed()),
                    shape,
                    allowed,
                    internal,
                )
            )
        fn = e.getFromNode().getID() if not internal else ""
        tn = e.getToNode().getID() if not internal else ""
        edges[eid] = Edge(eid, fn, tn, tuple(lanes), internal)
    junctions: dict[str, JunctionGeom] = {}
    for n in net.getNodes():
        shape = np.array([p[:2] for p in (n.getShape() or [])], dtype=np.float64).reshape(-1, 2)
        x, y = n.getCoord()[:2]
        junctions[n.getID()] = JunctionGeom(n.getID(), (float(x), float(y)), n.getType(), shape)
    xmin, ymin, xmax, ymax = net.getBoundary()
    origin = geo_origin_of(net_xml)
    road_net = RoadNetwork(edges, junctions, (float(xmin), float(ymin), float(xmax), float(ymax)), origin)
    if not road_net.road_edges():
        raise InputError("no edge that vehicles may use")
    return road_net
