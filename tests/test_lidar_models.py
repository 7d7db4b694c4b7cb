"""Datasheet LiDAR presets (``sensors.<kind>.lidar.model``) and intensity transfers, against the sheets."""

from __future__ import annotations

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.lidar import beam_pattern, intensity_model, rosette_pattern
from cosim.sensors.lidar_models import KITTI_EXPONENT, KITTI_GAIN, KITTI_REF_RANGE_M, report_intensity
from cosim.sensors.synthetic import actor, synthetic_scenario

from cosim.errors import ScenarioError
from cosim.scenario.lidar_presets import LIDAR_PRESETS
from cosim.scenario.loader import load_scenario, load_scenario_data
from cosim.scenario.model import LidarSpec, Mount, RigSpec, Scenario, SensorsSpec
from cosim.snapshot import AgentState, WorldSnapshot
from tests.helpers import SCENARIOS, WALL_ID, run_cli
from tests.helpers import wall_world as _wall_world

#: name -> (rings, lowest and highest elevation [deg], points per sweep or frame), as each sheet states them
SHEETS = {
    "hdl64e": (64, -24.33, 2.0, 1_333_000 / 10),  # 1.333 M points/s at 10 Hz (KITTI)
    "vlp32c": (32, -25.0, 15.0, 578_704 / 10),  # 32 lasers every 55.296 us
    "vlp16": (16, -15.0, 15.0, 289_352 / 10),  # 16 lasers every 55.296 us
    "os1_64": (64, -16.6, 16.6, 1_310_720 / 10),
    "os1_128": (128, -22.5, 22.5, 2_621_440 / 10),
    "pandar64": (64, -25.0, 15.0, 1_152_000 / 10),
    "avia": (1, None, None, 240_000 / 10),
}


def _lidar(model: str, kind: str = "vehicle", **beside) -> LidarSpec:
    sc = Scenario.model_validate({"name": "t", "sensors": {kind: {"lidar": {"model": model, **beside}}}})
    return getattr(sc.sensors, kind).lidar


def test_every_preset_has_a_sheet_here():
    assert set(SHEETS) == set(LIDAR_PRESETS) - {"generic"}


@pytest.mark.parametrize("model", sorted(SHEETS))
def test_preset_rings_span_and_points_per_sweep_match_the_sheet(model):
    rings, lo, hi, per_sweep = SHEETS[model]
    spec = _lidar(model)
    assert spec.model == model
    if spec.pattern == "spinning":
        d, ring = beam_pattern(spec)
        assert spec.channels == rings == len(np.unique(ring))
        elev = np.degrees(np.arcsin(d[:, 2]))
        assert abs(elev.min() - lo) < 0.2 and abs(elev.max() - hi) < 0.2
        n = len(d)
    else:
        n = len(rosette_pattern(spec, 1_000_000_000).directions)
    assert abs(n - per_sweep) / per_sweep < 0.005


def test_hdl64e_has_the_two_blocks_of_its_sheet():
    gaps = np.diff(_lidar("hdl64e").elevations_deg)
    upper, lower = gaps[32:], gaps[:31]
    assert np.allclose(upper, 1 / 3, atol=0.002) and np.allclose(lower, 0.5, atol=0.002)
    assert abs(gaps[31] - 0.5) < 0.002  # -8.83 to -8.33 between the blocks


@pytest.mark.parametrize("model", ["vlp32c", "pandar64"])
def test_non_uniform_tables_are_densest_near_the_horizon(model):
    e = np.asarray(_lidar(model).elevations_deg)
    gaps = np.diff(e)
    near = gaps[(e[:-1] > -3) & (e[:-1] < 1)]
    assert near.max() < 0.34 and gaps.max() > 4.0


@pytest.mark.parametrize("model", sorted(SHEETS))
def test_presets_drop_returns_by_physics_only(model):
    spec = _lidar(model)
    assert spec.dropoff_intensity_limit == 0.0  # CARLA's intensity rule off: real scans keep their dark near road
    assert spec.detection_range_10pct_m == LIDAR_PRESETS[model].detection_range_10pct_m


def test_vehicle_takes_the_dataset_mount_other_kinds_keep_theirs():
    assert _lidar("hdl64e").mount.xyz_m == (0.0, 0.0, 1.73)  # KITTI
    assert _lidar("vlp32c").mount.xyz_m == (0.0, 0.0, 1.84)  # nuScenes' 32-channel roof LiDAR
    assert _lidar("vlp16").mount.xyz_m == (0.0, 0.0, 1.9)  # no dataset: the rig's default
    assert _lidar("hdl64e", kind="rsu").mount.xyz_m == (0.0, 0.0, 0.3)
    assert _lidar("hdl64e", kind="drone").mount.xyz_m == (0.0, 0.0, -0.2)


def test_fields_beside_model_override_it():
    spec = _lidar("hdl64e", range_m=80.0, rotation_hz=20.0, mount={"xyz_m": [0.5, 0.0, 2.1]})
    assert (spec.range_m, spec.rotation_hz, spec.mount.xyz_m) == (80.0, 20.0, (0.5, 0.0, 2.1))
    assert spec.elevations_deg == LIDAR_PRESETS["hdl64e"].elevations_deg and spec.intensity_transfer == "kitti"
    # a ring count or span beside the model: evenly spaced rings over what was given
    spec = _lidar("hdl64e", channels=32)
    assert spec.elevations_deg is None and (spec.channels, spec.lower_fov_deg, spec.upper_fov_deg) == (32, -24.333, 2.0)
    spec = _lidar("vlp16", intensity_transfer="linear")
    assert spec.intensity_transfer == "linear"


def test_set_on_the_command_line_reaches_the_preset():
    loaded = load_scenario(SCENARIOS / "default.yaml",
                           ["sensors.vehicle.lidar.model=hdl64e", "sensors.vehicle.lidar.range_m=90"])
    spec = loaded.scenario.sensors.vehicle.lidar
    assert (spec.model, spec.channels, spec.range_m, spec.mount.xyz_m[2]) == ("hdl64e", 64, 90.0, 1.73)
    # the resolved scenario reloads to the same LiDAR (replay, export)
    again = load_scenario_data(loaded.resolved).scenario.sensors.vehicle.lidar
    assert again == spec


def test_generic_rig_resolves_as_before_the_presets():
    lidar = load_scenario(SCENARIOS / "default.yaml").resolved["sensors"]["vehicle"]["lidar"]
    assert not {"model", "elevations_deg", "intensity_transfer"} & set(lidar)
    assert _lidar("generic") == LidarSpec()


def test_unknown_model_names_the_key_and_the_known_ones():
    with pytest.raises(ScenarioError) as e:
        load_scenario(SCENARIOS / "default.yaml", ["sensors.vehicle.lidar.model=hdl65e"])
    text = str(e.value)
    assert "sensors.vehicle.lidar.model" in text and "'hdl64e'" in text and "'avia'" in text


@pytest.mark.integration  # a `cosim run` process, refused at the scenario
def test_bad_model_in_a_file_exits_2_with_its_line(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("name: t\nsensors:\n  vehicle:\n    lidar:\n      model: hdl65e\n")
    r = run_cli("run", str(f), "--out", str(tmp_path / "out"), timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert "bad.yaml:5: sensors.vehicle.lidar.model" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


# ---------------------------------------------------------------------------------------- transfers


def _reported(transfer: str, rho: float, cos: float, range_m: float = 20.0, retro: float = 0.0) -> float:
    spec = LidarSpec(intensity_transfer=transfer)
    i = intensity_model(np.array([rho]), np.array([retro]), np.array([cos]), np.array([range_m]), 0.0)
    return float(report_intensity(spec, i, np.array([retro > 0]), np.array([range_m]))[0])


def test_calibrated_reflectivity_is_the_sheets_byte():
    # Velodyne / Ouster / Hesai calibrated reflectivity: a 10 % Lambertian target reads 10, 80 % reads 80
    assert round(_reported("calibrated_100", 0.10, 1.0) * 255) == 10
    assert round(_reported("calibrated_100", 0.80, 1.0) * 255) == 80
    assert round(_reported("calibrated_100", 0.10, 0.5, range_m=60.0) * 255) == 5  # 60 deg incidence
    assert round(_reported("calibrated_100", 0.5, 1.0, retro=0.9) * 255) > 100  # retro-reflectors above 100
    # Livox: 0..150 for 0..100 % diffuse reflectance
    assert round(_reported("livox_150", 0.10, 1.0) * 255) == 15
    assert round(_reported("livox_150", 0.5, 1.0, retro=0.9) * 255) > 150


def test_kitti_transfer_and_linear():
    asphalt = _reported("kitti", 0.12, 0.26, range_m=7.0)  # road 7 m ahead of a 1.73 m sensor: 15 deg grazing
    assert asphalt == pytest.approx(KITTI_GAIN * (0.12 * 0.26 * (KITTI_REF_RANGE_M / 7.0) ** 2) ** KITTI_EXPONENT)
    assert 0.2 < asphalt < 0.5  # where KITTI's road points are
    assert _reported("kitti", 0.12, 0.26, range_m=30.0) < asphalt  # raw return strength: falls with range
    assert _reported("kitti", 0.5, 1.0, retro=0.9) > 0.9
    assert _reported("linear", 0.12, 0.26) == pytest.approx(0.12 * 0.26)


def test_rendered_wall_reads_its_reflectivity_in_calibrated_bytes():
    lidar = _lidar("vlp16", dropoff_general_rate=0.0, dropoff_intensity_limit=0.0, motion_distortion=False,
                   mount=Mount(xyz_m=(0.0, 0.0, 1.0)))
    sc = synthetic_scenario(vehicles=1, sensors=SensorsSpec(vehicle=RigSpec(lidar=lidar, cameras=[], gnss=None,
                                                                            imu=None)))
    suite = SensorSuite(sc, _wall_world(30.0), noise=False)
    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    lf = suite.render(WorldSnapshot(0, 0, (), (ego,)), np.random.default_rng(0)).agents["vehicle_0"].lidar
    ahead = (lf.instance_id == WALL_ID) & (np.abs(lf.points[:, 1]) < 0.5) & (lf.ring == 8)  # ring 8: +1 deg
    assert ahead.sum() >= 1
    # the building's reflectivity 0.35 at (nearly) normal incidence, 30 m of clear air: byte 35
    assert np.all(np.rint(lf.intensity[ahead] * 255) == 35)
    assert len(np.unique(lf.ring)) == 16


@pytest.mark.parametrize(("model", "diffuse_max"), [("vlp32c", 100), ("avia", 150)])
def test_rendered_car_reflectors_read_above_the_diffuse_scale(model, diffuse_max):
    """A car's licence plate and lamp reflectors are retro-reflective: above the sheet's diffuse range."""
    lidar = _lidar(model, motion_distortion=False, mount=Mount(xyz_m=(0.0, 0.0, 1.0)))
    sc = synthetic_scenario(vehicles=1, sensors=SensorsSpec(vehicle=RigSpec(lidar=lidar, cameras=[], gnss=None,
                                                                            imu=None)))
    suite = SensorSuite(sc, _wall_world(60.0), noise=False)
    car = actor(7, "car", 12.0, 0.0, 0.0, z_ground=0.0)  # its back to the sensor: plate and rear lamps
    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    lf = suite.render(WorldSnapshot(0, 0, (car,), (ego,)), np.random.default_rng(0)).agents["vehicle_0"].lidar
    byte = np.rint(lf.intensity[lf.instance_id == 7] * 255)
    assert (byte > diffuse_max).any() and (byte <= diffuse_max).any()

