"""A small synthetic episode with every topic of the format, written by the real episode writer.

For tests, the runnable example and trying the tools without running a simulation. Geometry is
simple and known: vehicles drive along +x at 10 m/s, a drone hovers at 60 m, an RSU stands still;
LiDAR points lie on a ring around each sensor; images are gradients; instance masks carry the
track id of one live actor.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import yaml
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.Vector2_pb2 import Vector2
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

from cosim.assemble import TrackRegistry, build_snapshot
from cosim.classes import class_table
from cosim.io.format import FORMAT_VERSION
from cosim.io.labels import label_messages, timestamp
from cosim.io.writer import EpisodeWriter
from cosim.protocol import DroneState, VehicleState
from cosim.snapshot import WorldSnapshot
from cosim.world.types import Junction, Prism, RsuSite, StaticLayout, World

TICK_NS = 200_000_000
CAMERAS = {"vehicle": ("front", "rear"), "rsu": ("front",), "drone": ("down",)}
_OPTICAL_FROM_FLU_Q = (-0.5, 0.5, -0.5, 0.5)  # body FLU <- optical (x right, y down, z forward)

IMU_SCHEMA: dict[str, Any] = {"title": "cosim.Imu", "type": "object"}
VISIBILITY_SCHEMA: dict[str, Any] = {"title": "cosim.Visibility", "type": "object"}


def synthetic_world() -> World:
    return World(
        "urban",
        b"<net/>",
        b"<routes/>",
        (0, 0, 200, 100),
        (Junction("j0", (50.0, 50.0), "traffic_light"),),
        (RsuSite("rsu_0", "j0", (45.0, 45.0, 8.0), 0.785, 8.0),),
        StaticLayout((Prism("road", ((-10.0, -4.0), (200.0, -4.0), (200.0, 4.0), (-10.0, 4.0)), 0.0, 0.02),)),
        (37.0, -122.0, 10.0),
    )


def synthetic_snapshot(tick: int, tracks: TrackRegistry, world: World) -> WorldSnapshot:
    t = tick * TICK_NS / 1e9
    cars = [
        VehicleState("bg.1", "truck", (5 + t, 3.0, 1.7), (8.0, 2.5, 3.4), 0.0, 0.0, 1.0, (1.0, 0, 0), 0.0, 0.0),
        VehicleState(
            "vehicle_0",
            "car",
            (10 + 10 * t, 0.0, 0.75),
            (4.5, 1.9, 1.5),
            0.0,
            0.0,
            10.0,
            (10.0, 0, 0),
            0.0,
            0.0,
            "vehicle_0",
        ),
    ]
    drones = [
        DroneState(
            "drone_0",
            (20.0, 5.0, 60.0),
            (0, 0, 0, 1),
            (0, 0, 0),
            (0, 0, 0),
            (0, 0, 9.8),
            (0, 0, 0, 1),
            12.5 * tick,
            "hover",
            "hold",
        )
    ]
    return build_snapshot(tick, tick * TICK_NS, cars, drones, world, tracks)


def _rig(agent: str, kind: str) -> list[tuple[str, str, tuple[float, ...], tuple[float, ...]]]:
    base = f"{agent}/base_link"
    out: list[tuple[str, str, tuple[float, ...], tuple[float, ...]]] = [
        (base, f"{agent}/lidar", (0.0, 0.0, 1.9), (0.0, 0.0, 0.0, 1.0)),
        (base, f"{agent}/gnss", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    ]
    for i, cam in enumerate(CAMERAS[kind]):
        yaw = math.pi * i
        out.append((base, f"{agent}/{cam}", (0.0, 0.0, 1.6), (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))))
        out.append((f"{agent}/{cam}", f"{agent}/{cam}/optical", (0.0, 0.0, 0.0), _OPTICAL_FROM_FLU_Q))
    if kind != "rsu":
        out.append((base, f"{agent}/imu", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    return out


def _points(tick: int, n: int, live: list[int]) -> PointCloud:
    """A 10 m ring of ``n`` points 1.9 m below the sensor, stored as the sensor exporter stores sweeps."""
    from cosim.io.sensor_messages import lidar_message

    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    xyz = np.stack([10 * np.cos(a), 10 * np.sin(a), np.full(n, -1.9)], axis=1)
    frame = SimpleNamespace(points=xyz, intensity=np.linspace(0, 1, n), ring=np.arange(n) % 16,
                            class_id=np.ones(n, np.uint8),
                            instance_id=np.where(np.arange(n) < n // 4, live[tick % len(live)], 0))
    return lidar_message("", frame, 0)  # the caller sets frame_id and timestamp


def _png(arr: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def sensor_messages(snapshot: WorldSnapshot, width: int, height: int) -> list[tuple[str, Any]]:
    """Every sensor topic of every agent for one tick (small, deterministic contents)."""
    ts = timestamp(snapshot.t_ns)
    live = sorted(a.track_id for a in snapshot.actors)
    out: list[tuple[str, Any]] = []
    for agent in snapshot.agents:
        a = agent.agent_id
        pc = _points(snapshot.tick, 64, live)
        pc.timestamp.CopyFrom(ts)
        pc.frame_id = f"{a}/lidar"
        out.append((f"/{a}/lidar", pc))
        for cam in CAMERAS[agent.kind]:
            frame = f"{a}/{cam}/optical"
            u = np.arange(width, dtype=np.uint8)[None, :].repeat(height, 0)
            rgb = np.stack([u, np.full_like(u, snapshot.tick * 10 % 256), u[::-1]], axis=2)
            out.append(
                (
                    f"/{a}/{cam}/image",
                    CompressedImage(timestamp=ts, frame_id=frame, format="png", data=_png(np.ascontiguousarray(rgb))),
                )
            )
            depth = np.full((height, width), 12.345, np.float32)
            out.append(
                (
                    f"/{a}/{cam}/depth",
                    RawImage(
                        timestamp=ts,
                        frame_id=frame,
                        width=width,
                        height=height,
                        encoding="32FC1",
                        step=4 * width,
                        data=depth.tobytes(),
                    ),
                )
            )
            sem = np.zeros((height, width), np.uint8)
            sem[height // 2 :] = 1
            out.append(
                (
                    f"/{a}/{cam}/semantic",
                    RawImage(
                        timestamp=ts,
                        frame_id=frame,
                        width=width,
                        height=height,
                        encoding="mono8",
                        step=width,
                        data=sem.tobytes(),
                    ),
                )
            )
            inst = np.zeros((height, width), np.int32)
            inst[: height // 4, : width // 4] = live[0]
            out.append(
                (
                    f"/{a}/{cam}/instance",
                    RawImage(
                        timestamp=ts,
                        frame_id=frame,
                        width=width,
                        height=height,
                        encoding="32SC1",
                        step=4 * width,
                        data=inst.tobytes(),
                    ),
                )
            )
            f = 0.5 * width / math.tan(math.radians(110) / 2)
            k = [f, 0, width / 2, 0, f, height / 2, 0, 0, 1]
            out.append(
                (
                    f"/{a}/{cam}/calibration",
                    CameraCalibration(
                        timestamp=ts,
                        frame_id=frame,
                        width=width,
                        height=height,
                        distortion_model="",
                        D=[],
                        K=k,
                        R=[1, 0, 0, 0, 1, 0, 0, 0, 1],
                        P=[f, 0, width / 2, 0, 0, f, height / 2, 0, 0, 0, 1, 0],
                    ),
                )
            )
        out.append(
            (
                f"/{a}/gnss",
                LocationFix(
                    timestamp=ts,
                    frame_id=f"{a}/gnss",
                    latitude=37.0,
                    longitude=-122.0,
                    altitude=10.0 + agent.position_m[2],
                    position_covariance=[0.25, 0, 0, 0, 0.25, 0, 0, 0, 0.25],
                    position_covariance_type=LocationFix.DIAGONAL_KNOWN,
                ),
            )
        )
        if agent.kind != "rsu":
            out.append(
                (
                    f"/{a}/imu",
                    (
                        "cosim.Imu",
                        IMU_SCHEMA,
                        {
                            "timestamp_ns": snapshot.t_ns,
                            "frame_id": f"{a}/imu",
                            "linear_acceleration_mps2": list(agent.specific_force_mps2),
                            "angular_velocity_radps": list(agent.angular_rate_radps),
                            "orientation": list(agent.rotation),
                        },
                    ),
                )
            )
        cells = np.zeros((8, 16, 2), np.uint8)  # layers: road, car (the exporter writes one per class)
        cells[3:5, :, 0] = 1
        x, y, z = agent.position_m
        grid = Grid(
            timestamp=ts,
            frame_id="map",
            pose=Pose(position=Vector3(x=x - 8.0, y=y - 4.0, z=z), orientation=Quaternion(w=1.0)),
            column_count=16,
            cell_size=Vector2(x=1.0, y=1.0),
            row_stride=32,
            cell_stride=2,
            fields=[
                PackedElementField(name="road", offset=0, type=1),
                PackedElementField(name="car", offset=1, type=1),
            ],
            data=cells.tobytes(),
        )
        out.append((f"/{a}/bev", grid))
        out.append(
            (
                f"/{a}/visibility",
                (
                    "cosim.Visibility",
                    VISIBILITY_SCHEMA,
                    {
                        "timestamp_ns": snapshot.t_ns,
                        "agent_id": a,
                        "objects": [{"track_id": live[0], "lidar_points": 16, "pixels": {CAMERAS[agent.kind][0]: 10}}],
                    },
                ),
            )
        )
    return out


def synthetic_metadata(n_ticks: int, agents: list[str], sensors: bool, world: World) -> dict[str, str]:
    return {
        "format_version": FORMAT_VERSION,
        "generator": "cosim synthetic",
        "scenario": "synthetic",
        "description": "synthetic test episode",
        "seed": "0",
        "weather": "clear",
        "lighting": "day",
        "environment": world.map_kind,
        "strategies": json.dumps(["hover"]),
        "tick_hz": "5.0",
        "tick_ns": str(TICK_NS),
        "n_ticks": str(n_ticks),
        "duration_s": repr(n_ticks * TICK_NS / 1e9),
        "agents": json.dumps(agents),
        "sensors_enabled": json.dumps(sensors),
        "geo_origin": json.dumps(list(world.geo_origin)),
        "map_bounds_m": json.dumps(list(world.bounds_m)),
        "class_table": json.dumps(class_table()),
        "versions": json.dumps({}),
    }


#: ``edit(tick, topic, message) -> None`` (drop it), a message, or a list of ``(t_ns, topic, message)``.
Edit = Callable[[int, str, Any], Any]


def synthetic_scenario(ticks: int, sensors: bool, width: int, height: int) -> dict[str, Any]:
    """The resolved scenario matching the synthetic episode's agents and rigs (its scenario.yaml)."""

    def cams(kind: str) -> list[dict[str, Any]]:
        return [{"name": c, "width": width, "height": height} for c in CAMERAS[kind]]

    doc = {
        "name": "synthetic",
        "description": "synthetic test episode",
        "duration_s": ticks * TICK_NS / 1e9,
        "agents": {"vehicles": {"count": 1}, "rsus": {"count": 1}, "drones": [{"strategy": "hover"}]},
        "sensors": {
            "enabled": sensors,
            "vehicle": {"cameras": cams("vehicle"), "imu": {}},
            "rsu": {"cameras": cams("rsu"), "imu": None},
            "drone": {"cameras": cams("drone"), "imu": {}},
        },
    }
    from cosim.scenario.model import Scenario

    return Scenario.model_validate(doc).model_dump(mode="json")


def write_synthetic_episode(
    path: str | Path,
    *,
    ticks: int = 10,
    sensors: bool = True,
    width: int = 32,
    height: int = 24,
    compression: str = "zstd",
    edit: Edit | None = None,
    metadata: dict[str, str] | None = None,
) -> Path:
    """Write a complete synthetic episode (3 agents: vehicle_0, rsu_0, drone_0) and return its path.

    ``edit`` sees every message before it is written and may drop, replace or re-time it (tests use it
    to make defective files); ``metadata`` overrides keys of the ``episode`` record.
    """
    from cosim.comm.links import LinkModel
    from cosim.comm.los import LinkScene
    from cosim.scenario.model import CommSpec

    world = synthetic_world()
    tracks = TrackRegistry()
    links = LinkModel(CommSpec(), LinkScene.from_layout(world.layout), world.map_kind, 0, TICK_NS)
    with EpisodeWriter(Path(path), compression=compression) as w:
        first = synthetic_snapshot(0, tracks, world)
        agents = [a.agent_id for a in first.agents]
        w.add_metadata("episode", {**synthetic_metadata(ticks, agents, sensors, world), **(metadata or {})})
        for k in range(ticks):
            snap = synthetic_snapshot(k, tracks, world)
            rig = [t for a in snap.agents for t in _rig(a.agent_id, a.kind)] if sensors else []
            messages = label_messages(snap, rig) + (sensor_messages(snap, width, height) if sensors else [])
            messages.append(links.message(snap))
            for topic, msg in messages:
                out = edit(k, topic, msg) if edit is not None else msg
                if out is None:
                    continue
                for t_ns, tp, m in out if isinstance(out, list) else [(snap.t_ns, topic, out)]:
                    w.write(tp, m, t_ns)
        scenario = yaml.safe_dump(synthetic_scenario(ticks, sensors, width, height), sort_keys=False).encode()
        w.add_attachment("scenario.yaml", "application/yaml", scenario)
        w.add_attachment("map.net.xml", "application/xml", world.net_xml)
        w.add_attachment("routes.rou.xml", "application/xml", world.routes_xml)
        wire = {k: v for k, v in world.to_wire().items() if k not in ("net_xml", "routes_xml")}
        w.add_attachment("world.json", "application/json", json.dumps(wire).encode())
        return w.finish()
