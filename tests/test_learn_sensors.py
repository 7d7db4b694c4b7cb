"""``cosim learn``'s per-sensor pillar encoders (``--encoders sensor``, issue 49's mixed LiDARs): how an agent's
LiDAR is named from its episode's resolved scenario, the encoders' order, which encoder an agent's points take
(and the fallback to its kind's for a LiDAR the model was not trained on), and that each encoder acts on its
own agents' pillars only. The run on a real episode with mixed LiDARs is in tests/test_agent_rigs.py."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from cosim.errors import InputError
from cosim.learn.samples import Setup, encoder_index, lidar_sensor, make_item, quantise, sensor_vocabulary

HAVE_TORCH = importlib.util.find_spec("torch") is not None
KIND_LIDAR = {"pattern": "spinning", "channels": 64, "range_m": 120.0}


def _resolved(**rigs: dict | None) -> dict:
    """A resolved scenario's agents and sensors: every kind on ``KIND_LIDAR`` but the drone (no LiDAR), with
    ``rigs`` as the agents' own rigs (a drone's by its index)."""
    drones = [{"strategy": "hover"}, {"strategy": "hover", "rig": rigs.pop("drone_1", None)}]
    vehicles = {k: v for k, v in rigs.items() if k.startswith("vehicle")}
    rsus = {k: v for k, v in rigs.items() if k.startswith("rsu")}
    return {"agents": {"vehicles": {"count": 3, "rigs": vehicles}, "rsus": {"count": 2, "rigs": rsus},
                       "drones": drones},
            "sensors": {"vehicle": {"lidar": dict(KIND_LIDAR)}, "rsu": {"lidar": dict(KIND_LIDAR)},
                        "drone": {"lidar": None}}}


def test_an_agents_lidar_is_named_by_its_preset_its_kind_or_a_digest_of_its_fields():
    resolved = _resolved(vehicle_1={"lidar": {**KIND_LIDAR, "model": "vlp16", "channels": 16}},
                         vehicle_2={"lidar": None}, rsu_1={"lidar": {**KIND_LIDAR, "channels": 32}},
                         drone_1={"lidar": {**KIND_LIDAR, "model": "os1_64"}})
    names = {a: lidar_sensor(resolved, a) for a in ("vehicle_0", "vehicle_1", "vehicle_2", "rsu_0", "rsu_1",
                                                    "drone_0", "drone_1")}
    assert names["vehicle_0"] == "vehicle" and names["rsu_0"] == "rsu"  # the kind's own LiDAR
    assert names["vehicle_1"] == "vlp16" and names["drone_1"] == "os1_64"
    assert names["vehicle_2"] is None and names["drone_0"] is None  # no LiDAR
    assert names["rsu_1"].startswith("custom-") and len(names["rsu_1"]) == len("custom-") + 8
    other = _resolved(rsu_1={"lidar": {**KIND_LIDAR, "channels": 16}})
    assert lidar_sensor(other, "rsu_1").startswith("custom-") and lidar_sensor(other, "rsu_1") != names["rsu_1"]
    assert lidar_sensor(resolved, "rsu_1") == names["rsu_1"]  # the same fields, the same name


def test_the_vocabulary_lists_the_kinds_first_then_the_other_lidars_sorted():
    maps = [{"vehicle_0": "vehicle", "vehicle_1": "vlp16", "drone_0": None},
            {"rsu_0": "os1_64", "vehicle_0": "vehicle", "drone_0": "drone", "rsu_1": "rsu"}]
    assert sensor_vocabulary(maps) == ("vehicle", "rsu", "drone", "os1_64", "vlp16")
    assert sensor_vocabulary([{"vehicle_0": "vlp32c"}]) == ("vlp32c",)


def test_an_agent_takes_its_lidars_encoder_else_its_kinds_else_one_error():
    setup = Setup(fusion="intermediate", agents="all", encoders="sensor", sensors=("vehicle", "rsu", "vlp16"))
    lidars = {"vehicle_0": "vehicle", "vehicle_1": "vlp16", "rsu_0": "rsu", "rsu_1": "os1_64", "drone_0": "drone"}
    assert [encoder_index(a, setup, lidars) for a in ("vehicle_0", "vehicle_1", "rsu_0")] == [0, 2, 1]
    assert encoder_index("rsu_1", setup, lidars) == 1  # an OS1-64 the model never saw: its kind's encoder
    assert encoder_index("vehicle_2", setup, {**lidars, "vehicle_2": None}) == 0  # no LiDAR, no pillars
    with pytest.raises(InputError, match=r"drone_0's LiDAR 'drone' has no encoder.*vehicle, rsu, vlp16"):
        encoder_index("drone_0", setup, lidars)
    kind = Setup(fusion="intermediate", agents="all", encoders="kind")
    assert [encoder_index(a, kind, lidars) for a in ("vehicle_1", "rsu_1", "drone_0")] == [0, 1, 2]


def test_the_sensors_travel_with_the_setup_and_need_encoders_sensor():
    setup = Setup(fusion="intermediate", agents="all", encoders="sensor", sensors=("vehicle", "vlp16"))
    assert Setup.from_dict(setup.to_dict()) == setup
    old = {k: v for k, v in Setup(fusion="intermediate", agents="all").to_dict().items() if k != "sensors"}
    assert Setup.from_dict(old).sensors == ()  # a checkpoint from before the per-sensor encoders
    with pytest.raises(InputError, match="give encoders sensor"):
        Setup(fusion="intermediate", agents="all", encoders="kind", sensors=("vlp16",))


def _item(setup: Setup, lidars: dict) -> dict:
    """An intermediate sample of a record with three agents a few metres apart, a cloud each."""
    agents = ["vehicle_0", "vehicle_1", "rsu_0"]
    poses = np.stack([np.eye(4)] * 3)
    poses[1, 0, 3], poses[2, 1, 3] = 10.0, 8.0
    pts = np.array([[5.0, 2.0, -1.0], [-3.0, 4.0, -0.5], [8.0, -6.0, -1.5]])
    rec = {"tick": 0, "t_ns": 0, "tick_ns": 200_000_000, "agents": agents, "map_from": poses,
           "points": [quantise(pts)[0]] * 3, "intensity": [np.full(3, 90, np.uint8)] * 3,
           "hits": [np.zeros((2, 0), np.int64)] * 3, "label_track_ids": np.zeros(0, np.int64), "label_classes": [],
           "label_centers": np.zeros((0, 3)), "label_rotations": np.zeros((0, 4)), "label_sizes": np.zeros((0, 3)),
           "agent_tracks": {}, "links": None, "link_delay_ms": None}
    return make_item(rec, "vehicle_0", setup, "ep", lidars=lidars)


def test_a_sample_names_each_agents_encoder():
    lidars = {"vehicle_0": "vehicle", "vehicle_1": "vlp16", "rsu_0": "rsu"}
    sensor = Setup(fusion="intermediate", agents="all", encoders="sensor", sensors=("vehicle", "rsu", "vlp16"))
    assert _item(sensor, lidars)["encoder"].tolist() == [0, 2, 1]
    kind = Setup(fusion="intermediate", agents="all", encoders="kind")
    assert _item(kind, lidars)["encoder"].tolist() == [0, 0, 1]


@pytest.mark.skipif(not HAVE_TORCH, reason="needs torch (pip install -e '.[learn]')")
def test_each_per_sensor_encoder_acts_on_its_own_agents_pillars_only():
    import torch

    from cosim.learn.grid import Grid
    from cosim.learn.model import PillarDetector

    torch.manual_seed(0)
    model = PillarDetector(Grid(), 1, width=8, fusion="intermediate", encoders="sensor", n_sensors=3).eval()
    assert len(model.sensor_pfn) == 2 and not hasattr(model, "kind_pfn")
    features = torch.randn(12, 9)
    counts = torch.tensor([3, 3, 3, 3])
    encoder = torch.tensor([0, 2, 1, 2])  # the pillars' encoders
    before = model.encode(features, counts, encoder)
    with torch.no_grad():
        model.sensor_pfn[1].weight.mul_(-2.0)  # the third sensor's encoder
    after = model.encode(features, counts, encoder)
    changed = ~torch.isclose(before, after).all(dim=1)
    assert changed.tolist() == [False, True, False, True]
    with pytest.raises(ValueError, match="number of sensors"):
        PillarDetector(Grid(), 1, fusion="intermediate", encoders="sensor")


def test_per_sensor_training_takes_the_lidars_of_its_episodes_and_refuses_none(monkeypatch):
    from cosim.learn import data

    maps = {"a": {"vehicle_0": "vehicle", "vehicle_1": "vlp16"}, "b": {"vehicle_0": "vlp32c", "drone_0": None},
            "dark": {"vehicle_0": None}}
    monkeypatch.setattr(data, "episode_lidars", lambda ref: maps[ref])
    setup = Setup(fusion="intermediate", agents="all", encoders="sensor")
    assert data.with_sensors(setup, ["a", "b"]).sensors == ("vehicle", "vlp16", "vlp32c")
    assert data.with_sensors(Setup(fusion="intermediate", agents="all", encoders="kind"), ["a"]).sensors == ()
    with pytest.raises(InputError, match=r"no agent of the 1 training and validation episode.* carries a LiDAR"):
        data.with_sensors(setup, ["dark"])
