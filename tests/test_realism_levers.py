"""The scene and sensor realism levers of issue 48: the ego's own body blocking its LiDAR (``self_occlusion``),
the energy ray drop of dark surfaces at range, and roadside clutter (``map.clutter``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.lidar import (
    BODY_DEPTH_M,
    BODY_LENGTH_SHARE,
    DETECTION_EXPONENT,
    drop_probability,
    own_body_range,
)
from cosim.sensors.meshes import empty_mesh
from cosim.sensors.rig import sensor_pose
from cosim.sensors.scene import StaticScene, TickScene
from cosim.sensors.synthetic import synthetic_scenario
from matplotlib.path import Path as MplPath

from cosim.geometry import quat_from_rpy
from cosim.scenario.loader import load_scenario, load_scenario_data
from cosim.scenario.model import LidarSpec, RigSpec, Scenario, SensorsSpec
from cosim.snapshot import Actor, AgentState, WorldSnapshot
from tests.helpers import SCENARIOS, run_cli, wall_world

ESTATE = (4.74, 1.99, 1.51)  # the catalogue's estate_1 (KITTI's car is a Passat estate, 4.77 x 1.82 x 1.52 m)


def _ego_actor() -> Actor:
    return Actor(1, "car", (0.0, 0.0, ESTATE[2] / 2), ESTATE, quat_from_rpy(0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                 "vehicle_0")


def _ego() -> AgentState:
    return AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), track_id=1)


def _spec(**fields) -> LidarSpec:
    return Scenario.model_validate({"name": "t", "sensors": {"vehicle": {"lidar": fields}}}).sensors.vehicle.lidar


def _sweep(spec: LidarSpec, seed: int = 0, noise: bool = False):
    sc = synthetic_scenario(vehicles=1, sensors=SensorsSpec(vehicle=RigSpec(lidar=spec, cameras=[], gnss=None,
                                                                            imu=None)))
    suite = SensorSuite(sc, wall_world(60.0), noise=noise)
    snap = WorldSnapshot(0, 0, (_ego_actor(),), (_ego(),))
    return suite.render(snap, np.random.default_rng(seed)).agents["vehicle_0"].lidar


# ------------------------------------------------------------------------------------------ self-occlusion

#: two rings: straight down onto the roof, and 5 deg down (clears the roof, meets the ground 20 m out)
_TWO_RINGS = {"channels": 2, "elevations_deg": [-89.0, -5.0], "lower_fov_deg": -89.0, "upper_fov_deg": -5.0,
              "horizontal_resolution_deg": 2.0, "motion_distortion": False, "dropoff_general_rate": 0.0,
              "mount": {"xyz_m": [0.0, 0.0, 1.73]}}


def test_a_ray_down_onto_the_own_roof_returns_nothing_one_over_it_does():
    off = _sweep(_spec(**_TWO_RINGS))
    on = _sweep(_spec(**_TWO_RINGS, self_occlusion=True))
    n_az = 180
    assert (off.ring == 0).sum() == n_az and (off.ring == 1).sum() == n_az  # without it: the ground under the car
    assert (on.ring == 0).sum() == 0  # with it: the roof blocks every beam straight down
    np.testing.assert_array_equal(on.points[on.ring == 1], off.points[off.ring == 1])  # over the roof: unchanged


def test_self_occlusion_drops_exactly_the_beams_whose_first_hit_is_the_own_body():
    from cosim.sensors.lidar import beam_pattern

    base = {"model": "hdl64e", "motion_distortion": False, "dropoff_general_rate": 0.0,
            "horizontal_resolution_deg": 1.0}
    off, on = _sweep(_spec(**base, self_occlusion=False)), _sweep(_spec(**base))  # on in the preset
    spec = _spec(**base)
    d, ring = beam_pattern(spec)
    scene = TickScene.build(StaticScene(empty_mesh()), (_ego_actor(),))
    own_t = own_body_range(scene, 1, sensor_pose(_ego(), spec.mount), d)
    blocked = np.isfinite(own_t)

    def beams(r: np.ndarray, xy: np.ndarray) -> set[tuple[int, int]]:
        """(ring, azimuth step) of returns or beams: a return's point lies along its beam"""
        step = np.rint((np.arctan2(xy[:, 1], xy[:, 0]) % (2 * math.pi)) / math.radians(1.0)).astype(int) % 360
        return set(zip(r.tolist(), step.tolist(), strict=True))

    k_off, k_on = beams(off.ring, off.points), beams(on.ring, on.points)
    k_blocked = beams(ring[blocked], d[blocked])
    assert k_on == k_off - k_blocked
    assert len(k_off & k_blocked) > 0  # the sweep without it had returns there (the ground by the car)
    assert blocked[ring == 0].any() and not blocked[ring == 63].any()  # the lowest ring loses some, the top none
    # the gap behind the car: more of the lowest ring than of ring 11, and the sides of the lowest ring clear
    assert blocked[ring == 0].sum() > blocked[ring == 11].sum()
    side = (ring == 0) & (np.abs(np.abs(np.degrees(np.arctan2(d[:, 1], d[:, 0]))) - 90.0) < 10.0)
    assert not blocked[side].any()


def test_own_body_is_a_slab_of_the_own_box_under_the_sensor():
    """The body's top lies BODY_DEPTH_M under the sensor over the own box's width and BODY_LENGTH_SHARE of its
    length: straight down that is the range; 30 deg down, the beam meets it behind the sensor, not beside."""
    scene = TickScene.build(StaticScene(empty_mesh()), (_ego_actor(),))
    pose = sensor_pose(_ego(), _spec(model="hdl64e").mount)
    c, s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    beams = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [-c, 0.0, -s], [0.0, c, -s], [0.0, 0.0, 1.0]])
    t = own_body_range(scene, 1, pose, beams)
    assert t[0] == pytest.approx(BODY_DEPTH_M)
    reach = BODY_DEPTH_M / math.tan(math.radians(30.0))  # where the 30 deg beams reach the body's top
    assert reach < BODY_LENGTH_SHARE * ESTATE[0] / 2 and reach > ESTATE[1] / 2  # so: behind yes, beside no
    assert t[2] == pytest.approx(BODY_DEPTH_M / s)
    assert not np.isfinite(t[[1, 3, 4]]).any()
    assert own_body_range(scene, 99, pose, beams) is None  # no such actor


def test_presets_and_defaults_of_self_occlusion():
    assert _spec(model="hdl64e").self_occlusion and not _spec(model="vlp32c").self_occlusion
    assert not LidarSpec().self_occlusion
    lidar = load_scenario(SCENARIOS / "default.yaml").resolved["sensors"]["vehicle"]["lidar"]
    assert "self_occlusion" not in lidar  # the generic rig's resolved scenario keeps its bytes
    assert _spec(model="generic") == _spec(model="generic", self_occlusion=False) == LidarSpec()


def test_generic_sweep_unchanged_when_the_lever_is_absent():
    """The generic rig (noise on, seeded) gives the same sweep with the lever absent and set false."""
    coarse = {"horizontal_resolution_deg": 1.0}
    a = _sweep(_spec(**coarse), seed=3, noise=True)
    b = _sweep(_spec(**coarse, self_occlusion=False), seed=3, noise=True)
    for name in ("points", "intensity", "ring", "class_id", "instance_id", "t_offset_ns"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


# ------------------------------------------------------------------------------------- energy ray drop


def test_drop_probability_falls_with_reflectivity_and_range_as_the_formula_says():
    spec = _spec(model="hdl64e")
    # black, dark, grey and white paint at 40 m; dark at 20, 60 and 80 m
    rho = np.array([0.05, 0.09, 0.3, 0.64, 0.09, 0.09, 0.09])
    rng_m = np.array([40.0, 40.0, 40.0, 40.0, 20.0, 60.0, 80.0])
    zeros = np.zeros(len(rho))
    p = drop_probability(spec, zeros + 0.5, rng_m, rho, zeros, np.zeros(len(rho), bool), zeros)
    p90 = 0.1 / spec.detection_range_10pct_m ** 2
    want = 1.0 - (1.0 - spec.dropoff_general_rate) / (1.0 + (p90 * rng_m ** 2 / rho) ** DETECTION_EXPONENT / 9.0)
    np.testing.assert_allclose(p, want, rtol=1e-12)
    assert p[0] > p[1] > p[2] > p[3]  # darker paint drops more
    assert p[4] < p[1] < p[5] < p[6]  # farther drops more
    glass = drop_probability(spec, zeros[:1] + 0.5, rng_m[:1], rho[3:4], zeros[:1], np.ones(1, bool), zeros[:1])
    assert glass[0] > p[3]  # glass passes or glances off most beams


def test_ray_drop_is_seeded():
    spec = _spec(model="hdl64e", motion_distortion=False, horizontal_resolution_deg=1.0)
    a, b, c = _sweep(spec, 5, True), _sweep(spec, 5, True), _sweep(spec, 6, True)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.n_points != c.n_points or not np.array_equal(a.points, c.points)


# ---------------------------------------------------------------------------------------- clutter


@pytest.fixture(scope="module")
def worlds(tmp_path_factory):
    from cosim.world import build_world

    data = {"name": "c", "seed": 4, "map": {"kind": "urban", "size_m": 200}, "parked": {"density_veh_per_km": 60}}
    off = build_world(load_scenario_data(data), tmp_path_factory.mktemp("off"))
    on = build_world(load_scenario_data({**data, "map": {**data["map"], "clutter": "kitti"}}),
                     tmp_path_factory.mktemp("on"))
    return data, off, on


def _samples(poly: np.ndarray, step_m: float = 0.1) -> np.ndarray:
    """Points covering a convex-or-not polygon (its vertices, edges and a grid over its box kept inside)."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + step_m, step_m), np.arange(lo[1], hi[1] + step_m, step_m))
    grid = np.stack([gx.ravel(), gy.ravel()], 1)
    edges = np.concatenate([np.linspace(a, b, 20) for a, b in zip(poly, np.roll(poly, -1, 0), strict=True)])
    inner = grid[MplPath(poly).contains_points(grid)]
    return np.concatenate([inner, 0.999 * edges + 0.001 * poly.mean(axis=0)])


@pytest.mark.integration
def test_clutter_is_off_the_road_and_out_of_every_label_box(worlds):
    from cosim.world.geom import rect
    from cosim.world.layout import road_polygons
    from cosim.world.network import read_network

    data, off, on = worlds
    none = load_scenario_data({**data, "map": {**data["map"], "clutter": "none"}})
    assert none.scenario == load_scenario_data(data).scenario  # absent and none: the same scenario
    assert "clutter" not in none.resolved["map"]  # and the same resolved scenario (the world's input)
    n = len(off.layout.prisms)
    assert on.layout.prisms[:n] == off.layout.prisms  # clutter only adds, after everything the layout placed
    clutter = on.layout.prisms[n:]
    kinds = {p.cls for p in clutter}
    assert {"building", "vegetation", "pole", "traffic_sign", "terrain"} <= kinds, kinds
    assert len(clutter) >= 100  # not vacuous
    keep_out = road_polygons(read_network(on.net_xml))
    keep_out += [np.array(p.footprint) for p in on.layout.prisms if p.cls == "sidewalk"]
    keep_out += [rect(v.center_m[0], v.center_m[1], v.size_m[0], v.size_m[1], v.yaw_rad) for v in on.parked]
    paths = [(MplPath(k), k.min(axis=0), k.max(axis=0)) for k in keep_out]
    for p in clutter:
        pts = _samples(np.array(p.footprint))
        for path, lo, hi in paths:
            if (pts.max(axis=0) < lo).any() or (pts.min(axis=0) > hi).any():
                continue
            assert not path.contains_points(pts).any(), (p.cls, p.footprint[0])
    assert len(on.parked) >= 5 and len(on.parked) == len(off.parked)  # the parking strip stays free


@pytest.mark.integration
def test_clutter_classes_and_heights(worlds):
    _, off, on = worlds
    n = len(off.layout.prisms)
    clutter = on.layout.prisms[n:]
    veg = [p.z1_m for p in clutter if p.cls == "vegetation"]
    assert min(veg) < 1.5 and max(veg) > 3.0  # vegetation of several heights
    assert all(p.instance_id == 0 for p in clutter if p.cls in ("vegetation", "terrain"))  # stuff
    things = [p.instance_id for p in clutter if p.cls not in ("vegetation", "terrain")]
    assert len(set(things)) == len(things) and min(things) > max(p.instance_id for p in on.layout.prisms[:n])
    banks = [p for p in clutter if p.cls == "terrain"]
    assert all(0.2 <= p.z1_m <= 1.2 + 1e-9 for p in banks)  # the ground rises beyond the kerb


# ----------------------------------------------------------------------------------------- bad values


@pytest.mark.integration  # `cosim run` processes, refused at the scenario
@pytest.mark.parametrize(("text", "where"), [
    ("name: t\nmap:\n  kind: urban\n  clutter: lots\n", "bad.yaml:4: map.clutter"),
    ("name: t\nsensors:\n  vehicle:\n    lidar:\n      self_occlusion: maybe\n",
     "bad.yaml:5: sensors.vehicle.lidar.self_occlusion"),
])
def test_bad_lever_values_exit_2_with_key_and_line(tmp_path, text, where):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    r = run_cli("run", str(f), "--out", str(tmp_path / "out"), timeout=60)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert where in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_clutter_kind_is_checked_on_load():
    with pytest.raises(Exception) as e:
        load_scenario_data({"name": "t", "map": {"clutter": "dense"}})
    assert "map.clutter" in str(e.value)


# ------------------------------------------------------------------------------- the gap measurement


def test_the_gap_measurement_finds_a_blind_sector_in_a_kitti_layout_scan(tmp_path):
    """benchmarks/realism_levers.py reads a KITTI scan laser by laser (each one's azimuth wraps once, behind):
    a synthetic scan, its lowest ring blind 60 deg behind and the next 20 deg ahead, gives those sectors."""
    from benchmarks.realism_levers import RINGS, kitti_gaps

    rows = []
    for k in range(64):  # file order: the top laser first
        elev = math.radians(2.0 - 0.4 * k)
        az = np.radians(np.concatenate([np.arange(0.1, 180.0, 0.2), np.arange(-179.9, 0.0, 0.2)]))
        if k == 63:
            az = az[np.abs(np.degrees(az)) < 150.0]  # 60 deg blind behind
        if k == 62:
            az = az[np.abs(np.degrees(az)) > 10.0]  # 20 deg blind ahead
        r = 10.0
        rows.append(np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az), r * np.sin(elev) + 0 * az,
                              np.zeros_like(az)], 1))
    scan = np.concatenate(rows).astype(np.float32)
    scan.tofile(tmp_path / "000000.bin")
    gaps = kitti_gaps([tmp_path / "000000.bin"])
    assert len(gaps) == RINGS
    assert gaps[0][0] == pytest.approx(2.0 - 0.4 * 63, abs=0.01) and gaps[0][2:] == (0, 60)
    assert gaps[1][2:] == (20, 0) and gaps[2][2:] == (0, 0)
