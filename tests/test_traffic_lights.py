"""Traffic lights at SUMO's signalised junctions (issue 28): heads at the stop lines, SUMO's live state in
the snapshot and the labels, and the lit lamp's colour in a camera."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cosim.scenario import load_scenario_data
from cosim.world.traffic_lights import head_colour, signal_heads

pytestmark = pytest.mark.integration


def _scenario(lighting: str = "day"):
    return load_scenario_data({
        "name": "lights", "seed": 3, "duration_s": 40, "map": {"kind": "urban", "size_m": 300},
        "traffic": {"density_veh_per_km": 10, "signals": "fixed"},
        "environment": {"lighting": lighting},
        "agents": {"vehicles": {"count": 1}, "rsus": {"count": 0}, "drones": []},
        "sensors": {"vehicle": {"lidar": None, "gnss": None, "imu": None,
                                "cameras": [{"name": "front", "width": 96, "height": 72, "fov_deg": 40,
                                             "mount": {"xyz_m": [0.0, 0.0, 1.5]}}]}},
    })


@pytest.fixture(scope="module")
def sumo_run(tmp_path_factory):
    """A small town's world and SUMO's signal states at every tick of 40 s (real libsumo)."""
    from cosim.traffic import TrafficSim
    from cosim.world import build_world

    tmp = tmp_path_factory.mktemp("lights")
    loaded = _scenario()
    world = build_world(loaded, tmp / "w")
    sim = TrafficSim(loaded.scenario, world, tmp / "s")
    try:
        states = []
        for k in range(0, loaded.scenario.n_ticks, 5):
            sim.step_to(k * loaded.scenario.tick_ns)
            states.append(sim.signal_states())
    finally:
        sim.close()
    return world, states


def test_every_signalised_approach_lane_has_a_head_at_its_stop_line(sumo_run):
    import xml.etree.ElementTree as ET

    world, states = sumo_run
    heads = signal_heads(world.net_xml)
    root = ET.fromstring(world.net_xml)
    controlled = {f"{c.get('from')}_{c.get('fromLane')}" for c in root.iter("connection")
                  if c.get("tl") and not c.get("from", "").startswith(":")}
    assert {h.head_id.split("/", 1)[1] for h in heads} == controlled
    assert {h.tls for h in heads} == set(states[0])  # every SUMO traffic light has heads
    ends = {ln.get("id"): [float(v) for v in ln.get("shape").split()[-1].split(",")] for ln in root.iter("lane")}
    for h in heads:
        x, y = ends[h.head_id.split("/", 1)[1]]
        assert np.hypot(h.center_m[0] - x, h.center_m[1] - y) < 1e-6 and 5.0 < h.center_m[2] < 6.5
        # each head shows exactly the links SUMO controls from its lane
        assert all(i < len(states[0][h.tls]) for i in h.links)


def _lit_colours(rgb: np.ndarray, mask: np.ndarray) -> set[str]:
    px = rgb[mask].astype(int)
    r, g, b = px[:, 0], px[:, 1], px[:, 2]
    found = set()
    if np.any((r > 200) & (g < 90)):
        found.add("red")
    if np.any((r > 200) & (g > 120) & (b < 90)):
        found.add("yellow")
    if np.any((g > 200) & (r < 150)):
        found.add("green")
    return found


@pytest.mark.parametrize("lighting", ["day", "dusk", "night"])
def test_a_traffic_lights_lit_colour_in_a_camera_is_sumos_state(sumo_run, lighting):
    """A camera 14 m in front of a head looks at it at several ticks: the lamp it sees lit has the colour of
    SUMO's state for that head's links, by day, at dusk and at night."""
    from cosim.sensors.assets.signals import FIRST_HEAD_INSTANCE
    from cosim.sensors.suite import SensorSuite

    from cosim.assemble import traffic_lights
    from cosim.geometry import quat_from_rpy
    from cosim.snapshot import AgentState, WorldSnapshot

    world, states = sumo_run
    heads = signal_heads(world.net_xml)
    k, head = next((k, h) for k, h in enumerate(heads)
                   if {head_colour(s[h.tls], h.links) for s in states} >= {"red", "green"})
    scenario = _scenario(lighting).scenario
    seen: dict[str, set[str]] = {}
    with SensorSuite(scenario, world, noise=False, block_px=1) as suite:
        cx, cy, cz = head.center_m
        f = np.array([np.cos(head.yaw_rad), np.sin(head.yaw_rad)])
        pos = (cx + 14 * f[0], cy + 14 * f[1], cz - 1.5)
        agent = AgentState("vehicle_0", "vehicle", pos, quat_from_rpy(0.0, 0.0, head.yaw_rad + np.pi))
        for tick, signals in enumerate(states):
            expected = head_colour(signals[head.tls], head.links)
            if expected in seen:
                continue
            snap = WorldSnapshot(tick, 0, (), (agent,), traffic_lights(world, signals))
            cam = suite.render(snap, np.random.default_rng(0)).agents["vehicle_0"].cameras["front"]
            mask = cam.instance == FIRST_HEAD_INSTANCE + k
            assert mask.sum() > 30, "the head is in view"
            seen[expected] = _lit_colours(cam.rgb, mask)
    assert {"red", "green"} <= set(seen)
    for expected, lit in seen.items():
        assert lit == {expected}, (lighting, expected, lit)


def test_an_episode_labels_sumos_signal_states_every_tick(tmp_path: Path):
    """``cosim run`` carries SUMO's states from the traffic worker to ``/labels/objects`` (format 1.3)."""
    import yaml

    from cosim.io import open_episode
    from tests.helpers import run_cli

    doc = _scenario().resolved
    doc["sensors"]["enabled"] = False
    doc["duration_s"] = 30
    path = tmp_path / "lights.yaml"
    path.write_text(yaml.safe_dump(doc))
    r = run_cli("run", str(path), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    ep = open_episode(next((tmp_path / "out").rglob("*.mcap")))
    assert ep.format_version == "1.4"
    shown: dict[str, set[str]] = {}
    for tick in ep.ticks():
        for t in json.loads(tick.raw("/labels/objects").data)["traffic_lights"]:
            assert t["state"] == head_colour(t["signal"], tuple(range(len(t["signal"]))))
            shown.setdefault(t["light_id"], set()).add(t["state"])
    assert len(shown) == len(signal_heads(ep.attachment("map.net.xml")))
    assert any({"red", "green"} <= s for s in shown.values())  # the states follow SUMO's cycle
