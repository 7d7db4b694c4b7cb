"""Traffic adapter: box conversion on a known lane, physics invariants of a short urban run, the fake."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from cosim.scenario import load_scenario_data
from cosim.traffic import FakeTraffic, TrafficSim
from cosim.traffic.metrics import convex_overlap_area, max_pairwise_overlap
from cosim.world import build_world
from cosim.world.layout import road_raster
from cosim.world.netgen import _run_tool, strip_header
from cosim.world.network import read_network

TICK_NS = 200_000_000


def _straight_net(tmp: Path) -> Path:
    """A 600 m two-way road along y = 50 (east-west), one lane per direction (no lane changes)."""
    nodes = ET.Element("nodes")
    ET.SubElement(nodes, "node", id="w", x="0", y="50", type="priority")
    ET.SubElement(nodes, "node", id="e", x="600", y="50", type="priority")
    edges = ET.Element("edges")
    ET.SubElement(edges, "edge", id="we", attrib={"from": "w", "to": "e", "numLanes": "1", "speed": "13.9"})
    ET.SubElement(edges, "edge", id="ew", attrib={"from": "e", "to": "w", "numLanes": "1", "speed": "13.9"})
    ET.ElementTree(nodes).write(tmp / "s.nod.xml")
    ET.ElementTree(edges).write(tmp / "s.edg.xml")
    _run_tool(
        "netconvert",
        ["-n", "s.nod.xml", "-e", "s.edg.xml", "-o", "s.net.xml", "--offset.disable-normalization"],
        tmp,
    )
    (tmp / "s.net.xml").write_bytes(strip_header((tmp / "s.net.xml").read_bytes()))
    return tmp / "s.net.xml"


@pytest.mark.integration
def test_box_centre_on_east_west_lane_centre(tmp_path: Path) -> None:
    net_file = _straight_net(tmp_path)
    loaded = load_scenario_data(
        {
            "name": "straight",
            "seed": 1,
            "duration_s": 10,
            "map": {"kind": "net", "file": str(net_file)},
            "traffic": {"density_veh_per_km": 0},
            "agents": {"vehicles": {"count": 2}, "rsus": {"count": 0}, "drones": []},
        }
    )
    world = build_world(loaded, tmp_path / "w")
    net = read_network(world.net_xml)
    centres = {ln.lane_id: float(ln.shape[:, 1].mean()) for ln in net.lanes(internal=False)}
    lane_y = {ln.lane_id: ln.shape for ln in net.lanes(internal=False)}
    sim = TrafficSim(loaded.scenario, world, tmp_path / "s")
    try:
        checked = 0
        for k in range(0, 30):
            for s in sim.step_to(k * TICK_NS):
                x, y = s.center_m[:2]
                # the lane the box centre is on: nearest lane centre line (all lanes are straight along x)
                lane = min(centres, key=lambda lid: abs(centres[lid] - y))
                shape = lane_y[lane]
                eastbound = shape[-1, 0] > shape[0, 0]
                if not shape[:, 0].min() + 10 < x < shape[:, 0].max() - 10:
                    continue
                assert abs(y - centres[lane]) < 0.1, (s.sumo_id, y, centres[lane])
                expected_yaw = 0.0 if eastbound else math.pi
                assert abs(math.remainder(s.yaw_rad - expected_yaw, 2 * math.pi)) < math.radians(1.0)
                assert s.center_m[2] == pytest.approx(0.5 * s.size_m[2])
                assert s.velocity_mps[0] == pytest.approx(s.speed_mps * math.cos(s.yaw_rad), abs=1e-9)
                checked += 1
        assert checked > 20
    finally:
        sim.close()


@pytest.mark.integration
def test_urban_run_invariants(tmp_path: Path) -> None:
    loaded = load_scenario_data({"name": "u", "seed": 5, "duration_s": 20, "map": {"kind": "urban", "size_m": 250}})
    sc = loaded.scenario
    world = build_world(loaded, tmp_path / "w")
    road = road_raster(read_network(world.net_xml), world.bounds_m, 0.25)
    sim = TrafficSim(sc, world, tmp_path / "s")
    connected = {f"vehicle_{i}" for i in range(sc.agents.vehicles.count)}
    on = total = 0
    try:
        for k in range(sc.n_ticks):
            states = sim.step_to(k * sc.tick_ns)
            assert [s.sumo_id for s in states] == sorted(s.sumo_id for s in states)
            assert connected <= {s.sumo_id for s in states}, f"tick {k}"
            assert {s.agent_id for s in states if s.agent_id} == connected
            overlap, pair = max_pairwise_overlap(states)
            assert overlap <= 0.05, f"tick {k}: {pair} overlap {overlap:.3f} m^2"
            pts = np.array([s.center_m[:2] for s in states])
            on += int(road.lookup(pts).sum())
            total += len(pts)
    finally:
        sim.close()
    assert on / total >= 0.99


def test_overlap_area_of_unit_squares() -> None:
    a = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert convex_overlap_area(a, a + np.array([0.5, 0.5])) == pytest.approx(0.25)
    assert convex_overlap_area(a, a + np.array([2.0, 0.0])) == 0.0


def test_fake_traffic_moves_straight(tmp_path: Path) -> None:
    loaded = load_scenario_data({"name": "f", "seed": 2})
    from cosim.world.types import StaticLayout, World

    world = World("urban", b"", b"", (0.0, 0.0, 400.0, 400.0), (), (), StaticLayout(()), (0.0, 0.0, 0.0))
    fake = FakeTraffic(loaded.scenario, world, tmp_path)
    a, b = fake.step_to(0), fake.step_to(10 * TICK_NS)
    assert [s.sumo_id for s in a] == [s.sumo_id for s in b]
    for s0, s1 in zip(a, b, strict=True):
        assert s1.center_m[0] - s0.center_m[0] == pytest.approx(2.0 * s0.speed_mps)
        assert s1.center_m[1] == s0.center_m[1]
    assert {s.agent_id for s in a if s.agent_id} == {
        f"vehicle_{i}" for i in range(loaded.scenario.agents.vehicles.count)
    }
