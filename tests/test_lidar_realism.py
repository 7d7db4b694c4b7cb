"""LiDAR realism on synthetic scenes with known geometry: motion distortion and deskew, intensity from
material, the rosette pattern, dual returns, labels after deskewing for every scan pattern."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.lidar import RETURN_LAST, RETURN_SINGLE, RETURN_STRONGEST, rosette_pattern, scan_pattern, sweep_ns
from cosim.sensors.rig import mount_rotation
from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world

from cosim.classes import SEMANTIC_ID
from cosim.errors import CosimError
from cosim.geometry import quat_from_rpy, rotation_matrix
from cosim.io import deskew
from cosim.io.decode import decode_point_cloud
from cosim.io.sensor_messages import frame_messages
from cosim.scenario.model import LidarSpec, Mount, RigSpec, Scenario, SensorsSpec
from cosim.snapshot import Actor, AgentState, WorldSnapshot
from cosim.world.types import Prism, StaticLayout, World

WALL_ID = 1_000_001
POLE_ID = 1_000_002
SPEED_MPS = 20.0


def _rect(x0, y0, x1, y1):
    return ((x0, y0), (x1, y0), (x1, y1), (x0, y1))


def _wall_world(pole: bool = False) -> World:
    prisms = [Prism("terrain", _rect(-300, -300, 300, 300), -1.0, 0.0),
              Prism("building", _rect(50, -40, 55, 40), 0.0, 30.0, WALL_ID)]
    if pole:
        prisms.append(Prism("pole", _rect(19.85, 4.85, 20.15, 5.15), 0.0, 6.0, POLE_ID))
    return World("synthetic", b"", b"", (-300, -300, 300, 300), (), (), StaticLayout(tuple(prisms)), (37.0, -122.0, 0))


def _scenario(lidar: LidarSpec) -> Scenario:
    return synthetic_scenario(sensors=SensorsSpec(vehicle=RigSpec(lidar=lidar, cameras=[], gnss=None, imu=None),
                              bev=False))


def _vehicle(speed: float = SPEED_MPS, x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0,
             rate_z: float = 0.0) -> AgentState:
    yaw = math.radians(yaw_deg)
    return AgentState("vehicle_0", "vehicle", (x, y, 0.0), quat_from_rpy(0.0, 0.0, yaw),
                      (speed * math.cos(yaw), speed * math.sin(yaw), 0.0), (0.0, 0.0, rate_z))


def _cloud(sc: Scenario, world: World, agent: AgentState, actors=(), t_ns: int = 1_000_000_000):
    """Render, export and decode the vehicle's sweep: (frame, decoded cloud)."""
    snap = WorldSnapshot(5, t_ns, tuple(actors), (agent,))
    with SensorSuite(sc, world, noise=False, encode_images=False) as suite:
        frames = suite.render(snap, np.random.default_rng(0))
    msg = dict(frame_messages(frames, t_ns))["/vehicle_0/lidar"]
    return frames.agents["vehicle_0"].lidar, decode_point_cloud(msg)


def _base_to_map(agent: AgentState) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation_matrix(agent.rotation)
    m[:3, 3] = agent.position_m
    return m


def _lidar_to_base(spec: LidarSpec) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = mount_rotation(spec.mount)
    m[:3, 3] = spec.mount.xyz_m
    return m


SPIN = LidarSpec(channels=16, horizontal_resolution_deg=0.5, lower_fov_deg=-15.0, upper_fov_deg=15.0)


# --------------------------------------------------------------------------- motion distortion


def test_a_wall_passed_at_speed_is_sheared_and_deskew_flattens_it():
    agent = _vehicle()
    _, pc = _cloud(_scenario(SPIN), _wall_world(), agent)
    wall = pc.points["instance_id"] == WALL_ID
    assert wall.sum() > 200
    tau = pc.points["t_offset_ns"][wall] * 1e-9
    x_raw = pc.xyz[wall, 0]
    # the sensor was v * tau behind its end position when each firing met the wall face at x = 50 m
    np.testing.assert_allclose(x_raw, 50.0 - SPEED_MPS * tau, atol=0.02)
    assert np.ptp(x_raw) > 0.15  # visibly sheared: the firings across the wall span > 7 ms
    flat = deskew(pc.xyz, pc.points["t_offset_ns"], _base_to_map(agent), _lidar_to_base(SPIN), agent.velocity_mps,
                  agent.angular_rate_radps)
    np.testing.assert_allclose(flat[wall, 0], 50.0, atol=0.02)


def test_deskew_undoes_a_turn_as_well():
    agent = _vehicle(speed=10.0, rate_z=0.8)
    _, pc = _cloud(_scenario(SPIN), _wall_world(), agent)
    wall = pc.points["instance_id"] == WALL_ID
    flat = deskew(pc.xyz, pc.points["t_offset_ns"], _base_to_map(agent), _lidar_to_base(SPIN), agent.velocity_mps,
                  agent.angular_rate_radps)
    assert np.ptp(pc.xyz[wall, 0]) > 0.3
    np.testing.assert_allclose(flat[wall, 0], 50.0, atol=0.02)


def test_a_standing_sensor_sees_a_passing_car_at_each_firing_time_through_foliage_too():
    """An RSU (static hits kept between ticks) looks at a fast car, partly through a tree crown: every return
    lies in the car's box moved to its firing time, the ones through the leaves included."""
    ang = np.arange(8) * math.pi / 4 + 0.3
    crown = Prism("vegetation", tuple((math.cos(a), -6.0 + math.sin(a)) for a in ang), 2.5, 9.0, 0)
    world = World("synthetic", b"", b"", (-100, -100, 100, 100), (), (),
                  StaticLayout((Prism("terrain", _rect(-100, -100, 100, 100), -1.0, 0.0), crown)), (37.0, -122.0, 0))
    spec = LidarSpec(channels=32, horizontal_resolution_deg=0.4, lower_fov_deg=-45.0, upper_fov_deg=0.0,
                     range_noise_m=0.0)
    sc = synthetic_scenario(vehicles=0, rsus=1,
                            sensors=SensorsSpec(rsu=RigSpec(lidar=spec, cameras=[], gnss=None, imu=None), bev=False))
    rsu = AgentState("rsu_0", "rsu", (0.0, -12.0, 6.0), quat_from_rpy(0.0, 0.0, 0.0))
    car = Actor(5, "car", (0.0, 0.0, 0.77), (4.5, 1.9, 1.5), quat_from_rpy(0.0, 0.0, 0.0), (40.0, 0.0, 0.0))
    snaps = [WorldSnapshot(k, k * 100_000_000, (car,), (rsu,)) for k in (1, 2)]
    with SensorSuite(sc, world, encode_images=False) as suite:
        frames = [suite.render(s, np.random.default_rng(0)).agents["rsu_0"].lidar for s in snaps]
    to_map = _base_to_map(rsu) @ _lidar_to_base(spec)
    for f in frames:  # the first sweep casts the static world, the second one reuses it
        sel = f.instance_id == car.track_id
        assert sel.sum() >= 30
        tau = f.t_offset_ns[sel] * 1e-9
        assert tau.max() < -0.005  # seen well before the sweep's end: the car is 0.2 m or more back there
        pts = f.points[sel].astype(np.float64) @ to_map[:3, :3].T + to_map[:3, 3]
        # lines of sight that cross the crown's core (y = -6 m, within 0.5 m of its axis, 3-8 m up)
        at = to_map[:3, 3] + (pts - to_map[:3, 3]) * ((-6.0 - to_map[1, 3]) / (pts[:, 1] - to_map[1, 3]))[:, None]
        assert np.count_nonzero((np.abs(at[:, 0]) < 0.5) & (at[:, 2] > 3.0) & (at[:, 2] < 8.0)) >= 5
        moved = pts - tau[:, None] * np.asarray(car.velocity_mps)  # into the box's frame at the tick
        excess = (np.abs(moved - np.asarray(car.center_m)) - np.asarray(car.size_m) / 2).max()
        assert excess <= 0.02, f"returns up to {excess:.2f} m outside the box moved to their firing times"


def test_t_offset_spans_the_sweep_and_distortion_off_is_one_snapshot():
    period = sweep_ns(SPIN)
    _, moving = _cloud(_scenario(SPIN), _wall_world(), _vehicle())
    t = moving.points["t_offset_ns"]
    step = period / round(360 / SPIN.horizontal_resolution_deg)
    assert t.max() == 0 and abs((t.max() - t.min()) - (period - step)) <= 1
    off = SPIN.model_copy(update={"motion_distortion": False})
    f_off, pc_off = _cloud(_scenario(off), _wall_world(), _vehicle())
    f_still, _ = _cloud(_scenario(SPIN), _wall_world(), _vehicle(speed=0.0))
    assert (pc_off.points["t_offset_ns"] == 0).all()
    # off, a moving sensor gives exactly the instantaneous sweep of a standing one
    assert np.array_equal(f_off.points, f_still.points) and np.array_equal(f_off.instance_id, f_still.instance_id)


# --------------------------------------------------------------------------------- intensity


def test_intensity_follows_the_lambertian_model_and_markings_outshine_asphalt():
    spec = LidarSpec(channels=32, horizontal_resolution_deg=0.2, lower_fov_deg=-30.0, upper_fov_deg=-2.0,
                     mount=Mount(xyz_m=(0.0, 0.0, 1.9)))
    agent = AgentState("vehicle_0", "vehicle", (-60.0, -2.0, 0.02), quat_from_rpy(0.0, 0.0, 0.0))
    frame, _ = _cloud(_scenario(spec), synthetic_world(), agent)
    rng_m = np.linalg.norm(frame.points, axis=1)
    road = frame.class_id == SEMANTIC_ID["road"]
    mark = frame.class_id == SEMANTIC_ID["lane_marking"]
    # flat ground 1.9 m below the sensor (road top at z = 0.02 m): cos(incidence) = height / range
    cos_inc = (1.9 - 0.0) / rng_m[road]
    np.testing.assert_allclose(frame.intensity[road], 0.10 * cos_inc, atol=1e-5)  # rho_asphalt cos(alpha)
    assert np.corrcoef(cos_inc, frame.intensity[road])[0, 1] > 0.99
    for lo, hi in ((3.0, 8.0), (8.0, 20.0)):
        band = (rng_m >= lo) & (rng_m < hi)
        assert (band & mark).sum() >= 3 and (band & road).sum() >= 3
        assert frame.intensity[band & mark].mean() > 2 * frame.intensity[band & road].mean()


def test_rain_wets_the_road():
    spec = LidarSpec(channels=16, horizontal_resolution_deg=1.0, lower_fov_deg=-30.0, upper_fov_deg=-5.0)
    agent = AgentState("vehicle_0", "vehicle", (-60.0, -2.0, 0.02), quat_from_rpy(0.0, 0.0, 0.0))
    dry, _ = _cloud(_scenario(spec), synthetic_world(), agent)
    wet_sc = _scenario(spec).model_copy(update={"environment": _scenario(spec).environment.model_copy(
        update={"weather": "rainy", "rain_rate_mm_h": 10.0})})
    wet, _ = _cloud(wet_sc, synthetic_world(), agent)
    road_d, road_w = dry.class_id == 1, wet.class_id == 1
    assert wet.intensity[road_w].mean() < 0.6 * dry.intensity[road_d].mean()


# ------------------------------------------------------------------------------ scan patterns


ROSETTE = LidarSpec(pattern="rosette", rotation_hz=10.0, point_rate_hz=100_000.0, rosette_fov_deg=70.4,
                    mount=Mount(xyz_m=(0.0, 0.0, 1.9)))


def test_rosette_covers_its_field_of_view_within_one_second():
    period = sweep_ns(ROSETTE)
    d = np.concatenate([rosette_pattern(ROSETTE, k * period).directions for k in range(1, 11)])
    r = np.degrees(np.arccos(np.clip(d[:, 0], -1, 1)))
    phi = np.arctan2(d[:, 2], d[:, 1])
    u, v = r * np.cos(phi), r * np.sin(phi)
    half = ROSETTE.rosette_fov_deg / 2
    assert r.max() <= half + 1e-6
    edges = np.arange(-math.ceil(half), math.ceil(half) + 1)
    hist, _, _ = np.histogram2d(u, v, bins=[edges, edges])
    c = edges[:-1] + 0.5
    inside = np.hypot(c[:, None], c[None, :]) + math.sqrt(0.5) <= half  # whole cell inside the FOV
    assert (hist[inside] > 0).mean() >= 0.95
    # non-repetitive: the second 0.1 s frame is not the first one again
    assert not np.allclose(rosette_pattern(ROSETTE, period).directions, rosette_pattern(ROSETTE, 2 * period).directions)


def test_rosette_point_rate_is_the_configured_one():
    down = ROSETTE.model_copy(update={"mount": Mount(xyz_m=(0.0, 0.0, 1.9), rpy_deg=(0.0, 90.0, 0.0))})
    frame, pc = _cloud(_scenario(down), _wall_world(), _vehicle(speed=0.0))
    assert frame.n_points == pytest.approx(ROSETTE.point_rate_hz / ROSETTE.rotation_hz, rel=0.01)
    t = pc.points["t_offset_ns"]
    assert abs((t.max() - t.min()) - sweep_ns(ROSETTE)) <= 1e9 / ROSETTE.point_rate_hz + 1


def test_unknown_scan_pattern_is_a_clear_error():
    with pytest.raises(CosimError, match="unknown LiDAR scan pattern 'raster'; known: rosette, spinning"):
        scan_pattern("raster")


# ----------------------------------------------------------------------------------- labels


def _inside(points_map: np.ndarray, actor, margin: float) -> np.ndarray:
    r = rotation_matrix(actor.rotation)
    local = (points_map - np.asarray(actor.center_m)) @ r
    return np.all(np.abs(local) <= np.asarray(actor.size_m) / 2 + margin, axis=1)


@pytest.mark.parametrize("spec", [SPIN.model_copy(update={"lower_fov_deg": -25.0}),
                                  ROSETTE.model_copy(update={"rosette_fov_deg": 90.0})], ids=["spinning", "rosette"])
def test_points_of_an_object_lie_in_its_box_after_deskewing(spec):
    base = synthetic_snapshot(n_vehicles=0, n_rsus=0, n_drones=0)
    agent = _vehicle(x=-50.0, y=0.0, rate_z=0.3)
    # the ego's own box moves with it (so the actors are cast per time slice, the own shape ignored)
    own_box = Actor(999, "car", (-50.0, 0.0, 0.77), (4.5, 1.9, 1.5), agent.rotation, agent.velocity_mps, "vehicle_0")
    agent = dataclasses.replace(agent, track_id=999)
    _, pc = _cloud(_scenario(spec), synthetic_world(), agent, (*base.actors, own_box))
    assert not (pc.points["instance_id"] == 999).any()
    flat = deskew(pc.xyz, pc.points["t_offset_ns"], _base_to_map(agent), _lidar_to_base(spec), agent.velocity_mps,
                  agent.angular_rate_radps)
    lidar_to_map = _base_to_map(agent) @ _lidar_to_base(spec)
    in_map = flat @ lidar_to_map[:3, :3].T + lidar_to_map[:3, 3]
    raw_map = pc.xyz @ lidar_to_map[:3, :3].T + lidar_to_map[:3, 3]
    checked, raw_outside = 0, 0
    for a in base.actors:
        own = pc.points["instance_id"] == a.track_id
        if own.sum() < 5:
            continue
        checked += 1
        assert _inside(in_map[own], a, 0.1).all(), a
        raw_outside += int((~_inside(raw_map[own], a, 0.1)).sum())
    assert checked >= 3
    assert raw_outside > 0  # before deskewing, the smear puts points outside their boxes


# ------------------------------------------------------------------------------ dual returns


def test_dual_returns_at_a_pole_edge_report_the_pole_and_the_wall_behind():
    spec = SPIN.model_copy(update={"dual_returns": True, "horizontal_resolution_deg": 0.2})
    _, pc = _cloud(_scenario(spec), _wall_world(pole=True), _vehicle(speed=0.0))
    kind = pc.points["return"]
    assert set(np.unique(kind)) == {RETURN_SINGLE, RETURN_STRONGEST, RETURN_LAST}
    strongest, last = kind == RETURN_STRONGEST, kind == RETURN_LAST
    assert strongest.sum() == last.sum()
    # at the pole's edges, the near half of a beam is the pole and the far half the wall or ground behind
    r = np.linalg.norm(pc.xyz, axis=1)
    beam = pc.points["ring"].astype(np.int64) * 10**9 - pc.points["t_offset_ns"]  # one key per firing
    far = {int(b): (float(rr), int(i)) for b, rr, i in zip(beam[last], r[last], pc.points["instance_id"][last],
                                                            strict=True)}
    pole = np.nonzero(strongest & (pc.points["instance_id"] == POLE_ID))[0]
    assert len(pole) >= 4
    for k in pole:
        r_far, inst_far = far[int(beam[k])]
        assert r_far > r[k] + 1.0 and inst_far != POLE_ID
    assert any(far[int(beam[k])][1] == WALL_ID for k in pole)
    single = _cloud(_scenario(SPIN.model_copy(update={"horizontal_resolution_deg": 0.2})), _wall_world(pole=True),
                    _vehicle(speed=0.0))[1]
    assert (single.points["return"] == RETURN_SINGLE).all()
    assert len(pc) == len(single) + last.sum()


def test_returns_are_stored_in_firing_order():
    """By firing time, the returns of one firing from the lowest ring up, a dual pair's last return after the
    other returns of its firing (docs/episode_format.md 3.4); with motion distortion off the same order."""
    spec = SPIN.model_copy(update={"dual_returns": True, "horizontal_resolution_deg": 0.2})
    frame, pc = _cloud(_scenario(spec), _wall_world(pole=True), _vehicle(speed=0.0))
    t, ring, kind = pc.points["t_offset_ns"].astype(np.int64), pc.points["ring"].astype(np.int64), pc.points["return"]
    assert (kind == RETURN_LAST).sum() >= 4 and len(np.unique(t)) > 1000
    assert (np.diff(t) >= 0).all()
    same = np.diff(t) == 0
    last = kind == RETURN_LAST
    # within a firing: rings rise among the first returns; a last return follows only last returns
    assert (np.diff(ring)[same & ~last[:-1] & ~last[1:]] > 0).all()
    assert not (same & last[:-1] & ~last[1:]).any()
    off = spec.model_copy(update={"motion_distortion": False})
    f_off, pc_off = _cloud(_scenario(off), _wall_world(pole=True), _vehicle(speed=0.0))
    assert (pc_off.points["t_offset_ns"] == 0).all()
    assert np.array_equal(pc_off.points["ring"], pc.points["ring"]) and np.array_equal(f_off.points, frame.points)


def test_a_standing_sensor_with_a_rosette_casts_each_frames_own_firings():
    """RSUs keep their static hits between ticks; a rosette fires new directions every frame."""
    sc = synthetic_scenario(vehicles=0, rsus=1,
                            sensors=SensorsSpec(rsu=RigSpec(lidar=ROSETTE, cameras=[], gnss=None, imu=None), bev=False))
    rsu = AgentState("rsu_0", "rsu", (9.5, 9.5, 7.0), quat_from_rpy(0.0, 0.3, math.radians(225.0)))
    snaps = [WorldSnapshot(k, k * 200_000_000, (), (rsu,)) for k in (1, 2)]
    with SensorSuite(sc, synthetic_world(), noise=False, encode_images=False) as suite:
        first, second = (suite.render(s, np.random.default_rng(0)).agents["rsu_0"].lidar for s in snaps)
    with SensorSuite(sc, synthetic_world(), noise=False, encode_images=False) as fresh:
        alone = fresh.render(snaps[1], np.random.default_rng(0)).agents["rsu_0"].lidar
    assert np.array_equal(second.points, alone.points) and np.array_equal(second.instance_id, alone.instance_id)
    assert not np.array_equal(first.points[:100], second.points[:100])


def test_deskew_tick_uses_the_poses_recorded_in_the_episode(tmp_path):
    """Through a real file: /tf, the labels' velocity and the IMU's rates give back a flat wall."""
    import yaml
    from cosim.sensors.rig import sensor_transforms

    from cosim.io import deskew_tick, open_episode
    from cosim.io.labels import label_messages
    from cosim.io.synthetic import synthetic_metadata
    from cosim.io.writer import EpisodeWriter
    from cosim.scenario.model import ImuSpec

    rig = RigSpec(lidar=SPIN, cameras=[], gnss=None, imu=ImuSpec(gyro_noise_radps=0.0, gyro_bias_radps=0.0))
    sc = synthetic_scenario(sensors=SensorsSpec(vehicle=rig, bev=False))
    agent = dataclasses.replace(_vehicle(rate_z=0.5), track_id=1)
    box = Actor(1, "car", (0.0, 0.0, 0.77), (4.5, 1.9, 1.5), agent.rotation, agent.velocity_mps, "vehicle_0")
    snap = WorldSnapshot(0, 0, (box,), (agent,))
    path = tmp_path / "wall.mcap"
    world = _wall_world()
    with SensorSuite(sc, world, noise=False, encode_images=False) as suite, EpisodeWriter(path) as w:
        w.add_metadata("episode", synthetic_metadata(1, ["vehicle_0"], True, world))
        fs = suite.render(snap, np.random.default_rng(0))
        for topic, msg in label_messages(snap, sensor_transforms(sc, agent)) + frame_messages(fs, 0):
            w.write(topic, msg, 0)
        w.add_attachment("scenario.yaml", "application/yaml", yaml.safe_dump(sc.model_dump(mode="json")).encode())
        w.finish()
    with open_episode(path) as ep:
        tick = ep.tick(0)
        raw = tick.points("vehicle_0")
        flat = deskew_tick(tick, "vehicle_0")
    wall = raw.points["instance_id"] == WALL_ID
    assert np.ptp(raw.xyz[wall, 0]) > 0.3
    np.testing.assert_allclose(flat[wall, 0], 50.0, atol=0.02)
