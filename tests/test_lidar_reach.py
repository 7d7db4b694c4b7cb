"""A LiDAR-only tick places only the actors its LiDARs can reach (issue 36, item 5): the same returns, bit for
bit, from a smaller scene."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.lidar import REACH_SLACK_M, actors_in_reach, reach_ball, scan_pattern
from cosim.sensors.synthetic import actor, synthetic_scenario, synthetic_snapshot, synthetic_world

from cosim.geometry import rpy_from_quat
from cosim.scenario.model import LidarSpec, RigSpec, SensorsSpec
from cosim.snapshot import AgentState

RANGE_M = 30.0


def _moving(snap, speed: float):
    def vel(q, s):
        yaw = rpy_from_quat(q)[2]
        return (s * math.cos(yaw), s * math.sin(yaw), 0.0)

    actors = tuple(dataclasses.replace(a, velocity_mps=vel(a.rotation, speed)) for a in snap.actors)
    agents = tuple(dataclasses.replace(a, velocity_mps=vel(a.rotation, speed if a.kind == "vehicle" else 0.0),
                                       angular_rate_radps=(0.0, 0.0, 0.2) if a.kind == "vehicle" else (0, 0, 0))
                   for a in snap.agents)
    return dataclasses.replace(snap, actors=actors, agents=agents)


def _frames(cull: bool, snap):
    lidar = LidarSpec(horizontal_resolution_deg=0.5, range_m=RANGE_M)
    sensors = SensorsSpec(vehicle=RigSpec(lidar=lidar, cameras=[]), rsu=RigSpec(lidar=lidar, cameras=[]), bev=False)
    suite = SensorSuite(synthetic_scenario(vehicles=2, rsus=1, sensors=sensors), synthetic_world(),
                        encode_images=False, workers=1, cull_actors=cull)
    try:
        frames = suite.render(snap, np.random.default_rng(7))
        tick = suite._prepare(snap, cameras=False, lidar_agents=list(snap.agents) if cull else None)
        return frames, len(tick.scene.actor_spheres)
    finally:
        suite.close()


def test_a_lidar_only_tick_returns_the_same_points_from_the_actors_in_reach():
    snap = _moving(synthetic_snapshot(2, 1, 0), 15.0)
    culled, n_culled = _frames(True, snap)
    full, n_full = _frames(False, snap)
    assert n_full == len(snap.actors) and 0 < n_culled <= n_full - 6  # the cut is real (12 of 20 kept)
    hit_tracks = set()
    for aid, f in full.agents.items():
        a, b = f.lidar, culled.agents[aid].lidar
        for name in ("points", "intensity", "ring", "class_id", "instance_id", "t_offset_ns", "return_kind"):
            x, y = getattr(a, name, None), getattr(b, name, None)
            assert (x is None) == (y is None) and (x is None or np.array_equal(x, y)), (aid, name)
        hit_tracks |= set(np.unique(a.instance_id).tolist())
    assert len(hit_tracks - {0}) >= 3  # actors were hit, and hit alike


def test_the_reach_bound_keeps_an_actor_across_the_range_and_drops_one_beyond_it():
    spec = LidarSpec(range_m=RANGE_M)
    car = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0), velocity_mps=(20.0, 0.0, 0.0))
    ball = reach_ball(car, spec)
    assert ball[2] == pytest.approx(1.0 / spec.rotation_hz)
    assert ball[1] == pytest.approx(RANGE_M + 20.0 / spec.rotation_hz + 2 * np.linalg.norm(spec.mount.xyz_m))
    near = actor(1, "car", ball[1] + 1.5, 0.0)  # the box's near end 0.75 m inside the ball
    beyond = actor(2, "car", ball[1] + 0.5 * np.linalg.norm(near.size_m) + REACH_SLACK_M + 0.5, 0.0)
    # at the same place, driving at the car: 3 m nearer at the sweep's start, so in reach
    fast = dataclasses.replace(beyond, track_id=3, velocity_mps=(-60.0, 0.0, 0.0))
    assert [a.track_id for a in actors_in_reach((near, beyond, fast), [ball])] == [1, 3]
    assert actors_in_reach((near,), []) == ()
    assert reach_ball(car, spec.model_copy(update={"motion_distortion": False}))[2] == 0.0


@pytest.mark.parametrize("pattern", ["spinning", "rosette"])
def test_a_sweep_lasts_at_most_one_rotation(pattern):
    """The reach bound moves actors over 1 / rotation_hz: no firing is earlier."""
    spec = LidarSpec(pattern=pattern, rotation_hz=10.0)
    for t_ns in (0, 200_000_000, 1_300_000_000):
        t = scan_pattern(spec.pattern)(spec, t_ns).t_offset_ns
        assert t.max() <= 0 and t.min() >= -1e9 / spec.rotation_hz
