"""What the shipped scenarios' data is worth (issue 27): traffic that moves, drones that start steady.

Real SUMO (libsumo) and the real drone backends, no sensors: each case builds the scenario's world and
steps the traffic (and the drones on it) the way the conductor's workers do.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import libsumo
import numpy as np
import pytest

from cosim.assemble import escort_targets_of
from cosim.drones.fleet import DroneFleet
from cosim.scenario.loader import load_scenario, shipped_scenarios
from cosim.scenario.model import EscortDrone
from cosim.traffic.sumo_sim import TrafficSim
from cosim.world import build_world

pytestmark = pytest.mark.integration  # real SUMO, drone backends and episodes throughout

STOPPED_MPS = 0.1  # [m/s]
#: The stopped share never exceeds this over 120 s. Issue 27 asks for 0.40; the urban town peaks at 0.41-0.44
#: (seeds 0 and 1, and every signal-plan constant tried: cycle 24-50 s, minimum green 3-5 s, actuated stretch
#: 1.5-2.5x), with single cars waiting at red lights of its 21 signalised junctions. netconvert's lockstep
#: plans gave 0.93. A regression bound, not the issue's target (issue 27 stays open on this point).
STOPPED_SHARE_BOUND = 0.45
TOWNS = ("town_urban_day_clear", "town_suburban_day_cloudy")


def _drone_cases() -> list[str]:
    """One shipped scenario per distinct (map, seed, drones, vehicles): the rest fly the same start."""
    seen: dict[str, str] = {}
    for name, path in shipped_scenarios():
        sc = load_scenario(path).scenario
        key = repr((sc.map, sc.seed, sc.agents.drones, sc.agents.vehicles, sc.agents.drone_backend))
        seen.setdefault(key, name)
    return sorted(seen.values())


@pytest.fixture(scope="module")
def town_traffic() -> dict[str, dict]:
    """120 s of each town's traffic: per tick, the stopped share of the vehicles on the map and each
    connected vehicle's speed."""
    out = {}
    for name in TOWNS:
        loaded = load_scenario(name, ["duration_s=120"])
        sc = loaded.scenario
        shares, speeds = [], {}
        with tempfile.TemporaryDirectory() as tmp:
            world = build_world(loaded, Path(tmp) / "world")
            with TrafficSim(sc, world, Path(tmp) / "sumo") as sim:
                for k in range(sc.n_ticks + 1):
                    states = sim.step_to(k * sc.tick_ns)
                    on_map = set(libsumo.vehicle.getIDList())
                    road = [s for s in states if s.cls != "pedestrian" and s.sumo_id in on_map]
                    shares.append(sum(s.speed_mps < STOPPED_MPS for s in road) / len(road))
                    for s in road:
                        if s.agent_id is not None or s.sumo_id.startswith("vehicle_"):
                            speeds.setdefault(s.sumo_id, []).append(s.speed_mps)
        out[name] = {"shares": shares, "speeds": speeds, "tick_s": 1 / sc.tick_hz, "n_conn": sc.agents.vehicles.count}
    return out


@pytest.mark.timeout(900)  # the fixture's 2 x 120 s of SUMO take ~40 s on a quiet machine, minutes on a busy one
@pytest.mark.parametrize("name", TOWNS)
def test_traffic_lights_do_not_stall_the_town(town_traffic, name):
    """Stopped share <= STOPPED_SHARE_BOUND at every tick of 120 s, no connected vehicle still for more than 30 s."""
    t = town_traffic[name]
    worst = max(t["shares"])
    at_s = t["shares"].index(worst) * t["tick_s"]
    assert worst <= STOPPED_SHARE_BOUND, f"{worst:.0%} of the vehicles stopped at t = {at_s:.1f} s"
    assert len(t["speeds"]) == t["n_conn"]
    for vid, v in t["speeds"].items():
        run = longest = 0
        for speed in v:
            run = run + 1 if speed < STOPPED_MPS else 0
            longest = max(longest, run)
        assert (longest - 1) * t["tick_s"] <= 30.0, f"{vid} stood still for {(longest - 1) * t['tick_s']:.1f} s"


def test_signal_plans_are_actuated_by_default_with_cycles_by_size_and_spread_offsets():
    from cosim.world.signals import plan_signals

    loaded = load_scenario("town_urban_day_clear")
    assert loaded.scenario.traffic.signals == "actuated"
    with tempfile.TemporaryDirectory() as tmp:
        net = build_world(loaded, Path(tmp)).net_xml
    import xml.etree.ElementTree as ET

    logics = ET.fromstring(net).findall("tlLogic")
    assert logics and all(tl.get("type") == "actuated" for tl in logics)
    cycles = {tl.get("id"): sum(float(p.get("duration")) for p in tl.findall("phase")) for tl in logics}
    links = {tl.get("id"): len(tl.find("phase").get("state")) for tl in logics}
    small, big = min(links, key=links.get), max(links, key=links.get)
    assert cycles[small] < cycles[big] <= 60  # longer cycles at bigger junctions, none of netconvert's 90 s
    assert len({tl.get("offset") for tl in logics}) > len(logics) // 2  # no lockstep
    assert plan_signals(net, "as_built", np.random.default_rng(0)) == net


@pytest.mark.parametrize("name", _drone_cases())
def test_drones_start_steady(name):
    """Every drone of a shipped scenario starts in its strategy's steady state: its first tick tilts at most
    10 degrees (netconvert-era starts: 28-29 degrees, escorts catching up from rest), and no drone tilts more
    than 25 degrees in the first 2 s (then: 42-50; steady starts alone: up to 34, escorts following their
    vehicles' braking at red lights and the highway patrol's first corner; the fleet's gentle start,
    cosim.drones.fleet.START_TILT_DEG, bounds it)."""
    loaded = load_scenario(name)
    sc = loaded.scenario
    escorts = {f"drone_{i}": d.target for i, d in enumerate(sc.agents.drones) if isinstance(d, EscortDrone)}
    tilts: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        world = build_world(loaded, Path(tmp) / "world")
        with TrafficSim(sc, world, Path(tmp) / "sumo") as sim:
            fleet = DroneFleet(sc, world)
            try:
                vehicles = sim.step_to(0)
                for k in range(int(2 * sc.tick_hz) + 1):  # drones step to tick k with the targets of k - 1
                    worst = 0.0
                    for d in fleet.step_to(k * sc.tick_ns, k, escort_targets_of(vehicles, escorts)):
                        x, y, _z, _w = d.rotation
                        up_z = 1.0 - 2.0 * (x * x + y * y)  # the body z axis' map z component
                        worst = max(worst, math.degrees(math.acos(min(1.0, max(-1.0, up_z)))))
                    tilts.append(worst)
                    vehicles = sim.step_to(k * sc.tick_ns)
            finally:
                fleet.close()
    assert tilts[1] <= 10.0, f"a drone tilted {tilts[1]:.1f} degrees in the first tick"
    assert max(tilts) <= 25.0, f"a drone tilted {max(tilts):.1f} degrees in the first 2 s"


@pytest.mark.parametrize("name", TOWNS)
def test_rsu_and_vehicle_cameras_see_labelled_objects(name):
    """At most 25 % of RSU and 15 % of connected-vehicle camera frames show no labelled object (pixels of
    ``/<agent>/visibility``), over the first 4 s at a tenth of the image size (a far object under a pixel
    is missed there, so the full-size shares are lower). On main: 45-47 % and 32 % (urban), 28 % and
    12 % (suburban). The issue's 10 % for RSUs is not reached: a few RSU cameras face quiet roads or a
    building (13 % over the shipped 20 s at a quarter size: benchmarks/data_quality.py)."""
    from benchmarks.data_quality import empty_frame_shares

    shares = empty_frame_shares(load_scenario(name, ["duration_s=4"]), 0.1)
    assert shares["rsu_empty"] <= 0.25 and shares["vehicle_empty"] <= 0.15, shares
