"""Drone flight dynamics, control and strategies (cosim.drones), on every registered backend.

Test worlds come from benchmarks.drone_demo (a few box buildings on a junction grid, empty net), so the
tests need neither SUMO nor the world builder. Acceptance numbers: ``python -m benchmarks.drone_report``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.drone_demo import demo_world
from benchmarks.drone_report import fly_escort, fly_hover, fly_patrol, rms
from cosim.drones import DroneFleet, backend_class, backend_names, register_backend
from cosim.drones.airframe import G_MPS2, airframe_for_mass
from cosim.drones.backends.base import DynamicsBackend
from cosim.drones.control import BodyState, Controller, mixer_matrix
from cosim.drones.fleet import build_strategy
from cosim.drones.obstacles import Obstacles
from cosim.drones.routes import road_graph
from cosim.drones.strategies import SWING_FEEDFORWARD, Escort, Hover, Patrol
from cosim.drones.wind import Wind
from cosim.errors import CollisionError, DroneCollisionError, InputError, ScenarioError, WorkerError
from cosim.geometry import rotation_matrix
from cosim.protocol import EscortTarget
from cosim.scenario.model import (
    AgentsSpec,
    EnvironmentSpec,
    EscortDrone,
    HoverDrone,
    PatrolDrone,
    Scenario,
    VehicleAgents,
)

BACKENDS = backend_names()
TICK_NS = 200_000_000


def scenario(drones: list, backend: str = "pybullet", seed: int = 0, **kw) -> Scenario:
    agents = AgentsSpec(drones=drones, drone_backend=backend, vehicles=VehicleAgents(count=1))
    return Scenario(name="drones-test", seed=seed, agents=agents, **kw)


def fly(fleet: DroneFleet, seconds: float, targets=None) -> list:
    """Step a fleet from t=0; the per-tick state lists (index 0: t=0)."""
    out = [fleet.step_to(0, 0, targets(0) if targets else {})]
    for k in range(1, round(seconds * 1e9 / TICK_NS) + 1):
        out.append(fleet.step_to(k * TICK_NS, k, targets(k) if targets else {}))
    return out


def level_state(p=(0.0, 0.0, 50.0)) -> BodyState:
    return BodyState(np.array(p), np.eye(3), np.zeros(3), np.zeros(3), np.array([0.0, 0.0, G_MPS2]))


# ------------------------------------------------------------------------------ pure functions


def test_registry_lists_known_backends_on_unknown_name():
    assert {"jsbsim", "pybullet"} <= set(BACKENDS)
    with pytest.raises(InputError, match=r"'xplane'.*jsbsim, pybullet"):
        backend_class("xplane")


def test_registry_rejects_a_second_registration():
    with pytest.raises(ValueError, match="already registered"):
        register_backend("pybullet")(type("Other", (DynamicsBackend,), {}))


def test_mixer_reproduces_the_wrench_within_limits():
    frame = airframe_for_mass(3.5)
    ctl = Controller(frame, 0.01)
    torque = np.array([0.3, -0.2, 0.05])
    t = ctl.mix(4 * frame.hover_thrust_n, torque)
    assert mixer_matrix(frame) @ t == pytest.approx([4 * frame.hover_thrust_n, *torque], abs=1e-9)
    # A yaw demand beyond the rotors' range gives way; thrust and roll/pitch are kept.
    t = ctl.mix(4 * frame.hover_thrust_n, np.array([0.3, -0.2, 50.0]))
    w = mixer_matrix(frame) @ t
    assert np.all(t >= 0) and np.all(t <= frame.rotor_max_thrust_n)
    assert w[:3] == pytest.approx([4 * frame.hover_thrust_n, 0.3, -0.2], abs=1e-9)
    assert 0 < w[3] < 50.0


def test_controller_tilts_toward_a_lateral_target():
    frame = airframe_for_mass(3.5)
    ctl = Controller(frame, 0.01)
    from cosim.drones.control import Reference

    ref = Reference(np.array([10.0, 0.0, 50.0]), np.zeros(3), np.zeros(3), 0.0)
    cmd = ctl.update(level_state(), ref)
    # To accelerate toward +x the body must pitch nose-down: rear rotors (1, 2) push harder.
    assert cmd[1] + cmd[2] > cmd[0] + cmd[3]


def test_wind_gusts_have_the_requested_spread_and_are_seeded():
    def series(seed: int) -> np.ndarray:
        w = Wind.create(3.0, 0.5, 1.5, 0.05, np.random.default_rng(seed))
        return np.array([w.step() for _ in range(40_000)])

    a, b, c = series(1), series(1), series(2)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a[:, :2].mean(axis=0) == pytest.approx([3 * math.cos(0.5), 3 * math.sin(0.5)], abs=0.3)
    assert a[:, 0].std() == pytest.approx(1.5, rel=0.2)
    assert a[:, 2].std() == pytest.approx(0.75, rel=0.2)


def test_obstacles_hit_and_heights():
    obs = Obstacles.from_layout(demo_world().layout)
    assert obs.hit(np.array([250.0, 150.0, 69.0]), 0.5) == "building 1000002 (top 70.0 m)"
    assert obs.hit(np.array([250.0, 150.0, 71.0]), 0.5) is None
    assert obs.hit(np.array([219.7, 150.0, 30.0]), 0.5) is not None  # grazing the wall
    assert obs.hit(np.array([219.0, 150.0, 30.0]), 0.5) is None
    assert obs.hit(np.array([50.0, 100.0, 0.3]), 0.5) == "ground"  # the road strip is no obstacle
    assert obs.hit(np.array([50.0, 100.0, 3.0]), 0.5) is None
    assert obs.top_near(250.0, 150.0, 1.0) == 70.0
    assert obs.top_near(50.0, 50.0, 10.0) == 0.0


def test_altitude_planning_clears_buildings_unless_turned_off():
    world = demo_world()
    obs = Obstacles.from_layout(world.layout)
    through_tower = [(200.0, 150.0), (300.0, 150.0)]
    planned = build_strategy(PatrolDrone(waypoints=through_tower, altitude_m=40.0), 0, world, obs)
    assert isinstance(planned, Patrol)
    assert planned.waypoints_m[:, 2] == pytest.approx(80.0)  # 70 m tower + 10 m clearance
    spec = PatrolDrone(waypoints=through_tower, altitude_m=40.0, clearance_m=25.0)
    assert build_strategy(spec, 0, world, obs).waypoints_m[0, 2] == pytest.approx(95.0)
    spec = PatrolDrone(waypoints=through_tower, altitude_m=40.0, plan_altitude=False)
    assert build_strategy(spec, 0, world, obs).waypoints_m[0, 2] == pytest.approx(40.0)
    # A hover far from buildings keeps its requested height.
    hover = build_strategy(HoverDrone(point=(350.0, 350.0), altitude_m=45.0), 0, world, obs)
    assert isinstance(hover, Hover) and hover.point_m[2] == pytest.approx(45.0)


def test_patrol_with_repeated_waypoints():
    world = demo_world()
    obs = Obstacles.from_layout(world.layout)
    p = build_strategy(PatrolDrone(waypoints=[(0, 0), (50, 0), (50, 0), (0, 0)]), 0, world, obs)
    assert p.waypoints_m[:, :2].tolist() == [[0.0, 0.0], [50.0, 0.0]]
    with pytest.raises(ScenarioError, match=r"agents\.drones\.0.*2 distinct waypoints"):
        DroneFleet(scenario([PatrolDrone(waypoints=[(5, 5), (5, 5)])]), world)


def test_default_hover_points_spread_over_junctions():
    world = demo_world()
    obs = Obstacles.from_layout(world.layout)
    points = [tuple(build_strategy(HoverDrone(), k, world, obs).point_m[:2]) for k in range(4)]
    assert len(set(points)) == 4
    junctions = {j.position_m for j in world.junctions}
    assert set(points) <= junctions
    assert points[0] == (200.0, 200.0)  # the central crossing first


def test_generated_patrol_loops_go_around_blocks_along_roads():
    world = demo_world(with_roads=True)
    obs = Obstacles.from_layout(world.layout)
    graph = road_graph(world.net_xml)
    assert sorted(b for b, _ in graph["j11"]) == ["j01", "j10", "j12", "j21"]
    taken: set = set()
    loops = [build_strategy(PatrolDrone(), k, world, obs, graph, taken).waypoints_m[:, :2] for k in range(4)]
    corners = {j.position_m for j in world.junctions}
    for wps in loops:
        # A 100 m block: 4 junctions joined by roads (axis-aligned legs of 100 m), counter-clockwise.
        assert len(wps) == 4 and {tuple(w) for w in wps} <= corners
        legs = np.roll(wps, -1, axis=0) - wps
        assert np.allclose(np.sort(np.abs(legs), axis=1), [[0.0, 100.0]] * 4)
        assert np.min(legs[:-1, 0] * legs[1:, 1] - legs[:-1, 1] * legs[1:, 0]) > 0
    assert len({frozenset(map(tuple, w.tolist())) for w in loops}) == 4  # four different blocks
    # A longer loop goes around the centre junction along the roads (the ring of 8 junctions; points
    # in the middle of a straight side are not waypoints).
    big = build_strategy(PatrolDrone(loop_length_m=800.0), 0, world, obs, graph, set()).waypoints_m[:, :2]
    assert {tuple(w) for w in big} <= corners - {(200.0, 200.0)}
    assert np.sum(np.linalg.norm(np.roll(big, -1, axis=0) - big, axis=1)) == pytest.approx(800.0)


def test_generated_patrol_loop_without_roads_circles_junctions():
    world = demo_world()
    obs = Obstacles.from_layout(world.layout)
    p = build_strategy(PatrolDrone(loop_length_m=600.0), 0, world, obs)
    wps = p.waypoints_m[:, :2]
    assert len(wps) >= 4
    assert {tuple(w) for w in wps} <= {j.position_m for j in world.junctions}
    angles = np.unwrap(np.arctan2(wps[:, 1] - 200.0, wps[:, 0] - 200.0))
    assert np.all(np.diff(angles) > 0)  # counter-clockwise around the centre junction
    perimeter = np.sum(np.linalg.norm(np.roll(wps, -1, axis=0) - wps, axis=1))
    assert 300.0 <= perimeter <= 1200.0
    assert p.waypoints_m[0, 2] >= 60.0  # default altitude; buildings here stay below 50 m


def test_escort_extrapolates_a_turning_target():
    """A car on a circle (radius 40 m, 10 m/s); the drone sees it one tick late and predicts it."""
    world = demo_world()
    esc = Escort((-8.0, 2.0), 40.0, 10.0, Obstacles.from_layout(world.layout), np.array([0.0, 0.0, 40.0]))
    r, v = 40.0, 10.0
    w = v / r

    def car(t: float) -> EscortTarget:
        a = w * t
        return EscortTarget(
            (r * math.cos(a), r * math.sin(a), 0.75), a + math.pi / 2, (-v * math.sin(a), v * math.cos(a), 0.0)
        )

    esc.observe(0.0, car(0.0))
    esc.observe(0.2, car(0.2))
    ref = esc.reference(0.4, level_state())
    truth = esc.offset_point(car(0.4))
    assert ref.position_m[:2] == pytest.approx(truth, abs=0.02)
    # Feed-forward velocity: the car's, plus a share of the offset point's swing about the car.
    v_point = (esc.offset_point(car(0.401)) - esc.offset_point(car(0.399))) / 0.002
    v_car = np.array(car(0.4).velocity_mps[:2])
    expected = v_car + SWING_FEEDFORWARD * (v_point - v_car)
    assert ref.velocity_mps[:2] == pytest.approx(expected, abs=0.02)


# ------------------------------------------------------------------------ with real engines


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_hover_acceptance_60s_default_gusts(backend):
    f = fly_hover(backend, seconds=60.0)
    assert rms(f.err_h_m) <= 0.5
    assert rms(f.err_v_m) <= 0.3
    s0, last = f.states[0], f.states[-1]
    assert s0.agent_id == "drone_0" and s0.strategy == "hover"
    assert s0.position_m == pytest.approx((300.0, 300.0, 50.0), abs=1e-3)
    assert s0.specific_force_mps2 == pytest.approx((0.0, 0.0, G_MPS2), abs=1e-6)
    # Gusts move it (a drone, not a spline), but only a little.
    assert f.err_h_m.max() > 0.01
    # Hovering: the IMU feels about +1 g along body up, the body is nearly level, energy was spent
    # at roughly the hover power of a 3.5 kg quad (a few hundred watts).
    assert last.specific_force_mps2[2] == pytest.approx(G_MPS2, abs=0.3)
    r = rotation_matrix(last.rotation)
    assert r[2, 2] > math.cos(math.radians(5))
    assert 200.0 * 60 < last.energy_used_j < 800.0 * 60
    assert last.strategy_state == "hold"
    # The gimbal holds the camera level: its z axis is map up, its x axis the body heading.
    g = rotation_matrix(last.gimbal_rotation)
    assert g[:, 2] == pytest.approx((0.0, 0.0, 1.0), abs=1e-9)
    assert math.atan2(g[1, 0], g[0, 0]) == pytest.approx(math.atan2(r[1, 0], r[0, 0]), abs=1e-9)


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_hover_in_still_air_stays_put(backend):
    env = EnvironmentSpec(wind_mps=0.0, gust_mps=0.0)
    sc = scenario([HoverDrone(point=(350.0, 350.0), altitude_m=45.0)], backend, duration_s=10, environment=env)
    fleet = DroneFleet(sc, demo_world())
    try:
        states = fly(fleet, 10.0)
    finally:
        fleet.close()
    pos = np.array([s[0].position_m for s in states])
    assert np.abs(pos - [350.0, 350.0, 45.0]).max() < 0.02


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_patrol_acceptance_reaches_every_waypoint_in_order(backend):
    f = fly_patrol(backend, loops=2)
    visits = f.extra["visits"]
    n = len(f.extra["waypoints"])
    assert [i for i, _ in visits] == [(k + 1) % n for k in range(2 * n)]
    assert max(d for _, d in visits) <= 2.0
    assert rms(f.err_h_m) <= 2.0
    # It flies like a multirotor: it tilts toward its horizontal acceleration.
    v = np.array([s.velocity_mps for s in f.states])
    acc = (v[2:] - v[:-2]) / 0.4
    tilt = np.array([rotation_matrix(s.rotation)[:2, 2] for s in f.states[1:-1]])
    strong = np.hypot(acc[:, 0], acc[:, 1]) > 1.0
    assert strong.sum() > 20
    agree = np.einsum("ij,ij->i", tilt[strong], acc[strong, :2]) > 0
    assert agree.mean() > 0.9
    speed = np.hypot(v[:, 0], v[:, 1])
    assert speed.max() <= 15.0 + 1.0  # max_speed_mps, with a little overshoot
    # The IMU's specific force is the kinematic acceleration minus gravity, in the body frame.
    sf = np.array([s.specific_force_mps2 for s in f.states[1:-1]])
    rot = [rotation_matrix(s.rotation) for s in f.states[1:-1]]
    g_up = np.array([0.0, 0.0, G_MPS2])
    kin = np.array([r.T @ (a + g_up) for r, a in zip(rot, acc, strict=True)])
    assert np.sqrt(np.mean((sf - kin) ** 2, axis=0)) == pytest.approx([0, 0, 0], abs=0.3)


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_escort_acceptance_follows_a_turning_car(backend):
    f = fly_escort(backend)
    assert f.extra["car_speed"].max() == pytest.approx(14.0, abs=0.1)
    assert rms(f.err_h_m) <= 5.0
    assert f.err_v_m.max() < 1.0
    labels = {s.strategy_state for s in f.states}
    assert labels <= {"tracking", "approach"}


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_collision_with_a_building_is_reported(backend):
    through_tower = [(200.0, 150.0), (300.0, 150.0)]
    low = PatrolDrone(waypoints=through_tower, altitude_m=40.0, plan_altitude=False)
    fleet = DroneFleet(scenario([low], backend), demo_world())
    try:
        with pytest.raises(CollisionError, match="drone_0 collided with building 1000002") as err:
            fly(fleet, 10.0)
    finally:
        fleet.close()
    assert err.value.agent_id == "drone_0" and 1 <= err.value.tick <= 50
    # The same patrol with altitude planning climbs over the tower.
    fleet = DroneFleet(scenario([PatrolDrone(waypoints=through_tower, altitude_m=40.0)], backend), demo_world())
    try:
        states = fly(fleet, 12.0)
    finally:
        fleet.close()
    assert min(s[0].position_m[2] for s in states) > 79.0


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_escort_climbs_over_a_tower_before_crossing_it(backend):
    """The target shows up only after t=0, behind the 70 m tower; the drone at 40 m must climb first."""
    spec = EscortDrone(target="vehicle_0", start=(250.0, 90.0), altitude_m=40.0, offset_m=(0.0, 0.0))
    car = EscortTarget((250.0, 220.0, 0.75), math.pi / 2, (0.0, 0.0, 0.0))
    fleet = DroneFleet(scenario([spec], backend), demo_world())
    try:
        states = fly(fleet, 40.0, lambda k: {} if k < 2 else {"drone_0": car})
    finally:
        fleet.close()
    pos = np.array([s[0].position_m for s in states])
    assert pos[0, 2] == pytest.approx(40.0, abs=0.1)
    over = (pos[:, 1] > 118.0) & (pos[:, 1] < 182.0)  # above the tower's footprint
    assert over.any() and pos[over, 2].min() > 70.0 + 0.5 * 10.0
    assert states[-1][0].strategy_state == "tracking"
    assert states[-1][0].position_m[:2] == pytest.approx((250.0, 220.0), abs=1.0)


@pytest.mark.integration
def test_pybullet_reports_engine_contacts_with_static_world():
    b = backend_class("pybullet")(airframe_for_mass(3.5), 0.01, demo_world())
    try:
        b.reset(np.array([219.0, 150.0, 30.0]), 0.0)  # 1 m from the tower's west wall, 0.4 m half size
        for _ in range(100):
            b.step(np.full(4, b.frame.hover_thrust_n), np.array([15.0, 0.0, 0.0]))  # blown into it
            if b.contact():
                break
        assert b.contact() == "building 1000002 (top 70.0 m)"
    finally:
        b.close()


@pytest.mark.integration
def test_fleet_is_deterministic_and_seeded():
    drones = [
        HoverDrone(backend="jsbsim"),
        PatrolDrone(backend="pybullet", speed_mps=8.0),
        EscortDrone(target="vehicle_0"),
    ]

    def targets(k: int) -> dict[str, EscortTarget]:
        t = max(k - 1, 0) * 0.2
        return {"drone_2": EscortTarget((100.0 + 10.0 * t, 100.0, 0.75), 0.0, (10.0, 0.0, 0.0))}

    def run(seed: int) -> list:
        fleet = DroneFleet(scenario(drones, "pybullet", seed=seed), demo_world())
        try:
            return fly(fleet, 6.0, targets)
        finally:
            fleet.close()

    a, b, c = run(7), run(7), run(8)
    assert a == b  # bit-identical dataclasses
    assert a[-1] != c[-1]
    ids = [s.agent_id for s in a[-1]]
    assert ids == ["drone_0", "drone_1", "drone_2"]
    assert [s.strategy for s in a[-1]] == ["hover", "patrol", "escort"]
    assert a[-1][1].strategy_state.startswith("to_wp_")


@pytest.mark.integration
def test_fleet_rejects_off_tick_times_and_holds_without_escort_target():
    fleet = DroneFleet(scenario([EscortDrone(target="vehicle_0", start=(50.0, 50.0))]), demo_world())
    try:
        with pytest.raises(WorkerError, match="first step must be t_ns=0"):
            fleet.step_to(TICK_NS, 1, {})
        s0 = fleet.step_to(0, 0, {})[0]
        assert s0.strategy_state == "lost"
        with pytest.raises(WorkerError, match="not a whole number"):
            fleet.step_to(TICK_NS // 2, 1, {})
        states = [fleet.step_to(k * TICK_NS, k, {})[0] for k in range(1, 26)]
    finally:
        fleet.close()
    assert states[-1].strategy_state == "lost"
    assert states[-1].position_m[:2] == pytest.approx(s0.position_m[:2], abs=0.5)


def test_fleet_rejects_physics_too_slow_for_the_controller():
    sc = Scenario(name="slow", agents=AgentsSpec(drones=[HoverDrone()], drone_physics_hz=10.0))
    with pytest.raises(ScenarioError, match=r"agents\.drone_physics_hz.*at least 20 Hz"):
        DroneFleet(sc, demo_world())


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_hover_holds_at_other_physics_rates(backend):
    for hz in (20.0, 400.0):
        agents = AgentsSpec(drones=[HoverDrone(point=(350.0, 350.0))], drone_backend=backend, drone_physics_hz=hz)
        fleet = DroneFleet(Scenario(name="rates", agents=agents), demo_world())
        try:
            states = fly(fleet, 10.0)
        finally:
            fleet.close()
        pos = np.array([s[0].position_m for s in states])
        assert np.abs(pos - [350.0, 350.0, 60.0]).max() < 0.5, hz


@pytest.mark.integration
def test_jsbsim_model_matches_airframe():
    frame = airframe_for_mass(5.0)
    b = backend_class("jsbsim")(frame, 0.01, demo_world())
    b.reset(np.array([0.0, 0.0, 50.0]), 0.0)
    mass, inertia = b.mass_properties()
    assert mass == pytest.approx(frame.mass_kg, rel=1e-3)
    # The core ball's radius is fixed in the aircraft file, so scaled inertia agrees to a few percent.
    assert inertia == pytest.approx(frame.inertia_kgm2, rel=0.05)
    s = b.state()
    assert s.position_m == pytest.approx([0.0, 0.0, 50.0], abs=0.01)
    b.close()


@pytest.mark.integration
def test_shipped_default_scenario_flies_over_its_built_world(tmp_path):
    """The default scenario's drones over the world the world builder makes (no SUMO traffic: the
    escorted car is parked at a junction), with altitude planning against its real buildings."""
    from pathlib import Path

    from cosim.scenario.loader import load_scenario
    from cosim.world.build import build_world

    repo = Path(__file__).resolve().parents[1]
    loaded = load_scenario(repo / "scenarios" / "default.yaml", ["duration_s=30", "sensors.enabled=false"])
    world = build_world(loaded, tmp_path)
    obs = Obstacles.from_layout(world.layout)
    j = world.junctions[len(world.junctions) // 2].position_m
    car = EscortTarget((j[0], j[1], 0.75), 0.0, (0.0, 0.0, 0.0))
    escorts = [f"drone_{i}" for i, d in enumerate(loaded.scenario.agents.drones) if d.strategy == "escort"]
    fleet = DroneFleet(loaded.scenario, world)
    try:
        states = fly(fleet, 30.0, lambda k: dict.fromkeys(escorts, car))
    finally:
        fleet.close()
    for per_tick in states:
        for s in per_tick:
            assert obs.hit(np.array(s.position_m), 1.0) is None
    assert [s.strategy for s in states[-1]] == [d.strategy for d in loaded.scenario.agents.drones]


# --------------------------------------------------------------------------- separation (issue 11)


def test_layers_separate_drones_that_share_airspace():
    from cosim.drones.separation import layer_gap, plan_layers

    gap = layer_gap(15.0)
    assert gap >= 15.0
    hover = np.array([[200.0, 200.0]])
    far_hover = np.array([[0.0, 0.0]])
    loop_over_hover = np.array([[190.0, 190.0], [300.0, 190.0], [300.0, 300.0], [190.0, 300.0]])
    # hover 60, patrol 70 over it, an escort 40, a far hover 70, a second escort 45
    z = plan_layers([60.0, 70.0, 40.0, 70.0, 45.0], [hover, loop_over_hover, None, far_hover, None], 15.0)
    assert z[0] == 60.0 and z[2] == 40.0  # free layers are kept
    assert z[1] == pytest.approx(60.0 + gap)  # raised, never lowered
    assert z[3] == 70.0  # the far hover meets neither the hover nor the loop, and clears the escort
    assert all(abs(z[4] - z[j]) >= gap - 1e-9 for j in range(4)) and z[4] >= 45.0  # an escort meets everyone
    # Separation 0 turns layering off.
    assert plan_layers([60.0, 60.0], [hover, hover], 0.0) == [60.0, 60.0]


def test_yield_rule_raises_the_lower_priority_drone_and_holds_it_until_clear():
    from cosim.drones.control import Reference
    from cosim.drones.separation import yield_plan

    # An escort (drone_1) 30 m west of a hover (drone_0), both at 60 m, flying east at 10 m/s toward it.
    pos = np.array([[100.0, 0.0, 60.0], [70.0, 0.0, 60.0], [400.0, 0.0, 60.0]])
    vel = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    y = yield_plan(pos, vel, ["hover", "escort", "patrol"], 15.0)
    assert not y[0].bands and not y[2].bands  # the hover yields to nobody; the far patrol meets nobody
    assert y[1].hold and len(y[1].bands) == 1
    ref = Reference(np.array([80.0, 0.0, 60.0]), np.array([10.0, 0, 0]), np.zeros(3), 0.0)
    out = y[1].apply(ref, pos[1])
    assert out.position_m[2] >= 60.0 + 15.0
    assert out.position_m[:2] == pytest.approx(pos[1, :2]) and not out.velocity_mps.any()  # holds: climb first
    # Moving away: no yielding. Once above the band, it goes on (raised, not held).
    assert not yield_plan(pos, -vel, ["hover", "escort", "patrol"], 15.0)[1].bands
    pos[1, 2] = 80.0
    y = yield_plan(pos, vel, ["hover", "escort", "patrol"], 15.0)
    assert y[1].bands and not y[1].hold
    out = y[1].apply(ref, pos[1])
    assert out.position_m[:2] == pytest.approx(ref.position_m[:2]) and out.position_m[2] >= 75.0


def test_yield_rule_backs_away_before_climbing_past_a_drone_close_above():
    """An escort whose vehicle passes under a hovering drone must climb over a building: it does not climb
    past the hover there (default, before: 5.1 m at tick 141) but backs away, then climbs where it is."""
    from cosim.drones.control import Reference
    from cosim.drones.separation import KEEP_OUT_HYSTERESIS_M, KEEP_OUT_M, yield_plan

    hover = np.array([200.0, 200.0, 60.0])
    vel = np.array([[0.0, 0.0, 0.0], [-8.0, 0.0, 0.0]])
    for below_m in (5.0, 15.0, 20.0):  # deep inside the band, just inside it, under it
        pos = np.array([hover, [205.0, 200.0, 60.0 - below_m]])
        y = yield_plan(pos, vel, ["hover", "escort"], 15.0)[1]
        climb = Reference(np.array([195.0, 200.0, 70.0]), np.array([-8.0, 0, 0]), np.zeros(3), 0.0)
        out = y.apply(climb, pos[1])
        assert out.position_m[0] == pytest.approx(200.0 + KEEP_OUT_M + KEEP_OUT_HYSTERESIS_M)  # away, east
        assert out.position_m[2] <= max(pos[1, 2], 60.0 - 18.0) + 1e-9  # no closer vertically than it is
    # Under the band and not climbing (its wanted altitude is lower): it flies on under the hover.
    level = Reference(np.array([195.0, 200.0, 30.0]), np.array([-8.0, 0, 0]), np.zeros(3), 0.0)
    assert y.apply(level, np.array([205.0, 200.0, 40.0])).position_m[0] == 195.0
    # Out at the keep-out radius it holds and climbs over.
    pos = np.array([hover, [200.0 + KEEP_OUT_M + 1.0, 200.0, 45.0]])
    y = yield_plan(pos, np.array([[0.0, 0, 0], [-1.0, 0, 0]]), ["hover", "escort"], 15.0)[1]
    out = y.apply(Reference(np.array([195.0, 200.0, 70.0]), np.zeros(3), np.zeros(3), 0.0), pos[1])
    assert out.position_m[:2] == pytest.approx(pos[1, :2]) and out.position_m[2] >= 60.0 + 15.0


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_drones_crossing_at_one_altitude_collide_unless_separated(backend):
    """Two patrols fly the same line in opposite directions at the same altitude: with separation
    off they collide (an error naming both drones and the tick); with the default they pass 15 m apart."""
    env = EnvironmentSpec(wind_mps=0.0, gust_mps=0.0)
    east = PatrolDrone(waypoints=[(20.0, 380.0), (380.0, 380.0)], altitude_m=60.0, speed_mps=10.0)
    west = PatrolDrone(waypoints=[(380.0, 380.0), (20.0, 380.0)], altitude_m=60.0, speed_mps=10.0)

    def run(separation_m: float) -> DroneFleet:
        agents = AgentsSpec(drones=[east, west], drone_backend=backend, vehicles=VehicleAgents(count=1),
                            drone_separation_m=separation_m)
        fleet = DroneFleet(Scenario(name="cross", agents=agents, environment=env), demo_world())
        try:
            fly(fleet, 40.0)
        finally:
            fleet.close()
        return fleet

    with pytest.raises(CollisionError, match=r"drone_0 collided with drone_1 .* at tick \d+") as err:
        run(0.0)
    assert isinstance(err.value, DroneCollisionError)
    assert err.value.other_id == "drone_1" and 60 <= err.value.tick <= 140  # they meet after ~18 s
    fleet = run(15.0)
    assert 15.0 < fleet.min_separation_m < 40.0  # they did meet, apart


@pytest.fixture(scope="module")
def shipped_flights(tmp_path_factory):
    """Every shipped scenario's drones for 30 s over its built world, escorts following real SUMO traffic.

    30 s is enough to fail: with ``agents.drone_separation_m=0`` four shipped scenarios bring two drones
    within 15 m in that time (``python -m benchmarks.drone_survey --duration 30 --set agents.drone_separation_m=0``)."""
    from benchmarks.drone_survey import Survey, shipped_scenarios
    from cosim.scenario.loader import load_scenario

    survey = Survey(tmp_path_factory.mktemp("survey"))
    out = {}
    for path in shipped_scenarios():
        loaded = load_scenario(path, ["duration_s=30", "sensors.enabled=false"])
        out[path.stem] = survey.measure(loaded)
    return out


@pytest.mark.integration
@pytest.mark.timeout(900)  # the module fixture flies every shipped scenario (about 15 s of CPU on a quiet machine)
def test_shipped_scenarios_keep_drones_apart(shipped_flights):
    assert len(shipped_flights) >= 12
    for name, m in shipped_flights.items():
        assert m["min_distance_m"] > m["separation_m"] == 15.0, (name, m)


@pytest.mark.integration
@pytest.mark.timeout(900)
def test_patrols_fly_over_lanes_on_every_map_kind(shipped_flights):
    medians: dict[str, list[float]] = {}
    for m in shipped_flights.values():
        medians.setdefault(m["map"], []).extend(m["patrol_median_lane_distance_m"].values())
    assert set(medians) == {"urban", "suburban", "rural", "highway"}
    for kind, values in medians.items():
        assert values and max(values) < 5.0, (kind, values)
