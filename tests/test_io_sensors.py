"""Round trip through the real sensor suite and exporter: render -> frame_messages -> EpisodeWriter ->
open_episode gives back the rendered arrays exactly, and the file validates."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml
from cosim.sensors import SensorSuite
from cosim.sensors.rig import sensor_transforms
from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world

from cosim.io import open_episode
from cosim.io.labels import label_messages
from cosim.io.sensor_messages import depth_image, frame_messages
from cosim.io.synthetic import synthetic_metadata
from cosim.io.validate import validate_episode
from cosim.io.writer import EpisodeWriter
from cosim.scenario.model import (
    CameraSpec,
    CommSpec,
    HoverDrone,
    LidarSpec,
    RigSpec,
    SensorsSpec,
    default_drone_rig,
    default_rsu_rig,
    default_vehicle_rig,
)

TICKS = 3


def _small(rig: RigSpec) -> RigSpec:
    cams = [CameraSpec(name=c.name, width=64, height=36, mount=c.mount, gimbal=c.gimbal) for c in rig.cameras]
    lidar = rig.lidar.model_copy(update={"channels": 16, "horizontal_resolution_deg": 2.0}) if rig.lidar else None
    assert lidar is None or isinstance(lidar, LidarSpec)
    return rig.model_copy(update={"cameras": cams, "lidar": lidar})


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    sc = synthetic_scenario(
        name="io_sensors",
        vehicles=2, rsus=1, drones=[HoverDrone()],
        sensors=SensorsSpec(
            vehicle=_small(default_vehicle_rig()),
            rsu=_small(default_rsu_rig()),
            drone=_small(default_drone_rig()),
            bev_cell_m=1.0,
        ),
        comm=CommSpec(enabled=False),  # sensors only: no link model writes /comm/links here
    )
    world = synthetic_world()
    suite = SensorSuite(sc, world)
    path = tmp_path_factory.mktemp("iosens") / "ep.mcap"
    frames = []
    with EpisodeWriter(path) as w:
        base = synthetic_snapshot(n_vehicles=2, n_rsus=1, n_drones=1)
        w.add_metadata("episode", synthetic_metadata(TICKS, [a.agent_id for a in base.agents], True, world))
        for k in range(TICKS):
            snap = dataclasses.replace(base, tick=k, t_ns=k * 200_000_000)
            rig = [t for a in snap.agents for t in sensor_transforms(sc, a)]
            fs = suite.render(snap, np.random.default_rng([0, k]))
            frames.append(fs)
            for topic, msg in label_messages(snap, rig) + frame_messages(fs, snap.t_ns):
                w.write(topic, msg, snap.t_ns)
        w.add_attachment("scenario.yaml", "application/yaml", yaml.safe_dump(sc.model_dump(mode="json")).encode())
        for name in ("map.net.xml", "routes.rou.xml", "world.json"):
            w.add_attachment(name, "application/octet-stream", b"x")
        w.finish()
    return path, frames


def test_a_rendered_episode_validates(rendered):
    path, _ = rendered
    report = validate_episode(path)
    assert report.ok, report.lines()
    assert report.ticks == TICKS


def test_reader_returns_the_rendered_arrays(rendered):
    path, frames = rendered
    with open_episode(path) as ep:
        for tick in ep.ticks():
            fs = frames[tick.index]
            for agent_id, af in fs.agents.items():
                if af.lidar is not None:
                    pc = tick.points(agent_id)
                    assert np.max(np.abs(pc.xyz - af.lidar.points)) <= 2.0**-8 + 1e-6  # half of 1/128 m
                    assert pc.points["x"].dtype == np.float32 and pc.stored["x"].dtype == np.float32
                    assert np.array_equal(pc.points["instance_id"], af.lidar.instance_id)
                    assert np.array_equal(pc.points["class_id"], af.lidar.class_id)
                    assert np.array_equal(pc.points["ring"], af.lidar.ring)
                for name, cam in af.cameras.items():
                    assert np.array_equal(tick.image(agent_id, name).array, cam.rgb)
                    assert np.array_equal(tick.depth(agent_id, name).array, depth_image(cam.depth), equal_nan=True)
                    assert np.array_equal(tick.semantic(agent_id, name).array, cam.semantic)
                    assert np.array_equal(tick.instance(agent_id, name).array, cam.instance.astype(np.int32))
                    cal = tick.calibration(agent_id, name)
                    assert np.array_equal(cal.K, cam.K) and (cal.width, cal.height) == (64, 36)
                    # the optical frame reached through /tf is the pose the camera rendered from
                    m = tick.transforms.to_root(f"{agent_id}/{name}/optical")
                    assert m[:3, :3] == pytest.approx(cam.pose.rotation, abs=1e-9)
                    assert m[:3, 3] == pytest.approx(cam.pose.position_m, abs=1e-9)
                if af.gnss is not None:
                    g = tick.gnss(agent_id)
                    assert (g.latitude_deg, g.longitude_deg) == (af.gnss.latitude_deg, af.gnss.longitude_deg)
                if af.bev is not None:
                    grid = tick.bev(agent_id)
                    assert grid.cells.dtype.names == tuple(af.bev.layers)
                    stacked = np.stack([grid.cells[n] for n in af.bev.layers], axis=2)
                    assert np.array_equal(stacked, af.bev.grid)
                if af.imu is not None:
                    imu = tick.imu(agent_id)
                    assert imu["linear_acceleration_mps2"] == list(af.imu.linear_acceleration_mps2)
                if af.visibility is not None:
                    vis = tick.visibility(agent_id)
                    assert [o["track_id"] for o in vis["objects"]] == [o.track_id for o in af.visibility.objects]


def _foxglove_xyz(msg) -> np.ndarray:
    """x, y, z (N, 3) of a ``foxglove.PointCloud`` read the way a viewer that knows only the schema reads it:
    each field's value at its offset, by its numeric type, unscaled (Foxglove's own rule: no unit field)."""
    numeric = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<f4", 8: "<f8"}
    raw = np.frombuffer(msg.data, np.uint8).reshape(-1, msg.point_stride)
    out = []
    for name in "xyz":
        (f,) = [f for f in msg.fields if f.name == name]
        t = np.dtype(numeric[f.type])
        out.append(raw[:, f.offset:f.offset + t.itemsize].copy().view(t)[:, 0].astype(np.float64))
    return np.stack(out, axis=1)


def test_the_default_lidar_encoding_reads_as_metres_in_a_foxglove_schema_only_reader(rendered):
    """What the Foxglove app draws (the stored numbers of x, y, z, unscaled) is cosim.io's metres, so the
    default episode's point clouds appear at true scale; the quantized option would be 256 times too large."""
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from mcap.reader import make_reader

    path, _ = rendered
    assert SensorsSpec().lidar_positions == "float32"
    seen = 0
    with open(path, "rb") as f, open_episode(path) as ep:
        by_tick = {(t.t_ns, a): t.points(a) for t in ep.ticks() for a in ep.agents if f"/{a}/lidar" in t}
        for _schema, channel, message in make_reader(f).iter_messages():
            if not channel.topic.endswith("/lidar"):
                continue
            msg = PointCloud.FromString(message.data)
            agent = channel.topic.split("/")[1]
            ours = by_tick[(message.log_time, agent)].xyz
            assert len(ours) > 50
            assert np.array_equal(_foxglove_xyz(msg), ours)
            seen += 1
    assert seen == TICKS * 4
