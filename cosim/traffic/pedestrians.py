"""Pedestrians from SUMO's pedestrian model: persons walking on sidewalks and crossings (docs/events.md).

:class:`Pedestrians` lives in :class:`cosim.traffic.TrafficSim`. At SUMO time 0 it puts
``pedestrians.density_per_km`` persons per km of road edge with a sidewalk at random places on the
sidewalks, each with a walking stage to a random sidewalk edge (SUMO's intermodal router: sidewalks,
walking areas, crossings); near the end of a walk the person gets a new one, so every pedestrian
stays for the whole episode under one id (``ped_<nnnn>``). SUMO's striping model moves them.

A share ``jaywalk_share`` of them are jaywalkers: now and then (every ``jaywalk_every_s`` on
average), walking mid-block on a sidewalk, one steps off the kerb and crosses straight to the
sidewalk of the opposite edge, outside any crossing. A crossing (also the ``jaywalk`` event's, see
:mod:`cosim.traffic.events`) is a straight walk at a steady speed that SUMO does not model (its
persons only walk where pedestrians are allowed): the person leaves SUMO for it, and is put back,
under the same id, on the far sidewalk with a new walk when it is over. So that cars see it, a
hidden standing SUMO vehicle (``evped_<id>``, never in the labels) as long and wide as the person
stands where it is on a car lane, moved from lane to lane as it crosses: cars brake for it by their
car-following, or run into it when it steps out right in front of them.

Each pedestrian is read as a :class:`cosim.protocol.VehicleState` of class ``pedestrian`` (the class
size of the sensors' synthetic table, standing on the sidewalk top on sidewalks and on the road
elsewhere), with its gait phase (walked distance over the stride, 0..1) for the walker's leg pose.
"""

from __future__ import annotations

import itertools
import logging
import math
import re
from dataclasses import dataclass

import libsumo
import numpy as np

from cosim.protocol import VehicleState
from cosim.scenario.model import PedestrianSpec
from cosim.sensors.assets.people import posed_box
from cosim.world.layout import ROAD_Z, SIDEWALK_Z

log = logging.getLogger(__name__)

SIZE_M = (0.5, 0.6, 1.75)  # length, width, height [m]: a walker's footprint for SUMO's blockers and kerb checks
STRIDE_M = 1.5  # [m] walked per gait cycle (two steps)
KERB_MARGIN_M = 6.0  # [m] a jaywalker leaves the sidewalk at least this far from either end of the edge
ROUTE_TRIES = 8
BLOCKER_TYPE = "pedestrian_blocker"  # the hidden vehicle cars see in a crossing pedestrian's place
_JUNCTION_LANE = re.compile(r"^:.+_([cw])\d+_\d+$")  # netconvert's crossing / walking area lane ids


@dataclass
class Crossing:
    """A straight walk across a road from ``start`` to ``end`` [m] at ``speed_mps`` from ``t0_ns`` on; then
    SUMO's model walks the person on from ``far_pos_m`` on ``far_edge`` (its sidewalk)."""

    start: tuple[float, float]
    end: tuple[float, float]
    t0_ns: int
    speed_mps: float
    far_edge: str
    far_pos_m: float
    back_in_sumo: bool = False

    @property
    def length_m(self) -> float:
        return math.dist(self.start, self.end)

    @property
    def yaw_rad(self) -> float:
        return math.atan2(self.end[1] - self.start[1], self.end[0] - self.start[0])

    def at(self, t_ns: int) -> tuple[float, float, bool]:
        """Map x, y at ``t_ns`` and whether the crossing is over."""
        f = (t_ns - self.t0_ns) * 1e-9 * self.speed_mps / max(self.length_m, 1e-9)
        f = min(max(f, 0.0), 1.0)
        return (self.start[0] + f * (self.end[0] - self.start[0]), self.start[1] + f * (self.end[1] - self.start[1]),
                f >= 1.0)


def sidewalk_lane(edge: str) -> str | None:
    """The lane of ``edge`` only pedestrians may use (its sidewalk), or None."""
    for i in range(libsumo.edge.getLaneNumber(edge)):
        lane = f"{edge}_{i}"
        if tuple(libsumo.lane.getAllowed(lane)) == ("pedestrian",):
            return lane
    return None


def nearest_on(shape: tuple[tuple[float, float], ...], x: float, y: float) -> tuple[float, float]:
    """The point of polyline ``shape`` nearest (x, y)."""
    best, best_d = shape[0], math.inf
    for (ax, ay), (bx, by) in itertools.pairwise(shape):
        dx, dy = bx - ax, by - ay
        f = ((x - ax) * dx + (y - ay) * dy) / max(dx * dx + dy * dy, 1e-12)
        f = min(max(f, 0.0), 1.0)
        p = (ax + f * dx, ay + f * dy)
        d = math.dist(p, (x, y))
        if d < best_d:
            best, best_d = p, d
    return best


class Pedestrians:
    """SUMO persons on the sidewalks; :meth:`after_step` after every SUMO step, :meth:`states` per tick."""

    def __init__(self, spec: PedestrianSpec, rng: np.random.Generator, step_s: float) -> None:
        self.spec = spec
        self._rng = rng
        self._step_s = step_s
        normal = sorted(e for e in libsumo.edge.getIDList() if not e.startswith(":"))
        self._edges = [e for e in normal if sidewalk_lane(e)]
        self._reverse = self._reverse_edges(normal)
        self.walkers: list[str] = []
        self.jaywalkers: set[str] = set()
        self.crossings: dict[str, Crossing] = {}
        self._odo: dict[str, float] = {}
        self._last_xy: dict[str, tuple[float, float]] = {}
        self._blockers: dict[str, str] = {}  # crossing person -> lane id its blocker was put on
        self._blocker_type = False
        self._n_routes = 0

    def reverse(self, edge: str) -> str | None:
        """The edge the other way between the same junctions (the far side of the road), or None."""
        return self._reverse.get(edge)

    @staticmethod
    def _reverse_edges(edges: list[str]) -> dict[str, str]:
        ends: dict[tuple[str, str], str] = {}
        for e in edges:
            ends[(libsumo.edge.getFromJunction(e), libsumo.edge.getToJunction(e))] = e
        return {e: ends[(b, a)] for (a, b), e in ends.items() if (b, a) in ends}

    # ---------------------------------------------------------------------------- population
    def populate(self) -> None:
        """Put the pedestrians on the sidewalks (at SUMO time 0)."""
        if self.spec.density_per_km <= 0:
            return
        if not self._edges:
            log.info("pedestrians: the network has no sidewalks; none are placed")
            return
        km = sum(libsumo.lane.getLength(f"{e}_0") for e in self._edges) / 1000.0
        n = round(self.spec.density_per_km * km)
        for k in range(n):
            pid = f"ped_{k:04d}"
            edge = self._edges[int(self._rng.integers(len(self._edges)))]
            length = libsumo.lane.getLength(f"{edge}_0")
            pos = float(self._rng.uniform(0.1, 0.9)) * length
            jay = bool(self._rng.random() < self.spec.jaywalk_share)
            libsumo.person.add(pid, edge, pos, depart=libsumo.simulation.getTime())
            if not self._walk_on(pid, edge):
                libsumo.person.appendWaitingStage(pid, 1e6)  # no way anywhere: it stands
            self.walkers.append(pid)
            if jay:
                self.jaywalkers.add(pid)
        log.info("pedestrians: %d on %.2f km of sidewalk edges, %d jaywalkers", n, km, len(self.jaywalkers))

    def _walk_on(self, pid: str, edge: str) -> bool:
        """Append a walking stage from ``edge`` to a random sidewalk edge; False when no route was found."""
        for _ in range(ROUTE_TRIES):
            target = self._edges[int(self._rng.integers(len(self._edges)))]
            if target == edge:
                continue
            stages = libsumo.simulation.findIntermodalRoute(edge, target, modes="")
            edges = [e for s in stages for e in s.edges]
            if len(edges) < 2:
                continue
            arrival = float(self._rng.uniform(0.2, 0.8)) * libsumo.lane.getLength(f"{target}_0")
            libsumo.person.appendWalkingStage(pid, edges, arrival)
            return True
        return False

    def add_crossing(self, pid: str, crossing: Crossing) -> None:
        """A new person (the ``jaywalk`` event's) that crosses along ``crossing``, then walks on in SUMO."""
        self.walkers.append(pid)
        self.crossings[pid] = crossing

    def blockers(self) -> set[str]:
        """SUMO ids of the hidden vehicles that stand in crossing pedestrians' places."""
        return {f"evped_{pid}" for pid in self._blockers}

    def _block(self, pid: str, x: float, y: float, vehicles: set[str]) -> None:
        """Keep a hidden standing vehicle where the crossing person is on a car lane; none elsewhere."""
        v = libsumo.vehicle
        bid = f"evped_{pid}"
        edge, pos, lane = libsumo.simulation.convertRoad(x, y, False, "passenger")
        on_lane = bool(edge) and not edge.startswith(":")
        if on_lane:
            lane_id = f"{edge}_{lane}"
            cx, cy = libsumo.simulation.convert2D(edge, pos, lane)
            on_lane = math.dist((cx, cy), (x, y)) <= libsumo.lane.getWidth(lane_id) / 2 + SIZE_M[1] / 2
        present = bid in vehicles
        if not on_lane:
            if pid in self._blockers:
                if present:
                    v.unsubscribe(bid)  # the traffic sim subscribed it when it departed
                v.remove(bid)  # also when SUMO has not put it in yet
                del self._blockers[pid]
            return
        front = min(pos + SIZE_M[0] / 2, libsumo.lane.getLength(lane_id))
        if present:
            if self._blockers[pid] != lane_id:  # onto the lane (and edge: a new route) the person is on now
                fx, fy = libsumo.simulation.convert2D(edge, front, lane)
                v.moveToXY(bid, edge, lane, fx, fy, libsumo.lane.getAngle(lane_id, front), 0)
        elif pid not in self._blockers:
            if not self._blocker_type:
                libsumo.vehicletype.copy("car_0", BLOCKER_TYPE)
                libsumo.vehicletype.setLength(BLOCKER_TYPE, SIZE_M[0])
                libsumo.vehicletype.setWidth(BLOCKER_TYPE, SIZE_M[1])
                libsumo.vehicletype.setMinGap(BLOCKER_TYPE, 0.1)
                self._blocker_type = True
            route = f"route_{bid}_{self._n_routes}"
            self._n_routes += 1
            libsumo.route.add(route, [edge])
            v.add(bid, route, typeID=BLOCKER_TYPE, depart="now", departLane=str(lane),
                  departPos=f"{front:.3f}", departSpeed="0")
            v.setSpeedMode(bid, 0)
            v.setLaneChangeMode(bid, 0)
            v.setSpeed(bid, 0.0)
        else:  # added, not in yet (SUMO waits for room): it goes in there when there is room
            return
        self._blockers[pid] = lane_id
        if present:
            v.setSpeed(bid, 0.0)

    def present(self) -> set[str]:
        """Ids of every pedestrian on the map now (in SUMO or crossing a road)."""
        return set(libsumo.person.getIDList()) | set(self.crossings)

    # ------------------------------------------------------------------------------ stepping
    def after_step(self, t_ns: int) -> None:
        """Carry crossings on (and put a person that has crossed back into SUMO), give walkers near their end
        a new walk, start jaywalks; keep every pedestrian's walked distance."""
        P = libsumo.person
        in_sumo = set(P.getIDList())
        vehicles = set(libsumo.vehicle.getIDList()) if self.crossings else set()
        for pid in self.walkers:
            cr = self.crossings.get(pid)
            if cr is not None and cr.back_in_sumo and pid in in_sumo:
                del self.crossings[pid]  # SUMO walks it on from the far sidewalk
                cr = None
            if cr is None and pid not in in_sumo:
                continue
            x, y = cr.at(t_ns)[:2] if cr is not None else P.getPosition(pid)
            prev = self._last_xy.get(pid)
            self._odo[pid] = self._odo.get(pid, 0.0) + (math.dist(prev, (x, y)) if prev else 0.0)
            self._last_xy[pid] = (x, y)
            if cr is not None:
                self._block(pid, x, y, vehicles)
                if cr.at(t_ns)[2] and not cr.back_in_sumo:
                    P.add(pid, cr.far_edge, cr.far_pos_m, depart=libsumo.simulation.getTime())
                    if not self._walk_on(pid, cr.far_edge):
                        P.appendWaitingStage(pid, 1e6)
                    cr.back_in_sumo = True
                continue
            road = P.getRoadID(pid)
            if road.startswith(":") or not road:
                continue
            if P.getRemainingStages(pid) == 1 and road == P.getEdges(pid)[-1]:
                self._walk_on(pid, road)
            elif pid in self.jaywalkers and self._rng.random() < self._step_s / self.spec.jaywalk_every_s:
                self._start_jaywalk(pid, road, t_ns)

    def _start_jaywalk(self, pid: str, road: str, t_ns: int) -> None:
        far = self._reverse.get(road)
        pos = libsumo.person.getLanePosition(pid)
        mid_block = KERB_MARGIN_M < pos < libsumo.lane.getLength(f"{road}_0") - KERB_MARGIN_M
        far_lane = sidewalk_lane(far) if far is not None else None
        if far is None or far_lane is None or not mid_block:
            return
        x, y = libsumo.person.getPosition(pid)
        end = nearest_on(libsumo.lane.getShape(far_lane), x, y)
        far_pos = libsumo.lane.getLength(far_lane) - pos  # the far edge runs the other way
        speed = max(libsumo.person.getMaxSpeed(pid), 1.0)
        libsumo.person.remove(pid)
        self.crossings[pid] = Crossing((x, y), end, t_ns, speed, far, min(max(far_pos, 0.5),
                                                                          libsumo.lane.getLength(far_lane) - 0.5))

    # ------------------------------------------------------------------------------- reading
    def states(self, t_ns: int) -> list[VehicleState]:
        """Every pedestrian on the map, sorted by id."""
        P = libsumo.person
        out = []
        for pid in sorted(set(self.walkers) & self.present()):
            cr = self.crossings.get(pid)
            if cr is not None:
                x, y, done = cr.at(t_ns)
                yaw, speed = cr.yaw_rad, 0.0 if done else cr.speed_mps
                ground = ROAD_Z[1]
            else:
                x, y = P.getPosition(pid)
                yaw, speed = math.radians(90.0 - P.getAngle(pid)), P.getSpeed(pid)
                ground = SIDEWALK_Z[1] if self.where(pid) == "sidewalk" else ROAD_Z[1]
            phase = (self._odo.get(pid, 0.0) / STRIDE_M) % 1.0
            # the label box is the tight box of this person's body in this pose (cosim.sensors.assets.people)
            size, (bx, by, bz) = posed_box(pid, phase, speed)
            c, s_ = math.cos(yaw), math.sin(yaw)
            out.append(VehicleState(
                sumo_id=pid, cls="pedestrian", center_m=(x + c * bx - s_ * by, y + s_ * bx + c * by, ground + bz),
                size_m=size, yaw_rad=math.atan2(math.sin(yaw), math.cos(yaw)), pitch_rad=0.0, speed_mps=speed,
                velocity_mps=(speed * math.cos(yaw), speed * math.sin(yaw), 0.0), accel_mps2=0.0, yaw_rate_radps=0.0,
                gait_phase=phase,
            ))
        return out

    def where(self, pid: str) -> str:
        """``sidewalk``, ``crossing``, ``walkingarea`` or ``road``: the kind of place the person is on."""
        if pid in self.crossings:
            return "road"
        lane = libsumo.person.getLaneID(pid)
        m = _JUNCTION_LANE.match(lane)
        if m:
            return {"c": "crossing", "w": "walkingarea"}[m.group(1)]
        return "sidewalk" if sidewalk_lane(libsumo.person.getRoadID(pid)) == lane else "road"
