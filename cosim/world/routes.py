"""Initial traffic as a SUMO route file: vehicle types, background vehicles and connected vehicles.

Every vehicle departs at SUMO time 0 at a drawn position on a drawn lane, spaced so that no two
overlap. Connected vehicles get a route inside the part of the network where their class can always
go on (the strongly connected core for its vClass), through the town rather than around it: they
depart on and head for the core's inner edges (:func:`inner_edges`, not touching a gateway junction
on the map's outer ring), where the traffic and the scenery are; the traffic adapter extends their
routes before they end, so they stay for the whole episode. Background vehicles drive to a sink, a road that ends
at a gateway of the map (:func:`gateways`: a junction on the edge of the network or a dead end), and
leave there; the adapter sends a new vehicle of the same class in from a source, so traffic changes
while the density stays as configured.

Class counts are a systematic sample of ``traffic.mix`` (:func:`class_counts`): within one of the
exact share per class in every episode, and the expected count is exactly the share, so the shares
over a batch follow the mix however small each episode is.
"""

from __future__ import annotations

import logging
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sumolib

from cosim.errors import InputError
from cosim.scenario.model import Scenario
from cosim.world.vtypes import SUMO_VCLASS, VehicleVariant, variants

log = logging.getLogger(__name__)

MIN_LANE_M = 20.0  # [m] shortest lane a vehicle departs on
END_CLEARANCE_M = 12.0  # [m] no departure closer than this to a lane's end
ROUTE_TARGETS = 1  # random destinations in the initial route (the adapter extends routes as they run out)
GATEWAY_M = 30.0  # [m] junctions this close to the edge of the network's junction bounds are gateways


@dataclass(frozen=True)
class PlannedVehicle:
    vehicle_id: str
    variant: VehicleVariant
    lane_id: str
    lane_index: int
    pos_m: float  # front bumper along the lane [m]
    route: tuple[str, ...]


def class_counts(mix: dict[str, float], n: int, rng: np.random.Generator) -> dict[str, int]:
    """Vehicles per class for ``n`` vehicles: a systematic sample of ``mix`` (shares sum to 1).

    The classes' shares are laid end to end on [0, n) and counted at the points u, u + 1, ...,
    u + n - 1 for one uniform draw u: every class gets the floor or the ceiling of ``share * n``,
    the counts sum to ``n``, and the expected count of every class is exactly ``share * n`` (no
    class is rounded up or down in every episode, so a batch of small episodes keeps the mix).
    """
    classes = sorted(mix)
    edges = np.concatenate([[0.0], np.cumsum([mix[c] * n for c in classes])])
    edges[-1] = n  # no rounding slack at the end
    points = float(rng.uniform(0.0, 1.0)) + np.arange(n)
    hits = np.searchsorted(edges, points, side="right") - 1
    return {c: int(np.count_nonzero(hits == i)) for i, c in enumerate(classes)}


def read_sumolib(net_xml: bytes) -> sumolib.net.Net:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.net.xml"
        path.write_bytes(net_xml)
        return sumolib.net.readNet(str(path))


def strong_core(net: sumolib.net.Net, vclass: str) -> list[str]:
    """Ids of edges of the largest strongly connected edge set that ``vclass`` may use, sorted."""
    allowed = sorted((e for e in net.getEdges() if e.allows(vclass)), key=lambda e: e.getID())
    best: set[str] = set()
    seen: set[str] = set()
    for ref in sorted(allowed, key=lambda e: (-e.getLength(), e.getID())):
        if ref.getID() in seen:
            continue
        fwd = {e.getID() for e in net.getReachable(ref, vclass)} | {ref.getID()}
        bwd = {e.getID() for e in net.getReachable(ref, vclass, useIncoming=True)} | {ref.getID()}
        core = fwd & bwd
        seen |= core
        if len(core) > len(best):
            best = core
        if len(best) * 2 >= len(allowed):
            break
    return sorted(best)


def random_route(
    net: sumolib.net.Net,
    start: str,
    core: list[str],
    vclass: str,
    rng: np.random.Generator,
    n_targets: int = ROUTE_TARGETS,
) -> list[str]:
    """Route from edge ``start`` through ``n_targets`` random core edges (shortest paths between them)."""
    route = [start]
    for _ in range(n_targets):
        for _attempt in range(10):
            target = core[int(rng.integers(len(core)))]
            if target == route[-1]:
                continue
            path, _cost = net.getShortestPath(net.getEdge(route[-1]), net.getEdge(target), vClass=vclass)
            if path:
                route.extend(e.getID() for e in path[1:])
                break
    return route


def gateways(net: sumolib.net.Net) -> set[str]:
    """Ids of the junctions where traffic enters and leaves the map: dead ends (the network's own
    fringe) and junctions within :data:`GATEWAY_M` of the bounds of all junctions (where the roads
    of a generated town or highway would go on beyond the map)."""
    nodes = [n for n in net.getNodes() if n.getType() != "internal"]
    if not nodes:
        return set()
    xy = np.array([n.getCoord()[:2] for n in nodes])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    out = set()
    for n, (x, y) in zip(nodes, xy, strict=True):
        near = min(x - lo[0], hi[0] - x, y - lo[1], hi[1] - y) <= GATEWAY_M
        neighbours = {e.getToNode().getID() for e in n.getOutgoing()}
        neighbours |= {e.getFromNode().getID() for e in n.getIncoming()}
        if near or n.getType() == "dead_end" or len(neighbours - {n.getID()}) <= 1:
            out.add(n.getID())
    return out


def inner_edges(net: sumolib.net.Net, core: list[str]) -> list[str]:
    """The edges of ``core`` that neither start nor end at a :func:`gateways` junction (sorted); all of
    ``core`` when none does (a map that is all fringe)."""
    gates = gateways(net)
    inner = [e for e in core
             if net.getEdge(e).getFromNode().getID() not in gates and net.getEdge(e).getToNode().getID() not in gates]
    return inner or list(core)


def sources_and_sinks(net: sumolib.net.Net, vclass: str) -> tuple[list[str], list[str]]:
    """Edges ``vclass`` may use that leave a gateway (sources) and that end at one (sinks), sorted.
    Sources are at least :data:`MIN_LANE_M` long, so that the longest vehicle enters on its edge
    (a bus inserted on a short U-turn connector would reach back over the junction behind it).

    A network without gateways (none can happen on a non-empty network: its outermost junctions
    are gateways) gets every allowed edge as both: vehicles then enter and leave at the roadside,
    as from a parking place.
    """
    gates = gateways(net)
    edges = sorted((e for e in net.getEdges() if e.getFunction() != "internal" and e.allows(vclass)),
                   key=lambda e: e.getID())
    sources = [e.getID() for e in edges if e.getFromNode().getID() in gates and e.getLength() >= MIN_LANE_M]
    sinks = [e.getID() for e in edges if e.getToNode().getID() in gates]
    if not sources or not sinks:
        every = [e.getID() for e in edges if e.getLength() >= MIN_LANE_M]
        return every, every
    return sources, sinks


def route_to_sink(
    net: sumolib.net.Net, start: str, sinks: list[str], vclass: str, rng: np.random.Generator, attempts: int = 10
) -> list[str] | None:
    """Shortest route from edge ``start`` to a randomly drawn sink edge, or None when none is reachable."""
    for _ in range(attempts):
        sink = sinks[int(rng.integers(len(sinks)))]
        if sink == start:
            return [start]
        path, _cost = net.getShortestPath(net.getEdge(start), net.getEdge(sink), vClass=vclass)
        if path:
            return [e.getID() for e in path]
    return None


class _LaneOccupancy:
    """Occupied front-bumper intervals per lane, so departures keep their gaps."""

    def __init__(self) -> None:
        self.spans: dict[str, list[tuple[float, float]]] = {}

    def free(self, lane_id: str, lo: float, hi: float) -> bool:
        return all(hi <= a or lo >= b for a, b in self.spans.get(lane_id, []))

    def take(self, lane_id: str, lo: float, hi: float) -> None:
        self.spans.setdefault(lane_id, []).append((lo, hi))


def plan_vehicles(
    net: sumolib.net.Net, scenario: Scenario, road_km: float, rng: np.random.Generator,
    group: tuple[PlannedVehicle, ...] | None = None,
) -> list[PlannedVehicle]:
    """Connected vehicles first (ids vehicle_<i>), then background (ids bg_<nnnn>).

    Connected vehicles' routes stay in the strongly connected core; background routes end at a sink.
    ``group``: the connected vehicles already planned (cosim/world/group.py); background keeps clear of them.
    """
    n_bg = round(scenario.traffic.density_veh_per_km * road_km)
    n_conn = scenario.agents.vehicles.count
    # the mix holds for all vehicles on the road, connected ones included
    counts = class_counts(dict(scenario.traffic.mix), n_bg + n_conn, rng)
    conn_cls = scenario.agents.vehicles.vclass
    counts[conn_cls] = max(0, counts.get(conn_cls, 0) - n_conn)
    wanted: list[tuple[str, str]] = [
        (f"vehicle_{i}", scenario.agents.vehicles.vclass) for i in range(scenario.agents.vehicles.count)
    ]
    bg_classes = [c for c in sorted(counts) for _ in range(counts[c])]
    order = rng.permutation(len(bg_classes))
    wanted += [(f"bg_{k:04d}", bg_classes[i]) for k, i in enumerate(order)]

    cores: dict[str, list[str]] = {}
    inner: dict[str, list[str]] = {}
    sinks: dict[str, list[str]] = {}
    lanes: dict[str, list[sumolib.net.lane.Lane]] = {}
    inner_lanes: dict[str, list[sumolib.net.lane.Lane]] = {}
    occ = _LaneOccupancy()
    out: list[PlannedVehicle] = []
    for p in group or ():
        occ.take(p.lane_id, p.pos_m - p.variant.length_m - p.variant.min_gap_m - 1.0, p.pos_m + 4.0)
        out.append(p)
    for vid, cls in wanted:
        if group is not None and vid.startswith("vehicle_"):
            continue
        vclass = SUMO_VCLASS[cls]
        if vclass not in cores:
            cores[vclass] = strong_core(net, vclass)
            inner[vclass] = inner_edges(net, cores[vclass])
            sinks[vclass] = sources_and_sinks(net, vclass)[1]
            lanes[vclass], inner_lanes[vclass] = (
                [ln for eid in edges for ln in net.getEdge(eid).getLanes()
                 if ln.allows(vclass) and ln.getLength() >= MIN_LANE_M]
                for edges in (cores[vclass], inner[vclass])
            )
        if not lanes[vclass]:
            if vid.startswith("vehicle_"):
                raise InputError(f"the map has no road where connected vehicles of class {cls!r} can drive")
            log.info("no %s can drive on this map; skipping %s", cls, vid)
            continue
        of_class = variants()[cls]
        variant = of_class[int(rng.integers(len(of_class)))]
        cand = inner_lanes[vclass] if vid.startswith("vehicle_") and inner_lanes[vclass] else lanes[vclass]
        weights = np.array([ln.getLength() for ln in cand])
        weights /= weights.sum()
        placed = None
        for _attempt in range(60):
            ln = cand[int(rng.choice(len(cand), p=weights))]
            lo_lim = variant.length_m + 2.0
            hi_lim = ln.getLength() - END_CLEARANCE_M
            if hi_lim <= lo_lim:
                continue
            pos = float(rng.uniform(lo_lim, hi_lim))
            span = (pos - variant.length_m - variant.min_gap_m - 1.0, pos + 4.0)
            if occ.free(ln.getID(), *span):
                occ.take(ln.getID(), *span)
                placed = (ln, pos)
                break
        if placed is None:
            if vid.startswith("vehicle_"):
                raise InputError(
                    f"no free place to insert connected vehicle {vid}: the map is too small for {len(wanted)} vehicles"
                )
            log.info("no free place for %s; traffic is denser than the map holds", vid)
            continue
        ln, pos = placed
        start = ln.getEdge().getID()
        route = None if vid.startswith("vehicle_") else route_to_sink(net, start, sinks[vclass], vclass, rng)
        if route is None:  # connected, or no sink reachable: drive in the core (routes are extended)
            targets = inner[vclass] if vid.startswith("vehicle_") else cores[vclass]
            route = random_route(net, start, targets, vclass, rng)
        out.append(PlannedVehicle(vid, variant, ln.getID(), ln.getIndex(), round(pos, 2), tuple(route)))
    return out


def routes_xml(planned: list[PlannedVehicle]) -> bytes:
    """SUMO route file: the vTypes of every variant, then every vehicle departing at time 0."""
    root = ET.Element("routes")
    table = variants()
    for cls in sorted(table):
        for v in table[cls]:
            ET.SubElement(
                root,
                "vType",
                {
                    "id": v.type_id,
                    "vClass": v.vclass,
                    "length": f"{v.length_m:.2f}",
                    "width": f"{v.width_m:.2f}",
                    "height": f"{v.height_m:.2f}",
                    "minGap": f"{v.min_gap_m:.2f}",
                    "maxSpeed": f"{v.max_speed_mps:.2f}",
                    "accel": f"{v.accel_mps2:.2f}",
                    "decel": f"{v.decel_mps2:.2f}",
                    "sigma": "0.5",
                },
            )
    for p in sorted(planned, key=lambda p: p.vehicle_id):
        veh = ET.SubElement(
            root,
            "vehicle",
            {
                "id": p.vehicle_id,
                "type": p.variant.type_id,
                "depart": "0.00",
                "departLane": str(p.lane_index),
                "departPos": f"{p.pos_m:.2f}",
                "departSpeed": "0.00",
            },
        )
        ET.SubElement(veh, "route", {"edges": " ".join(p.route)})
    ET.indent(root)
    return b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root) + b"\n"
