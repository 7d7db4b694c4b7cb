"""Drone flight dynamics, control and strategies (cosim.drones), on every registered backend.

Test worlds are built here as World objects (a few Prism buildings, junctions, empty net), so the
tests need neither SUMO nor the world builder.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cosim.drones import DroneFleet, backend_class, backend_names
from cosim.drones.airframe import G_MPS2, airframe_for_mass
from cosim.errors import InputError
from cosim.geometry import rotation_matrix
from cosim.scenario.model import AgentsSpec, HoverDrone, Scenario
from cosim.world.types import Junction, Prism, StaticLayout, World

BACKENDS = backend_names()


def box(x0: float, y0: float, x1: float, y1: float, top: float, iid: int) -> Prism:
    return Prism("building", ((x0, y0), (x1, y0), (x1, y1), (x0, y1)), 0.0, top, iid)


def small_world() -> World:
    """400 m square, a 3x3 grid of junctions 100 m apart, a few buildings between the roads."""
    junctions = tuple(
        Junction(f"j{i}{j}", (100.0 * i + 100.0, 100.0 * j + 100.0), "priority")
        for i in range(3)
        for j in range(3)
    )
    prisms = (
        box(120, 120, 180, 180, 25.0, 1_000_001),
        box(220, 120, 280, 180, 70.0, 1_000_002),  # a tower
        box(120, 220, 180, 280, 15.0, 1_000_003),
        Prism("road", ((0, 95), (400, 95), (400, 105), (0, 105)), 0.0, 0.02, 0),
    )
    return World(
        "urban",
        b"",
        b"",
        (0.0, 0.0, 400.0, 400.0),
        junctions,
        (),
        StaticLayout(prisms),
        (37.3352, -121.8811, 20.0),
    )


def scenario(drones: list, backend: str, **kw) -> Scenario:
    return Scenario(name="drones-test", agents=AgentsSpec(drones=drones, drone_backend=backend), **kw)


def fly(fleet: DroneFleet, seconds: float, tick_ns: int, targets=None):
    """Step a fleet from t=0; returns the list of per-tick state lists (index 0: t=0)."""
    out = [fleet.step_to(0, 0, targets(0) if targets else {})]
    for k in range(1, round(seconds * 1e9 / tick_ns) + 1):
        out.append(fleet.step_to(k * tick_ns, k, targets(k) if targets else {}))
    return out


def test_registry_lists_known_backends_on_unknown_name():
    assert {"jsbsim", "pybullet"} <= set(BACKENDS)
    with pytest.raises(InputError, match=r"jsbsim.*pybullet"):
        backend_class("xplane")


@pytest.mark.integration
@pytest.mark.parametrize("backend", BACKENDS)
def test_hover_starts_level_and_holds_point(backend):
    sc = scenario([HoverDrone(point=(300.0, 300.0), altitude_m=50.0)], backend, duration_s=20)
    fleet = DroneFleet(sc, small_world())
    try:
        states = fly(fleet, 20.0, sc.tick_ns)
    finally:
        fleet.close()
    s0 = states[0][0]
    assert s0.agent_id == "drone_0" and s0.strategy == "hover"
    assert s0.position_m == pytest.approx((300.0, 300.0, 50.0), abs=1e-3)
    assert s0.specific_force_mps2 == pytest.approx((0.0, 0.0, G_MPS2), abs=1e-6)
    pos = np.array([s[0].position_m for s in states])
    err = pos - np.array([300.0, 300.0, 50.0])
    assert math.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2)) < 0.5
    assert math.sqrt(np.mean(err[:, 2] ** 2)) < 0.3
    last = states[-1][0]
    # Hovering: the IMU feels about +1 g along body up, the body is nearly level, energy was spent.
    assert last.specific_force_mps2[2] == pytest.approx(G_MPS2, abs=0.3)
    r = rotation_matrix(last.rotation)
    assert r[2, 2] > math.cos(math.radians(5))
    assert last.energy_used_j > 20.0 * 200.0
    assert last.strategy_state == "hold"
    # The gimbal holds the camera level: its z axis is map up, its x axis the body heading.
    g = rotation_matrix(last.gimbal_rotation)
    assert g[:, 2] == pytest.approx((0.0, 0.0, 1.0), abs=1e-9)
    assert math.atan2(g[1, 0], g[0, 0]) == pytest.approx(math.atan2(r[1, 0], r[0, 0]), abs=1e-9)


@pytest.mark.integration
def test_jsbsim_model_matches_airframe():
    frame = airframe_for_mass(5.0)
    b = backend_class("jsbsim")(frame, 0.01, small_world())
    b.reset(np.array([0.0, 0.0, 50.0]), 0.0)
    mass, inertia = b.mass_properties()
    assert mass == pytest.approx(frame.mass_kg, rel=1e-3)
    # The core ball's radius is fixed in the aircraft file, so scaled inertia agrees to a few percent.
    assert inertia == pytest.approx(frame.inertia_kgm2, rel=0.05)
    b.close()
