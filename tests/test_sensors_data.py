"""Sensor data as stored: depth beyond 65 m, ground past the map's edge, compact LiDAR records, BEV switch."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import zstandard
from cosim.sensors import SensorSuite
from cosim.sensors.lidar import beam_pattern
from cosim.sensors.meshes import FAR_GROUND_M
from cosim.sensors.rig import sensor_pose
from cosim.sensors.synthetic import synthetic_scenario, synthetic_world

from cosim.geometry import quat_from_rpy
from cosim.io.decode import decode_compressed_image, decode_point_cloud
from cosim.io.points import POSITION_QUANTUM_M, encode_points
from cosim.io.sensor_messages import frame_messages
from cosim.scenario.loader import load_scenario
from cosim.scenario.model import HoverDrone, Scenario, SensorsSpec
from cosim.snapshot import AgentState, WorldSnapshot
from cosim.world.build import build_world

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted((REPO / "scenarios").glob("*.yaml"))


def _drone_scenario(**sensors) -> Scenario:
    return synthetic_scenario(vehicles=0, drones=[HoverDrone()],
                              sensors=SensorsSpec(image_scale=0.1, **sensors))


def _drone(x: float, y: float, z: float, yaw_rad: float = 0.3) -> AgentState:
    q = quat_from_rpy(0.0, 0.0, yaw_rad)
    return AgentState("drone_0", "drone", (x, y, z), q, gimbal_rotation=q)


# ------------------------------------------------------------------------------- depth (item 1)


def test_nadir_depth_at_120_m_survives_the_round_trip():
    """A nadir camera 120 m up: every ground pixel keeps its depth through the stored image (16-bit
    millimetres saturated at 65.535 m and came back as 'no hit')."""
    sc = _drone_scenario()
    snap = WorldSnapshot(0, 0, (), (_drone(-60.0, -100.0, 120.0),))
    with SensorSuite(sc, synthetic_world(), noise=False, encode_images=False) as suite:
        frames = suite.render(snap, np.random.default_rng(0))
    cam = frames.agents["drone_0"].cameras["down"]
    msgs = dict(frame_messages(frames, 0))
    depth_m = decode_compressed_image(msgs["/drone_0/down/depth"]).depth_m
    assert np.isfinite(cam.depth).all() and not np.isnan(depth_m).any()
    assert np.max(np.abs(depth_m - cam.depth)) <= 2.0**-11  # half of the 1/1024 m grid
    # flat terrain (top z = 0) below the 0.15 m camera offset: planar depth = 119.85 m everywhere
    ground = cam.semantic == 6
    assert ground.mean() > 0.5
    assert depth_m[ground] == pytest.approx(120.0 - 0.15, abs=0.002)


# ------------------------------------------------------------------------- far ground (item 2)

_WORLDS: dict[tuple, object] = {}


def _world(loaded):
    sc = loaded.scenario
    key = (sc.map.model_dump_json(), sc.seed, sc.agents.rsus.model_dump_json())
    if key not in _WORLDS:
        with tempfile.TemporaryDirectory() as tmp:
            _WORLDS[key] = build_world(loaded, Path(tmp))
    return _WORLDS[key]


#: [m] probe drones fly this high: above every shipped drone altitude (40-80 m), at the LiDAR's range.
PROBE_ALTITUDE_M = 120.0


def _probes(world) -> WorldSnapshot:
    """At the map's four corners, 2 m inside, facing outward (diagonally): a vehicle rig on the ground,
    an RSU rig 10 m up and a drone rig :data:`PROBE_ALTITUDE_M` up."""
    x0, y0, x1, y1 = world.bounds_m
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    agents = []
    spots = [(x, y) for x in (x0 + 2, x1 - 2) for y in (y0 + 2, y1 - 2)]
    for i, (x, y) in enumerate(spots):
        q = quat_from_rpy(0.0, 0.0, math.atan2(y - cy, x - cx))
        agents.append(AgentState(f"vehicle_{i}", "vehicle", (x, y, 0.0), q))
        agents.append(AgentState(f"rsu_{i}", "rsu", (x, y, 10.0), q))
        agents.append(AgentState(f"drone_{i}", "drone", (x, y, PROBE_ALTITUDE_M), q, gimbal_rotation=q))
    return WorldSnapshot(0, 0, (), tuple(agents))


def _ground_z(world) -> float:
    return max(p.z1_m for p in world.layout.prisms if p.cls == "terrain")


_VOIDS: dict[str, list[str]] = {}


@pytest.mark.integration  # builds every shipped world with SUMO's netgenerate/netconvert
@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_no_void_below_the_horizon_in_shipped_worlds(path):
    """Cameras at the map's edge see ground (never class 0) wherever their ray meets the ground plane
    within the far ground's reach; every LiDAR beam that meets the ground within range returns.
    Scenarios with the same world and rigs share one render (noise off: weather changes nothing here)."""
    loaded = load_scenario(path)
    sc = loaded.scenario
    sensors = sc.sensors.model_copy(update={"image_scale": 0.1, "bev": False})
    key = f"{sc.map.model_dump_json()} {sc.seed} {sc.agents.rsus.model_dump_json()} {sensors.model_dump_json()}"
    if key not in _VOIDS:
        _VOIDS[key] = _voids(_world(loaded), sc.model_copy(update={"sensors": sensors}))
    assert _VOIDS[key] == []


def _voids(world, sc: Scenario) -> list[str]:
    snap = _probes(world)
    z_ground = _ground_z(world)
    with SensorSuite(sc, world, noise=False, encode_images=False) as suite:
        frames = suite.render(snap, np.random.default_rng(0))
        rigs = {a.agent_id: suite.rig(a) for a in snap.agents}
    out: list[str] = []
    n_checked = 0
    for agent in snap.agents:
        af = frames.agents[agent.agent_id]
        for name, cam in af.cameras.items():
            h, w = cam.semantic.shape
            xs = (np.arange(w) + 0.5 - cam.K[0, 2]) / cam.K[0, 0]
            ys = (np.arange(h) + 0.5 - cam.K[1, 2]) / cam.K[1, 1]
            rays = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.ones((h, 1))), -1)
            d = rays @ cam.pose.rotation.T
            with np.errstate(divide="ignore"):
                t = (z_ground - cam.pose.position_m[2]) / d[..., 2]
            reach = np.where(d[..., 2] < 0, t * np.hypot(d[..., 0], d[..., 1]), np.inf)
            below = reach < 0.9 * FAR_GROUND_M
            empty = int((below & ((cam.semantic == 0) | ~np.isfinite(cam.depth))).sum())
            if empty:
                out.append(f"{agent.agent_id} {name}: {empty} of {int(below.sum())} pixels below the horizon void")
            n_checked += int(below.sum())
        spec = rigs[agent.agent_id].lidar
        if spec is None:
            continue
        d_sensor, _ = beam_pattern(spec)
        pose = sensor_pose(agent, spec.mount)
        dz = d_sensor @ pose.rotation[2]
        with np.errstate(divide="ignore"):
            t = (z_ground - pose.position_m[2]) / dz
        expect = (dz < 0) & (t < spec.range_m - 1.0)
        n_az = round(360.0 / spec.horizontal_resolution_deg)
        pts = af.lidar.points
        az = np.round(np.arctan2(pts[:, 1], pts[:, 0]) / (2 * math.pi / n_az)).astype(int) % n_az
        got = np.zeros(len(d_sensor), bool)
        got[af.lidar.ring.astype(int) * n_az + az] = True
        missing = int((expect & ~got).sum())
        if missing:
            out.append(f"{agent.agent_id}: {missing} of {int(expect.sum())} downward LiDAR beams empty")
    if n_checked < 10_000:
        out.append(f"only {n_checked} pixels checked")
    return out


# -------------------------------------------------------------------- compact LiDAR (item 6)


def _sweep(seed: int = 0, n_az: int = 1024, channels: int = 64):
    """A plausible sweep: a 1.9 m high LiDAR over flat ground with walls at 15-60 m, 2 cm range noise."""
    rng = np.random.default_rng(seed)
    el = np.radians(np.linspace(-25.0, 10.0, channels))[:, None]
    az = np.linspace(0, 2 * np.pi, n_az, endpoint=False)[None, :]
    wall = 15.0 + 45.0 * (0.5 + 0.5 * np.sin(3 * az))
    r_ground = np.where(el < 0, 1.9 / np.maximum(np.sin(-el), 1e-6), np.inf)
    r = np.minimum(r_ground, wall / np.cos(el)) + rng.normal(0, 0.02, (channels, n_az))
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)
    xyz = (d * r[..., None]).reshape(-1, 3)
    n = len(xyz)
    inten = np.clip(0.3 * np.cos(el) * np.ones_like(az) + rng.normal(0, 0.02, (channels, n_az)), 0, 1).ravel()
    ring = np.repeat(np.arange(channels), n_az)
    cls = np.where(np.broadcast_to(r_ground < wall / np.cos(el), r.shape).ravel(), 1, 4).astype(np.uint8)
    inst = np.where(cls == 4, 1_000_000 + (np.arange(n) // 3000), 0).astype(np.uint32)
    return xyz, inten, ring, cls, inst


def _zstd_size(data: bytes) -> int:
    return len(zstandard.compress(data))


def test_compact_points_halve_the_stored_bytes_and_keep_the_data():
    xyz, inten, ring, cls, inst = _sweep()
    old = np.zeros(len(xyz), np.dtype({"names": ["x", "y", "z", "intensity", "ring", "class_id", "instance_id"],
                                        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "u1", "<u4"],
                                        "offsets": [0, 4, 8, 12, 16, 18, 20], "itemsize": 24}))
    for k, name in enumerate("xyz"):
        old[name] = xyz[:, k]
    old["intensity"], old["ring"], old["class_id"], old["instance_id"] = inten, ring, cls, inst
    new = encode_points(xyz, inten, ring, cls, inst, kind="quantized")
    assert new.dtype.itemsize == 13 and new["x"].dtype == np.int16
    assert _zstd_size(new.tobytes()) <= 0.5 * _zstd_size(old.tobytes())
    # positions within half a count, intensity within half a step, labels exact
    from cosim.io.sensor_messages import lidar_message

    frame = type("F", (), {"points": xyz.astype(np.float32), "intensity": inten.astype(np.float32), "ring": ring,
                           "class_id": cls, "instance_id": inst})()
    pc = decode_point_cloud(lidar_message("vehicle_0", frame, 0, positions="quantized"))
    assert np.max(np.abs(pc.xyz - xyz)) <= POSITION_QUANTUM_M / 2 + 1e-4
    assert np.max(np.abs(pc.points["intensity"] - inten)) <= 0.5 / 255 + 1e-6
    for k in ("ring", "class_id", "instance_id"):
        assert np.array_equal(pc.points[k], {"ring": ring, "class_id": cls, "instance_id": inst}[k])
    # beyond the int16 reach, positions widen to int32; float32 by default (viewers)
    far = encode_points(xyz * 3.0, inten, ring, cls, inst, kind="quantized")
    assert far["x"].dtype == np.int32
    assert np.max(np.abs(far["x"] * POSITION_QUANTUM_M - xyz[:, 0] * 3.0)) <= POSITION_QUANTUM_M / 2 + 1e-4
    floats = decode_point_cloud(lidar_message("vehicle_0", frame, 0))
    assert floats.stored["x"].dtype == np.float32 and np.max(np.abs(floats.xyz - frame.points)) <= 2.0**-8 + 1e-6


def test_bev_grids_are_optional():
    snap = WorldSnapshot(0, 0, (), (_drone(0.0, 0.0, 40.0),))
    for bev in (True, False):
        with SensorSuite(_drone_scenario(bev=bev), synthetic_world(), noise=False, encode_images=False) as suite:
            topics = {t for t, _ in frame_messages(suite.render(snap, np.random.default_rng(0)), 0)}
        assert ("/drone_0/bev" in topics) == bev and "/drone_0/lidar" in topics
