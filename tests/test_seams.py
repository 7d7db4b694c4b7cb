"""The plug-in seams: a toy link model, a toy metric and a toy sensor kind, each one function or class plus
its registration; the registries' semantics; kind lists derived from the schema. No engines: fast."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pytest
from pydantic import BaseModel, Field

from cosim.errors import InputError
from cosim.registry import Registry

# ------------------------------------------------------------------------------------- registry


def test_a_registry_refuses_a_second_entry_and_lists_the_known_names_for_an_unknown_one():
    reg: Registry[int] = Registry("widget")
    reg.register("b")(2)
    reg.add("a", 1)
    with pytest.raises(ValueError, match="widget 'a' is already registered"):
        reg.add("a", 3)
    with pytest.raises(InputError, match=r"unknown widget 'c'; known: a, b"):
        reg.get("c")
    assert reg.get("a") == 1 and reg.names() == ["a", "b"] and [n for n, _ in reg.items()] == ["b", "a"]
    reg.remove("a")
    assert "a" not in reg and len(reg) == 1


# ----------------------------------------------------------------------------------- link model


def test_a_toy_link_model_is_one_function_and_a_name():
    from cosim.comm.links import check_link_models, pair_channels
    from cosim.comm.los import LOS, NLOS
    from cosim.comm.models import LINK_MODELS, PairGeometry, PathLoss

    @LINK_MODELS.register("toy_wall")
    def toy_wall(g: PairGeometry) -> PathLoss:  # 60 dB plus 1 dB per metre, 20 dB more when blocked
        return PathLoss(60.0 + g.d3d_m, 80.0 + g.d3d_m, 1.0, 2.0, (5.0, 6.0))

    try:
        types = ["vehicle-vehicle", "vehicle-vehicle", "vehicle-rsu"]
        state = np.array([LOS, NLOS, LOS])
        d = np.array([10.0, 20.0, 30.0])
        h = np.array([1.6, 1.6, 1.6])
        args = (types, state, d, d, h, h + 4.0, np.full(3, np.nan), np.full(3, np.nan), "urban", "umi_av", 5.9)
        default = pair_channels(*args)
        toy = pair_channels(*args, overrides={"vehicle-vehicle": "toy_wall"})
        assert toy.model == ("toy_wall", "toy_wall", "tr38901_umi_sc")
        assert toy.path_loss_db[:2] == pytest.approx([70.0, 100.0])
        assert toy.sigma_db[:2] == pytest.approx([1.0, 2.0]) and toy.decorrelation_m[:2] == pytest.approx([5.0, 6.0])
        assert default.model[:2] == ("tr37885_urban", "tr37885_urban")
        assert toy.path_loss_db[2] == default.path_loss_db[2]  # other link types keep their model
        check_link_models({"vehicle-vehicle": "toy_wall"})
        with pytest.raises(InputError, match=r"unknown link model 'nope'; known: .*toy_wall"):
            check_link_models({"vehicle-vehicle": "nope"})
        with pytest.raises(InputError, match="unknown link type 'car-car'"):
            check_link_models({"car-car": "toy_wall"})
    finally:
        LINK_MODELS.remove("toy_wall")


def test_the_scenario_picks_link_models_per_link_type():
    from cosim.scenario.model import CommSpec

    assert CommSpec().link_models == {}
    assert CommSpec(link_models={"rsu-drone": "free_space"}).link_models == {"rsu-drone": "free_space"}


# --------------------------------------------------------------------------------------- metric


def _frame():
    from cosim.eval.dataset import FrameTruth
    from cosim.eval.predictions import parse_record

    box = {"center_m": [10.0, 0.0, 0.0], "size_m": [4.0, 2.0, 1.5], "yaw_rad": 0.0, "class": "car", "score": 0.9}
    rec = parse_record({"episode": "ep", "tick": 0, "ego": "vehicle_0", "boxes": [box, box]}, Path("p.jsonl"), 1)
    c = np.array([[10.0, 0.0, 0.0]])
    inside = np.array([True])
    truth = FrameTruth("ep", 0, "vehicle_0", np.array([1]), ("car",), c, np.array([[4.0, 2.0, 1.5]]), np.zeros(1),
                       inside, inside, None, None, np.eye(4))
    return rec, truth


def test_a_toy_metric_is_one_class_and_a_name_and_reaches_the_results_and_tables():
    from cosim.eval.evaluate import (
        METRICS,
        EvalOptions,
        EvalResult,
        FrameInputs,
        Metric,
        _score_frame,
        eval_tables,
        register_metric,
    )
    from cosim.eval.tables import Table

    @register_metric("box_count")
    class BoxCount(Metric):
        def __init__(self, n: int = 0):
            self.n = n

        @classmethod
        def empty(cls, options):
            return cls()

        @classmethod
        def score(cls, frame: FrameInputs):
            return cls(len(frame.rec.classes))

        def merge(self, other):
            self.n += other.n

        def summary(self, options):
            return {"boxes": self.n}

        @classmethod
        def tables(cls, result):
            return [Table("box_count", "Predicted boxes", ["agents", "boxes"],
                          [["all", result.metrics("all")["box_count"]["boxes"]]])]

    try:
        rec, truth = _frame()
        options = EvalOptions()
        frame = _score_frame(rec, truth, options, set(), None)
        total = frame.results["box_count"].empty(options)
        total.merge(frame.results["box_count"])
        total.merge(frame.results["box_count"])
        frame.results["box_count"] = total
        result = EvalResult({("all", "overall", "all"): frame}, options, ["vehicle"], 1, 1, 0)
        m = result.metrics("all")
        assert m["box_count"] == {"boxes": 4} and m["detection"]["vehicle"]["n_det"] == 2
        assert [t.name for t in eval_tables(result)][-1] == "box_count"
        only = EvalOptions(metrics=("box_count",))
        assert set(_score_frame(rec, truth, only, set(), None).results) == {"box_count"}
        with pytest.raises(InputError, match="unknown metric 'boxes'; known: box_count, detection, segmentation"):
            EvalOptions(metrics=("boxes",))
        with pytest.raises(ValueError, match="already registered"):
            register_metric("detection")(BoxCount)
    finally:
        METRICS.remove("box_count")


# ---------------------------------------------------------------------------------- sensor kind


def test_a_toy_sensor_kind_is_one_module_and_a_registration():
    from cosim.sensors import SensorSuite
    from cosim.sensors.kinds import SENSOR_KINDS, SensorContext, SensorKind, register_sensor_kind
    from cosim.sensors.rig import rig_transforms
    from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world
    from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair

    from cosim.io.sensor_messages import frame_messages
    from cosim.scenario.model import Model, RigSpec, SensorsSpec

    class AltimeterSpec(Model):
        offset_m: float = 0.0

    class AltimeterRig(RigSpec):  # the kind's spec: a rig field named like the kind
        altimeter: AltimeterSpec | None = AltimeterSpec(offset_m=0.5)

    def render(ctx: SensorContext) -> float:
        return float(ctx.agent.position_m[2]) + ctx.spec.offset_m

    def message(agent_id: str, height_m: float, t_ns: int) -> KeyValuePair:
        return KeyValuePair(key=f"{agent_id}/altimeter", value=f"{height_m:.2f}")

    register_sensor_kind(SensorKind("altimeter", render, message))
    try:
        rig = AltimeterRig(lidar=None, cameras=[], gnss=None, imu=None)
        sc = synthetic_scenario(sensors=SensorsSpec(vehicle=rig, bev=False))
        world = synthetic_world()
        snap = synthetic_snapshot(n_vehicles=1, n_rsus=0, n_drones=0)
        ego = next(a for a in snap.agents if a.agent_id == "vehicle_0")
        with SensorSuite(sc, world, noise=False) as suite:
            frames = suite.render(snap, np.random.default_rng(0))
        af = frames.agents["vehicle_0"]
        assert af.sensors == {"altimeter": pytest.approx(ego.position_m[2] + 0.5)} and af.gnss is None
        topics = dict(frame_messages(frames, frames.t_ns))
        assert topics["/vehicle_0/altimeter"].value == f"{ego.position_m[2] + 0.5:.2f}"
        assert ("vehicle_0/base_link", "vehicle_0/altimeter") in {t[:2] for t in rig_transforms(rig, ego)}
        with pytest.raises(ValueError, match="sensor kind 'altimeter' is already registered"):
            register_sensor_kind(SensorKind("altimeter", render, message))
    finally:
        SENSOR_KINDS.remove("altimeter")
    assert SENSOR_KINDS.names() == ["gnss"]


# ------------------------------------------------------------------------ kinds from the schema


def test_event_and_strategy_kinds_follow_from_the_schema_unions():
    from cosim.io.events import EVENTS_SCHEMA
    from cosim.scenario import loader
    from cosim.scenario.model import DRONE_STRATEGIES, EVENT_KINDS, union_tags

    class A(BaseModel):
        kind: Literal["a"] = "a"

    class B(BaseModel):
        kind: Literal["b1", "b2"] = "b1"

    assert union_tags(Annotated[A | B, Field(discriminator="kind")]) == ("a", "b1", "b2")
    assert DRONE_STRATEGIES == ("hover", "patrol", "escort")
    assert {"breakdown", "cut_in", "construction_zone"} <= set(EVENT_KINDS)
    kind_enum = EVENTS_SCHEMA["properties"]["events"]["items"]["properties"]["kind"]["enum"]
    assert kind_enum == list(EVENT_KINDS)
    assert {*DRONE_STRATEGIES, *EVENT_KINDS} == loader._UNION_TAGS
