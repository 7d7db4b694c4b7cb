"""The drone fleet: one dynamics backend, controller, wind and strategy per drone, stepped in lockstep.

``DroneFleet.step_to(t_ns, tick, escort_targets)`` advances every drone to ``t_ns`` at the physics
rate and returns one :class:`cosim.protocol.DroneState` per drone, in drone index order
(drone_0, drone_1, ...). The drone worker process wraps this; nothing here touches Zenoh.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from cosim.drones.airframe import Airframe, airframe_for_mass, rotor_power_w
from cosim.drones.backends import backend_class
from cosim.drones.backends.base import DynamicsBackend
from cosim.drones.control import BodyState, Controller, Limits, yaw_of
from cosim.drones.obstacles import Obstacles
from cosim.drones.routes import (
    LanePaths,
    RoadGraph,
    hover_point,
    lane_paths,
    patrol_loop,
    ranked_junctions,
    road_graph,
    world_centre,
)
from cosim.drones.separation import Yield, closest_pair, plan_layers, yield_plan
from cosim.drones.strategies import (
    Escort,
    GoTo,
    Hover,
    Patrol,
    Strategy,
    climb_first,
    planned_altitude,
    polyline_points,
)
from cosim.drones.wind import Wind
from cosim.errors import CollisionError, DroneCollisionError, ScenarioError, WorkerError
from cosim.geometry import quat_from_matrix, quat_from_rpy
from cosim.protocol import DroneState, EscortTarget
from cosim.scenario.model import EscortDrone, HoverDrone, PatrolDrone, Scenario
from cosim.world.types import World

log = logging.getLogger(__name__)

WIND_STREAM = 0xD12E  # SeedSequence tag of the drones' random streams
MIN_PHYSICS_HZ = 20.0  # [Hz] the attitude and rate loops need at least this (unstable at 5 Hz)
LAND_HOLD_M = 0.5  # [m] a landed drone holds this far above the surface under it (no touchdown model)
#: A gentle start: over the first START_S of an episode every drone's tilt is limited to START_TILT_DEG
#: (its attitude loop overshoots by a degree or two), so that a drone placed in its strategy's steady state
#: eases into the manoeuvres it meets at once (an escort whose vehicle brakes at a red light lags a few
#: metres behind for a moment instead of pitching at 30 degrees or more; a patrol's first corner).
START_S = 2.0  # [s]
START_TILT_DEG = 21.0  # [deg]


@dataclass
class _Drone:
    agent_id: str
    backend: DynamicsBackend
    controller: Controller
    wind: Wind
    strategy: Strategy
    radius_m: float
    size_m: tuple[float, float, float]
    clearance_m: float | None  # None: no altitude planning, no climb-first guard
    limits: Limits | None = None  # the flight envelope after the start (the controller's during START_S is gentler)
    energy_j: float = 0.0
    state: BodyState | None = None  # the backend's state after the last reset or step


def build_strategy(
    spec: HoverDrone | PatrolDrone | EscortDrone,
    kind_index: int,
    world: World,
    obstacles: Obstacles,
    roads: RoadGraph | None = None,
    taken: set | None = None,
    lanes: LanePaths | None = None,
) -> Strategy:
    """The strategy of one drone; ``kind_index`` counts drones of the same strategy (0, 1, ...);
    generated patrol loops follow ``roads`` (:func:`road_graph`) when given, avoiding blocks in
    ``taken`` (see :func:`patrol_loop`) over the lane centre lines ``lanes`` (:func:`lane_paths`).

    The planned altitude covers the whole path the strategy flies, including the transit from
    ``spec.start`` when one is given. An escort starts at its offset point when the first
    ``step_to`` (t=0) carries its target; otherwise it waits, hovering, at ``spec.start`` or above
    the k-th ranked junction until a target arrives.
    """
    clearance = spec.clearance_m if spec.plan_altitude else None
    start = None if spec.start is None else np.array([spec.start], dtype=np.float64)
    if isinstance(spec, HoverDrone):
        xy = np.array(spec.point if spec.point is not None else hover_point(world, kind_index), dtype=np.float64)
        path = xy[None, :] if start is None else np.vstack([start, xy[None, :]])
        z = planned_altitude(obstacles, polyline_points(path), spec.altitude_m, clearance)
        return Hover(np.array([xy[0], xy[1], z]))
    if isinstance(spec, PatrolDrone):
        if spec.waypoints is not None:
            wps = np.array(spec.waypoints, dtype=np.float64)
        else:
            wps = patrol_loop(world, kind_index, spec.loop_length_m, roads, taken, lanes)
        path = np.vstack([wps, wps[:1]]) if start is None else np.vstack([start, wps, wps[:1]])
        z = planned_altitude(obstacles, polyline_points(path), spec.altitude_m, clearance)
        return Patrol(np.column_stack([wps, np.full(len(wps), z)]), spec.speed_mps, spec.reach_radius_m)
    if isinstance(spec, EscortDrone):
        if start is not None:
            xy = start[0]
        else:
            js = ranked_junctions(world)
            xy = np.array(js[kind_index % len(js)].position_m, dtype=np.float64) if js else world_centre(world)
        z = planned_altitude(obstacles, xy[None, :], spec.altitude_m, clearance)
        return Escort(spec.offset_m, spec.altitude_m, clearance, obstacles, np.array([xy[0], xy[1], z]))
    raise TypeError(f"unknown drone spec {type(spec).__name__}")


def way_of(spec: HoverDrone | PatrolDrone | EscortDrone, strategy: Strategy) -> np.ndarray | None:
    """(N, 2) where a drone can fly, for layer planning: a hover's point, a patrol's loop (with the
    transit from ``spec.start``); None for an escort (it goes wherever its vehicle goes)."""
    if isinstance(strategy, Hover):
        way = strategy.point_m[None, :2]
    elif isinstance(strategy, Patrol):
        way = strategy.waypoints_m[:, :2]
    else:
        return None
    return way if spec.start is None else np.vstack([np.array([spec.start], dtype=np.float64), way])


def flight_z(strategy: Strategy) -> float:
    """[m] the planned flight z of a strategy before layering (an escort: at its start)."""
    return float(strategy.start()[0][2])


class DroneFleet:
    """All drones of a scenario, physics at ``agents.drone_physics_hz``.

    Drones keep ``agents.drone_separation_m`` from each other (:mod:`cosim.drones.separation`:
    altitude layers, and yielding in flight); two drones closer than their rotor discs allow raise
    :class:`DroneCollisionError`. ``min_separation_m`` is the smallest centre distance between two
    drones seen at any physics step so far (inf with fewer than two drones).
    """

    def __init__(self, scenario: Scenario, world: World):
        a = scenario.agents
        if a.drone_physics_hz < MIN_PHYSICS_HZ:
            raise ScenarioError(
                f"drone physics at {a.drone_physics_hz:g} Hz is too slow for the flight controller; "
                f"use at least {MIN_PHYSICS_HZ:g} Hz (100 recommended)",
                path="agents.drone_physics_hz",
            )
        self.scenario = scenario
        self.world = world
        self.tick_ns = scenario.tick_ns
        self.substeps = round(a.drone_physics_hz / scenario.tick_hz)
        self.dt_s = 1.0 / a.drone_physics_hz
        self.obstacles = Obstacles.from_layout(world.layout)
        self.frame: Airframe = airframe_for_mass(a.drone_mass_kg)
        seeds = np.random.SeedSequence([scenario.seed, WIND_STREAM]).spawn(len(a.drones) + 1)
        wind_dir = float(np.random.default_rng(seeds[0]).uniform(-math.pi, math.pi))
        env = scenario.environment
        half = self.frame.half_extents_m
        needs_roads = any(isinstance(d, PatrolDrone) and d.waypoints is None for d in a.drones)
        roads = road_graph(world.net_xml) if needs_roads else {}
        lanes = lane_paths(world.net_xml) if needs_roads else {}
        taken: set = set()
        counts: dict[str, int] = {}
        self._drones: list[_Drone] = []
        self._t_ns: int | None = None
        self.separation_m = a.drone_separation_m
        self._contact_m = 2.0 * float(math.hypot(half[0], half[1]))  # [m] two rotor-tip circles touch
        self._yields: list[Yield] = []
        self.min_separation_m = math.inf
        try:
            for i, spec in enumerate(a.drones):
                k = counts.get(spec.strategy, 0)
                counts[spec.strategy] = k + 1
                try:
                    strategy = build_strategy(spec, k, self.world, self.obstacles, roads, taken, lanes)
                except ValueError as exc:
                    raise ScenarioError(str(exc), path=f"agents.drones.{i}") from exc
                backend = backend_class(a.drone_backend_of(i))(self.frame, self.dt_s, world)
                limits = Limits.for_speed(spec.max_speed_mps, self.frame)
                start_limits = dataclasses.replace(
                    limits, max_tilt_rad=min(limits.max_tilt_rad, math.radians(START_TILT_DEG)))
                wind = Wind.create(env.wind_mps, wind_dir, env.gust_mps, self.dt_s, np.random.default_rng(seeds[i + 1]))
                drone = _Drone(
                    f"drone_{i}",
                    backend,
                    Controller(self.frame, self.dt_s, start_limits),
                    wind,
                    strategy,
                    radius_m=float(math.hypot(half[0], half[1])) * 0.75,
                    size_m=(2 * half[0], 2 * half[1], 2 * half[2]),
                    clearance_m=spec.clearance_m if spec.plan_altitude else None,
                    limits=limits,
                )
                self._drones.append(drone)
            layers = plan_layers(
                [flight_z(d.strategy) for d in self._drones],
                [way_of(spec, d.strategy) for spec, d in zip(a.drones, self._drones, strict=True)],
                self.separation_m,
            )
            for spec, d, z in zip(a.drones, self._drones, layers, strict=True):
                d.strategy.fly_at(z)
                self._place(d, spec.start)
                log.info(
                    "%s: %s on %s, starts at %s",
                    d.agent_id,
                    spec.strategy,
                    d.backend.name,
                    np.round(d.state.position_m, 1).tolist(),
                )
            self._check_separation(0)
        except Exception:
            self.close()
            raise

    @staticmethod
    def _place(d: _Drone, start: tuple[float, float] | None) -> None:
        """At the strategy's start, in its steady state (:meth:`Strategy.start_velocity`); a given ``start``
        point begins at rest."""
        pos, yaw = d.strategy.start()
        if start is not None:
            pos = np.array([start[0], start[1], pos[2]])
        d.backend.reset(pos, yaw, d.strategy.start_velocity() if start is None else None)
        d.state = d.backend.state()
        d.controller.yaw_setpoint_rad = yaw
        d.controller.vel_integral[:] = 0.0

    @property
    def agent_ids(self) -> list[str]:
        return [d.agent_id for d in self._drones]

    def step_to(self, t_ns: int, tick: int, escort_targets: dict[str, EscortTarget]) -> list[DroneState]:
        """Advance to ``t_ns`` (0 on the first call: initial states, no integration).

        ``escort_targets`` maps drone agent id -> its target's state at the previous tick (at t=0:
        the state at t=0). Raises :class:`CollisionError` when a drone hits an obstacle or the ground.
        """
        if self._t_ns is None:
            if t_ns != 0:
                raise WorkerError("drones", f"the first step must be t_ns=0, got {t_ns}", tick=tick)
            for i, d in enumerate(self._drones):
                if isinstance(d.strategy, Escort):
                    d.strategy.observe(0.0, escort_targets.get(d.agent_id))
                    self._place(d, self.scenario.agents.drones[i].start)
            self._check_separation(0)
            self._t_ns = 0
            return [self._state_of(d) for d in self._drones]
        span = t_ns - self._t_ns
        if span <= 0 or span % self.tick_ns:
            raise WorkerError(
                "drones",
                f"step to t_ns={t_ns} from t_ns={self._t_ns} is not a whole number of {self.tick_ns} ns ticks",
                tick=tick,
            )
        t_prev_s = self._t_ns * 1e-9
        for d in self._drones:
            if isinstance(d.strategy, Escort):
                d.strategy.observe(t_prev_s, escort_targets.get(d.agent_id))
        n_steps = (span // self.tick_ns) * self.substeps
        for k in range(n_steps):
            if k % self.substeps == 0:
                self._yields = yield_plan(
                    np.array([d.state.position_m for d in self._drones]).reshape(-1, 3),
                    np.array([d.state.velocity_mps for d in self._drones]).reshape(-1, 3),
                    [d.strategy.name for d in self._drones],
                    self.separation_m,
                )
            t_s = t_prev_s + k * self.dt_s
            for d, y in zip(self._drones, self._yields, strict=True):
                self._physics_step(d, y, t_s, tick)
            self._check_separation(tick)
        self._t_ns = t_ns
        return [self._state_of(d) for d in self._drones]

    def command(self, action: dict, tick: int) -> str | None:
        """Apply one closed-loop client action (cosim.actions, already validated) from now on;
        returns why it cannot be applied, else None. The drone keeps its airframe and speed limit."""
        from cosim.actions import Escort as EscortAction
        from cosim.actions import GoTo as GoToAction
        from cosim.actions import Land, SetStrategy, parse_action

        a = parse_action(action)
        if a.agent not in self.agent_ids:
            return f"no drone {a.agent}"
        i = self.agent_ids.index(a.agent)
        d, spec = self._drones[i], self.scenario.agents.drones[i]
        pos = np.array(d.state.position_m, dtype=np.float64)
        if isinstance(a, GoToAction):
            goal = np.array(a.position_m, dtype=np.float64)
            z = planned_altitude(self.obstacles, polyline_points(np.array([pos[:2], goal])), a.altitude_m,
                                 d.clearance_m)
            d.strategy = GoTo(pos, np.array([goal[0], goal[1], z]), min(a.speed_mps, spec.max_speed_mps),
                              start_velocity_mps=np.array(d.state.velocity_mps, dtype=np.float64))
        elif isinstance(a, Land):
            surface = self.obstacles.top_near(float(pos[0]), float(pos[1]), d.radius_m)
            goal = np.array([pos[0], pos[1], surface + d.radius_m + LAND_HOLD_M])
            d.strategy = GoTo(pos, goal, a.speed_mps, name="land", arrived_label="landed")
        elif isinstance(a, SetStrategy | EscortAction):
            new = a.drone if isinstance(a, SetStrategy) else EscortDrone(
                target=a.target, offset_m=a.offset_m, altitude_m=a.altitude_m, clearance_m=spec.clearance_m,
                plan_altitude=spec.plan_altitude)
            generated = isinstance(new, PatrolDrone) and new.waypoints is None
            roads = road_graph(self.world.net_xml) if generated else None
            lanes = lane_paths(self.world.net_xml) if generated else None
            try:
                d.strategy = build_strategy(new, i, self.world, self.obstacles, roads, set(), lanes)
            except ValueError as exc:
                return str(exc)
        else:
            return f"{a.type} is not a drone action"
        log.info("%s at tick %d: %s", a.agent, tick, a.type)
        return None

    def _check_separation(self, tick: int) -> None:
        """Track the smallest distance between two drones; raise when two touch."""
        if len(self._drones) < 2:
            return
        dist, i, j = closest_pair(np.array([d.state.position_m for d in self._drones]))
        self.min_separation_m = min(self.min_separation_m, dist)
        if dist < self._contact_m:
            raise DroneCollisionError(self._drones[i].agent_id, self._drones[j].agent_id, tick, dist)

    def _physics_step(self, d: _Drone, y: Yield, t_s: float, tick: int) -> None:
        """One physics step of ``dt_s`` starting at ``t_s``: guidance, separation, control, dynamics, checks."""
        s = d.state
        if t_s >= START_S and d.limits is not None:
            d.controller.limits, d.limits = d.limits, None
        ref = y.apply(d.strategy.reference(t_s, s), s.position_m)
        if d.clearance_m is not None:
            ref = climb_first(ref, s, self.obstacles)
        cmd = d.controller.update(s, ref)
        d.backend.step(cmd, d.wind.step())
        d.energy_j += rotor_power_w(d.backend.rotors.thrust_n, self.frame) * self.dt_s
        d.state = d.backend.state()
        what = d.backend.contact() or self.obstacles.hit(d.state.position_m, d.radius_m)
        if what is not None:
            raise CollisionError(d.agent_id, tick, what)

    def _state_of(self, d: _Drone) -> DroneState:
        s: BodyState = d.state
        return DroneState(
            agent_id=d.agent_id,
            position_m=tuple(float(v) for v in s.position_m),
            rotation=quat_from_matrix(s.rotation),
            velocity_mps=tuple(float(v) for v in s.velocity_mps),
            angular_rate_radps=tuple(float(v) for v in s.rate_radps),
            specific_force_mps2=tuple(float(v) for v in s.specific_force_mps2),
            gimbal_rotation=quat_from_rpy(0.0, 0.0, yaw_of(s.rotation)),
            energy_used_j=float(d.energy_j),
            strategy=d.strategy.name,
            strategy_state=d.strategy.label(),
            size_m=d.size_m,
        )

    def close(self) -> None:
        for d in self._drones:
            d.backend.close()
        self._drones = []
