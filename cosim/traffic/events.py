"""The scenario timeline on SUMO: breakdowns, accidents, lane closures and road blocks (docs/events.md).

:class:`Timeline` lives in the traffic worker's :class:`cosim.traffic.TrafficSim`. At each event's
``at_s`` it resolves the place (the lane nearest a map point, or ``ahead_m`` along a connected
vehicle's route) and acts through libsumo:

- ``breakdown``: a car inserted standing in the lane, speed held at 0, hazard lights on at dusk/night.
- ``accident``: two cars standing in the lane; the rear one's box is turned by ``angle_deg`` so its
  front corner touches the front car's rear (label poses are pinned to that geometry).
- ``lane_closure`` / ``construction_zone``: a hidden standing SUMO vehicle as long as the span holds
  the lane (so traffic merges or waits, and nothing enters the span), plus a barrier, a sign and
  cones along the open side as ``static_obstacle`` boxes.
- ``road_block``: every lane of the edge but its sidewalk disallowed to all classes, barriers across
  them, and every vehicle whose remaining route uses the edge rerouted.
- ``jaywalk``: a SUMO person put on the kerb at the place, crossing the road straight to the far
  kerb outside any crossing (:class:`cosim.traffic.pedestrians.Crossing`), then walking on.
- ``cut_in``: a car inserted in the lane beside the connected vehicle, at its speed, that changes
  into the connected vehicle's lane with ``gap_m`` between its rear and the connected vehicle's front.

Each event has one record per tick for the ``/events`` topic (:meth:`Timeline.records`).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import libsumo
import numpy as np

from cosim.protocol import VehicleState
from cosim.scenario.model import (
    AccidentEvent,
    BreakdownEvent,
    CutInEvent,
    EventSpec,
    JaywalkEvent,
    LaneClosureEvent,
    RoadBlockEvent,
    Scenario,
)
from cosim.traffic.pedestrians import Crossing, Pedestrians, nearest_on, sidewalk_lane

log = logging.getLogger(__name__)

SIGNAL_HAZARD = 8  # TraCI VEH_SIGNAL_BLINKER_EMERGENCY
INCIDENT_TYPE = "car_incident"  # a car of variant 0 with a short min gap (cars standing bumper to bumper)
CONTACT_OVERLAP_M = 0.01  # [m] the rear car's corner reaches this far into the front car's box (touching)
CONE_SIZE_M = (0.4, 0.4, 0.7)
BARRIER_DEPTH_M, BARRIER_HEIGHT_M = 0.3, 1.0
SIGN_SIZE_M = (0.15, 1.0, 1.8)
EDGE_MARGIN_M = 1.0  # [m] kept from the ends of an edge when placing
HAZARD_PERIOD_NS = 666_666_667  # hazard lamps blink at 1.5 Hz, lit the first half of each period
CUT_IN_LANE_CHANGE_S = 2.0  # [s] the cut-in's lane change
CUT_IN_WAIT_S = 15.0  # [s] a cut_in waits this long for room beside the connected vehicle, then fails
CUT_IN_ROOM_M = 40.0  # [m] of its edge left ahead of the cutting car when it appears (room to change lane)


@dataclass(frozen=True, slots=True)
class LanePoint:
    """A place on a lane: edge id, lane index, position along it [m]."""

    edge: str
    lane: int
    pos_m: float

    @property
    def lane_id(self) -> str:
        return f"{self.edge}_{self.lane}"


@dataclass
class _Active:
    """What one event put into the simulation."""

    index: int
    spec: EventSpec
    place: LanePoint | None = None
    active_from_ns: int | None = None
    vehicles: list[str] = field(default_factory=list)  # SUMO ids shown in labels
    hidden: list[str] = field(default_factory=list)  # SUMO ids not shown (closure blockers)
    obstacles: list[VehicleState] = field(default_factory=list)
    zone_m: list[tuple[float, float]] = field(default_factory=list)  # closed area (map polygon)
    note: str = ""


def lane_pose(edge: str, lane: int, pos_m: float) -> tuple[float, float, float]:
    """Map x, y and ENU heading [rad] of a lane's centre line at ``pos_m``."""
    length = libsumo.lane.getLength(f"{edge}_{lane}")
    p = min(max(pos_m, 0.0), length)
    a = libsumo.simulation.convert2D(edge, max(0.0, p - 0.5), lane)
    b = libsumo.simulation.convert2D(edge, min(length, p + 0.5), lane)
    x, y = libsumo.simulation.convert2D(edge, p, lane)
    return x, y, math.atan2(b[1] - a[1], b[0] - a[0])


def offset(x: float, y: float, yaw: float, ahead_m: float, left_m: float) -> tuple[float, float]:
    c, s = math.cos(yaw), math.sin(yaw)
    return x + ahead_m * c - left_m * s, y + ahead_m * s + left_m * c


def rect(cx: float, cy: float, yaw: float, length_m: float, width_m: float) -> list[tuple[float, float]]:
    """Corners (counter-clockwise) of a rectangle centred at cx, cy, turned by yaw."""
    return [offset(cx, cy, yaw, sx * length_m / 2, sy * width_m / 2) for sx, sy in ((1, -1), (1, 1), (-1, 1), (-1, -1))]


def static_box(sid: str, x: float, y: float, z_ground: float, yaw: float, size_m: tuple[float, float, float]
               ) -> VehicleState:
    return VehicleState(sumo_id=sid, cls="static_obstacle", center_m=(x, y, z_ground + size_m[2] / 2), size_m=size_m,
                        yaw_rad=yaw, pitch_rad=0.0, speed_mps=0.0, velocity_mps=(0.0, 0.0, 0.0), accel_mps2=0.0,
                        yaw_rate_radps=0.0)


class Timeline:
    """Applies a scenario's events to the running SUMO simulation (one per TrafficSim)."""

    def __init__(self, scenario: Scenario, destinations: Callable[[str], list[str]], rng: np.random.Generator,
                 pedestrians: Pedestrians) -> None:
        """``destinations(vid)``: edges a vehicle may be sent to instead when its destination is blocked;
        ``pedestrians``: where the ``jaywalk`` event's person walks."""
        self.scenario = scenario
        self._pedestrians = pedestrians
        self._cut_ins: dict[str, tuple[str, int]] = {}  # cutting car -> (connected vehicle, t0 ns) until it is in
        self._cut_in_deadline: dict[int, int] = {}  # cut_in event index -> last time to place it [ns]
        self._destinations = destinations
        self._rng = rng
        self._pending = sorted(enumerate(scenario.events), key=lambda ie: (ie[1].at_s, ie[0]))
        self._active: list[_Active] = []
        self.hazard_lights = scenario.environment.lighting in ("dusk", "night")
        self.pinned: dict[str, tuple[float, float, float]] = {}  # SUMO id -> label centre x, y and yaw
        if scenario.events:
            libsumo.vehicletype.copy("car_0", INCIDENT_TYPE)
            libsumo.vehicletype.setMinGap(INCIDENT_TYPE, 0.1)

    # ------------------------------------------------------------------------------ stepping
    def before_step(self, t_ns: int) -> None:
        """Start every event due at episode time ``t_ns`` (called before the SUMO step to ``t_ns``)."""
        while self._pending and round(self._pending[0][1].at_s * 1e9) <= t_ns:
            index, spec = self._pending.pop(0)
            event = _Active(index, spec)
            self._active.append(event)
            try:
                place = self._resolve(spec)
                event.place, event.note = (None, place) if isinstance(place, str) else (place, "")
                if event.place is not None:
                    {BreakdownEvent: self._breakdown, AccidentEvent: self._accident, LaneClosureEvent: self._closure,
                     RoadBlockEvent: self._block, JaywalkEvent: self._jaywalk, CutInEvent: self._cut_in,
                     }[type(spec)](event, t_ns)
            except libsumo.TraCIException as exc:
                event.place, event.note = None, f"not placed: {exc}"
            if event.place is None:
                event.note = event.note or "not placed: no lane for cars at the given place"
                log.warning("event %d (%s) %s", index, spec.kind, event.note)

    def after_step(self, t_ns: int) -> None:
        """Hold stopped vehicles; mark events active once SUMO has inserted their vehicles."""
        present = set(libsumo.vehicle.getIDList()) | self._pedestrians.present()
        for e in self._active:
            if e.place is None:
                continue
            if isinstance(e.spec, CutInEvent):
                self._cut_in_step(e, present, t_ns)
                if e.place is None:
                    continue
            elif not isinstance(e.spec, JaywalkEvent):
                for vid in e.vehicles + e.hidden:
                    if vid in present:
                        libsumo.vehicle.setSpeed(vid, 0.0)
            placed = bool(e.vehicles + e.hidden + e.obstacles) or isinstance(e.spec, RoadBlockEvent)
            if e.active_from_ns is None and placed and all(v in present for v in e.vehicles + e.hidden):
                e.active_from_ns = t_ns

    def hazard_lamps_on(self, vid: str, t_ns: int) -> bool:
        """Whether ``vid`` is a broken-down car whose hazard lamps are lit at ``t_ns`` (they blink)."""
        for e in self._active:
            if (isinstance(e.spec, BreakdownEvent) and vid in e.vehicles and e.active_from_ns is not None
                    and self._hazard(e.spec)):
                return (t_ns - e.active_from_ns) % HAZARD_PERIOD_NS < HAZARD_PERIOD_NS // 2
        return False

    def hidden(self) -> set[str]:
        return {v for e in self._active for v in e.hidden}

    def event_vehicles(self) -> set[str]:
        return {v for e in self._active for v in e.vehicles + e.hidden}

    def obstacles(self) -> list[VehicleState]:
        """Static obstacles of the events that are active."""
        return [o for e in self._active if e.active_from_ns is not None for o in e.obstacles]

    def records(self) -> list[dict[str, object]]:
        """Every event of the scenario as it stands (one entry each, in scenario order)."""
        out: dict[int, dict[str, object]] = {}
        for index, spec in self._pending:
            out[index] = {"id": f"event_{index}", "kind": spec.kind, "at_ns": round(spec.at_s * 1e9),
                          "state": "pending"}
        for e in self._active:
            rec: dict[str, object] = {
                "id": f"event_{e.index}",
                "kind": e.spec.kind,
                "at_ns": round(e.spec.at_s * 1e9),
                "state": "failed" if e.place is None else ("active" if e.active_from_ns is not None else "starting"),
                "active_from_ns": e.active_from_ns,
                "vehicles": [v for v in e.vehicles if not v.endswith("_ped")],
                "obstacles": [o.sumo_id for o in e.obstacles],
                "zone_m": [list(p) for p in e.zone_m],
            }
            if e.place is not None:
                rec.update(edge=e.place.edge, lane=e.place.lane, lane_pos_m=round(e.place.pos_m, 3))
            if isinstance(e.spec, BreakdownEvent):
                rec["hazard_lights"] = self._hazard(e.spec)
            if isinstance(e.spec, JaywalkEvent):
                rec["pedestrians"] = [v for v in e.vehicles if v.endswith("_ped")]
            if e.note:
                rec["note"] = e.note
            out[e.index] = rec
        return [out[i] for i in sorted(out)]

    # ------------------------------------------------------------------------------- placing
    def _resolve(self, spec: EventSpec) -> LanePoint | str | None:
        """The event's place; None when there is no lane for cars there, or why it could not be placed."""
        if spec.position_m is not None:
            edge, pos, lane = libsumo.simulation.convertRoad(spec.position_m[0], spec.position_m[1], False,
                                                             "passenger")
            if not edge or edge.startswith(":"):
                return None
            return self._car_lane(LanePoint(edge, int(lane), float(pos)))
        vid = spec.ahead_of
        assert vid is not None
        v = libsumo.vehicle
        route = list(v.getRoute(vid))
        idx, lane = v.getRouteIndex(vid), v.getLaneIndex(vid)
        road = v.getRoadID(vid)
        pos = v.getLanePosition(vid) + spec.ahead_m
        if road.startswith(":"):  # in a junction: the route index still names the edge it came from
            idx, pos = idx + 1, spec.ahead_m
            links = libsumo.lane.getLinks(v.getLaneID(vid))
            if links:  # the lane the junction lane leads onto
                lane = int(str(links[0][0]).rsplit("_", 1)[1])
        for edge in route[max(idx, 0):]:
            length = libsumo.lane.getLength(f"{edge}_0")
            if pos <= length - EDGE_MARGIN_M:
                return self._car_lane(LanePoint(edge, lane, max(pos, EDGE_MARGIN_M)))
            pos -= length
        return f"not placed: the route of {vid} ends less than {spec.ahead_m:g} m ahead of it"

    @staticmethod
    def _car_lane(place: LanePoint) -> LanePoint | None:
        """The place on the lane nearest ``place.lane`` that cars may use, or None."""
        n = libsumo.edge.getLaneNumber(place.edge)
        for lane in sorted(range(n), key=lambda i: (abs(i - place.lane), i)):
            allowed = libsumo.lane.getAllowed(f"{place.edge}_{lane}")
            if (not allowed or "passenger" in allowed) and "passenger" not in libsumo.lane.getDisallowed(
                    f"{place.edge}_{lane}"):
                return LanePoint(place.edge, lane, place.pos_m)
        return None

    def _fit(self, place: LanePoint, length_m: float) -> LanePoint:
        """The place moved back along its lane so that ``length_m`` behind it fits on the edge."""
        lane_len = libsumo.lane.getLength(place.lane_id)
        pos = min(max(place.pos_m, length_m + EDGE_MARGIN_M), lane_len - EDGE_MARGIN_M)
        return LanePoint(place.edge, place.lane, pos)

    def _insert(self, vid: str, place: LanePoint, type_id: str) -> None:
        """A standing vehicle whose front is at ``place`` (SUMO inserts it as soon as there is room)."""
        libsumo.route.add(f"route_{vid}", [place.edge])
        libsumo.vehicle.add(vid, f"route_{vid}", typeID=type_id, depart="now", departLane=str(place.lane),
                            departPos=f"{place.pos_m:.3f}", departSpeed="0")
        libsumo.vehicle.setSpeedMode(vid, 0)
        libsumo.vehicle.setLaneChangeMode(vid, 0)

    def _hazard(self, spec: BreakdownEvent) -> bool:
        return self.hazard_lights if spec.hazard_lights is None else spec.hazard_lights

    # ------------------------------------------------------------------------------ the kinds
    def _breakdown(self, e: _Active, t_ns: int) -> None:
        assert isinstance(e.spec, BreakdownEvent) and e.place is not None
        length = libsumo.vehicletype.getLength(INCIDENT_TYPE)
        e.place = self._fit(e.place, length)
        vid = f"ev{e.index}_0"
        self._insert(vid, e.place, INCIDENT_TYPE)
        if self._hazard(e.spec):
            libsumo.vehicle.setSignals(vid, SIGNAL_HAZARD)
        e.vehicles.append(vid)

    def _accident(self, e: _Active, t_ns: int) -> None:
        assert isinstance(e.spec, AccidentEvent) and e.place is not None
        length = libsumo.vehicletype.getLength(INCIDENT_TYPE)
        width = libsumo.vehicletype.getWidth(INCIDENT_TYPE)
        e.place = self._fit(e.place, 2 * length + 1.0)
        front, rear = f"ev{e.index}_0", f"ev{e.index}_1"
        self._insert(front, e.place, INCIDENT_TYPE)
        rear_place = LanePoint(e.place.edge, e.place.lane, e.place.pos_m - length - 0.2)
        self._insert(rear, rear_place, INCIDENT_TYPE)
        e.vehicles += [front, rear]
        # the front car along the lane; the rear one turned by theta, its foremost corner just inside
        # the middle of the front car's rear face
        fx, fy, fyaw = lane_pose(e.place.edge, e.place.lane, e.place.pos_m - length / 2)
        self.pinned[front] = (fx, fy, fyaw)
        theta = math.radians(e.spec.angle_deg)
        corner_ahead = length / 2 * math.cos(theta) + width / 2 * math.sin(theta)
        corner_left = length / 2 * math.sin(theta) - width / 2 * math.cos(theta)
        contact = offset(fx, fy, fyaw, -length / 2 + CONTACT_OVERLAP_M, 0.0)
        rx, ry = offset(contact[0], contact[1], fyaw, -corner_ahead, -corner_left)
        self.pinned[rear] = (rx, ry, fyaw + theta)

    def _closure(self, e: _Active, t_ns: int) -> None:
        assert isinstance(e.spec, LaneClosureEvent) and e.place is not None
        spec = e.spec
        start = self._fit(LanePoint(e.place.edge, e.place.lane, e.place.pos_m + spec.length_m), spec.length_m)
        e.place = LanePoint(start.edge, start.lane, start.pos_m - spec.length_m)
        lane_w = libsumo.lane.getWidth(start.lane_id)
        blk = f"ev{e.index}_blk"
        type_id = f"closure_{e.index}"
        libsumo.vehicletype.copy("car_0", type_id)
        libsumo.vehicletype.setLength(type_id, spec.length_m)
        libsumo.vehicletype.setWidth(type_id, max(0.5, lane_w - 0.4))
        libsumo.vehicletype.setMinGap(type_id, 0.1)
        self._insert(blk, start, type_id)
        e.hidden.append(blk)
        z = libsumo.simulation.convert3D(start.edge, start.pos_m, start.lane)[2]
        n_lanes = libsumo.edge.getLaneNumber(start.edge)
        sides = [s for s, open_lane in ((1.0, start.lane + 1), (-1.0, start.lane - 1)) if 0 <= open_lane < n_lanes]
        x0, y0, yaw0 = lane_pose(start.edge, start.lane, e.place.pos_m + BARRIER_DEPTH_M / 2)
        e.obstacles.append(static_box(f"ev{e.index}_barrier", x0, y0, z, yaw0,
                                      (BARRIER_DEPTH_M, lane_w - 0.4, BARRIER_HEIGHT_M)))
        sx, sy, syaw = lane_pose(start.edge, start.lane, e.place.pos_m + 1.5)
        e.obstacles.append(static_box(f"ev{e.index}_sign", sx, sy, z, syaw, SIGN_SIZE_M))
        n_cones = int(spec.length_m // spec.cone_spacing_m)
        for side in sides:
            for k in range(1, n_cones + 1):
                cx, cy, cyaw = lane_pose(start.edge, start.lane, e.place.pos_m + k * spec.cone_spacing_m - 0.5)
                px, py = offset(cx, cy, cyaw, 0.0, side * (lane_w / 2 - CONE_SIZE_M[1] / 2 - 0.05))
                e.obstacles.append(static_box(f"ev{e.index}_cone_{'l' if side > 0 else 'r'}{k}", px, py, z, cyaw,
                                              CONE_SIZE_M))
        mx, my, myaw = lane_pose(start.edge, start.lane, e.place.pos_m + spec.length_m / 2)
        e.zone_m = rect(mx, my, myaw, spec.length_m, lane_w)

    def _reroute_around(self, vid: str, edge: str) -> None:
        """A new route avoiding ``edge``; a new destination when ``edge`` was the destination."""
        v = libsumo.vehicle
        with contextlib.suppress(libsumo.TraCIException):  # no route at all: handled below
            v.rerouteTraveltime(vid)
        if edge not in v.getRoute(vid)[v.getRouteIndex(vid) + 1:]:
            return
        candidates = [d for d in self._destinations(vid) if d != edge]
        for k in self._rng.permutation(len(candidates))[:20]:
            try:
                v.changeTarget(vid, candidates[int(k)])
            except libsumo.TraCIException:
                continue
            if edge not in v.getRoute(vid)[v.getRouteIndex(vid) + 1:]:
                return
        log.info("road block: no way around %s for %s; it waits before the block", edge, vid)

    def _block(self, e: _Active, t_ns: int) -> None:
        """Every lane of the edge but its sidewalk closed to all classes (people walk on, as past a closed
        street; SUMO cannot route a walking person around a closed sidewalk and stops), a barrier across each."""
        assert e.place is not None
        edge = e.place.edge
        pending = set(libsumo.simulation.getPendingVehicles())
        waiting = [vid for other in self._active if other is not e and other.place is not None
                   and other.place.edge == edge for vid in other.vehicles + other.hidden if vid in pending]
        if waiting:  # closing the lanes under a vehicle SUMO has yet to insert is a fatal SUMO error
            e.place, e.note = None, f"not placed: {', '.join(waiting)} of another event wait(s) to enter edge {edge}"
            return
        walk = sidewalk_lane(edge)
        lanes = [i for i in range(libsumo.edge.getLaneNumber(edge)) if f"{edge}_{i}" != walk]
        for i in lanes:
            libsumo.lane.setDisallowed(f"{edge}_{i}", ["all"])
        for vid in libsumo.vehicle.getIDList():
            route = libsumo.vehicle.getRoute(vid)
            if edge in route[libsumo.vehicle.getRouteIndex(vid) + 1:]:
                self._reroute_around(vid, edge)
        z = libsumo.simulation.convert3D(edge, 1.0, lanes[0])[2]
        for i in lanes:
            w = libsumo.lane.getWidth(f"{edge}_{i}")
            x, y, yaw = lane_pose(edge, i, 1.0)
            e.obstacles.append(static_box(f"ev{e.index}_barrier_{i}", x, y, z, yaw, (BARRIER_DEPTH_M, w - 0.2,
                                                                                      BARRIER_HEIGHT_M)))
        length = libsumo.lane.getLength(f"{edge}_{lanes[0]}")
        e.place = LanePoint(edge, lanes[0], 0.0)
        poly: list[tuple[float, float]] = []
        for lane, pos, left in ((lanes[0], 0.0, -0.5), (lanes[0], length, -0.5), (lanes[-1], length, 0.5),
                                (lanes[-1], 0.0, 0.5)):
            x, y, yaw = lane_pose(edge, lane, pos)
            poly.append(offset(x, y, yaw, 0.0, left * libsumo.lane.getWidth(f"{edge}_{lane}")))
        e.zone_m = poly

    def _jaywalk(self, e: _Active, t_ns: int) -> None:
        """A person on the ``from_side`` kerb at the place, crossing straight over to the other kerb."""
        assert isinstance(e.spec, JaywalkEvent) and e.place is not None
        edge = e.place.edge
        rev = self._pedestrians.reverse(edge)
        x, y, yaw = lane_pose(edge, e.place.lane, e.place.pos_m)
        right = self._kerb_point(edge, x, y, yaw, -1.0)
        left = self._kerb_point(rev, x, y, yaw, 1.0) if rev is not None else self._kerb_point(None, x, y, yaw, 1.0)
        (start, start_edge), (end, end_edge) = (right, left) if e.spec.from_side == "right" else (left, right)
        if start_edge is None or end_edge is None:
            e.place, e.note = None, f"not placed: no sidewalk on either side of edge {edge!r} to walk from and to"
            return
        pid = f"ev{e.index}_ped"
        far = libsumo.simulation.convertRoad(end[0], end[1], False, "pedestrian")
        far_pos = far[1] if far[0] == end_edge else libsumo.lane.getLength(f"{end_edge}_0") / 2
        self._pedestrians.add_crossing(pid, Crossing(start, end, t_ns, e.spec.speed_mps, end_edge, far_pos))
        e.vehicles.append(pid)
        mx, my = (start[0] + end[0]) / 2, (start[1] + end[1]) / 2
        e.zone_m = rect(mx, my, math.atan2(end[1] - start[1], end[0] - start[0]), math.dist(start, end) + 1.0, 2.0)

    def _kerb_point(self, edge: str | None, x: float, y: float, yaw: float, side: float
                    ) -> tuple[tuple[float, float], str | None]:
        """The point of ``edge``'s sidewalk centre line nearest the lane point (x, y), and the edge; without
        a sidewalk, a point beside the road on ``side`` (+1 left, -1 right) and no edge."""
        lane = sidewalk_lane(edge) if edge is not None else None
        if lane is None:
            return offset(x, y, yaw, 0.0, side * 8.0), None
        return nearest_on(libsumo.lane.getShape(lane), x, y), edge

    def _cut_in(self, e: _Active, t_ns: int) -> None:
        """Armed at ``at_s``; placed at the first step from then on where it fits (:meth:`_try_cut_in`)."""
        e.note = ""
        self._cut_in_deadline[e.index] = t_ns + round(CUT_IN_WAIT_S * 1e9)
        self._try_cut_in(e, t_ns)

    def _try_cut_in(self, e: _Active, t_ns: int) -> None:
        """A car beside the connected vehicle, ``ahead_m`` + ``gap_m`` ahead of its front, at its speed; while
        the connected vehicle is in a junction or too near the end of its edge, the event waits (up to
        :data:`CUT_IN_WAIT_S`), then fails."""
        assert isinstance(e.spec, CutInEvent) and e.spec.ahead_of is not None
        cv = e.spec.ahead_of
        v = libsumo.vehicle
        road = v.getRoadID(cv)
        lane = v.getLaneIndex(cv)
        length = libsumo.vehicletype.getLength(INCIDENT_TYPE)
        front = v.getLanePosition(cv) + e.spec.ahead_m + e.spec.gap_m + length
        lanes: list[int] = []
        if not road.startswith(":"):
            n = libsumo.edge.getLaneNumber(road)
            sides = {"left": [lane + 1], "right": [lane - 1], "any": [lane + 1, lane - 1]}[e.spec.side]
            lanes = [i for i in sides if 0 <= i < n and self._car_lane(LanePoint(road, i, 0.0)) is not None
                     and self._car_lane(LanePoint(road, i, 0.0)).lane == i]
        room = bool(lanes) and front + CUT_IN_ROOM_M < libsumo.lane.getLength(f"{road}_{lane}")
        if not room:
            if t_ns >= self._cut_in_deadline[e.index]:
                e.place, e.note = None, (f"not placed: in {CUT_IN_WAIT_S:g} s {cv} was never on an edge with a lane "
                                         f"for cars beside it and {front + CUT_IN_ROOM_M:.0f} m ahead")
                del self._cut_in_deadline[e.index]
            return
        del self._cut_in_deadline[e.index]
        e.place = LanePoint(road, lanes[0], front)
        vid = f"ev{e.index}_0"
        route = list(v.getRoute(cv))[v.getRouteIndex(cv):]
        libsumo.route.add(f"route_{vid}", route)
        v.add(vid, f"route_{vid}", typeID=INCIDENT_TYPE, depart="now", departLane=str(lanes[0]),
              departPos=f"{front:.3f}", departSpeed=f"{v.getSpeed(cv):.3f}")
        v.setLaneChangeMode(vid, 0)  # only the cut-in's change, forced (not waiting for a safe gap)
        e.vehicles.append(vid)
        self._cut_ins[vid] = (cv, t_ns)

    def _cut_in_step(self, e: _Active, present: set[str], t_ns: int) -> None:
        """Until placed: try again; once the car is in, hold it level with the connected vehicle and change
        into its lane."""
        if e.index in self._cut_in_deadline:
            self._try_cut_in(e, t_ns)
            return
        vid = e.vehicles[0] if e.vehicles else ""
        if vid not in self._cut_ins or vid not in present:
            return
        cv, _ = self._cut_ins[vid]
        v = libsumo.vehicle
        if cv not in present or v.getRoadID(vid) != v.getRoadID(cv):
            del self._cut_ins[vid]
            return
        target = v.getLaneIndex(cv)
        if v.getLaneIndex(vid) == target:
            del self._cut_ins[vid]
            v.setSpeed(vid, -1.0)  # in the lane: it drives on by SUMO's model
            return
        v.setSpeed(vid, max(v.getSpeed(cv), 1.0))
        v.changeLane(vid, target, CUT_IN_LANE_CHANGE_S)
