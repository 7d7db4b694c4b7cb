"""What the shipped scenarios' data is worth (issue 27): traffic that moves, drones that start steady.

Real SUMO (libsumo) and the real drone backends, no sensors: each case builds the scenario's world and
steps the traffic (and the drones on it) the way the conductor's workers do.
"""

from __future__ import annotations

import math
import tempfile
import xml.etree.ElementTree as ET
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
#: Issue 27: the stopped share never exceeds 40 % over 120 s. netconvert's lockstep plans gave 93 % (urban); with
#: replanned signals at every junction of the urban grid the peak was 41-44 % (single cars at reds of its 21
#: lights); with lights along the avenues only (cosim.world.netgen.URBAN) and a 2 s all-red interval (ALL_RED_S)
#: it is 39 / 33 / 39 % over seeds 0-2 (34 / 33 / 32 % without the all-red interval); suburban 25 %.
STOPPED_SHARE_BOUND = 0.40
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
                    states = sim.step_to(k * sc.tick_ns, pedestrians=False)  # the vehicles' speeds alone
                    on_map = set(libsumo.vehicle.getIDList())
                    road = [s for s in states if s.cls != "pedestrian" and s.sumo_id in on_map]
                    shares.append(sum(s.speed_mps < STOPPED_MPS for s in road) / len(road))
                    for s in road:
                        if s.agent_id is not None or s.sumo_id.startswith("vehicle_"):
                            speeds.setdefault(s.sumo_id, []).append(s.speed_mps)
        out[name] = {"shares": shares, "speeds": speeds, "tick_s": 1 / sc.tick_hz, "n_conn": sc.agents.vehicles.count}
    return out


@pytest.mark.timeout(900)  # the fixture's 2 x 120 s of SUMO take ~12 CPU-s on a quiet machine, minutes on a busy one
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


@pytest.fixture(scope="module")
def urban_net() -> bytes:
    loaded = load_scenario("town_urban_day_clear")
    assert loaded.scenario.traffic.signals == "actuated"
    with tempfile.TemporaryDirectory() as tmp:
        return build_world(loaded, Path(tmp)).net_xml


def test_urban_lights_stand_along_the_avenues_and_side_street_crossings_keep_priority_rules(urban_net):
    """Every junction of three or more roads where an avenue (a main road, edge priority 3) passes is signalised;
    every one where only side streets meet has priority rules (on main: all 21 were signalised)."""
    root = ET.fromstring(urban_net)
    incoming: dict[str, list[int]] = {}
    for e in root.findall("edge"):
        if e.get("function") is None:  # roads (not internal, crossing or walking-area edges)
            incoming.setdefault(e.get("to"), []).append(int(e.get("priority")))
    kinds = {j.get("id"): j.get("type") for j in root.findall("junction")}
    crossings = {j: p for j, p in incoming.items() if len(p) >= 3}
    avenue = {j for j, p in crossings.items() if 3 in p}
    assert avenue and avenue != set(crossings)
    assert {j for j in crossings if kinds[j] == "traffic_light"} == avenue
    assert all(kinds[j] == "priority" for j in set(crossings) - avenue)


def test_signal_plans_are_actuated_by_default_with_cycles_by_size_and_spread_offsets(urban_net):
    from cosim.world.signals import plan_signals

    net = urban_net
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
    """Issue 27: at most 10 % of RSU and 15 % of connected-vehicle camera frames show no labelled object (pixels
    of ``/<agent>/visibility``), over the shipped 20 s sampled once a second (tick_hz 1: the same traffic, SUMO
    steps at 20 Hz either way) at a quarter of the image size, as benchmarks/data_quality.py measures at 5 Hz.
    Both windows give the same shares: main 710633b urban 10.6 % RSU / 3.3 % vehicle here, 10.6 / 3.5 % at
    5 Hz; suburban 4.7 / 1.5 % and 4.7 / 1.1 %. (At a tenth of the size far objects fall under a pixel:
    suburban RSUs 12 % empty at 1 Hz.)"""
    from benchmarks.data_quality import empty_frame_shares

    shares = empty_frame_shares(load_scenario(name, ["duration_s=20", "tick_hz=1"]), 0.25)
    assert shares["rsu_empty"] <= 0.10 and shares["vehicle_empty"] <= 0.15, shares
