"""Procedural surface detail and wet roads (issue 14): each effect measured on a scene of known geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
from cosim.sensors import SensorSuite
from cosim.sensors.environment import WET_ROAD_ALBEDO
from cosim.sensors.surface import ASPHALT_PATCH_MEAN, FLOOR_M, WINDOW_SPACING_M, WINDOW_Z0_M
from cosim.sensors.synthetic import synthetic_scenario

from cosim.scenario.model import CameraSpec, Mount, RigSpec, Scenario, SensorsSpec
from cosim.snapshot import AgentState, WorldSnapshot
from cosim.world.types import Prism, StaticLayout, World

TERRAIN = Prism("terrain", ((-300, -300), (300, -300), (300, 300), (-300, 300)), -1.0, 0.0)
ROAD = Prism("road", ((-200, -10), (200, -10), (200, 10), (-200, 10)), 0.0, 0.02)


def _world(*prisms) -> World:
    return World("synthetic", b"", b"", (-300, -300, 300, 300), (), (), StaticLayout((TERRAIN, *prisms)),
                 (37.0, -122.0, 10.0))


def _scenario(env: dict, detail: bool = True, z_m: float = 1.6, pitch_deg: float = 0.0, size=(320, 240)) -> Scenario:
    cam = CameraSpec(name="front", width=size[0], height=size[1], fov_deg=90.0, vignetting=0.0,
                     mount=Mount(xyz_m=(0.0, 0.0, z_m), rpy_deg=(0.0, pitch_deg, 0.0)))
    return synthetic_scenario(seed=1, environment=env,
                              sensors=SensorsSpec(vehicle=RigSpec(lidar=None, cameras=[cam], gnss=None, imu=None),
                                                  sun_shadows=False, surface_detail=detail))


def _render(sc: Scenario, world: World, **atm_changes):
    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    with SensorSuite(sc, world, noise=False, encode_images=False) as suite:
        if atm_changes:
            suite.atm = dataclasses.replace(suite.atm, **atm_changes)
        return suite.render(WorldSnapshot(0, 0, (), (ego,)), np.random.default_rng(0)).agents["vehicle_0"].cameras[
            "front"]


def _linear(rgb: np.ndarray) -> np.ndarray:
    return (rgb.astype(np.float64) / 255.0) ** 2.2


def test_asphalt_grain_near_the_camera_fades_to_its_mean_far_away_without_aliasing():
    world = _world(ROAD)
    on = _render(_scenario({"lighting": "day"}, pitch_deg=4.0), world)
    off = _render(_scenario({"lighting": "day"}, detail=False, pitch_deg=4.0), world)
    road = (on.semantic == on.semantic[-1, 160]) & np.isfinite(on.depth)
    lum = on.rgb.astype(float).mean(axis=2)
    near = road & (on.depth < 4.0)
    far = road & (on.depth > 40.0)
    assert near.sum() > 2000 and far.sum() > 150

    def neighbour_diff(mask):
        both = mask[:, 1:] & mask[:, :-1]
        return np.abs(np.diff(lum, axis=1))[both]

    assert neighbour_diff(near).std() > 0.8  # grain: neighbouring pixels differ near the camera
    assert np.abs(lum[near] - lum[near].mean()).mean() > 2.0
    assert neighbour_diff(far).mean() < 0.6  # filtered by the footprint: no pixel-to-pixel noise far away
    flat = off.rgb.astype(float).mean(axis=2)
    assert neighbour_diff(near).std() > 5 * np.abs(np.diff(flat, axis=1))[near[:, 1:] & near[:, :-1]].std()
    # far away the filtered detail tends to the asphalt's mean albedo factor (no drift with distance)
    ratio_far = _linear(on.rgb)[far].mean() / _linear(off.rgb)[far].mean()
    assert abs(ratio_far - (1 - ASPHALT_PATCH_MEAN)) < 0.02, ratio_far


_WALL = Prism("building", ((20.0, -60.0), (30.0, -60.0), (30.0, 60.0), (20.0, 60.0)), 0.0, 30.0, 1_000_010)


def _window_row(frame) -> int:
    """Image row through the middle of the first-floor windows on the wall 20 m ahead."""
    z = FLOOR_M + WINDOW_Z0_M + 0.8
    fy, cy = frame.K[1, 1], frame.K[1, 2]
    return int(cy - fy * (z - frame.pose.position_m[2]) / 20.0)


def test_facade_shows_a_window_grid_at_the_configured_spacing():
    f = _render(_scenario({"lighting": "day"}, z_m=5.0), _world(_WALL))
    row = f.rgb[_window_row(f)].astype(float).mean(axis=1)
    assert np.all(f.semantic[_window_row(f)] == f.semantic[120, 160])  # the wall fills the row
    x = row - row.mean()
    ac = np.array([np.dot(x[:-lag], x[lag:]) for lag in range(1, 80)])
    lag = 1 + int(np.argmax(ac[5:])) + 5
    expect = WINDOW_SPACING_M * f.K[0, 0] / 20.0
    assert abs(lag - expect) <= 1.0, (lag, expect)
    assert x.std() > 10  # glass is clearly darker than the wall


def test_lit_windows_only_at_night_and_the_same_every_render():
    world = _world(_WALL)
    wall_mask = None
    out = {}
    for lighting in ("day", "night"):
        f = _render(_scenario({"lighting": lighting}, z_m=5.0), world)
        wall_mask = f.instance == 1_000_010
        lum = f.rgb.astype(float).mean(axis=2)[wall_mask]
        out[lighting] = (lum, f.rgb)
    day, night = out["day"][0], out["night"][0]
    wall_day = np.median(day)
    assert day.max() <= wall_day + 12  # by day windows only darken the wall
    bright = night > 4 * np.median(night) + 30
    assert 0.04 < bright.mean() < 0.4, bright.mean()  # a share of the windows glows
    again = _render(_scenario({"lighting": "night"}, z_m=5.0), world)
    assert np.array_equal(again.rgb, out["night"][1])  # deterministic per building and window
    flat = _render(_scenario({"lighting": "night"}, z_m=5.0, detail=False), world)
    assert flat.rgb.astype(float).mean(axis=2)[wall_mask].max() < 60  # no detail: no lit windows


def test_wet_road_is_darker_by_the_configured_factor():
    world = _world(ROAD)
    sc = _scenario({"weather": "rainy", "lighting": "day", "rain_rate_mm_h": 0.01}, detail=False, z_m=20.0,
                   pitch_deg=90.0)
    no_specular = {"sun_rgb": np.zeros(3), "sky_zenith": np.zeros(3), "sky_horizon": np.zeros(3)}
    wet = _render(sc, world, **no_specular)
    dry = _render(sc, world, wet_roads=False, **no_specular)
    road = wet.semantic == wet.semantic[120, 160]
    assert road.mean() > 0.3
    ratio = _linear(wet.rgb)[road].mean() / _linear(dry.rgb)[road].mean()
    assert abs(ratio - WET_ROAD_ALBEDO) < 0.02, ratio
    # with the sky: the water film reflects it, most at grazing angles
    grazing = _scenario({"weather": "rainy", "lighting": "day", "rain_rate_mm_h": 0.01}, detail=False, pitch_deg=5.0)
    w2, d2 = _render(grazing, world), _render(grazing, world, wet_roads=False)
    far = (w2.semantic == w2.semantic[-1, 160]) & (w2.depth > 40)
    assert _linear(w2.rgb)[far].mean() > _linear(d2.rgb)[far].mean()


def test_wet_road_at_night_reflects_a_street_lamp_at_its_mirror_point():
    from cosim.sensors.camera import project_points
    from cosim.sensors.meshes import LAMP_ARM_MIN_Z_M

    top = LAMP_ARM_MIN_Z_M + 7.0
    world = _world(ROAD, Prism("street_light", ((21.9, -0.1), (22.1, -0.1), (22.1, 0.1), (21.9, 0.1)), 0.02, top,
                               1_000_002),
                   Prism("street_light", ((20.0, -0.2), (22.0, -0.2), (22.0, 0.2), (20.0, 0.2)), top - 0.3, top,
                         1_000_003))
    sc = _scenario({"weather": "rainy", "lighting": "night", "rain_rate_mm_h": 0.01}, detail=False)
    wet = _render(sc, world)
    dry = _render(sc, world, wet_roads=False)
    spec = _linear(wet.rgb) - WET_ROAD_ALBEDO * _linear(dry.rgb)
    road = wet.semantic == wet.semantic[-1, 160]
    s = np.where(road, spec.mean(axis=2), 0.0)
    # the lamp head's underside (the emitter) mirrored in the road plane, seen from the camera
    lamp = np.array([21.0, 0.0, top - 0.3])
    c = wet.pose.position_m
    mirror = np.array([lamp[0], lamp[1], 2 * 0.02 - lamp[2]])
    t = (0.02 - c[2]) / (mirror[2] - c[2])
    point = c + t * (mirror - c)
    uv, front = project_points(point[None], wet.pose, wet.K)
    assert front[0]
    v, u = np.unravel_index(np.argmax(s), s.shape)
    # the highlight is centred on the mirror point's column and stretched along it (a Blinn-Phong lobe
    # weighted by the lamp's irradiance peaks a little towards the lamp): the mirror point is on it
    assert abs(u + 0.5 - uv[0, 0]) <= 2, ((u, v), uv)
    mv, mu = int(uv[0, 1]), int(uv[0, 0])
    assert s[mv, mu] > 0.5 * s.max(), (s[mv, mu], s.max(), (u, v), uv)
    assert s.max() > 0.02 and s.max() > 10 * np.median(s[road])
    assert np.abs(_linear(wet.rgb) - _linear(dry.rgb))[~road].max() < 0.01  # only the road is wet
