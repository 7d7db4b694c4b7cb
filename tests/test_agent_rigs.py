"""Per-agent rigs (``agents.vehicles.rigs``, ``agents.rsus.rigs``, a drone's ``rig``): merged field by field over
the kind's rig, refused with one located message, and one real episode of mixed LiDARs and camera-only agents
through every command that reads episodes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cosim.io import open_episode
from cosim.scenario.lidar_presets import LIDAR_PRESETS
from cosim.scenario.loader import load_scenario, load_scenario_data
from cosim.scenario.model import Scenario, default_drone_rig, default_vehicle_rig
from tests.helpers import SCENARIOS, cli_in_process, run_cli, write_file, write_sweep

DEFAULT = str(SCENARIOS / "default.yaml")


def _scenario(*overrides: str) -> Scenario:
    return load_scenario(DEFAULT, overrides).scenario


def test_an_agents_rig_is_merged_field_by_field_over_its_kinds_rig():
    sc = _scenario("sensors.vehicle.lidar.range_noise_m=0.05", "sensors.vehicle.cameras=[{name: front, width: 64}]",
                   "agents.vehicles.rigs.vehicle_1.lidar.range_m=80",
                   "agents.vehicles.rigs.vehicle_2.lidar.model=vlp16",
                   "agents.vehicles.rigs.vehicle_3.lidar=null",
                   "agents.rsus.rigs.rsu_1.cameras=[]",
                   "agents.drones.0.rig.lidar.range_m=50")
    kind = sc.sensors.vehicle
    assert sc.rig_for("vehicle_0") == kind
    one = sc.rig_for("vehicle_1")
    assert (one.lidar.range_m, one.lidar.range_noise_m, one.cameras, one.imu) == (80.0, 0.05, kind.cameras, kind.imu)
    two = sc.rig_for("vehicle_2").lidar
    vlp16 = LIDAR_PRESETS["vlp16"].fields()
    assert (two.model, two.channels, list(two.elevations_deg)) == ("vlp16", 16, vlp16["elevations_deg"])
    assert two.mount == kind.lidar.mount and sc.rig_for("vehicle_2").cameras == kind.cameras
    three = sc.rig_for("vehicle_3")
    assert three.lidar is None and three.cameras == kind.cameras and three.gnss == kind.gnss
    assert sc.rig_for("rsu_1").cameras == [] and sc.rig_for("rsu_1").lidar == sc.sensors.rsu.lidar
    assert sc.rig_for("rsu_0") == sc.sensors.rsu
    drone = sc.rig_for("drone_0")
    assert drone.lidar.range_m == 50 and drone.lidar.lower_fov_deg == -90.0  # still the drone's downward LiDAR
    assert drone.lidar.mount == default_drone_rig().lidar.mount and drone.cameras == default_drone_rig().cameras
    assert sc.rig_for("drone_1") == sc.sensors.drone


def test_a_preset_on_an_agent_of_a_kind_without_lidar_lies_over_the_kinds_default_lidar():
    sc = _scenario("sensors.vehicle.lidar=null", "agents.vehicles.rigs.vehicle_0.lidar.model=os1_64")
    lidar = sc.rig_for("vehicle_0").lidar
    assert lidar.model == "os1_64" and lidar.channels == 64
    assert lidar.mount.xyz_m[:2] == default_vehicle_rig().lidar.mount.xyz_m[:2]
    assert sc.rig_for("vehicle_1").lidar is None


def test_the_resolved_scenario_leaves_out_absent_rigs_and_round_trips_given_ones():
    plain = load_scenario(DEFAULT).resolved["agents"]
    assert "rigs" not in plain["vehicles"] and "rigs" not in plain["rsus"]
    assert all("rig" not in d for d in plain["drones"])
    loaded = load_scenario(DEFAULT, ["agents.vehicles.rigs.vehicle_1.lidar.model=vlp32c",
                                     "agents.rsus.rigs.rsu_0.lidar=null", "agents.drones.2.rig.cameras=[]"])
    again = load_scenario_data(loaded.resolved).scenario
    for agent in loaded.scenario.agent_ids():
        assert again.rig_for(agent) == loaded.scenario.rig_for(agent), agent
    assert again.rig_for("vehicle_1").lidar.channels == 32 and again.rig_for("rsu_0").lidar is None


def test_a_sweep_axis_varies_the_mix(tmp_path):
    from cosim.batch.plan import plan_file

    sweep = write_sweep(tmp_path, """\
name: mix
set: {sensors.enabled: false, duration_s: 1, agents.vehicles.rigs.vehicle_2.lidar: null}
axes:
  v1: {key: agents.vehicles.rigs.vehicle_1.lidar.model, values: [vlp16, os1_64]}
count: 2
""")
    plan = plan_file(sweep)
    got = {}
    for ep in plan.episodes:
        sc = load_scenario_data(ep.scenario).scenario
        got[ep.labels["v1"]] = (sc.rig_for("vehicle_1").lidar.channels, sc.rig_for("vehicle_2").lidar,
                                sc.rig_for("vehicle_0").lidar.model)
    assert got == {"vlp16": (16, None, "generic"), "os1_64": (64, None, "generic")}


BAD = [  # (the agents section's lines, the key path named, words of the message); the override is on line 7
    ("vehicles:\n    count: 3\n    rigs:\n      vehicle_3: {lidar: null}", "agents.vehicles.rigs.vehicle_3",
     "no agent 'vehicle_3'"),
    ("vehicles:\n    count: 3\n    rigs:\n      rsu_0: {lidar: null}", "agents.vehicles.rigs.rsu_0",
     "not a vehicle id"),
    ("vehicles:\n    count: 3\n    rigs:\n      vehicle_1: {lidr: null}", "agents.vehicles.rigs.vehicle_1.lidr",
     "did you mean 'lidar'"),
    ("vehicles:\n    count: 3\n    rigs:\n      vehicle_1: {lidar: {model: vlp17}}",
     "agents.vehicles.rigs.vehicle_1.lidar.model", "'vlp16'"),
    ("rsus:\n    count: 2\n    rigs:\n      rsu_1: {lidar: {channels: 0}}", "agents.rsus.rigs.rsu_1.lidar.channels",
     "greater than or equal to 1"),
    ("drones:\n    - strategy: hover\n      rig:\n        lidar: {modle: vlp16}", "agents.drones.0.rig.lidar.modle",
     "did you mean 'model'"),
]


@pytest.mark.parametrize(("agents", "key", "words"), BAD)
def test_a_bad_override_is_one_message_naming_key_and_line_exit_2(tmp_path, capsys, agents, key, words):
    f = write_file(tmp_path, "bad.yaml", f"extends: default\nname: bad\nagents:\n  {agents}\n")
    status, _, err = cli_in_process(capsys, "run", str(f), "--dry-run", "--out", str(tmp_path / "out"))
    assert status == 2
    assert err.count("\n") == 1 and f"{f}:7: {key}: " in err and words in err, err


def test_a_bad_override_by_set_names_the_set(tmp_path, capsys):
    status, _, err = cli_in_process(capsys, "run", DEFAULT, "--dry-run", "--out", str(tmp_path / "out"),
                                    "--set", "agents.rsus.rigs.rsu_9.lidar=null")
    assert status == 2 and "--set agents.rsus.rigs.rsu_9.lidar=null: agents.rsus.rigs.rsu_9: no agent" in err, err


# ------------------------------------------------------------------ one real episode of mixed rigs

MIXED = ["duration_s=0.4", "map.size_m=300", "traffic.density_veh_per_km=6", "sensors.image_scale=0.05",
         "agents.vehicles.count=2", "agents.rsus.count=1", "agents.drones=[{strategy: hover, rig: {lidar: null}}]",
         "agents.vehicles.rigs.vehicle_0.lidar.model=vlp16", "agents.vehicles.rigs.vehicle_1.lidar=null",
         "agents.rsus.rigs.rsu_0.lidar.model=vlp32c"]


@pytest.fixture(scope="module")
def mixed(tmp_path_factory) -> Path:
    """A real 2-tick episode: vehicle_0 with a VLP-16, vehicle_1 camera-only, rsu_0 with a VLP-32C, drone_0
    camera-only."""
    out = tmp_path_factory.mktemp("mixed")
    r = run_cli("run", DEFAULT, "--out", str(out), "-q", *(a for s in MIXED for a in ("--set", s)))
    assert r.returncode == 0, r.stderr[-3000:]
    return next(out.glob("*.mcap"))


@pytest.mark.integration
def test_each_agent_records_its_own_lidar_and_the_episode_validates(mixed, capsys):
    status, out, err = cli_in_process(capsys, "validate", str(mixed))
    assert status == 0, out + err
    with open_episode(mixed) as ep:
        lidars = {t for t in ep.topics if t.endswith("/lidar")}
        assert lidars == {"/vehicle_0/lidar", "/rsu_0/lidar"}
        assert {"/vehicle_1/front/image", "/drone_0/down/image"} <= set(ep.topics)
        tick = next(iter(ep.ticks()))
        rings = {a: len(np.unique(tick.points(a).points["ring"])) for a in ("vehicle_0", "rsu_0")}
    assert 8 < rings["vehicle_0"] <= 16 and 16 < rings["rsu_0"] <= 32


@pytest.mark.integration
def test_every_export_writes_each_agents_own_lidar_and_none_for_the_camera_only(mixed, tmp_path, capsys):
    for fmt in ("opv2v", "airv2x", "kitti"):
        status, out, err = cli_in_process(capsys, "export", str(mixed), "--format", fmt, "--out",
                                          str(tmp_path / fmt), "--every", "2", "-q")
        assert status == 0, (fmt, out + err)
    opv2v = next((tmp_path / "opv2v" / "train").iterdir())
    pcds = {p.parent.name for p in opv2v.glob("*/*.pcd")}
    yamls = {p.parent.name for p in opv2v.glob("*/000000.yaml")}
    assert len(pcds) == 2 and len(yamls) == 4 and pcds < yamls, (pcds, yamls)  # vehicle_0 and rsu_0 of 4 agents
    airv2x = next((tmp_path / "airv2x" / "train").iterdir()) / "timestamp_000000"
    assert len(list(airv2x.glob("agent_*/metadata.pkl"))) == 4 and len(list(airv2x.glob("agent_*/lidar.pcd"))) == 2
    kitti = tmp_path / "kitti" / "training"
    assert len(list((kitti / "velodyne").glob("*.bin"))) == 1  # vehicle_0 alone: vehicle_1 has no LiDAR
    assert len(list((kitti / "label_2").glob("*.txt"))) == 1


@pytest.mark.integration
def test_learn_eval_coverage_and_render_take_an_agent_without_lidar(mixed, tmp_path, capsys):
    run = tmp_path / "run"
    status, out, err = cli_in_process(capsys, "learn", "train", str(mixed), "--out", str(run), "--steps", "2",
                                      "--batch-size", "2", "--fusion", "intermediate", "--encoders", "kind",
                                      "--agents", "all", "--no-val", "--threads", "1", "-q")
    assert status == 0, out + err
    assert "4 samples" in out  # two egos (one of them camera-only) at two ticks
    preds = tmp_path / "pred.jsonl"
    status, out, err = cli_in_process(capsys, "learn", "predict", str(run), str(mixed), "--out", str(preds), "-q")
    assert status == 0, out + err
    records = [json.loads(line) for line in preds.read_text().splitlines()]
    assert {r["ego"] for r in records} == {"vehicle_0", "vehicle_1"}
    status, out, err = cli_in_process(capsys, "eval", "--gt", str(mixed), "--pred", str(preds), "--out",
                                      str(tmp_path / "eval"))
    assert status == 0 and (tmp_path / "eval" / "eval.json").is_file(), out + err
    status, out, err = cli_in_process(capsys, "coverage", str(mixed), "--out", str(tmp_path / "cov"))
    assert status == 0, out + err
    cov = json.loads((tmp_path / "cov" / "coverage.json").read_text())
    assert cov, "coverage.json is empty"
    status, out, err = cli_in_process(capsys, "render", str(mixed), "--out", str(tmp_path / "render"), "--ticks",
                                      "0", "--dpi", "30")
    assert status == 0, out + err
    sheets = {p.name for p in (tmp_path / "render").glob("contact_*.png")}
    assert {"contact_vehicle_1_t0000.png", "contact_drone_0_t0000.png", "contact_vehicle_0_t0000.png"} <= sheets


@pytest.mark.integration
def test_per_sensor_encoders_give_each_lidar_of_the_episode_its_own(mixed, tmp_path, capsys):
    import torch

    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import episode_lidars

    lidars = episode_lidars(load_dataset(mixed)[0])
    assert lidars == {"vehicle_0": "vlp16", "vehicle_1": None, "rsu_0": "vlp32c", "drone_0": None}, lidars
    run = tmp_path / "run"
    status, out, err = cli_in_process(capsys, "learn", "train", str(mixed), "--out", str(run), "--steps", "2",
                                      "--batch-size", "2", "--fusion", "intermediate", "--encoders", "sensor",
                                      "--agents", "all", "--no-val", "--threads", "1", "-q")
    assert status == 0, out + err
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ckpt["setup"]["sensors"] == ["vlp16", "vlp32c"]
    assert sorted(k for k in ckpt["model"] if k.startswith("sensor_pfn")) == ["sensor_pfn.0.weight"]
    preds = tmp_path / "pred.jsonl"
    status, out, err = cli_in_process(capsys, "learn", "predict", str(run), str(mixed), "--out", str(preds), "-q")
    assert status == 0, out + err
    assert {json.loads(line)["ego"] for line in preds.read_text().splitlines()} == {"vehicle_0", "vehicle_1"}
