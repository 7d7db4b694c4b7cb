"""``cosim export`` on a real full-rig episode, read back by a format reader written from docs/exports.md.

The reader below (``x_to_world``, box corners, the PCD via Open3D as ``pcd_to_np`` reads it, the devkit's
map stacking) follows the document and the loaders' documented behaviour, not the exporter's code: it
imports nothing from ``cosim.exporters``.
"""

from __future__ import annotations

import json
import math
import pickle
import shutil
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import yaml
from PIL import Image

from cosim.io import open_episode
from tests.helpers import REPO, run_cli

pytestmark = pytest.mark.integration

# ---------------------------------------------------------------- the format, as docs/exports.md states it

AIRV2X_CLASS = {"pedestrian": 0, "bicycle": 1, "motorcycle": 2, "car": 3, "van": 4, "truck": 5, "bus": 6}
ROAD_USERS = ("car", "van", "truck", "bus", "motorcycle", "bicycle")
DEVKIT_CAMERAS = {
    "vehicle": ["front_camera", "front_left_camera", "front_right_camera", "rear_camera", "rear_left_camera",
                "rear_right_camera"],
    "rsu": ["back_camera", "front_camera", "left_camera", "right_camera"],
    "drone": ["bev_camera"],
}


def x_to_world(pose) -> np.ndarray:
    """docs/exports.md: translation (x, y, z), rotation Rz(yaw) Ry(-pitch) Rx(-roll), degrees."""
    x, y, z, roll, yaw, pitch = (math.radians(v) if i > 2 else v for i, v in enumerate(pose))

    def rz(a):
        return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])

    def ry(a):
        return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])

    def rx(a):
        return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])

    m = np.eye(4)
    m[:3, :3] = rz(yaw) @ ry(-pitch) @ rx(-roll)
    m[:3, 3] = (x, y, z)
    return m


def add_poses(rel, agent):
    """The devkit's composition: number by number."""
    return [a + b for a, b in zip(rel, agent, strict=True)]


def box_pose(obj) -> list[float]:
    loc, cen = obj["location"], obj["center"]
    angles = obj["location"][3:6] if len(loc) == 6 else obj["angle"]
    return [loc[0] + cen[0], loc[1] + cen[1], loc[2] + cen[2], *angles]


def box_corners(obj) -> np.ndarray:
    hl, hw, hh = obj["extent"]
    c = np.array([[sx * hl, sy * hw, sz * hh, 1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return (x_to_world(box_pose(obj)) @ c.T).T[:, :3]


def inside_box(obj, world_xyz: np.ndarray, margin_m: float) -> np.ndarray:
    local = (np.linalg.inv(x_to_world(box_pose(obj))) @ np.c_[world_xyz, np.ones(len(world_xyz))].T).T[:, :3]
    return (np.abs(local) <= np.asarray(obj["extent"]) + margin_m).all(axis=1)


def read_pcd(path: Path) -> np.ndarray:
    """As ``pcd_to_np`` does: Open3D points and the red channel as intensity, (N, 4)."""
    pcd = o3d.io.read_point_cloud(str(path))
    return np.hstack([np.asarray(pcd.points), np.asarray(pcd.colors)[:, :1]])


def rgb24(path: Path) -> np.ndarray:
    a = np.asarray(Image.open(path).convert("RGB")).astype(np.int64)
    return a[..., 0] + 256 * a[..., 1] + 65536 * a[..., 2]


def devkit_label_map(paths: list[Path]) -> np.ndarray:
    """``_wrap_segmentation_map``: threshold > 10, stack (later wins), transpose, flip the second axis."""
    label = None
    for k, p in enumerate(paths):
        m = np.asarray(Image.open(p).convert("L")) > 10
        label = np.zeros(m.shape, np.uint8) if label is None else label
        label[m] = k
    return label.T[:, ::-1]


def load_yaml(path: Path):
    """``yaml.safe_load`` semantics (the C loader when PyYAML has it: same result, faster)."""
    return yaml.load(path.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def tick_extras(seq: Path, tick: int) -> dict:
    """docs/exports.md: the tick's ``<tick>_cosim.json`` beside the agent folders, with its track ids as ints."""
    doc = json.loads((seq / f"{tick:06d}_cosim.json").read_text())
    doc["objects"] = {int(t): o for t, o in doc["objects"].items()}
    for extra in doc["agents"].values():
        extra["lidar_points"] = {int(t): n for t, n in extra["lidar_points"].items()}
    return doc


def wrap_deg(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def assert_boxes_match(table: dict, objs) -> None:
    """Every labelled box is in ``table`` (track id -> exported box) with its centre, size and yaw (1 cm, 0.1 deg)."""
    assert sorted(table) == sorted(int(t) for t in objs.track_ids)  # every object kept
    for i, track in enumerate(objs.track_ids):
        pose = box_pose(table[int(track)])
        cx, cy, cz = objs.centers_m[i]
        assert np.allclose(pose[:3], [cx, -cy, cz], atol=0.01)
        assert np.allclose(2 * np.asarray(table[int(track)]["extent"]), objs.sizes_m[i], atol=0.01)
        assert abs(wrap_deg(pose[4] + math.degrees(objs.yaws_rad[i]))) < 0.1


# ---------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def episode(export_episode) -> Path:
    """tests/conftest.py's ``export_episode``: a short full-rig episode with LiDAR noise off."""
    return export_episode


@pytest.fixture(scope="module")
def airv2x(episode, tmp_path_factory) -> Path:
    from cosim.exporters.export import ExportOptions, run_export

    out = tmp_path_factory.mktemp("airv2x_export")
    run_export(episode, "airv2x", out, ExportOptions(masks=True))
    return out


@pytest.fixture(scope="module")
def opv2v(episode, tmp_path_factory) -> Path:
    from cosim.exporters.export import run_export

    out = tmp_path_factory.mktemp("opv2v_export")
    run_export(episode, "opv2v", out, split="val")
    return out


@pytest.fixture(scope="module")
def labels(episode):
    with open_episode(episode) as ep:
        return {t.index: t.labels for t in ep.ticks(topics="/labels/objects")}, ep.agents


def only(folder: Path) -> Path:
    items = [p for p in folder.iterdir() if p.is_dir()]
    assert len(items) == 1, items
    return items[0]


# ------------------------------------------------------------------------------------------------ AirV2X


def test_airv2x_layout_every_agent_every_timestamp(airv2x, labels):
    by_tick, agents = labels
    seq = only(airv2x / "train")
    assert len(seq.name) == 19 and seq.name[:4].isdigit() and seq.name.count("_") == 5
    stamps = sorted(p for p in seq.iterdir() if p.is_dir())
    assert [int(p.name.split("_")[1]) for p in stamps] == sorted(by_tick)
    cond = json.loads((seq / "conditions.json").read_text())
    assert cond["agent_counts"] == {"vehicle": 5, "rsu": 5, "drone": 5}
    assert cond["weather"] == "clear" and len(cond["strategies"]) == 5
    for stamp in stamps:
        folders = sorted(p for p in stamp.iterdir() if p.is_dir())
        assert len(folders) == len(agents)
        for f in folders:
            int(f.name.split("_")[1])
            meta = pickle.loads((f / "metadata.pkl").read_bytes())
            kind = meta["agent_type"]
            names = {p.name for p in f.iterdir()}
            for cam in DEVKIT_CAMERAS[kind]:
                assert f"{cam}.png" in names and f"{cam.removesuffix('_camera')}_depth.png" in names
                assert cam in meta
                with Image.open(f / f"{cam}.png") as im:
                    assert im.mode == "RGB"
            assert [k for k in meta if "camera" in k] == [k for k in meta if k in DEVKIT_CAMERAS[kind]]
            assert "lidar.pcd" in names
            assert sorted(n for n in names if n.startswith("map_")) == sorted(
                [f"map_static_{s}.png" for s in ("background", "lane", "road")]
                + [f"map_dynamic_bev_layer_{k}.png" for k in range(7)])


def test_airv2x_boxes_round_trip_to_the_labels(airv2x, labels):
    by_tick, _ = labels
    seq = only(airv2x / "train")
    for tick, objs in by_tick.items():
        table = pickle.loads((seq / f"timestamp_{tick:06d}" / "objects.pkl").read_bytes())
        assert_boxes_match(table, objs)
        for i, track in enumerate(objs.track_ids):
            assert table[int(track)]["class"] == AIRV2X_CLASS.get(objs.classes[i], 7)
            assert isinstance(table[int(track)]["speed"], float)


def test_airv2x_lidar_points_land_in_their_boxes_through_the_loaders_pose_composition(airv2x):
    """The y-flip trap: points read from the .pcd and moved to the world the devkit's way lie in their box."""
    seq = only(airv2x / "train")
    checked = inside = 0
    for stamp in sorted(p for p in seq.iterdir() if p.is_dir())[1::2]:
        table = pickle.loads((stamp / "objects.pkl").read_bytes())
        for f in sorted(p for p in stamp.iterdir() if p.is_dir()):
            meta = pickle.loads((f / "metadata.pkl").read_bytes())
            pts = read_pcd(f / "lidar.pcd")
            ids = np.load(f / "lidar_labels.npz")["instance_id"]
            assert len(ids) == len(pts) and (pts[:, 3] >= 0).all() and pts[:, 3].max() <= 1
            lidar_world = add_poses(meta["lidar"]["lidar_pose"], meta["odometry"]["ego_pos"])
            world = (x_to_world(lidar_world) @ np.c_[pts[:, :3], np.ones(len(pts))].T).T[:, :3]
            for track in np.unique(ids[(ids > 0) & (ids < 1_000_000)]):
                sel = ids == track
                ok = inside_box(table[int(track)], world[sel], 0.1)
                checked += int(sel.sum())
                inside += int(ok.sum())
    assert checked > 1000
    assert inside >= 0.99 * checked


def test_airv2x_cameras_project_box_corners_onto_their_instance_pixels(airv2x):
    seq = only(airv2x / "train")
    stamp = sorted(p for p in seq.iterdir() if p.is_dir())[2]
    table = pickle.loads((stamp / "objects.pkl").read_bytes())
    tested = 0
    for f in sorted(p for p in stamp.iterdir() if p.is_dir()):
        meta = pickle.loads((f / "metadata.pkl").read_bytes())
        ego = meta["odometry"]["ego_pos"]
        lidar_world = add_poses(meta["lidar"]["lidar_pose"], ego)
        for cam in DEVKIT_CAMERAS[meta["agent_type"]]:
            entry = meta[cam]
            cam_world = add_poses(entry["cords"], ego)
            K = np.asarray(entry["intrinsic"])
            world_to_cam = np.linalg.inv(x_to_world(cam_world))
            # the extrinsic is the same LiDAR -> camera transform the poses give
            assert np.allclose(entry["extrinsic"], world_to_cam @ x_to_world(lidar_world), atol=1e-6)
            inst = rgb24(f / f"{cam.removesuffix('_camera')}_instance.png")
            _h, w = inst.shape
            for track in np.unique(inst[(inst > 0) & (inst < 1_000_000)]):
                rows, cols = np.nonzero(inst == track)
                if len(rows) < 30:
                    continue
                c = (world_to_cam @ np.c_[box_corners(table[int(track)]), np.ones(8)].T)[:3]
                if (c[0] < 0.5).any():
                    continue  # a corner behind the camera: no rectangle to compare
                uvw = K @ np.stack([c[1], -c[2], c[0]])
                u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]
                inside = ((cols + 0.5 >= u.min() - 1) & (cols + 0.5 <= u.max() + 1)
                          & (rows + 0.5 >= v.min() - 1) & (rows + 0.5 <= v.max() + 1))
                assert inside.mean() >= 0.99, (f, cam, track)
                # and the box is where the pixels are, not just somewhere large around them
                assert u.max() - u.min() < 4 * (np.ptp(cols) + 2) + 2 * w / 3
                tested += 1
    assert tested >= 10


def test_airv2x_bev_dynamic_layers_agree_with_boxes_and_lidar(airv2x):
    seq = only(airv2x / "train")
    stamp = sorted(p for p in seq.iterdir() if p.is_dir())[1]
    table = pickle.loads((stamp / "objects.pkl").read_bytes())
    pixels = hits = total = 0
    for f in sorted(p for p in stamp.iterdir() if p.is_dir()):
        meta = pickle.loads((f / "metadata.pkl").read_bytes())
        ego = meta["odometry"]["ego_pos"]
        label = devkit_label_map([f / f"map_dynamic_bev_layer_{k}.png" for k in range(7)])
        static = devkit_label_map([f / f"map_static_{s}.png" for s in ("background", "lane", "road")])
        assert label.shape == (512, 512) and (static > 0).any()
        yaw = math.radians(ego[4])
        a, b = np.nonzero(label)
        y, x = (a + 0.5 - 256) / 4, (b + 0.5 - 256) / 4
        wx = ego[0] + math.cos(yaw) * x - math.sin(yaw) * y
        wy = ego[1] + math.sin(yaw) * x + math.cos(yaw) * y
        for k in range(1, 7):
            sel = label[a, b] == k
            if not sel.any():
                continue
            covered = np.zeros(int(sel.sum()), bool)
            for o in table.values():
                if o["class"] == k:
                    flat = dict(o, location=[*o["location"][:2], 0.0, 0.0, o["location"][4], 0.0],
                                center=[*o["center"][:2], 0.0], extent=[*o["extent"][:2], 1e3])
                    covered |= inside_box(flat, np.c_[wx[sel], wy[sel], np.zeros(sel.sum())], 0.01)
            assert covered.all(), (f, k)
            pixels += int(sel.sum())
        # LiDAR returns of vehicles, moved into the map's frame, fall on their class's pixels
        pts = read_pcd(f / "lidar.pcd")
        ids = np.load(f / "lidar_labels.npz")["instance_id"]
        lidar_world = add_poses(meta["lidar"]["lidar_pose"], ego)
        world = (x_to_world(lidar_world) @ np.c_[pts[:, :3], np.ones(len(pts))].T).T[:, :3]
        dx, dy = world[:, 0] - ego[0], world[:, 1] - ego[1]
        px, py = math.cos(yaw) * dx + math.sin(yaw) * dy, -math.sin(yaw) * dx + math.cos(yaw) * dy
        ia, ib = np.floor(256 + 4 * py).astype(int), np.floor(256 + 4 * px).astype(int)
        for track in np.unique(ids[(ids > 0) & (ids < 1_000_000)]):
            k = table[int(track)]["class"]
            if not 1 <= k <= 6:
                continue
            sel = (ids == track) & (ia >= 1) & (ia < 511) & (ib >= 1) & (ib < 511)
            near = np.zeros(int(sel.sum()), bool)
            for da in (-1, 0, 1):
                for db in (-1, 0, 1):
                    near |= label[ia[sel] + da, ib[sel] + db] == k
            hits += int(near.sum())
            total += int(sel.sum())
    assert pixels > 500
    assert total > 500 and hits >= 0.97 * total


# ------------------------------------------------------------------------------------------------- OPV2V


def test_opv2v_layout_ego_is_a_vehicle_and_files_parse(opv2v, labels):
    by_tick, agents = labels
    seq = only(opv2v / "validate")
    folders = sorted(p.name for p in seq.iterdir() if p.is_dir())
    assert len(folders) == len(agents)
    ints = [int(n) for n in folders]
    assert folders[0].startswith("+") and ints[0] > 0  # the ego after OpenCOOD's sort
    assert sum(1 for i in ints if i < 0) == 5
    protocol = yaml.safe_load((seq / "data_protocol.yaml").read_text())
    assert protocol["conditions"]["agent_counts"]["rsu"] == 5
    for name in folders:
        stems = sorted(p.stem for p in (seq / name).glob("*.yaml"))
        assert stems == [f"{k:06d}" for k in sorted(by_tick)]
        doc = yaml.safe_load((seq / name / f"{stems[0]}.yaml").read_text())
        assert doc["RSU"] == (int(name) < 0)
        if tick_extras(seq, int(stems[0]))["agents"][name]["kind"] in ("vehicle", "rsu"):
            assert all((seq / name / f"{stems[0]}_camera{i}.png").is_file() for i in range(4))
            assert [f"camera{i}" for i in range(4)] == [k for k in doc if k.startswith("camera")]
        assert len(read_pcd(seq / name / f"{stems[0]}.pcd")) > 100
        assert (opv2v / "additional" / "validate" / seq.name / name / f"{stems[0]}_bev_dynamic.png").is_file()


def test_opv2v_boxes_round_trip_and_vehicles_are_the_seen_road_users(opv2v, labels):
    by_tick, _ = labels
    seq = only(opv2v / "validate")
    for name in sorted(p.name for p in seq.iterdir() if p.is_dir()):
        for tick, objs in by_tick.items():
            doc = load_yaml(seq / name / f"{tick:06d}.yaml")
            extras = tick_extras(seq, tick)
            every, agent = extras["objects"], extras["agents"][name]
            assert_boxes_match(every, objs)
            for i, track in enumerate(objs.track_ids):
                assert every[int(track)]["class"] == objs.classes[i]
            seen = {t for t, o in every.items()
                    if o["class"] in ROAD_USERS and agent["lidar_points"].get(t, 0) > 0 and t != agent["track_id"]}
            assert set(doc["vehicles"]) == seen
            for t, v in doc["vehicles"].items():
                assert v == {k: every[t][k] for k in ("location", "center", "angle", "extent", "speed")}


def test_opv2v_points_land_in_their_boxes_with_the_yaml_lidar_pose(opv2v):
    seq = only(opv2v / "validate")
    checked = inside = 0
    for name in sorted(p.name for p in seq.iterdir() if p.is_dir()):
        doc = load_yaml(seq / name / "000002.yaml")
        pts = read_pcd(seq / name / "000002.pcd")
        ids = np.load(seq / name / "000002_lidar_labels.npz")["instance_id"]
        world = (x_to_world(doc["lidar_pose"]) @ np.c_[pts[:, :3], np.ones(len(pts))].T).T[:, :3]
        every = tick_extras(seq, 2)["objects"]
        for track in np.unique(ids[(ids > 0) & (ids < 1_000_000)]):
            sel = ids == track
            inside += int(inside_box(every[int(track)], world[sel], 0.1).sum())
            checked += int(sel.sum())
    # several hundred object points in one tick: the ray-drop model (glass, dark and far surfaces) and the
    # hulls' windows return fewer points than the old boxes did
    assert checked > 500 and inside >= 0.99 * checked, (checked, inside)


#: The keys of an agent's ``<tick>.yaml`` that OpenCOOD reads (docs/exports.md): nothing else goes in it.
OPENCOOD_YAML_KEYS = {"camera0", "camera1", "camera2", "camera3", "ego_speed", "lidar_pose", "plan_trajectory",
                      "predicted_ego_pos", "true_ego_pos", "RSU", "vehicles"}


def test_opv2v_agent_yamls_hold_only_what_opencood_reads_and_the_tick_file_holds_the_objects(opv2v, labels):
    by_tick, agents = labels
    seq = only(opv2v / "validate")
    folders = sorted(p.name for p in seq.iterdir() if p.is_dir())
    assert sorted(p.name for p in seq.glob("*_cosim.json")) == [f"{k:06d}_cosim.json" for k in sorted(by_tick)]
    for tick, objs in by_tick.items():
        extras = tick_extras(seq, tick)
        assert extras["tick"] == tick and sorted(extras["agents"]) == folders
        assert sorted(extras["objects"]) == sorted(int(t) for t in objs.track_ids)
        assert sorted(a["agent_id"] for a in extras["agents"].values()) == sorted(agents)
        for name in folders:
            doc = load_yaml(seq / name / f"{tick:06d}.yaml")
            assert set(doc) <= OPENCOOD_YAML_KEYS, set(doc) - OPENCOOD_YAML_KEYS
            assert set(doc["vehicles"]) <= set(extras["agents"][name]["lidar_points"])


def test_opv2v_export_says_where_opencood_drops_agents_beyond_its_default_max_cav(episode, labels, smeared, tmp_path):
    """15 agents: the summary prints one warning line naming the folders OpenCOOD's default ``max_cav`` (7) drops,
    and ``data_protocol.yaml`` says it too; a 4-agent episode gets no warning."""
    from cosim.exporters.export import ExportOptions, run_export

    n = len(labels[1])
    r = run_cli("export", str(episode), "--format", "opv2v", "--out", str(tmp_path / "full"), "--every", "5")
    assert r.returncode == 0, r.stderr
    warnings = [line for line in r.stdout.splitlines() if line.startswith("warning: ")]
    seq = only(tmp_path / "full" / "train")
    folders = sorted(p.name for p in seq.iterdir() if p.is_dir())
    assert len(warnings) == 1 and seq.name in warnings[0] and "too many cavs" in warnings[0], r.stdout
    assert f"set train_params.max_cav: {n}" in warnings[0]
    assert warnings[0].split("drops ")[1].split(":")[0] == ", ".join(folders[7:])
    opencood = yaml.safe_load((seq / "data_protocol.yaml").read_text())["opencood"]
    assert opencood["agent_folders"] == n and opencood["default_max_cav"] == 7
    assert f"max_cav: {n}" in opencood["note"]
    small = run_export(smeared, "opv2v", tmp_path / "small", ExportOptions(every=5))
    assert small.warnings == ()
    small_note = yaml.safe_load((only(tmp_path / "small" / "train") / "data_protocol.yaml").read_text())["opencood"]
    assert small_note["agent_folders"] < 7 and "within" in small_note["note"]


def test_camera_files_keep_the_episodes_jpeg_or_with_png_images_are_png_of_the_same_pixels(episode, opv2v, airv2x,
                                                                                          tmp_path):
    """The loaders open camera files with Pillow or OpenCV, which decode by content: by default a camera file is
    the episode's JPEG bytes; ``png_images`` writes a PNG of the same pixels."""
    from cosim.exporters.export import ExportOptions, run_export

    from cosim.io.decode import parse_proto

    run_export(episode, "opv2v", tmp_path, ExportOptions(every=5, png_images=True))
    seq, png_seq = only(opv2v / "validate"), only(tmp_path / "train")
    folders = yaml.safe_load((seq / "data_protocol.yaml").read_text())["agent_folders"]
    air = only(airv2x / "train") / "timestamp_000000"
    numbers = json.loads((air.parent / "conditions.json").read_text())["agent_numbers"]
    with open_episode(episode) as ep:
        tick = ep.tick(0)
        for agent, cam, opv2v_name, airv2x_name in (("vehicle_0", "front", "camera0", "front_camera"),
                                                    ("rsu_1", "rear", "camera3", "back_camera"),
                                                    ("drone_0", "down", "down", "bev_camera")):
            raw = tick.raw(f"/{agent}/{cam}/image")
            jpeg = bytes(parse_proto(raw.schema_name, raw.data, raw.schema_data).data)
            assert jpeg[:2] == b"\xff\xd8"
            kept = seq / folders[agent] / f"000000_{opv2v_name}.png"
            assert kept.read_bytes() == jpeg
            assert (air / f"agent_{numbers[agent]:06d}" / f"{airv2x_name}.png").read_bytes() == jpeg
            png = png_seq / folders[agent] / f"000000_{opv2v_name}.png"
            assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
            pixels = np.asarray(Image.open(png))
            assert pixels.ndim == 3 and pixels.shape[2] == 3
            assert np.array_equal(np.asarray(Image.open(kept).convert("RGB")), pixels)
            assert np.array_equal(tick.image(agent, cam).array[..., :3], pixels)


# ------------------------------------------------------------------------------- determinism, options, CLI


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_every_2_halves_the_timestamps(episode, labels, tmp_path):
    from cosim.exporters.export import ExportOptions, run_export

    run_export(episode, "opv2v", tmp_path, ExportOptions(every=2))
    seq = only(tmp_path / "train")
    agent = sorted(p for p in seq.iterdir() if p.is_dir())[0]
    assert sorted(p.stem for p in agent.glob("*.yaml")) == [f"{k:06d}" for k in sorted(labels[0])[::2]]


def test_a_batch_folder_keeps_its_splits(episode, tmp_path):
    from cosim.exporters.export import ExportOptions, run_export

    from cosim.batch.manifest import Manifest
    from cosim.io.manifest import sha256_file

    batch = tmp_path / "batch"
    with Manifest(batch / "manifest.jsonl") as m:
        for split in ("train", "val"):
            (batch / split).mkdir(parents=True)
            shutil.copy(episode, batch / split / f"{split}-0000.mcap")
            f = batch / split / f"{split}-0000.mcap"
            m.append({"episode": f"{split}-0000", "split": split, "file": f"{split}/{f.name}", "status": "done",
                      "sha256": sha256_file(f), "size_bytes": f.stat().st_size})
        m.append({"episode": "test-0000", "split": "test", "file": "test/test-0000.mcap", "status": "failed"})
    out = tmp_path / "out"
    result = run_export(batch, "opv2v", out, ExportOptions(every=5))
    assert len(result.written) == 2
    assert sorted(p.name for p in out.iterdir()) == ["additional", "train", "validate"]
    assert only(out / "train").name == only(out / "validate").name  # same episode bytes, same name


def test_a_crash_leaves_nothing_complete_and_exports_are_identical_resumed_or_parallel(episode, tmp_path,
                                                                                     monkeypatch):
    from cosim.exporters import airv2x as airv2x_module
    from cosim.exporters.export import ExportOptions, run_export

    original = airv2x_module.AirV2XFormat.write_tick

    def crash(self, view):
        if view.index == 4:
            raise OSError("disk full (test)")
        original(self, view)

    resumed = tmp_path / "resumed"
    monkeypatch.setattr(airv2x_module.AirV2XFormat, "write_tick", crash)
    with pytest.raises(OSError):
        run_export(episode, "airv2x", resumed, ExportOptions(every=2))
    assert not (resumed / "train").exists()  # only the hidden partial folder
    monkeypatch.setattr(airv2x_module.AirV2XFormat, "write_tick", original)
    result = run_export(episode, "airv2x", resumed, ExportOptions(every=2))
    seq = only(resumed / "train")
    assert result.written == (seq,) and not (resumed / ".cosim-partial").exists()
    assert len([p for p in seq.iterdir() if p.is_dir()]) == 3

    parallel = tmp_path / "parallel"
    r = run_cli("export", str(episode), "--format", "airv2x", "--out", str(parallel), "--every", "2",
                "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "1 sequence(s) written" in r.stdout
    a, b = _files(resumed), _files(parallel)
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []
    assert "1 skipped" in run_cli("export", str(episode), "--format", "airv2x", "--out", str(parallel),
                                  "--every", "2").stdout


def test_bad_input_is_one_message_and_exit_status_2(episode, tmp_path, capsys):
    from cosim.cli import main

    for args, needle in [
        (["--format", "nuscenes", "--out", str(tmp_path)],
         "unknown export format 'nuscenes'; known: airv2x, kitti, opv2v"),
        (["--format", "airv2x", "--out", str(tmp_path / "2024_01_02_03_04_05")], "date-like"),
        (["--format", "airv2x", "--out", str(tmp_path), "--every", "0"], "--every must be >= 1"),
        (["--format", "opv2v", "--out", str(tmp_path), "--raw-lidar", "--objects-at-tick"],
         "cannot go with --raw-lidar"),
    ]:
        assert main(["export", str(episode), *args]) == 2
        assert needle in capsys.readouterr().err
    assert main(["export", str(tmp_path / "missing.mcap"), "--format", "opv2v", "--out", str(tmp_path)]) == 2
    assert "no episode file or batch folder" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


# --------------------------------------------------------------------------------------- training reader


def test_the_cooperative_dataset_gives_ego_frame_boxes_and_points(episode, labels):
    from cosim.io.dataset import CooperativeDataset

    ds = CooperativeDataset([episode])
    by_tick, _agents = labels
    assert len(ds) == len(by_tick) * 5  # every tick, every vehicle as ego
    s = ds[3]
    assert s["ego"] == s["agents"][0] and s["ego"].startswith("vehicle_")
    assert s["boxes"].shape[1] == 7 and s["boxes"].dtype == np.float32
    lo, hi = np.array(ds.lidar_range_m[:3]), np.array(ds.lidar_range_m[3:])
    assert ((s["boxes"][:, :3] >= lo) & (s["boxes"][:, :3] <= hi)).all()
    # the ego's own LiDAR returns of each box's track lie in that box (ego frame, noise off)
    pts, ids = s["lidar"][0], s["lidar_instance"][0]
    for box, track in zip(s["boxes"], s["track_ids"], strict=True):
        sel = ids == track
        if sel.sum() < 20:
            continue
        x, y, z, length, width, height, yaw = box
        d = pts[sel, :3] - [x, y, z]
        lx = math.cos(yaw) * d[:, 0] + math.sin(yaw) * d[:, 1]
        ly = -math.sin(yaw) * d[:, 0] + math.cos(yaw) * d[:, 1]
        inside = (abs(lx) <= length / 2 + 0.1) & (abs(ly) <= width / 2 + 0.1) & (abs(d[:, 2]) <= height / 2 + 0.1)
        assert inside.mean() >= 0.99
    assert len(s["lidar"]) == len(s["agents"]) and s["lidar_to_ego"].shape == (len(s["agents"]), 4, 4)


def test_the_training_example_runs(episode):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(REPO / "examples" / "train_loop.py"), str(episode), "--steps", "3"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "step 2" in r.stdout


# ------------------------------------------------------------------------- LiDAR motion compensation


@pytest.fixture(scope="module")
def smeared(smeared_episode) -> Path:
    """tests/conftest.py's ``smeared_episode``: the default LiDARs (motion distortion on)."""
    return smeared_episode


def loader_box(obj, lidar_pose) -> tuple[np.ndarray, float, np.ndarray]:
    """An exported box as both loaders hold it (``project_world_objects``): its corners taken into the LiDAR
    frame by the pose composition, then a yaw-only box there: centre (3,), yaw about the frame's z, and
    length, width, height measured along the frame's level plane and its z (a tilt is dropped)."""
    to_lidar = np.linalg.inv(x_to_world(lidar_pose)) @ x_to_world(box_pose(obj))
    axes = to_lidar[:3, :3]
    half = np.asarray(obj["extent"], np.float64)
    yaw = math.atan2(axes[1, 0], axes[0, 0])
    size = 2 * half * [np.hypot(*axes[:2, 0]), np.hypot(*axes[:2, 1]), abs(axes[2, 2])]
    return to_lidar[:3, 3], yaw, size


def in_loader_box(obj, lidar_pose, xyz: np.ndarray, margin_m: float) -> np.ndarray:
    """Which points (N, 3) of a cloud in its exported frame lie in :func:`loader_box` grown by ``margin_m``."""
    centre, yaw, size = loader_box(obj, lidar_pose)
    c, s = math.cos(yaw), math.sin(yaw)
    d = xyz - centre
    local = np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]]
    return (np.abs(local) <= size / 2 + margin_m).all(axis=1)


def exported_clouds(root: Path, layout: str):
    """(observer kind, lidar_pose, points (N, 3), instance ids (N,), box table, speed of a box [m/s]) of every
    exported cloud; the pose as the loader composes it: AirV2X ``lidar_pose`` added to ``ego_pos``, OPV2V the
    yaml's ``lidar_pose``; the boxes AirV2X ``objects.pkl``, OPV2V ``cosim.objects`` (every class)."""
    seq = only(root / "train")
    if layout == "airv2x":
        for stamp in sorted(p for p in seq.iterdir() if p.is_dir()):
            table = pickle.loads((stamp / "objects.pkl").read_bytes())
            for f in sorted(p for p in stamp.iterdir() if p.is_dir()):
                meta = pickle.loads((f / "metadata.pkl").read_bytes())
                pose = add_poses(meta["lidar"]["lidar_pose"], meta["odometry"]["ego_pos"])
                yield (meta["agent_type"], pose, read_pcd(f / "lidar.pcd")[:, :3],
                       np.load(f / "lidar_labels.npz")["instance_id"], table, lambda o: float(o["speed"]))
    else:
        for agent in sorted(p for p in seq.iterdir() if p.is_dir()):
            for y in sorted(agent.glob("*.yaml")):
                doc, extras = load_yaml(y), tick_extras(seq, int(y.stem))
                yield (extras["agents"][agent.name]["kind"], doc["lidar_pose"], read_pcd(y.with_suffix(".pcd"))[:, :3],
                       np.load(agent / f"{y.stem}_lidar_labels.npz")["instance_id"], extras["objects"],
                       lambda o: float(o["speed"]) / 3.6)


def in_box_counts(root: Path, layout: str, margin_m: float = 0.1) -> dict[tuple[str, str], list[int]]:
    """(observer kind, ``static`` below 0.1 m/s or ``moving``) -> [points with an instance id of a labelled
    object, of them in that object's :func:`loader_box`], over every agent and tick of an export."""
    counts: dict[tuple[str, str], list[int]] = {}
    for kind, pose, xyz, ids, table, speed in exported_clouds(root, layout):
        for track in np.unique(ids[(ids > 0) & (ids < 1_000_000)]):
            obj = table[int(track)]
            sel = ids == track
            c = counts.setdefault((kind, "static" if abs(speed(obj)) < 0.1 else "moving"), [0, 0])
            c[0] += int(sel.sum())
            c[1] += int(in_loader_box(obj, pose, xyz[sel], margin_m).sum())
    return counts


def share(counts: dict[tuple[str, str], list[int]], kinds=("vehicle", "rsu", "drone"),
          speeds=("static", "moving")) -> tuple[int, float]:
    n = sum(counts.get((k, s), [0, 0])[0] for k in kinds for s in speeds)
    inside = sum(counts.get((k, s), [0, 0])[1] for k in kinds for s in speeds)
    return n, inside / max(1, n)


def test_the_loader_box_keeps_a_level_box_and_drops_a_tilt():
    """The re-implemented loader box: exact for a box level in a level frame, yaw only in a tilted one."""
    obj = {"location": [10.0, 2.0, 0.0], "center": [0.0, 0.0, 0.75], "angle": [0.0, 30.0, 0.0],
           "extent": [2.0, 1.0, 0.75]}
    centre, yaw, size = loader_box(obj, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert np.allclose(centre, [10.0, 2.0, 0.75]) and math.isclose(yaw, math.radians(30.0))
    assert np.allclose(size, [4.0, 2.0, 1.5])
    corner_top = (x_to_world(box_pose(obj)) @ [2.0, 1.0, 0.75, 1.0])[:3]
    assert in_loader_box(obj, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], corner_top[None], 0.01).all()
    tilted = [0.0, 0.0, 0.0, 0.0, 0.0, 20.0]  # the frame pitched 20 deg: the box's tilt in it is dropped
    local = (np.linalg.inv(x_to_world(tilted)) @ [*corner_top, 1.0])[:3]
    assert not in_loader_box(obj, tilted, local[None], 0.1).all()


@pytest.mark.parametrize("layout", ["airv2x", "opv2v"])
def test_exported_lidar_is_compensated_to_the_tick_pose_by_default(smeared, layout, tmp_path):
    """With the default settings, >= 98 % of the LiDAR points of static objects lie in their exported boxes
    through the loaders' pose composition and box form; ``raw_lidar`` keeps the points as fired (and smeared)."""
    from cosim.exporters.export import ExportOptions, run_export

    run_export(smeared, layout, tmp_path / "default", ExportOptions())
    checked, static_share = share(in_box_counts(tmp_path / "default", layout), speeds=("static",))
    assert checked > 500 and static_share >= 0.98, (checked, static_share)
    run_export(smeared, layout, tmp_path / "raw", ExportOptions(raw_lidar=True))
    raw_checked, raw_share = share(in_box_counts(tmp_path / "raw", layout), speeds=("static",))
    assert raw_checked == checked and raw_share < static_share


@pytest.mark.parametrize("layout", ["airv2x", "opv2v"])
def test_drone_clouds_are_level_so_the_loaders_boxes_hold_their_points(smeared, layout, tmp_path):
    """A drone tilts as it flies, and both loaders keep only a box's yaw in the LiDAR frame: a drone's cloud
    and ``lidar_pose`` are in the level frame at its LiDAR, so >= 97 % of the points of every object it sees,
    static or moving (smeared by its own motion over the sweep), lie in the loaders' boxes."""
    from cosim.exporters.export import ExportOptions, run_export

    run_export(smeared, layout, tmp_path, ExportOptions())
    rolls_pitches = [abs(wrap_deg(v)) for kind, pose, *_ in exported_clouds(tmp_path, layout) if kind == "drone"
                     for v in (pose[3], pose[5])]
    assert rolls_pitches and max(rolls_pitches) < 1e-6
    checked, drone_share = share(in_box_counts(tmp_path, layout), kinds=("drone",))
    assert checked > 300 and drone_share >= 0.97, (checked, drone_share)


@pytest.mark.parametrize("layout", ["airv2x", "opv2v"])
def test_by_default_moving_objects_points_lie_in_their_tick_boxes(smeared, layout, tmp_path):
    """Both datasets were recorded with a LiDAR that takes a sweep at one instant, so by default each moving
    object's points are moved with its recorded velocity to where it is at the tick: >= 98 % of the points
    of moving objects lie in the loaders' boxes. ``objects_at_tick=False`` (``--object-motion``) keeps the
    objects' own motion: their points trail their boxes."""
    from cosim.exporters.export import ExportOptions, run_export

    run_export(smeared, layout, tmp_path / "default", ExportOptions())
    run_export(smeared, layout, tmp_path / "motion", ExportOptions(objects_at_tick=False))
    default, motion = in_box_counts(tmp_path / "default", layout), in_box_counts(tmp_path / "motion", layout)
    n, moving = share(default, speeds=("moving",))
    assert n > 500 and moving >= 0.98 and moving > share(motion, speeds=("moving",))[1], (n, moving)
    assert share(default)[1] >= 0.98
