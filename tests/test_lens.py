"""Lens distortion (Brown-Conrady, ``plumb_bob``) kept consistent from the renderer to every consumer:
the calibration's projection (``cosim.geometry.project_to_image``), the label agreement of distorted
images, the box drawing of ``cosim render``, and the exports, which resample distorted images onto
the pinhole ``K`` they write (docs/exports.md)."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import yaml
from cosim.exporters.undistort import pinhole_remap
from cosim.sensors import SensorSuite
from cosim.sensors.camera import pixel_grid
from cosim.sensors.rig import intrinsics
from cosim.sensors.synthetic import synthetic_scenario, synthetic_snapshot, synthetic_world
from PIL import Image

from cosim.errors import FormatError
from cosim.geometry import distort, project_to_image, rotation_matrix, undistort
from cosim.io import open_episode
from cosim.io.decode import decode_calibration, parse_proto
from cosim.io.sensor_messages import calibration_message
from cosim.scenario.model import (
    CameraSpec,
    Mount,
    RigSpec,
    SensorsSpec,
    default_rsu_rig,
    default_vehicle_rig,
)
from cosim.snapshot import AgentState, WorldSnapshot
from cosim.world.types import Prism, StaticLayout, World
from tests.helpers import convex_hull as _convex_hull
from tests.helpers import run_cli
from tests.helpers import signed_dist_inside as _signed_dist_inside

#: A strong barrel lens, monotonic over a 90 deg field (k2 > 0 keeps r (1 + k1 r^2 + k2 r^4) rising):
#: it moves the corners of a 4:3 image by about 60 px at 480 px width.
LENS = (-0.25, 0.06, 0.001, -0.002, 0.0)
FOV_DEG = 90.0


def _calibration(frame):
    """The /calibration message of a rendered camera frame, decoded as a reader sees it."""
    return decode_calibration(calibration_message("cam/optical", frame, 0))


# ----------------------------------------------------------------------------------- projection


def test_projection_sends_the_renderers_pixel_rays_back_to_their_pixel_centres():
    cam = CameraSpec(name="c", width=64, height=48, fov_deg=FOV_DEG, distortion=LENS)
    K = intrinsics(cam)
    x, y = pixel_grid(cam, K)  # the rays the renderer casts, one per pixel centre
    rays = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1) * 7.5
    uv, front = project_to_image(rays, K, LENS)
    col, row = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
    assert front.all()
    assert np.abs(uv - np.stack([col.ravel(), row.ravel()], axis=1)).max() < 1e-6
    pin, _ = project_to_image(rays, K, None)
    assert np.abs(pin - uv).max() > 10  # the lens matters: a pinhole projection misses by pixels
    xy = np.random.default_rng(0).uniform(-0.9, 0.9, (100, 2))
    assert np.allclose(undistort(distort(xy, LENS), LENS), xy, atol=1e-9)
    assert project_to_image(np.array([[0.0, 0.0, -1.0]]), K, LENS)[1].tolist() == [False]
    with pytest.raises(ValueError, match="5 plumb_bob"):
        project_to_image(rays[:1], K, (0.1, 0.0, 0.0, 0.0))


def test_calibration_carries_the_lens_and_projects_through_it():
    frame = _render_block(LENS)[0]
    cal = _calibration(frame)
    assert cal.distortion_model == "plumb_bob" and tuple(cal.D) == LENS and cal.distorted
    p = np.array([[1.0, -0.5, 3.0], [0.2, 0.1, 10.0]])
    assert np.array_equal(cal.project(p)[0], project_to_image(p, cal.K, LENS)[0])
    odd = type(cal)(**{**cal.__dict__, "distortion_model": "equidistant"})
    with pytest.raises(FormatError, match="equidistant"):
        odd.project(p)
    assert not _calibration(_render_block(None)[0]).distorted


# ----------------------------------------------------------------------------------- a known point


def _render_block(lens, noise: bool = False):
    """A 0.5 m block near the corner of the view of a 480 x 360, 90 deg camera: (frame, block centre)."""
    centre = np.array([12.0, 6.5, 4.5])
    half = 0.25
    foot = tuple((float(centre[0] + dx), float(centre[1] + dy)) for dx, dy in
                 ((-half, -half), (half, -half), (half, half), (-half, half)))
    prisms = (Prism("terrain", ((-300, -300), (300, -300), (300, 300), (-300, 300)), -1.0, 0.0),
              Prism("pole", foot, centre[2] - half, centre[2] + half, 1_000_005))
    world = World("synthetic", b"", b"", (-300, -300, 300, 300), (), (), StaticLayout(prisms), (37.0, -122.0, 10.0))
    cam = CameraSpec(name="front", width=480, height=360, fov_deg=FOV_DEG, distortion=lens,
                     mount=Mount(xyz_m=(0.0, 0.0, 1.6)))
    sc = synthetic_scenario(sensors=SensorsSpec(vehicle=RigSpec(lidar=None, cameras=[cam], gnss=None, imu=None)))
    ego = AgentState("vehicle_0", "vehicle", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    with SensorSuite(sc, world, noise=noise, encode_images=False) as suite:
        frames = suite.render(WorldSnapshot(0, 0, (), (ego,)), np.random.default_rng(0))
    return frames.agents["vehicle_0"].cameras["front"], centre


def test_undistorted_images_put_a_known_point_where_the_pinhole_K_projects_it():
    """The export's resampling (exporters/undistort.py) of a distorted camera's instance image: the block's
    pixels are centred where the pinhole K projects its centre (0.5 px), and they cover the block as a
    pinhole camera renders it; the recorded (distorted) image does not (the lens moved it by pixels)."""
    lensed, centre = _render_block(LENS)
    pinhole, _ = _render_block(None)
    cal = _calibration(lensed)
    remap = pinhole_remap(cal.width, cal.height, cal.K, cal.D)
    assert remap is not None and pinhole_remap(cal.width, cal.height, cal.K, np.zeros(5)) is None
    exported = remap.nearest_of(lensed.instance, 0)
    uv, front = project_to_image(lensed.pose.to_frame(centre[None]), cal.K)  # the pinhole K alone
    assert front[0]

    def centroid(mask):
        v, u = np.nonzero(mask)
        assert len(u) > 50
        return np.array([u.mean() + 0.5, v.mean() + 0.5])

    assert np.linalg.norm(centroid(exported == 1_000_005) - uv[0]) <= 0.5
    assert np.linalg.norm(centroid(lensed.instance == 1_000_005) - uv[0]) > 10
    a, b = exported == 1_000_005, pinhole.instance == 1_000_005
    assert (a & b).sum() / (a | b).sum() > 0.85  # the same silhouette as the pinhole camera's
    # RGB, depth and semantic take the same resampling
    rgb = remap.bilinear(lensed.rgb)
    assert rgb.shape == lensed.rgb.shape and rgb.dtype == np.uint8
    assert np.abs(rgb[b].astype(int) - pinhole.rgb[b].astype(int)).mean() < 12
    depth = remap.nearest_of(lensed.depth, np.nan)
    assert np.nanmax(np.abs(depth[a & b] - pinhole.depth[a & b])) < 0.3


# ----------------------------------------------------------------------------------- label agreement


def _hull(pts: np.ndarray) -> np.ndarray:
    """Convex hull (CCW) of 2D points, through tests/test_sensors.py's (on Python floats: faster)."""
    return _convex_hull(np.unique(np.round(pts, 9), axis=0).tolist())


def _box_edge_points(actor, n: int = 48) -> np.ndarray:
    """Points (12 n, 3) along the 12 edges of an actor's box [m, map]."""
    sgn = np.array([[i, j, k] for i in (-.5, .5) for j in (-.5, .5) for k in (-.5, .5)])
    corners = sgn * np.asarray(actor.size_m) @ rotation_matrix(actor.rotation).T + np.asarray(actor.center_m)
    edges = [(i, j) for i in range(8) for j in range(i + 1, 8) if np.count_nonzero(sgn[i] != sgn[j]) == 1]
    f = np.linspace(0.0, 1.0, n)[:, None]
    return np.concatenate([corners[i] + f * (corners[j] - corners[i]) for i, j in edges])


def test_instance_pixels_of_a_distorted_camera_lie_in_boxes_projected_through_the_lens():
    """The label-agreement check of tests/test_sensors.py on barrel-distorted cameras with shot and read
    noise and vignetting: every instance pixel lies inside the hull of its box's edges projected through
    the calibration (K and D); projected with K alone (a pinhole), boxes near the image edges miss their
    pixels, so the check does see the lens."""
    def rig(base):
        cams = [CameraSpec(name=c.name, width=256, height=192, fov_deg=FOV_DEG, mount=c.mount, distortion=LENS,
                           read_noise=0.002, shot_noise=0.0002, vignetting=0.25) for c in base.cameras]
        return RigSpec(lidar=None, cameras=cams, gnss=None, imu=None)

    sc = synthetic_scenario(vehicles=5, rsus=5,
                            sensors=SensorsSpec(vehicle=rig(default_vehicle_rig()), rsu=rig(default_rsu_rig())))
    snap = synthetic_snapshot(5, 5, 0)
    with SensorSuite(sc, synthetic_world(), noise=True) as suite:
        frames = suite.render(snap, np.random.default_rng(0))
    checked, pinhole_misses = 0, 0
    for agent in snap.agents:
        for name, frame in frames.agents[agent.agent_id].cameras.items():
            cal = _calibration(frame)
            assert cal.distorted
            noisy = frame.rgb.astype(int)
            assert noisy.std() > 0
            for actor in snap.actors:
                if actor.agent_id == agent.agent_id:
                    continue
                vv, uu = np.nonzero(frame.instance == actor.track_id)
                if len(vv) < 20:
                    continue
                p = frame.pose.to_frame(_box_edge_points(actor))
                if np.any(p[:, 2] < 0.5):
                    continue
                uv, _ = cal.project(p)
                if np.any(uv < 0) or np.any(uv[:, 0] > cal.width) or np.any(uv[:, 1] > cal.height):
                    continue  # partly out of the picture: its hull is not the box's outline
                centres = np.stack([uu + 0.5, vv + 0.5], axis=1)
                d = _signed_dist_inside(_hull(uv), centres)
                assert np.all(d >= -1.5), f"{actor.track_id} pixels outside its box in {agent.agent_id}/{name}"
                checked += 1
                pin, _ = project_to_image(p, cal.K)
                if np.mean(_signed_dist_inside(_hull(pin), centres) < -1.5) > 0.2:
                    pinhole_misses += 1
    assert checked >= 50
    assert pinhole_misses >= 20


# ----------------------------------------------------------------------------------- cosim render


def test_render_draws_box_edges_through_the_lens():
    from cosim.io.render import LENS_EDGE_PIECES, project_box_edges

    cam = CameraSpec(name="c", width=320, height=240, fov_deg=FOV_DEG, distortion=LENS)
    K = intrinsics(cam)
    corners = np.array([[[x, y, z] for z in (6.0, 9.0) for y in (-2.0, 1.0) for x in (1.0, 3.0)]])  # optical
    pin = project_box_edges(corners, np.eye(4), K)
    lens = project_box_edges(corners, np.eye(4), K, LENS, (320, 240))
    assert pin.shape == (1, 12, 2, 2) and lens.shape == (1, 12 * LENS_EDGE_PIECES, 2, 2)
    pieces = lens.reshape(12, LENS_EDGE_PIECES, 2, 2)
    assert np.array_equal(pieces[:, 1:, 0], pieces[:, :-1, 1])  # each edge one connected curve
    ends = np.stack([pieces[:, 0, 0], pieces[:, -1, 1]], axis=1)  # its ends are the corners through the lens
    corner_uv, _ = project_to_image(corners[0], K, LENS)
    assert np.allclose(np.sort(ends.reshape(-1, 2), axis=0), np.sort(np.repeat(corner_uv, 3, axis=0), axis=0))
    mid = pieces[:, LENS_EDGE_PIECES // 2, 0]
    assert np.abs(mid - (ends[:, 0] + ends[:, 1]) / 2).max() > 1  # and the edges bend


# ----------------------------------------------------------------------------------- exports


@pytest.fixture(scope="module")
def lens_episode(tmp_path_factory) -> Path:
    """A real 1 s PNG episode: 3 vehicles whose six cameras have a strong lens, 1 RSU with pinhole cameras."""
    from cosim.scenario import load_scenario

    d = tmp_path_factory.mktemp("lens_episode")
    # PNG: the export keeps a pinhole camera's recorded image bytes, which this test compares.
    sc = load_scenario("default", ["duration_s=1", "sensors.image_scale=0.15", "map.size_m=300",
                                   "output.image_format=png"]).scenario
    doc = sc.model_dump(mode="json")
    doc["agents"]["vehicles"]["count"] = 3
    doc["agents"]["rsus"]["count"] = 1
    doc["agents"]["drones"] = []
    for kind in ("vehicle", "rsu"):
        doc["sensors"][kind]["lidar"] = None
    for cam in doc["sensors"]["vehicle"]["cameras"]:
        cam.update(distortion=list(LENS), fov_deg=FOV_DEG)
    (d / "scenario.yaml").write_text(yaml.safe_dump(doc))
    r = run_cli("run", str(d / "scenario.yaml"), "--out", str(d), "-q")
    assert r.returncode == 0, r.stderr
    return next(d.glob("*.mcap"))


def _x_to_world(pose) -> np.ndarray:
    """docs/exports.md: a six-number CARLA pose as the loaders build it, Rz(yaw) Ry(-pitch) Rx(-roll)."""
    x, y, z = pose[:3]
    roll, yaw, pitch = np.radians(pose[3:6])
    cy, sy, cr, sr, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    m = np.eye(4)
    m[:3, :3] = [[cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
                 [sp, -cp * sr, cp * cr]]
    m[:3, 3] = (x, y, z)
    return m


def _carla_corners(obj) -> np.ndarray:
    loc, cen = obj["location"], obj["center"]
    pose = [loc[0] + cen[0], loc[1] + cen[1], loc[2] + cen[2], *loc[3:6]]
    hl, hw, hh = obj["extent"]
    c = np.array([[sx * hl, sy * hw, sz * hh, 1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return (_x_to_world(pose) @ c.T).T[:, :3]


def _rgb24(a: np.ndarray) -> np.ndarray:
    a = a.astype(np.int64)
    return a[..., 0] + 256 * a[..., 1] + 65536 * a[..., 2]


@pytest.mark.integration  # lens_episode is a real `cosim run`
def test_export_of_a_distorted_camera_is_exact_for_its_pinhole_intrinsic(lens_episode, tmp_path):
    """AirV2X export (masks on) read the devkit's way: each box projected with the exported ``intrinsic`` and
    poses holds its exported instance pixels; the recorded distorted masks would not fit (so the export did
    undistort); pinhole cameras (the RSU's) keep the episode's image bytes; OPV2V writes the same images."""
    from cosim.exporters.export import ExportOptions, run_export

    run_export(lens_episode, "airv2x", tmp_path / "a", ExportOptions(masks=True))
    run_export(lens_episode, "opv2v", tmp_path / "o")
    seq = next((tmp_path / "a" / "train").iterdir())
    oseq = next((tmp_path / "o" / "train").iterdir())
    numbers = json.loads((seq / "conditions.json").read_text())["agent_numbers"]
    folders = yaml.safe_load((oseq / "data_protocol.yaml").read_text())["agent_folders"]
    tested = raw_misses = pinhole_same = opv2v_same = 0
    with open_episode(lens_episode) as ep:
        for stamp in sorted(p for p in seq.iterdir() if p.is_dir()):
            tick = ep.tick(int(stamp.name.split("_")[1]))
            table = pickle.loads((stamp / "objects.pkl").read_bytes())
            for agent, number in numbers.items():
                f = stamp / f"agent_{number:06d}"
                meta = pickle.loads((f / "metadata.pkl").read_bytes())
                ego = meta["odometry"]["ego_pos"]
                for key, entry in meta.items():
                    if "camera" not in key:
                        continue
                    cosim_name = {"front_camera": "front", "back_camera": "rear", "left_camera": "left",
                                  "right_camera": "right"}.get(key, key.removesuffix("_camera"))
                    cal = tick.calibration(agent, cosim_name)
                    assert np.array_equal(np.asarray(entry["intrinsic"]), cal.K)  # K is written as recorded
                    png = (f / f"{key}.png").read_bytes()
                    undone = meta["cosim"].get("undistorted", {}).get(cosim_name)
                    assert undone == (list(LENS) if cal.distorted else None)
                    if not cal.distorted:
                        raw = tick.raw(f"/{agent}/{cosim_name}/image")
                        assert parse_proto(raw.schema_name, raw.data, raw.schema_data).data == png  # unchanged
                        pinhole_same += 1
                        continue
                    if agent.startswith("vehicle") and cosim_name == "front":
                        assert (oseq / folders[agent] / f"{tick.index:06d}_camera0.png").read_bytes() == png
                        opv2v_same += 1
                    base = key.removesuffix("_camera")
                    inst = _rgb24(np.asarray(Image.open(f / f"{base}_instance.png").convert("RGB")))
                    recorded = tick.instance(agent, cosim_name).array
                    world_to_cam = np.linalg.inv(_x_to_world([a + b for a, b in zip(entry["cords"], ego, strict=True)]))
                    K = np.asarray(entry["intrinsic"])
                    for track in np.unique(inst[(inst > 0) & (inst < 1_000_000)]):
                        rows, cols = np.nonzero(inst == track)
                        if len(rows) < 20 or int(track) not in table:
                            continue
                        c = (world_to_cam @ np.c_[_carla_corners(table[int(track)]), np.ones(8)].T)[:3]
                        if (c[0] < 0.5).any():
                            continue
                        uvw = K @ np.stack([c[1], -c[2], c[0]])  # Unreal camera axes -> OpenCV
                        u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]

                        def inside(r, q, u=u, v=v):
                            return ((q + 0.5 >= u.min() - 1) & (q + 0.5 <= u.max() + 1)
                                    & (r + 0.5 >= v.min() - 1) & (r + 0.5 <= v.max() + 1))

                        assert inside(rows, cols).mean() >= 0.99, (f, key, track)
                        rr, rc = np.nonzero(recorded == track)
                        if inside(rr, rc).mean() < 0.95:
                            raw_misses += 1
                        tested += 1
    assert tested >= 10 and raw_misses >= 2 and pinhole_same >= 4 and opv2v_same >= 3


@pytest.mark.integration  # lens_episode is a real `cosim run`
def test_training_reader_gives_each_cameras_lens(lens_episode):
    from cosim.io.dataset import CooperativeDataset

    far = {"vehicle": 1e6, "rsu": 1e6, "drone": 1e6}
    sample = CooperativeDataset([lens_episode], cameras=True, comm_range_m=far)[0]
    assert len(sample["distortions"]) == len(sample["intrinsics"]) == len(sample["agents"]) == 4
    for agent, lenses, names in zip(sample["agents"], sample["distortions"], sample["camera_names"], strict=True):
        assert lenses.shape == (len(names), 5) and len(names) > 0
        expected = np.array(LENS) if agent.startswith("vehicle") else np.zeros(5)
        assert (lenses == expected).all(), (agent, lenses)


def test_a_lens_the_renderer_cannot_invert_is_a_scenario_error_naming_the_camera(tmp_path):
    from cosim.errors import ScenarioError
    from cosim.scenario import load_scenario

    f = tmp_path / "lens.yaml"
    f.write_text("name: t\nsensors:\n  vehicle:\n    cameras:\n      - name: front\n        fov_deg: 110\n"
                 "        distortion: [-0.1, 0, 0, 0, 0]\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(f)
    assert err.value.path == "sensors.vehicle.cameras" and err.value.line == 4
    assert "'front'" in str(err.value) and "one to one" in str(err.value)
    f.write_text(f.read_text().replace("110", "90").replace("-0.1, 0, 0, 0, 0", ", ".join(map(str, LENS))))
    assert load_scenario(f).scenario.sensors.vehicle.cameras[0].distortion == LENS


# ---------------------------------------------------------------------- the calibration of a distorted camera


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
