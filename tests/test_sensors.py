"""Sensors on synthetic scenes with known geometry: ranges, depths, labels, frames, messages."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.meshes import ACTOR_TEMPLATES, VEHICLE_CLASSES, static_mesh, template_for, triangulate_polygon
from cosim.sensors.rig import sensor_transforms
from cosim.sensors.synthetic import actor, synthetic_scenario, synthetic_snapshot, synthetic_world
from PIL import Image

from cosim.classes import SEMANTIC_ID
from cosim.geometry import quat_from_rpy, rotation_matrix
from cosim.scenario.model import (
    AgentsSpec,
    CameraSpec,
    GnssSpec,
    HoverDrone,
    ImuSpec,
    LidarSpec,
    Mount,
    RigSpec,
    RsuAgents,
    Scenario,
    SensorsSpec,
    VehicleAgents,
    default_rsu_rig,
    default_vehicle_rig,
)
from cosim.snapshot import AgentState, WorldSnapshot
from tests.helpers import WALL_ID
from tests.helpers import convex_hull as _convex_hull
from tests.helpers import signed_dist_inside as _signed_dist_inside
from tests.helpers import wall_world as _wall_world


def _scenario(vehicle_rig: RigSpec, n_vehicles: int = 1, **env) -> Scenario:
    return synthetic_scenario(environment=env or {},
                              vehicles=n_vehicles,
                              sensors=SensorsSpec(vehicle=vehicle_rig))


def _ray_box(o, d, lo, hi):
    """Entry distance of rays o (3,), d (N, 3) into the axis-aligned box [lo, hi] (inf if missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (np.asarray(lo) - o) / d
        t2 = (np.asarray(hi) - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tmax >= tmin) & (tmax > 0), np.maximum(tmin, 0), np.inf)


# ------------------------------------------------------------------------------------- meshes


def test_concave_footprint_triangulation_covers_exact_area():
    poly = np.array([(0, 0), (10, 0), (10, 10), (6, 10), (6, 3), (4, 3), (4, 10), (0, 10)], float)  # U shape
    pts, tris = triangulate_polygon(poly[::-1])  # clockwise input on purpose
    assert len(tris) == len(pts) - 2
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    assert np.all(cross > 0)
    assert math.isclose(0.5 * cross.sum(), 100 - 2 * 7, rel_tol=1e-9)
    # centroids of all triangles lie inside the U (not in the notch)
    cen = (a + b + c) / 3
    assert not np.any((cen[:, 0] > 4) & (cen[:, 0] < 6) & (cen[:, 1] > 3))


def test_static_mesh_labels_every_triangle():
    world = synthetic_world()
    mesh = static_mesh(world.layout)
    assert mesh.n_triangles > 100
    assert set(np.unique(mesh.semantic)) <= set(SEMANTIC_ID.values())
    buildings = mesh.instance[mesh.semantic == SEMANTIC_ID["building"]]
    assert np.all(buildings >= 1_000_000)


@pytest.mark.parametrize("cls", sorted([*ACTOR_TEMPLATES, *VEHICLE_CLASSES, "pedestrian"]))
def test_actor_templates_fill_their_box(cls):
    tpl = template_for(cls)
    lo, hi = tpl.vertices.min(0), tpl.vertices.max(0)
    assert np.all(lo >= -0.5 - 1e-6) and np.all(hi <= 0.5 + 1e-6)
    assert np.all(hi - lo > 0.85), f"{cls} shape does not span its box: {hi - lo}"
    assert len(tpl.triangles) > 12, f"{cls} is a bare box"


# -------------------------------------------------------------------------------------- LiDAR


def test_lidar_ranges_match_analytic_distances_and_labels():
    lidar = LidarSpec(channels=21, upper_fov_deg=10.0, lower_fov_deg=-10.0, horizontal_resolution_deg=1.0,
                      range_m=200.0, mount=Mount(xyz_m=(0.0, 0.0, 2.0)))
    sc = _scenario(RigSpec(lidar=lidar, cameras=[], gnss=None, imu=None))
    suite = SensorSuite(sc, _wall_world(50.0), noise=False)
    car = actor(7, "car", 20.0, 10.0, 30.0, z_ground=0.0)
    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    frames = suite.render(WorldSnapshot(0, 0, (car,), (ego,)), np.random.default_rng(0))
    lf = frames.agents["vehicle_0"].lidar
    assert lf.n_points > 500
    pts = lf.points.astype(np.float64)
    r = np.linalg.norm(pts, axis=1)
    d = pts / r[:, None]
    o = np.array([0.0, 0.0, 2.0])
    t_ground = np.where(d[:, 2] < 0, -o[2] / np.where(d[:, 2] < 0, d[:, 2], -1), np.inf)
    t_wall = _ray_box(o, d, (50, -40, 0), (55, 40, 30))
    on_car = lf.instance_id == 7
    # every return off the car is at the analytic distance of the nearer of ground and wall
    analytic = np.minimum(t_ground, t_wall)
    assert np.max(np.abs(r[~on_car] - analytic[~on_car])) < 0.01
    expect_cls = np.where(t_wall < t_ground, SEMANTIC_ID["building"], SEMANTIC_ID["terrain"])
    expect_inst = np.where(t_wall < t_ground, WALL_ID, 0)
    assert np.array_equal(lf.class_id[~on_car], expect_cls[~on_car])
    assert np.array_equal(lf.instance_id[~on_car], expect_inst[~on_car])
    # returns on the car lie inside its box and carry its class
    assert on_car.sum() > 10
    assert np.all(lf.class_id[on_car] == SEMANTIC_ID["car"])
    rot = rotation_matrix(car.rotation)
    local = (pts[on_car] + o - np.asarray(car.center_m)) @ rot
    assert np.all(np.abs(local) <= np.asarray(car.size_m) / 2 + 1e-3)
    # the points are in the sensor frame: the horizontal ring straight ahead hits the wall at 50 m
    ahead = (lf.ring == 10) & (np.abs(pts[:, 1]) < 1e-6) & (pts[:, 0] > 0)
    assert np.allclose(pts[ahead, 0], 50.0, atol=0.01)


def test_own_actor_is_invisible_to_own_sensors():
    rig = RigSpec(lidar=LidarSpec(horizontal_resolution_deg=2.0, mount=Mount(xyz_m=(0.0, 0.0, 1.2))),
                  cameras=[CameraSpec(name="front", width=64, height=48, mount=Mount(xyz_m=(0.0, 0.0, 1.0)))],
                  gnss=None, imu=None)
    sc = _scenario(rig, n_vehicles=2)
    suite = SensorSuite(sc, _wall_world(), noise=False)
    a0 = actor(1, "car", 0.0, 0.0, z_ground=0.0, agent_id="vehicle_0")
    a1 = actor(2, "car", 10.0, 0.0, z_ground=0.0, agent_id="vehicle_1")
    agents = (AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), a0.rotation, track_id=1),
              AgentState("vehicle_1", "vehicle", (10.0, 0.0, 0.0), a1.rotation, track_id=2))
    f = suite.render(WorldSnapshot(0, 0, (a0, a1), agents), np.random.default_rng(0))
    v0 = f.agents["vehicle_0"]
    assert not np.any(v0.lidar.instance_id == 1)
    assert np.any(v0.lidar.instance_id == 2)
    assert not np.any(v0.cameras["front"].instance == 1)
    assert np.any(v0.cameras["front"].instance == 2)


def test_a_sensors_own_shape_is_skipped_exactly_as_a_scene_without_it():
    """Every sensor shares one actor scene: rays whose nearest actor hit is on the sensor's own shape take their
    nearest other hit, which must be exactly what a scene without the own shape gives (t and triangle), also
    for a second car touching the first (a fixed step past the own faces, and Open3D's list_intersections,
    both got some of these rays wrong)."""
    from cosim.sensors.scene import StaticScene, TickScene, cast, place_actors

    own = actor(1, "car", 0.0, 0.0, z_ground=0.0)
    length = float(own.size_m[0])
    other = actor(2, "car", length, 0.0, z_ground=0.0)  # bumper to bumper
    scene = TickScene.build(StaticScene(static_mesh(_wall_world().layout)), (own, other))
    rng = np.random.default_rng(3)
    d = rng.normal(size=(4000, 3))
    d[:, 2] = -np.abs(d[:, 2]) * 0.3  # mostly down and sideways, through the own body
    rays = np.concatenate([np.broadcast_to([0.0, 0.0, 1.2], d.shape), d / np.linalg.norm(d, axis=1, keepdims=True)],
                          axis=1).astype(np.float32)
    t, gid = scene.cast(rays, exclude_track=1, with_static=False)
    ref_mesh, _ = place_actors((other,))
    ref_scene = TickScene.build(scene.static, (other,))
    t_ref, prim_ref = cast(ref_scene._actor_scene(), rays)
    first = scene.n_static + int(np.sum(scene.actor_track == 1))  # the other car's triangles follow the own ones
    assert np.array_equal(t, t_ref)
    hit = prim_ref >= 0
    assert hit.sum() > 300 and ref_mesh.n_triangles == scene.actors.n_triangles - (first - scene.n_static)
    assert np.array_equal(gid[hit], first + prim_ref[hit])
    assert np.all(gid[~hit] == scene.miss)
    own_first = cast(scene._actor_scene(), rays)[1]
    assert np.sum(np.take(scene.actor_track, own_first[own_first >= 0]) == 1) > 1000  # the own shape was in the way


# ------------------------------------------------------------------------------------- camera


@pytest.mark.parametrize("block_px", [1, 8])
def test_camera_depth_matches_wall_at_50_m(block_px):
    cam = CameraSpec(name="front", width=320, height=180, mount=Mount(xyz_m=(0.0, 0.0, 1.6)))
    sc = _scenario(RigSpec(lidar=None, cameras=[cam], gnss=None, imu=None))
    suite = SensorSuite(sc, _wall_world(50.0), noise=False, block_px=block_px)
    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    cf = suite.render(WorldSnapshot(0, 0, (), (ego,)), np.random.default_rng(0)).agents["vehicle_0"].cameras["front"]
    wall = cf.instance == WALL_ID
    assert wall.mean() > 0.15
    assert np.max(np.abs(cf.depth[wall] - 50.0)) < 0.01
    assert np.all(cf.semantic[wall] == SEMANTIC_ID["building"])
    # ground pixels: planar depth of the ground plane z = 0 seen from 1.6 m
    ground = cf.semantic == SEMANTIC_ID["terrain"]
    v = np.nonzero(ground)[0] + 0.5
    y = (v - cf.K[1, 2]) / cf.K[1, 1]
    assert np.max(np.abs(cf.depth[ground] - 1.6 / y)) < 0.01 * np.max(1.6 / y)
    sky = cf.semantic == 0
    assert np.all(np.isinf(cf.depth[sky]))
    assert sky.any() and ground.any()


def test_adaptive_casting_agrees_with_full_casting():
    from cosim.scenario.model import default_vehicle_rig

    rig = default_vehicle_rig()
    cams = [CameraSpec(name=c.name, width=320, height=180, mount=c.mount) for c in rig.cameras]
    sc = _scenario(RigSpec(lidar=None, cameras=cams, gnss=None, imu=None), n_vehicles=5)
    snap = synthetic_snapshot(5, 0, 0)
    world = synthetic_world()
    full = SensorSuite(sc, world, block_px=1, noise=False).render(snap, np.random.default_rng(0))
    fast = SensorSuite(sc, world, block_px=8, noise=False).render(snap, np.random.default_rng(0))
    same = total = 0
    rel = []
    for aid, af in full.agents.items():
        for name, cf in af.cameras.items():
            cg = fast.agents[aid].cameras[name]
            eq = (cf.instance == cg.instance) & (cf.semantic == cg.semantic)
            same += int(eq.sum())
            total += eq.size
            both = eq & np.isfinite(cf.depth)
            rel.append(np.abs(cf.depth[both] - cg.depth[both]) / cf.depth[both])
    rel = np.concatenate(rel)
    assert same / total > 0.995
    assert np.mean(rel < 1e-4) > 0.995 and rel.max() < 0.05


def _compose(transforms, child: str):
    """map <- child from an agent's base_link pose and its sensor_transforms list."""
    by_child = {c: (p, np.asarray(t), rotation_matrix(q)) for p, c, t, q in transforms}
    rot, pos = np.eye(3), np.zeros(3)
    chain = []
    while child in by_child:
        chain.append(by_child[child])
        child = by_child[child][0]
    for _, t, r in reversed(chain):
        pos = pos + rot @ t
        rot = rot @ r
    return child, rot, pos


def test_labels_poses_calibration_and_pixels_agree():
    """Projected 3D boxes (via /tf transforms and calibration) contain the instance pixels."""
    from cosim.scenario.model import default_drone_rig, default_rsu_rig, default_vehicle_rig

    def small(rig):
        cams = [CameraSpec(name=c.name, width=320, height=180, mount=c.mount, gimbal=c.gimbal) for c in rig.cameras]
        return RigSpec(lidar=None, cameras=cams, gnss=None, imu=None)

    sc = Scenario(name="t", agents=AgentsSpec(vehicles=VehicleAgents(count=5), rsus=RsuAgents(count=5),
                                              drones=[HoverDrone()] * 5),
                  sensors=SensorsSpec(vehicle=small(default_vehicle_rig()), rsu=small(default_rsu_rig()),
                                      drone=small(default_drone_rig())))
    snap = synthetic_snapshot()
    frames = SensorSuite(sc, synthetic_world(), noise=False).render(snap, np.random.default_rng(0))
    checked = 0
    for agent in snap.agents:
        tfs = sensor_transforms(sc, agent)
        rb, pb = rotation_matrix(agent.rotation), np.asarray(agent.position_m)
        for name, cf in frames.agents[agent.agent_id].cameras.items():
            root, r_rel, p_rel = _compose(tfs, f"{agent.agent_id}/{name}/optical")
            assert root == f"{agent.agent_id}/base_link"
            rot, pos = rb @ r_rel, pb + rb @ p_rel
            assert np.allclose(rot, cf.pose.rotation, atol=1e-9) and np.allclose(pos, cf.pose.position_m)
            for a in snap.actors:
                if a.agent_id == agent.agent_id:
                    continue
                sgn = np.array([[i, j, k] for i in (-.5, .5) for j in (-.5, .5) for k in (-.5, .5)])
                corners = sgn * np.asarray(a.size_m) @ rotation_matrix(a.rotation).T + np.asarray(a.center_m)
                pc = (corners - pos) @ rot
                if np.any(pc[:, 2] < 0.5):
                    continue
                uvw = pc @ cf.K.T
                uv = uvw[:, :2] / uvw[:, 2:3]
                if np.any(uv < 0) or np.any(uv[:, 0] > cf.width) or np.any(uv[:, 1] > cf.height):
                    continue
                vv, uu = np.nonzero(cf.instance == a.track_id)
                if len(vv) < 20:
                    continue
                hull = _convex_hull(uv)
                d = _signed_dist_inside(hull, np.stack([uu + 0.5, vv + 0.5], axis=1))
                assert np.all(d >= -2.0), f"{a.track_id} pixels outside its box in {agent.agent_id}/{name}"
                assert np.mean(d >= 0) >= 0.9
                checked += 1
    assert checked >= 10


# --------------------------------------------------------------------------- weather, lighting


def _town_lidar_scenario(**env) -> Scenario:
    # a long-range unit: the ray drop's energy term would otherwise lose the grazing ground beyond 60 m
    lidar = LidarSpec(horizontal_resolution_deg=0.7, range_m=200.0, detection_range_10pct_m=1000.0)
    rig = RigSpec(lidar=lidar, cameras=[], gnss=None, imu=None)
    return synthetic_scenario(environment=env, rsus=2,
                              sensors=SensorsSpec(vehicle=rig, rsu=rig))


def test_fog_removes_far_returns_and_adds_backscatter():
    snap = synthetic_snapshot(1, 2, 0)
    world = synthetic_world()
    clear = SensorSuite(_town_lidar_scenario(weather="clear"), world).render(snap, np.random.default_rng(1))
    fog = SensorSuite(_town_lidar_scenario(weather="foggy", fog_visibility_m=50.0), world).render(
        snap, np.random.default_rng(1))
    far_clear = sum(int((np.linalg.norm(a.lidar.points, axis=1) > 100).sum()) for a in clear.agents.values())
    far_fog = sum(int((np.linalg.norm(a.lidar.points, axis=1) > 100).sum()) for a in fog.agents.values())
    assert far_clear > 500
    assert far_fog <= 0.1 * far_clear
    near_spurious = sum(int(((a.lidar.class_id == 0) & (np.linalg.norm(a.lidar.points, axis=1) < 6)).sum())
                        for a in fog.agents.values())
    assert near_spurious > 50
    # intensity falls with distance in fog more than in clear air (same surfaces, 20-40 m)
    def mean_int(fs):
        vals = [a.lidar.intensity[(np.linalg.norm(a.lidar.points, axis=1) > 20)
                                  & (np.linalg.norm(a.lidar.points, axis=1) < 40) & (a.lidar.class_id > 0)]
                for a in fs.agents.values()]
        return float(np.mean(np.concatenate(vals)))
    assert mean_int(fog) < 0.5 * mean_int(clear)


def test_rain_adds_dropout_and_spurious_near_returns():
    snap = synthetic_snapshot(1, 2, 0)
    world = synthetic_world()
    clear = SensorSuite(_town_lidar_scenario(weather="clear"), world).render(snap, np.random.default_rng(1))
    rain = SensorSuite(_town_lidar_scenario(weather="rainy", rain_rate_mm_h=25.0), world).render(
        snap, np.random.default_rng(1))
    n_clear = sum(a.lidar.n_points for a in clear.agents.values())
    real_rain = sum(int((a.lidar.class_id > 0).sum()) for a in rain.agents.values())
    spur = sum(int((a.lidar.class_id == 0).sum()) for a in rain.agents.values())
    assert real_rain < 0.95 * n_clear
    assert spur > 20


def _camera_scenario(lighting: str, weather: str = "clear") -> Scenario:
    cams = [CameraSpec(name="front", width=240, height=136, mount=Mount(xyz_m=(0, 0, 1.6), rpy_deg=(0, 8, 0)))]
    return synthetic_scenario(environment={"lighting": lighting, "weather": weather},
                              vehicles=5,
                              sensors=SensorsSpec(vehicle=RigSpec(lidar=None, cameras=cams, gnss=None, imu=None)))


def test_night_is_darker_with_lit_pools_under_street_lights():
    snap = synthetic_snapshot(5, 0, 0)
    world = synthetic_world()
    day = SensorSuite(_camera_scenario("day"), world).render(snap, np.random.default_rng(0))
    night = SensorSuite(_camera_scenario("night"), world).render(snap, np.random.default_rng(0))
    d = np.concatenate([a.cameras["front"].rgb.ravel() for a in day.agents.values()]).astype(float)
    n = np.concatenate([a.cameras["front"].rgb.ravel() for a in night.agents.values()]).astype(float)
    assert n.mean() < 0.5 * d.mean()
    # under the street lights (y = 8, x = -60, -30, 30, 60) the road is much brighter than between them
    lit, dark = [], []
    for af in night.agents.values():
        cf = af.cameras["front"]
        road = (cf.semantic == SEMANTIC_ID["road"]) | (cf.semantic == SEMANTIC_ID["sidewalk"])
        v, u = np.nonzero(road & np.isfinite(cf.depth))
        x = (u + 0.5 - cf.K[0, 2]) / cf.K[0, 0] * cf.depth[v, u]
        y = (v + 0.5 - cf.K[1, 2]) / cf.K[1, 1] * cf.depth[v, u]
        p = np.stack([x, y, cf.depth[v, u]], axis=1) @ cf.pose.rotation.T + cf.pose.position_m
        lum = cf.rgb[v, u].mean(axis=1)
        dist = np.min(np.hypot(p[:, None, 0] - np.array([-60, -30, 30, 60]), p[:, None, 1] - 8.0), axis=1)
        lit.append(lum[dist < 4])
        dark.append(lum[(dist > 14) & (np.abs(p[:, 1]) > 3)])
    assert np.concatenate(lit).mean() > 2.0 * np.concatenate(dark).mean()


# ------------------------------------------------------------------------- GNSS, IMU, BEV, ...


def test_gnss_and_imu_without_noise_are_exact():
    rig = RigSpec(lidar=None, cameras=[], gnss=GnssSpec(noise_m=0.0), imu=ImuSpec())
    sc = _scenario(rig)
    suite = SensorSuite(sc, _wall_world(), noise=False)
    ego = AgentState("vehicle_0", "vehicle", (0.0, 1000.0, 5.0), quat_from_rpy(0, 0, 0.3),
                     angular_rate_radps=(0.0, 0.0, 0.2), specific_force_mps2=(1.0, 0.5, 9.8))
    af = suite.render(WorldSnapshot(0, 0, (), (ego,)), np.random.default_rng(0)).agents["vehicle_0"]
    assert abs(af.gnss.latitude_deg - 37.0 - 1000.0 / 110_996.0) < 2e-5  # ~111 km per degree of latitude
    assert af.gnss.longitude_deg == pytest.approx(-122.0, abs=1e-9)
    assert af.gnss.altitude_m == pytest.approx(15.0)
    assert af.imu.linear_acceleration_mps2 == (1.0, 0.5, 9.8)
    assert af.imu.angular_velocity_radps == (0.0, 0.0, 0.2)
    noisy = SensorSuite(sc, _wall_world()).render(WorldSnapshot(0, 0, (), (ego,)), np.random.default_rng(0))
    acc = np.array(noisy.agents["vehicle_0"].imu.linear_acceleration_mps2)
    assert 0 < np.abs(acc - (1.0, 0.5, 9.8)).max() < 1.0


def test_bev_has_road_under_ego_and_boxes_of_the_right_area():
    sc = _scenario(RigSpec(lidar=None, cameras=[], gnss=None, imu=None), n_vehicles=5)
    snap = synthetic_snapshot(5, 0, 0)
    f = SensorSuite(sc, synthetic_world(), noise=False).render(snap, np.random.default_rng(0))
    bev = f.agents["vehicle_0"].bev
    ny, nx, _ = bev.grid.shape
    assert (ny, nx) == (320, 512)
    road = bev.grid[..., bev.layers.index("road")]
    assert road[ny // 2, nx // 2] == 1
    cars = bev.grid[..., bev.layers.index("car")]
    # the ego car: 4.5 x 1.9 m at 0.25 m cells -> ~137 cells around the centre
    ego_cells = cars[ny // 2 - 6:ny // 2 + 6, nx // 2 - 12:nx // 2 + 12].sum()
    assert abs(ego_cells - 4.5 * 1.9 / 0.0625) < 25
    assert bev.grid[..., bev.layers.index("bus")].sum() > 0


def test_visibility_counts_match_frames_and_render_is_deterministic():
    from cosim.scenario.model import default_vehicle_rig

    rig = default_vehicle_rig()
    cams = [CameraSpec(name=c.name, width=160, height=96, mount=c.mount) for c in rig.cameras[:2]]
    sc = _scenario(RigSpec(lidar=LidarSpec(horizontal_resolution_deg=1.0), cameras=cams, gnss=GnssSpec(),
                           imu=ImuSpec()), n_vehicles=5, weather="rainy")
    snap = synthetic_snapshot(5, 0, 0)
    suite = SensorSuite(sc, synthetic_world())
    a = suite.render(snap, np.random.default_rng(5))
    b = suite.render(snap, np.random.default_rng(5))
    for aid, fa in a.agents.items():
        fb = b.agents[aid]
        assert np.array_equal(fa.lidar.points, fb.lidar.points)
        assert fa.gnss == fb.gnss and fa.imu == fb.imu
        for name, ca in fa.cameras.items():
            assert np.array_equal(ca.rgb, fb.cameras[name].rgb)
        for o in fa.visibility.objects:
            assert o.lidar_points == int((fa.lidar.instance_id == o.track_id).sum())
            for name, cnt in o.pixels.items():
                assert cnt == int((fa.cameras[name].instance == o.track_id).sum())
    assert any(o.visible for f in a.agents.values() for o in f.visibility.objects)


def test_rsu_sensors_keep_the_static_world_and_cast_only_what_moves():
    """RSUs keep their static hits (made at a tick with other actors): the LiDAR gives exactly the data of
    a fresh cast; the cameras agree with one ray per pixel (static part adaptive, actors cast per pixel)
    and cast fewer rays than a moving camera."""
    import dataclasses

    from cosim.scenario.model import default_rsu_rig

    cams = [CameraSpec(name=c.name, width=160, height=96, mount=c.mount) for c in default_rsu_rig().cameras]
    cams.append(CameraSpec(name="up", width=160, height=96, mount=Mount(rpy_deg=(0.0, -10.0, 0.0))))  # sky too
    rig = RigSpec(lidar=LidarSpec(horizontal_resolution_deg=1.0), cameras=cams, gnss=None, imu=None)
    sc = synthetic_scenario(vehicles=0, rsus=3,
                            sensors=SensorsSpec(rsu=rig))
    world = synthetic_world()
    first = synthetic_snapshot(0, 3, 0)
    moved = tuple(dataclasses.replace(a, center_m=(a.center_m[0] + 4.0, *a.center_m[1:])) for a in first.actors[:-3])
    second = WorldSnapshot(1, 200_000_000, moved, first.agents)
    warm = SensorSuite(sc, world, noise=False)
    warm.render(first, np.random.default_rng(0))
    a = warm.render(second, np.random.default_rng(0))
    # references: the same agents as if they moved (nothing kept), adaptive and one ray per pixel
    as_moving = dataclasses.replace(second, agents=tuple(dataclasses.replace(g, kind="vehicle") for g in second.agents))
    b = SensorSuite(sc, world, noise=False).render(as_moving, np.random.default_rng(0))
    exact = SensorSuite(sc, world, noise=False, block_px=1).render(as_moving, np.random.default_rng(0))
    assert a.timing_s["rays"] < b.timing_s["rays"]
    moved_ids = [x.track_id for x in moved]
    n_lidar = agree = total = on_actors = agree_on_actors = 0
    for aid, fa in a.agents.items():
        for k in ("points", "intensity", "ring", "class_id", "instance_id"):
            assert np.array_equal(getattr(fa.lidar, k), getattr(b.agents[aid].lidar, k)), (aid, "lidar", k)
        n_lidar += int(np.isin(fa.lidar.instance_id, moved_ids).sum())
        for name, ca in fa.cameras.items():
            ce = exact.agents[aid].cameras[name]
            same = ca.instance == ce.instance
            actor = np.isin(ce.instance, moved_ids)
            agree, total = agree + int(same.sum()), total + same.size
            on_actors, agree_on_actors = on_actors + int(actor.sum()), agree_on_actors + int((same & actor).sum())
            m = same & np.isfinite(ce.depth)
            np.testing.assert_allclose(ca.depth[m], ce.depth[m], rtol=1e-4, atol=1e-3)
    assert on_actors > 100 and n_lidar > 0  # the moved actors are in view
    assert agree_on_actors >= 0.999 * on_actors
    assert agree >= 0.9995 * total
    assert any(np.isinf(c.depth).any() for f in a.agents.values() for c in f.cameras.values())


# -------------------------------------------------------------------------------- messages


def test_frame_messages_topics_and_round_trips():
    from cosim.io.decode import decode_compressed_image, decode_point_cloud
    from cosim.io.sensor_messages import frame_messages

    cams = [CameraSpec(name="front", width=96, height=64, mount=Mount(xyz_m=(0, 0, 1.6)))]
    sc = _scenario(RigSpec(lidar=LidarSpec(horizontal_resolution_deg=2.0), cameras=cams, gnss=GnssSpec(),
                           imu=ImuSpec()), n_vehicles=1)
    snap = synthetic_snapshot(1, 0, 0)
    f = SensorSuite(sc, synthetic_world()).render(snap, np.random.default_rng(0))
    msgs = dict(frame_messages(f, 123_000_000_000))
    expect = {"/vehicle_0/lidar", "/vehicle_0/front/image", "/vehicle_0/front/depth", "/vehicle_0/front/semantic",
              "/vehicle_0/front/instance", "/vehicle_0/front/calibration", "/vehicle_0/gnss", "/vehicle_0/imu",
              "/vehicle_0/bev", "/vehicle_0/visibility"}
    assert set(msgs) == expect
    af = f.agents["vehicle_0"]
    cf = af.cameras["front"]
    img = msgs["/vehicle_0/front/image"]
    assert img.timestamp.ToNanoseconds() == 123_000_000_000 and img.format == "png"
    assert img.frame_id == "vehicle_0/front/optical"
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(img.data))), cf.rgb)
    depth = msgs["/vehicle_0/front/depth"]
    assert depth.format == "cosim-depth"
    depth_m = decode_compressed_image(depth).depth_m
    fin = np.isfinite(cf.depth)
    assert np.array_equal(np.isnan(depth_m), ~fin)
    assert np.max(np.abs(depth_m[fin] - cf.depth[fin])) <= 2.0**-11
    inst = msgs["/vehicle_0/front/instance"]
    assert inst.encoding == "32SC1"
    assert np.array_equal(np.frombuffer(inst.data, "<i4").reshape(64, 96), cf.instance.astype(np.int32))
    pc = msgs["/vehicle_0/lidar"]
    assert pc.frame_id == "vehicle_0/lidar"
    assert [fl.name for fl in pc.fields][-3:] == ["instance_id", "t_offset_ns", "return"]
    rec = decode_point_cloud(pc).points
    assert np.array_equal(rec["instance_id"], af.lidar.instance_id)
    for k, name in enumerate("xyz"):
        assert np.max(np.abs(rec[name] - af.lidar.points[:, k])) <= 2.0**-8 + 1e-6  # half of 1/128 m
    assert np.max(np.abs(rec["intensity"] - af.lidar.intensity)) <= 0.5 / 255 + 1e-6
    cal = msgs["/vehicle_0/front/calibration"]
    assert list(cal.K) == list(cf.K.ravel()) and len(cal.P) == 12
    schema_name, _schema, payload = msgs["/vehicle_0/imu"]
    assert schema_name == "cosim.Imu" and payload["timestamp_ns"] == 123_000_000_000
    grid = msgs["/vehicle_0/bev"]
    assert grid.column_count == 512 and len(grid.data) == 512 * 320 * len(grid.fields)
    jpeg = dict(frame_messages(f, 0, image_format="jpeg"))["/vehicle_0/front/image"]
    assert jpeg.format == "jpeg" and jpeg.data[:2] == b"\xff\xd8"


# ----------------------------------------------- render processes, sun shadows, night light, the camera model


def _small_rig_scenario(**env) -> Scenario:
    vcams = [CameraSpec(name=c.name, width=96, height=64, mount=c.mount) for c in default_vehicle_rig().cameras[:2]]
    rcams = [CameraSpec(name=c.name, width=96, height=64, mount=c.mount) for c in default_rsu_rig().cameras[:2]]
    lidar = LidarSpec(horizontal_resolution_deg=2.0)
    return synthetic_scenario(environment=env or {},
                              vehicles=3, rsus=2,
                              sensors=SensorsSpec(vehicle=RigSpec(lidar=lidar, cameras=vcams),
                                                  rsu=RigSpec(lidar=lidar, cameras=rcams)))


def _frame_bytes(frames) -> list[tuple[str, bytes]]:
    from cosim.io.sensor_messages import frame_messages

    return [(topic, msg.SerializeToString() if hasattr(msg, "SerializeToString") else repr(msg).encode())
            for topic, msg in frame_messages(frames, frames.t_ns)]


def test_render_processes_give_the_same_bytes_as_one_process():
    sc = _small_rig_scenario(weather="rainy", lighting="dusk")
    world = synthetic_world()
    snaps = [synthetic_snapshot(3, 2, 0), synthetic_snapshot(3, 2, 0, tick=1)]
    out = []
    def stop():
        raise RuntimeError("stop")

    for processes in (0, 2):
        with SensorSuite(sc, world, processes=processes) as suite:
            if processes:  # a frame abandoned half-way leaves nothing behind for the next ones
                with pytest.raises(RuntimeError, match="stop"):
                    suite.render(snaps[0], np.random.default_rng(99), check=stop)
            rng = np.random.default_rng(7)
            out.append([_frame_bytes(suite.render(s, rng)) for s in snaps])
    assert [len(x) for x in out[0]] == [len(x) for x in out[1]]
    assert out[0] == out[1]
    assert any(t.endswith("/image") for t, _ in out[0][0])


def _pillar_world(sun_dir: np.ndarray):
    """Flat terrain with a 4 x 4 m pillar 8 m from the origin towards the sun, tall enough to shade the origin."""
    from cosim.world.types import Prism, StaticLayout, World

    u = sun_dir[:2] / np.linalg.norm(sun_dir[:2])
    c = 8.0 * u
    height = 8.0 * sun_dir[2] / np.linalg.norm(sun_dir[:2]) + 10.0
    foot = tuple((float(c[0] + dx), float(c[1] + dy)) for dx, dy in ((-2, -2), (2, -2), (2, 2), (-2, 2)))
    prisms = (Prism("terrain", ((-300, -300), (300, -300), (300, 300), (-300, 300)), -1.0, 0.0),
              Prism("building", foot, 0.0, height, 1_000_001))
    return World("synthetic", b"", b"", (-300, -300, 300, 300), (), (), StaticLayout(prisms), (37.0, -122.0, 10.0))


def _down_camera_scenario(lighting: str, seed: int = 3, **cam) -> Scenario:
    from cosim.scenario.model import Mount

    cam = {"width": 128, "height": 96, **cam}
    down = CameraSpec(name="down", fov_deg=90.0, mount=Mount(xyz_m=(0.0, 0.0, 20.0), rpy_deg=(0.0, 90.0, 0.0)), **cam)
    return synthetic_scenario(seed=seed, environment={"lighting": lighting},
                              sensors=SensorsSpec(vehicle=RigSpec(lidar=None, cameras=[down], gnss=None, imu=None),
                                                  surface_detail=False))  # flat surfaces: the light alone is measured


def _ego_snapshot():
    from cosim.snapshot import AgentState, WorldSnapshot

    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    return WorldSnapshot(0, 0, (), (ego,))


def _pixel_of(frame, point) -> tuple[int, int]:
    from cosim.sensors.camera import project_points

    uv, front = project_points(np.asarray([point], float), frame.pose, frame.K)
    assert front[0]
    return int(uv[0, 1]), int(uv[0, 0])


@pytest.mark.parametrize("lighting", ["day", "dusk"])
def test_sun_shadow_darkens_by_the_suns_share_and_is_as_sharp_as_one_ray_per_pixel(lighting):
    from cosim.sensors.camera import to_srgb
    from cosim.sensors.meshes import material_of

    sc = _down_camera_scenario(lighting, vignetting=0.0)
    probe = SensorSuite(sc, _pillar_world(np.array([1.0, 0.0, 1.0])), noise=False, encode_images=False)
    sun_dir, atm = probe.atm.sun_dir, probe.atm
    probe.close()
    world = _pillar_world(sun_dir)
    snap = _ego_snapshot()
    with SensorSuite(sc, world, noise=False, encode_images=False) as suite:
        f = suite.render(snap, np.random.default_rng(0)).agents["vehicle_0"].cameras["down"]
    with SensorSuite(sc, world, noise=False, encode_images=False, block_px=1) as exact_suite:
        exact = exact_suite.render(snap, np.random.default_rng(0)).agents["vehicle_0"].cameras["down"]
    albedo = np.asarray(material_of("terrain", 0)[0], np.float64)
    ambient = albedo * atm.ambient_rgb  # up-facing: sees the whole sky
    sunlit = ambient + albedo * atm.sun_rgb * sun_dir[2]
    u = sun_dir[:2] / np.linalg.norm(sun_dir[:2])
    in_shadow = _pixel_of(f, (0.0, 0.0, 0.0))
    in_sun = _pixel_of(f, (-6.0 * u[1], 6.0 * u[0], 0.0))  # beside the shadow (the pillar is 4 m wide)
    got_shadow = f.rgb[in_shadow].astype(int)
    got_sun = f.rgb[in_sun].astype(int)
    assert np.abs(got_shadow - to_srgb(ambient, atm.exposure).astype(int)).max() <= 1, (got_shadow, ambient)
    assert np.abs(got_sun - to_srgb(sunlit, atm.exposure).astype(int)).max() <= 1, (got_sun, sunlit)
    assert (got_sun - got_shadow).min() > 5
    # adaptive casting refines shadow edges down to pixels: the image equals one ray per pixel
    assert np.mean(np.any(f.rgb != exact.rgb, axis=2)) < 0.002
    # sensors.sun_shadows: false lights the same pixel as if the pillar were not there
    off = sc.model_copy(update={"sensors": sc.sensors.model_copy(update={"sun_shadows": False})})
    with SensorSuite(off, world, noise=False, encode_images=False) as flat_suite:
        flat = flat_suite.render(snap, np.random.default_rng(0)).agents["vehicle_0"].cameras["down"]
    assert np.abs(flat.rgb[in_shadow].astype(int) - to_srgb(sunlit, atm.exposure).astype(int)).max() <= 1


def test_night_street_light_falls_off_without_steps():
    """A street light over a flat road at night: neighbouring road pixels differ by at most 2 sRGB levels."""
    from cosim.sensors.meshes import LAMP_ARM_MIN_Z_M

    from cosim.world.types import Prism, StaticLayout, World

    top = LAMP_ARM_MIN_Z_M + 7.0  # a 9 m street light
    prisms = (Prism("terrain", ((-300, -300), (300, -300), (300, 300), (-300, 300)), -1.0, 0.0),
              Prism("road", ((-200, -10), (200, -10), (200, 10), (-200, 10)), 0.0, 0.02),
              Prism("street_light", ((11.9, -0.1), (12.1, -0.1), (12.1, 0.1), (11.9, 0.1)), 0.02, top, 1_000_002),
              Prism("street_light", ((10.0, -0.2), (12.0, -0.2), (12.0, 0.2), (10.0, 0.2)), top - 0.3, top,
                    1_000_003))
    world = World("synthetic", b"", b"", (-300, -300, 300, 300), (), (), StaticLayout(prisms), (37.0, -122.0, 10.0))
    with SensorSuite(_down_camera_scenario("night", width=256, height=192, vignetting=0.0), world, noise=False,
                     encode_images=False) as suite:
        f = suite.render(_ego_snapshot(), np.random.default_rng(0)).agents["vehicle_0"].cameras["down"]
    road = f.semantic == f.semantic[_pixel_of(f, (0.0, 0.0, 0.02))]
    rgb = f.rgb.astype(int)
    lit = rgb.max(axis=2) > 20
    dx = np.abs(np.diff(rgb, axis=1)).max(axis=2)[road[:, 1:] & road[:, :-1] & lit[:, 1:]]
    dy = np.abs(np.diff(rgb, axis=0)).max(axis=2)[road[1:] & road[:-1] & lit[1:]]
    assert len(dx) > 1000 and len(dy) > 1000  # a lit road fills much of the view
    assert max(dx.max(), dy.max()) <= 2
    assert rgb[road].max() - rgb[road & lit].min() > 30  # the pool of light does fall off


@pytest.mark.parametrize(("read", "shot", "level"), [(0.004, 0.0, 0.3), (0.002, 0.0004, 0.25), (0.0, 0.001, 0.6)])
def test_sensor_noise_has_the_configured_standard_deviation(read, shot, level):
    from cosim.sensors.camera import FULL_SCALE, sensor_codes

    cam = CameraSpec(name="c", width=320, height=240, read_noise=read, shot_noise=shot, vignetting=0.0)
    K = np.array([[160.0, 0, 160], [0, 160.0, 120], [0, 0, 1]])
    flat = np.full((240, 320, 3), level, np.float32)
    clean = sensor_codes(flat.copy(), cam, K, 1.0, None)
    noisy = sensor_codes(flat.copy(), cam, K, 1.0, np.random.default_rng(1))
    again = sensor_codes(flat.copy(), cam, K, 1.0, np.random.default_rng(1))
    other = sensor_codes(flat.copy(), cam, K, 1.0, np.random.default_rng(2))
    expect = np.sqrt(shot * level + read**2) * FULL_SCALE
    assert np.all(clean == level * FULL_SCALE)
    assert abs((noisy - clean).std() / expect - 1) < 0.02
    assert abs((noisy - clean).mean()) < 0.02 * expect
    assert np.array_equal(noisy, again) and not np.array_equal(noisy, other)  # seeded


def test_vignetting_darkens_the_corners_by_the_configured_fraction():
    from cosim.sensors.camera import sensor_codes

    cam = CameraSpec(name="c", width=64, height=48, vignetting=0.3)
    K = np.array([[32.0, 0, 32], [0, 32.0, 24], [0, 0, 1]])
    out = sensor_codes(np.full((48, 64, 3), 0.5, np.float32), cam, K, 1.0, None)
    centre, corner = out[23:25, 31:33].mean(), out[0, 0, 0]
    assert abs(corner / centre - 0.7) < 0.01


def test_rendered_noise_is_seeded_and_off_without_noise():
    sc = _down_camera_scenario("day", read_noise=0.01)
    world = _pillar_world(np.array([1.0, 0.0, 1.0]))
    snap = _ego_snapshot()
    with SensorSuite(sc, world, encode_images=False) as suite:
        a = suite.render(snap, np.random.default_rng(4)).agents["vehicle_0"].cameras["down"]
        b = suite.render(snap, np.random.default_rng(4)).agents["vehicle_0"].cameras["down"]
        c = suite.render(snap, np.random.default_rng(5)).agents["vehicle_0"].cameras["down"]
    with SensorSuite(sc, world, noise=False, encode_images=False) as quiet:
        q = quiet.render(snap, np.random.default_rng(4)).agents["vehicle_0"].cameras["down"]
    assert np.array_equal(a.rgb, b.rgb) and not np.array_equal(a.rgb, c.rgb)
    d = a.rgb.astype(int) - q.rgb.astype(int)
    assert d.std() > 1.0 and abs(d.mean()) < 1.0


def test_rain_streaks_never_appear_in_front_of_nearer_geometry():
    from cosim.sensors.camera import RAIN_FAR_M, rain_streaks

    depth = np.full((360, 480), np.inf, np.float32)
    depth[:, :240] = 8.0  # a wall 8 m away on the left half
    vv, uu, dd = rain_streaks(depth, 100.0, 240.0, np.random.default_rng(0))
    assert np.all(dd < depth[vv, uu])
    on_wall = uu < 240
    assert on_wall.sum() > 20 and (~on_wall).sum() > 5 * on_wall.sum()  # only the nearest drops cover the wall
    assert dd[~on_wall].max() > 0.5 * RAIN_FAR_M
