"""Sensors over a world built by ``build_world`` (real SUMO network and layout), small resolutions."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.synthetic import world_snapshot

from cosim.classes import SEMANTIC_CLASSES, SEMANTIC_ID
from cosim.scenario.loader import load_scenario_data

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def world_and_scenario(tmp_path_factory):
    from cosim.world.build import build_world

    data = {
        "name": "sensors_world", "seed": 3, "map": {"kind": "urban", "size_m": 200},
        "environment": {"weather": "rainy", "lighting": "night"},
        "agents": {"vehicles": {"count": 2}, "rsus": {"count": 2},
                   "drones": [{"strategy": "hover", "altitude_m": 50}]},
    }
    loaded = load_scenario_data(data)
    small = json.loads(json.dumps(loaded.resolved))
    for kind in ("vehicle", "rsu", "drone"):
        rig = small["sensors"][kind]
        rig["cameras"] = [dict(c, width=160, height=96) for c in rig["cameras"]]
        rig["lidar"]["horizontal_resolution_deg"] = 1.0
    loaded = load_scenario_data(small)
    world = build_world(loaded, tmp_path_factory.mktemp("world"))
    return world, loaded.scenario


def test_built_world_renders_consistent_labels(world_and_scenario):
    world, sc = world_and_scenario
    suite = SensorSuite(sc, world)
    snap = world_snapshot(world, 2, 1, 10, seed=1)
    frames = suite.render(snap, np.random.default_rng(0))
    assert set(frames.agents) == {a.agent_id for a in snap.agents}
    seen_classes: set[int] = set()
    for af in frames.agents.values():
        assert af.lidar.n_points > 1000
        assert np.all(af.lidar.class_id < len(SEMANTIC_CLASSES))
        for cf in af.cameras.values():
            seen_classes |= set(np.unique(cf.semantic).tolist())
            bld = cf.semantic == SEMANTIC_ID["building"]
            assert np.all(cf.instance[bld] >= 1_000_000)
            road = cf.semantic == SEMANTIC_ID["road"]
            assert np.all(cf.instance[road] == 0)
            assert np.all(np.isfinite(cf.depth[cf.semantic > 0]))
            assert np.all(np.isinf(cf.depth[cf.semantic == 0]))
    assert {SEMANTIC_ID["road"], SEMANTIC_ID["building"]} <= seen_classes
    # every RSU sees something of its junction: road around it in its BEV and in its LiDAR
    for a in snap.agents:
        if a.kind == "rsu":
            af = frames.agents[a.agent_id]
            assert af.bev.grid[..., af.bev.layers.index("road")].sum() > 100
            assert np.any(af.lidar.class_id == SEMANTIC_ID["road"])


def test_built_world_messages_write_an_episode(world_and_scenario, tmp_path):
    from cosim.io.sensor_messages import frame_messages
    from cosim.io.writer import EpisodeWriter

    world, sc = world_and_scenario
    suite = SensorSuite(sc, world)
    snap = world_snapshot(world, 2, 1, 5, seed=2)
    msgs = frame_messages(suite.render(snap, np.random.default_rng(0)), snap.t_ns)
    w = EpisodeWriter(tmp_path / "ep.mcap", compression="zstd")
    for topic, m in msgs:
        w.write(topic, m, snap.t_ns)
    path = w.finish()
    assert path.stat().st_size > 10_000
    assert w.message_count == len(msgs)
    assert {t for t, _ in msgs} >= {"/vehicle_0/lidar", "/rsu_0/front/image", "/drone_0/down/depth", "/drone_0/imu"}
