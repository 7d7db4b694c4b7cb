"""The SUMO adapter: start libsumo on a World, step to a time, read every vehicle as a VehicleState.

libsumo allows one simulation per process; the traffic worker owns one :class:`TrafficSim`.
SUMO time = :data:`WARMUP_S` + episode time: vehicles depart at SUMO time 0 (standing) and the
warm-up lets them get moving, so at episode t = 0 every connected vehicle is on the road.
Connected vehicles' routes are extended before they end (:meth:`TrafficSim._extend_routes`), so they
stay for the whole episode on a network where their class can always go on. Background vehicles
drive to a sink at the edge of the map (:func:`cosim.world.routes.sources_and_sinks`) and leave; each
one that leaves is replaced by a new vehicle of the same class (a new id ``bg_<nnnn>``, never reused)
entering from a random source, so the number of vehicles and the class shares stay as planned while
the vehicles change (:meth:`TrafficSim._replace`).
"""

from __future__ import annotations

import bisect
import logging
import math
import xml.etree.ElementTree as ET
from fractions import Fraction
from pathlib import Path
from typing import Any

import libsumo
import numpy as np
from libsumo import constants as tc

from cosim.errors import WorkerError
from cosim.geometry import sumo_front_to_center, wrap_angle
from cosim.protocol import VehicleState
from cosim.scenario.model import Scenario
from cosim.traffic.events import Timeline
from cosim.traffic.pedestrians import Pedestrians
from cosim.world.netgen import sumo_binary
from cosim.world.routes import inner_edges, read_sumolib, sources_and_sinks, strong_core
from cosim.world.types import World
from cosim.world.vtypes import SUMO_VCLASS, class_of_type, variants

log = logging.getLogger(__name__)

WARMUP_S = 4  # [s] SUMO time before episode t = 0 (a whole number of seconds)
REROUTE_EDGES_LEFT = 2  # extend a route when the vehicle is on one of its last edges
LANE_CHANGE_S = 1.5  # [s] duration of a lane change (continuous, not a sideways jump)
IMPATIENCE_S = 20.0  # [s] a driver waiting at a minor link (a left turn across a busy road, say) grows fully
# impatient in this time and takes a smaller gap (SUMO --time-to-impatience, default 300 s: cars waited 30 s+)
TRAIL_M = 40.0  # [m] of driven path kept per vehicle (longer than the longest vehicle)
#: per-vehicle values read every SUMO step (one subscription call instead of one call per value)
SUBSCRIBED = (tc.VAR_DISTANCE, tc.VAR_ROAD_ID, tc.VAR_LANEPOSITION, tc.VAR_LANE_INDEX, tc.VAR_ROUTE_INDEX)
SEED_SALT = 7919  # SUMO's --seed = (scenario seed * salt + 1) mod 2^31


def sumo_seed(seed: int) -> int:
    return (seed * SEED_SALT + 1) % (2**31 - 1)


class TrafficSim:
    """libsumo on ``world``; :meth:`step_to` advances in ``traffic.step_hz`` sub-steps."""

    def __init__(self, scenario: Scenario, world: World, workdir: Path) -> None:
        if libsumo.simulation.isLoaded():
            raise WorkerError("traffic", "a SUMO simulation is already running in this process (libsumo allows one)")
        self.scenario = scenario
        workdir = Path(workdir)
        workdir.mkdir(parents=True, exist_ok=True)
        net_path = workdir / "traffic.net.xml"
        routes_path = workdir / "traffic.rou.xml"
        net_path.write_bytes(world.net_xml)
        routes_path.write_bytes(world.routes_xml)
        self.step_hz = Fraction(scenario.traffic.step_hz).limit_denominator(10_000)
        step_s = 1 / self.step_hz
        if (step_s * 1000).denominator != 1:  # SUMO keeps time in whole milliseconds
            raise WorkerError(
                "traffic",
                f"traffic.step_hz = {float(self.step_hz):g} Hz gives a SUMO step of {float(step_s) * 1000:.4g} ms; "
                "SUMO steps in whole milliseconds (use for example 10, 20, 25, 40 or 50 Hz)",
            )
        self._rng = np.random.default_rng([scenario.seed, 10])
        net = read_sumolib(world.net_xml)
        self._targets = {c: inner_edges(net, strong_core(net, c)) for c in sorted(set(SUMO_VCLASS.values()))}
        self._gates = {c: sources_and_sinks(net, c) for c in sorted(set(SUMO_VCLASS.values()))}
        planned = [v.get("id", "") for v in ET.fromstring(world.routes_xml).iter("vehicle")] if world.routes_xml else []
        self._next_bg = 1 + max((int(v[3:]) for v in planned if v.startswith("bg_") and v[3:].isdigit()), default=-1)
        self._first_new = self._next_bg  # ids from here on entered during the run
        self._class: dict[str, str] = {}  # background vehicle id -> object class, from its departure
        cmd = [
            sumo_binary("sumo"),
            "-n",
            str(net_path),
            "-r",
            str(routes_path),
            "--step-length",
            f"{float(step_s):.6f}",
            "--begin",
            "0",
            "--seed",
            str(sumo_seed(scenario.seed)),
            "--no-step-log",
            "true",
            "--no-warnings",
            "true",
            "--duration-log.disable",
            "true",
            "--xml-validation",
            "never",
            "--time-to-teleport",
            "-1",
            "--time-to-teleport.highways",
            "-1",
            "--collision.action",
            "warn",
            "--lanechange.duration",
            f"{LANE_CHANGE_S}",
            "--time-to-impatience",
            f"{IMPATIENCE_S:g}",
        ]
        try:
            libsumo.start(cmd)
        except libsumo.TraCIException as exc:
            raise WorkerError("traffic", f"SUMO failed to start: {exc}") from exc
        self._step = 0  # SUMO steps done
        self._warmup_steps = int(WARMUP_S * self.step_hz)
        self._prev_yaw: dict[str, float] = {}
        self._trails: dict[str, list[tuple[float, str, float, int]]] = {}
        self._route_len: dict[str, int] = {}
        self.teleports = 0  # vehicles SUMO teleported (jam resolution is off, so this stays 0)
        self.collisions = 0  # vehicles SUMO found in a collision (lane-based check)
        self.entered = 0  # background vehicles that entered after SUMO time 0 (replacements)
        self.left = 0  # background vehicles that reached their sink and left the map
        self._closed = False
        self.pedestrians = Pedestrians(scenario.pedestrians, np.random.default_rng([scenario.seed, 12]), float(step_s))
        self.pedestrians.populate()
        self.timeline = Timeline(scenario, self._destinations, np.random.default_rng([scenario.seed, 11]),
                                 self.pedestrians)
        self._advance_to(self._warmup_steps)
        present = set(libsumo.vehicle.getIDList())
        missing = [f"vehicle_{i}" for i in range(scenario.agents.vehicles.count) if f"vehicle_{i}" not in present]
        if missing:
            self.close()
            raise WorkerError("traffic", f"connected vehicles not on the road at t=0: {', '.join(missing)}")

    # ------------------------------------------------------------------------------- stepping
    def _advance_to(self, target_step: int) -> None:
        dt = float(1 / self.step_hz)
        while self._step < target_step:
            if self._step == target_step - 1:
                self._prev_yaw = {
                    v: math.radians(90.0 - self._heading_deg(v, libsumo.vehicle.getLength(v)))
                    for v in libsumo.vehicle.getIDList()
                }
            t_after_ns = round((self._step + 1 - self._warmup_steps) / self.step_hz * 1_000_000_000)
            self.timeline.before_step(t_after_ns)
            libsumo.simulationStep()
            self._step += 1
            self.timeline.after_step(t_after_ns)
            self.pedestrians.after_step(t_after_ns)
            self.teleports += libsumo.simulation.getStartingTeleportNumber()
            self.collisions += libsumo.simulation.getCollidingVehiclesNumber()
            for vid in libsumo.simulation.getDepartedIDList():
                libsumo.vehicle.subscribe(vid, SUBSCRIBED)
                if not vid.startswith(("vehicle_", "ev")):
                    self._class[vid] = class_of_type(libsumo.vehicle.getTypeID(vid))
                    self.entered += vid >= f"bg_{self._first_new:04d}"
            for vid in sorted(libsumo.simulation.getArrivedIDList()):
                self._trails.pop(vid, None)
                self._route_len.pop(vid, None)
                cls = self._class.pop(vid, None)
                if cls is not None:
                    self.left += 1
                    self._replace(cls)
            res = libsumo.vehicle.getAllSubscriptionResults()
            self._record_trails(res)
            self._extend_routes(res)
        self._dt = dt

    def _replace(self, cls: str) -> None:
        """Send a new background vehicle of class ``cls`` in from a random source to a random sink.

        It is added now and departs at the next step, at the start of its source edge at the highest
        safe speed (SUMO keeps it waiting while the entry is blocked)."""
        vclass = SUMO_VCLASS[cls]
        sources, sinks = self._gates[vclass]
        of_class = variants()[cls]
        variant = of_class[int(self._rng.integers(len(of_class)))]
        vid = f"bg_{self._next_bg:04d}"
        for _ in range(10 if sources and sinks else 0):
            a = sources[int(self._rng.integers(len(sources)))]
            b = sinks[int(self._rng.integers(len(sinks)))]
            try:
                edges = libsumo.simulation.findRoute(a, b, vType=variant.type_id).edges
            except libsumo.TraCIException:  # an event closed the source edge to this type (a road block)
                continue
            if not edges:
                continue
            libsumo.route.add(f"route_{vid}", list(edges))
            libsumo.vehicle.add(vid, f"route_{vid}", typeID=variant.type_id, depart="now", departLane="best",
                                departPos="base", departSpeed="max")
            self._next_bg += 1
            return
        log.info("no route from a source to a sink for a %s; the map keeps one fewer", cls)

    def _destinations(self, vid: str) -> list[str]:
        """Where a vehicle may be sent: anywhere in its class's core for connected vehicles, sinks otherwise."""
        vclass = libsumo.vehicle.getVehicleClass(vid)
        if vid.startswith("vehicle_"):
            return list(self._targets.get(vclass, []))
        return list(self._gates.get(vclass, ([], []))[1])

    def _extend_routes(self, res: dict[str, dict[int, object]]) -> None:
        """Give every connected vehicle on one of its last route edges a new random destination (sorted
        id order); background vehicles drive on to their sink."""
        v = libsumo.vehicle
        for vid in sorted(res):
            if not vid.startswith("vehicle_"):
                continue
            r = res[vid]
            idx = int(r[tc.VAR_ROUTE_INDEX])
            if vid not in self._route_len:
                self._route_len[vid] = len(v.getRoute(vid))
            if idx < self._route_len[vid] - REROUTE_EDGES_LEFT or str(r[tc.VAR_ROAD_ID]).startswith(":"):
                continue
            route = v.getRoute(vid)
            targets = self._targets.get(v.getVehicleClass(vid), [])
            for _ in range(8 if targets else 0):
                target = targets[int(self._rng.integers(len(targets)))]
                if target in route[idx:]:
                    continue
                try:
                    v.changeTarget(vid, target)
                except libsumo.TraCIException:
                    continue
                self._route_len[vid] = len(v.getRoute(vid))
                break

    def step_to(self, t_ns: int, pedestrians: bool = True) -> list[VehicleState]:
        """Advance to episode time ``t_ns`` and return every vehicle, sorted by SUMO id, then the events' obstacles
        and the pedestrians. ``pedestrians=False`` leaves the pedestrians out (the simulation is the same: their
        states are only read, and their posed label boxes are most of a town's step) for callers that need the
        vehicles alone."""
        if self._closed:
            raise WorkerError("traffic", "step_to after close")
        steps = Fraction(t_ns, 1_000_000_000) * self.step_hz
        if steps.denominator != 1:
            raise WorkerError("traffic", f"t_ns = {t_ns} is not a whole number of SUMO steps at {self.step_hz} Hz")
        target = self._warmup_steps + int(steps)
        if target < self._step:
            raise WorkerError("traffic", f"cannot step back to t_ns = {t_ns}")
        self._advance_to(target)
        hidden = self.timeline.hidden() | self.pedestrians.blockers()
        vehicles = [self._read(v, t_ns) for v in sorted(libsumo.vehicle.getIDList()) if v not in hidden]
        return vehicles + self.timeline.obstacles() + (self.pedestrians.states(t_ns) if pedestrians else [])

    def events(self) -> list[dict[str, object]]:
        """The scenario's events as they stand (records of the ``/events`` topic, SUMO ids)."""
        return self.timeline.records()

    def signal_states(self) -> dict[str, str]:
        """SUMO's current state string of every traffic light (one character per link index), by id."""
        tl = libsumo.trafficlight
        return {t: tl.getRedYellowGreenState(t) for t in sorted(tl.getIDList())}

    def _record_trails(self, res: dict[str, dict[int, object]]) -> None:
        """Append every vehicle's (odometer, road, lane position, lane index) to its trail."""
        for vid, r in res.items():
            odo, road = float(r[tc.VAR_DISTANCE]), str(r[tc.VAR_ROAD_ID])
            pos, idx = float(r[tc.VAR_LANEPOSITION]), int(r[tc.VAR_LANE_INDEX])
            trail = self._trails.setdefault(vid, [])
            if trail and trail[-1][1] == road and trail[-1][3] != idx and not road.startswith(":"):
                # a lane change: the part of the trail on this edge moves to the new lane with it
                trail[:] = [(o, rd, p, idx if rd == road else i) for o, rd, p, i in trail]
            if not trail or odo > trail[-1][0] + 0.2 or trail[-1][1] != road:
                trail.append((odo, road, pos, idx))
            while len(trail) > 2 and trail[1][0] < odo - TRAIL_M:
                trail.pop(0)

    def _heading_deg(self, vid: str, length_m: float) -> float:
        """Heading [deg clockwise from north] of the chord from the vehicle's back to its front (:meth:`_chord`)."""
        return self._chord(vid, length_m)[0]

    def _chord(self, vid: str, length_m: float) -> tuple[float, float]:
        """Heading [deg clockwise from north] and length [m] of the chord from the vehicle's back to its
        front, both on the lane centre lines of the path it drove (its trail); length ``length_m`` when
        SUMO's angle is used.

        SUMO's own angle also turns a vehicle by its lateral motion and keeps that turn when a lane change
        ends standing still, so a long vehicle's box would reach into the next lane; the lane chord does
        not, and it follows curves and junctions like SUMO's. Before a vehicle has driven its own length
        on a lane, SUMO's angle is used."""
        v = libsumo.vehicle
        road, pos, idx = v.getRoadID(vid), v.getLanePosition(vid), v.getLaneIndex(vid)
        odo = v.getDistance(vid)
        target = odo - length_m
        trail = self._trails.get(vid, [])
        k = bisect.bisect_right(trail, target, key=lambda e: e[0]) - 1  # odometers never decrease
        if k < 0:
            if road.startswith(":") or pos < length_m:
                return v.getAngle(vid), length_m
            back = libsumo.simulation.convert2D(road, pos - length_m, idx)
        else:
            o0, r0, p0, i0 = trail[k]
            back_pos = p0 + (target - o0)
            lane_len = libsumo.lane.getLength(f"{r0}_{i0}")
            if back_pos > lane_len and k + 1 < len(trail):
                o1, r1, p1, i1 = trail[k + 1]
                r0, i0, back_pos = r1, i1, max(0.0, p1 - (o1 - target))
                lane_len = libsumo.lane.getLength(f"{r0}_{i0}")
            back = libsumo.simulation.convert2D(r0, min(back_pos, lane_len), i0)
        front = libsumo.simulation.convert2D(road, pos, idx)
        dx, dy = front[0] - back[0], front[1] - back[1]
        chord = math.hypot(dx, dy)
        if chord < 0.5 * length_m:
            return v.getAngle(vid), length_m
        return math.degrees(math.atan2(dx, dy)) % 360.0, chord

    def _read(self, vid: str, t_ns: int) -> VehicleState:
        v = libsumo.vehicle
        length, width, height = v.getLength(vid), v.getWidth(vid), v.getHeight(vid)
        fx, fy, fz = v.getPosition3D(vid)
        heading, chord = self._chord(vid, length)
        # the box's centre is the chord's midpoint: on a curve the chord is shorter than the vehicle, and a
        # box hung from the front bumper would put all of the difference behind it (a 13 m truck turning
        # right swung its back 2 m into the next lane, over a car waiting there); centred, the box reaches
        # past both ends of the chord by half of it
        cx, cy, yaw = sumo_front_to_center(fx, fy, heading, chord)
        if vid in self.timeline.pinned:  # an incident's pose (e.g. an accident's turned car)
            cx, cy, yaw = self.timeline.pinned[vid]
        slope = math.radians(v.getSlope(vid))
        pitch = -slope  # FLU: a positive pitch is nose down
        cz = fz - 0.5 * length * math.sin(slope) + 0.5 * height
        speed = v.getSpeed(vid)
        prev = None if vid in self.timeline.pinned else self._prev_yaw.get(vid)
        yaw_rate = 0.0 if prev is None else wrap_angle(yaw - prev) / self._dt
        vel = (
            speed * math.cos(slope) * math.cos(yaw),
            speed * math.cos(slope) * math.sin(yaw),
            speed * math.sin(slope),
        )
        return VehicleState(
            sumo_id=vid,
            cls=class_of_type(v.getTypeID(vid)),
            center_m=(cx, cy, cz),
            size_m=(length, width, height),
            yaw_rad=yaw,
            pitch_rad=pitch,
            speed_mps=speed,
            velocity_mps=vel,
            accel_mps2=v.getAcceleration(vid),
            yaw_rate_radps=yaw_rate,
            agent_id=vid if vid.startswith("vehicle_") else None,
            hazard_lamps_on=self.timeline.hazard_lamps_on(vid, t_ns),
        )

    # --------------------------------------------------------------------- client actions
    def command(self, action: dict[str, Any]) -> str | None:
        """Apply one closed-loop client action (cosim.actions, already validated) to a vehicle;
        returns SUMO's reason when it refuses (no route to the edge, vehicle gone), else None."""
        v, vid, kind = libsumo.vehicle, action["agent"], action["type"]
        try:
            if kind == "set_speed":
                v.setSpeed(vid, -1.0 if action["speed_mps"] is None else action["speed_mps"])
            elif kind == "slow_down":
                v.slowDown(vid, action["speed_mps"], action["duration_s"])
            elif kind == "change_lane":
                lanes = libsumo.edge.getLaneNumber(v.getRoadID(vid)) if not v.getRoadID(vid).startswith(":") else 0
                if action["lane_index"] >= lanes:
                    return f"{vid} is on edge {v.getRoadID(vid)!r} with {lanes} lanes"
                v.changeLane(vid, action["lane_index"], action["duration_s"])
            elif kind == "change_target":
                v.changeTarget(vid, action["edge"])
            elif kind == "set_route":
                v.setRoute(vid, action["edges"])
            else:
                return f"{kind} is not a vehicle action"
        except libsumo.TraCIException as exc:
            return f"SUMO: {exc}"
        if kind in ("change_target", "set_route"):
            self._route_len[vid] = len(v.getRoute(vid))
        return None

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            libsumo.close()

    def __enter__(self) -> TrafficSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
