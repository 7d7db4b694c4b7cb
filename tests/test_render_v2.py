"""Renderer v2 (issue 14): render processes, sun shadows, smooth night light, the camera model."""

from __future__ import annotations

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world

from cosim.scenario.model import (
    CameraSpec,
    LidarSpec,
    RigSpec,
    Scenario,
    SensorsSpec,
    default_rsu_rig,
    default_vehicle_rig,
)


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


# ------------------------------------------------------------------------------------- shadows

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


# -------------------------------------------------------------------------------- camera model

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


def test_distorted_calibration_projects_a_point_where_the_renderer_put_it():
    """A small block seen near the corner of a barrel-distorted camera: the centroid of its instance
    pixels is where the calibration (K, D) projects its centre, within 0.5 px; D is in the calibration."""
    from cosim.io.sensor_messages import calibration_message
    from cosim.scenario.model import Mount
    from cosim.snapshot import AgentState, WorldSnapshot
    from cosim.world.types import Prism, StaticLayout, World

    centre = np.array([12.0, 6.5, 4.5])
    half = 0.25
    foot = tuple((float(centre[0] + dx), float(centre[1] + dy)) for dx, dy in
                 ((-half, -half), (half, -half), (half, half), (-half, half)))
    prisms = (Prism("terrain", ((-300, -300), (300, -300), (300, 300), (-300, 300)), -1.0, 0.0),
              Prism("pole", foot, centre[2] - half, centre[2] + half, 1_000_005))
    world = World("synthetic", b"", b"", (-300, -300, 300, 300), (), (), StaticLayout(prisms), (37.0, -122.0, 10.0))
    D = (-0.25, 0.06, 0.001, -0.002, 0.0)
    frames = {}
    for name, dist in (("pinhole", None), ("lens", D)):
        cam = CameraSpec(name="front", width=480, height=360, fov_deg=90.0, distortion=dist,
                         mount=Mount(xyz_m=(0.0, 0.0, 1.6)))
        sc = synthetic_scenario(sensors=SensorsSpec(vehicle=RigSpec(lidar=None, cameras=[cam], gnss=None, imu=None)))
        ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
        with SensorSuite(sc, world, noise=False, encode_images=False) as suite:
            frames[name] = suite.render(WorldSnapshot(0, 0, (), (ego,)), np.random.default_rng(0)).agents[
                "vehicle_0"].cameras["front"]
    from cosim.sensors.camera import project_points

    f = frames["lens"]
    calib = calibration_message("vehicle_0/front/optical", f, 0)
    assert calib.distortion_model == "plumb_bob" and tuple(calib.D) == D
    K = np.array(calib.K).reshape(3, 3)
    got = {}
    for name, fr in frames.items():
        v, u = np.nonzero(fr.instance == 1_000_005)
        assert len(u) > 50
        got[name] = np.array([u.mean() + 0.5, v.mean() + 0.5])
    uv, front = project_points(centre[None], f.pose, K, tuple(calib.D))
    assert front[0]
    assert np.linalg.norm(got["lens"] - uv[0]) <= 0.5, (got, uv)
    assert np.linalg.norm(got["lens"] - got["pinhole"]) > 10  # the lens did move it


def test_rain_streaks_never_appear_in_front_of_nearer_geometry():
    from cosim.sensors.camera import RAIN_FAR_M, rain_streaks

    depth = np.full((360, 480), np.inf, np.float32)
    depth[:, :240] = 8.0  # a wall 8 m away on the left half
    vv, uu, dd = rain_streaks(depth, 100.0, 240.0, np.random.default_rng(0))
    assert np.all(dd < depth[vv, uu])
    on_wall = uu < 240
    assert on_wall.sum() > 20 and (~on_wall).sum() > 5 * on_wall.sum()  # only the nearest drops cover the wall
    assert dd[~on_wall].max() > 0.5 * RAIN_FAR_M
