"""The KITTI object layout: cosim/io/kitti.py's readers and writers on hand-made numbers, and
``cosim export --format kitti`` on a real episode (docs/exports.md, "KITTI")."""

from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cosim.errors import InputError
from cosim.io import kitti, open_episode
from tests.helpers import run_cli

#: KITTI's axes: camera x = -velodyne y, camera y = -velodyne z, camera z = velodyne x.
VELO_TO_CAM_AXES = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _rot(axis: int, a_rad: float) -> np.ndarray:
    c, s = math.cos(a_rad), math.sin(a_rad)
    i, j = [k for k in range(3) if k != axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def hand_calib(tilted: bool = False) -> kitti.KittiCalib:
    """A calib with camera 0 at velodyne (0.27, 0.0, -0.08) [m] (Tr's translation (0, 0.08, -0.27) in the
    camera's axes), f = 700 px, principal point (620, 190) px, camera 2 0.06 m to the left of camera 0 (P2's
    fourth column f * 0.06); ``tilted`` adds small rotations to Tr and R0_rect, as a real rig's calib has."""
    r = VELO_TO_CAM_AXES
    r0 = np.eye(3)
    if tilted:
        r = _rot(0, 0.01) @ _rot(1, -0.02) @ r @ _rot(2, 0.03)
        r0 = _rot(1, 0.004) @ _rot(0, -0.006)
    tr = np.c_[r, [0.0, 0.08, -0.27]]
    k = np.array([[700.0, 0.0, 620.0], [0.0, 700.0, 190.0], [0.0, 0.0, 1.0]])
    p0 = np.c_[k, np.zeros(3)]
    p2 = p0.copy()
    p2[0, 3] = 700.0 * 0.06
    return kitti.KittiCalib(P0=p0, P1=p0, P2=p2, P3=p2, R0_rect=r0, Tr_velo_to_cam=tr,
                            Tr_imu_to_velo=np.c_[np.eye(3), [-0.8, 0.3, -0.9]])


def test_a_known_point_goes_through_kitti_calib_as_kitti_says():
    """Velodyne (10, 2, -1) is 2 m to the left and 1 m below the LiDAR: in the camera, x = -2, y = 1 (down)
    plus the camera's offset, z = 10 less the camera's 0.27 m ahead; then P2 puts it left of and below the
    principal point."""
    calib = hand_calib()
    cam = calib.velo_to_rect(np.array([[10.0, 2.0, -1.0]]))
    np.testing.assert_allclose(cam, [[-2.0, 1.08, 9.73]], atol=1e-12)
    np.testing.assert_allclose(calib.rect_to_velo(cam), [[10.0, 2.0, -1.0]], atol=1e-12)
    uv, depth = calib.rect_to_image(cam, camera=2)
    np.testing.assert_allclose(depth, [9.73])
    np.testing.assert_allclose(uv, [[620.0 + 700.0 * (-2.0 + 0.06) / 9.73, 190.0 + 700.0 * 1.08 / 9.73]])
    np.testing.assert_allclose(calib.velo_from_cam @ calib.cam_from_velo, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(calib.velo_from_imu[:3, 3], [-0.8, 0.3, -0.9])


def test_a_velodyne_box_becomes_kittis_bottom_centre_and_rotation_y():
    """A car 10 m ahead, 2 m left, centre 0.9 m below the LiDAR, 1.5 m tall, heading 0.3 rad left of the
    LiDAR's x: KITTI's location is its bottom centre (1.65 m below the LiDAR) in the camera, and
    rotation_y = -yaw - pi/2."""
    calib = hand_calib()
    box = np.array([[10.0, 2.0, -0.9, 4.0, 1.8, 1.5, 0.3]])
    loc, ry = kitti.boxes_from_velo(box, calib)
    np.testing.assert_allclose(loc, [[-2.0, 1.65 + 0.08, 9.73]], atol=1e-12)
    np.testing.assert_allclose(ry, [-0.3 - math.pi / 2])
    obj = kitti.KittiObject("Car", 0.0, 0, 0.0, (0, 0, 1, 1), h=1.5, w=1.8, l=4.0, location=loc[0],
                            rotation_y=ry[0])
    np.testing.assert_allclose(kitti.boxes_to_velo([obj], calib), box, atol=1e-12)


@pytest.mark.parametrize("tilted", [False, True])
def test_boxes_round_trip_velo_cam_velo(tilted):
    rng = np.random.default_rng(7)
    calib = hand_calib(tilted)
    boxes = np.c_[rng.uniform(-60, 60, (50, 2)), rng.uniform(-2, 0, 50), rng.uniform(0.5, 12, (50, 3)),
                  rng.uniform(-math.pi, math.pi, 50)]
    loc, ry = kitti.boxes_from_velo(boxes, calib)
    objs = [kitti.KittiObject("Car", 0.0, 0, 0.0, (0, 0, 1, 1), h=b[5], w=b[4], l=b[3], location=p, rotation_y=r)
            for b, p, r in zip(boxes, loc, ry, strict=True)]
    back = kitti.boxes_to_velo(objs, calib)
    np.testing.assert_allclose(back[:, :6], boxes[:, :6], atol=1e-9)
    assert np.abs(kitti.wrap_rad(back[:, 6] - boxes[:, 6])).max() < 1e-9
    assert kitti.boxes_to_velo([], calib).shape == (0, 7)


def test_points_in_boxes_and_corners_agree():
    box = np.array([[5.0, -1.0, 0.5, 4.0, 2.0, 1.0, math.pi / 2]])
    corners = kitti.box_corners_velo(box)[0]
    # Rotated a quarter turn: the 4 m length lies along y.
    np.testing.assert_allclose(np.ptp(corners, axis=0), [2.0, 4.0, 1.0], atol=1e-12)
    inside = kitti.points_in_boxes(np.array([[5.0, 0.9, 0.5], [5.0, 1.1, 0.5], [6.1, -1.0, 0.5]]), box)
    assert inside[:, 0].tolist() == [True, False, False]
    assert kitti.points_in_boxes(corners * 0.999 + box[0, :3] * 0.001, box).all()


def test_calib_file_round_trips_and_missing_keys_are_named(tmp_path):
    calib = hand_calib(tilted=True)
    path = tmp_path / "000000.txt"
    path.write_text(kitti.format_calib(calib))
    lines = path.read_text().splitlines()
    assert [ln.split(":")[0] for ln in lines] == [k for k, _ in kitti.CALIB_KEYS]
    assert all(len(ln.split()) == 1 + math.prod(s) for ln, (_, s) in zip(lines, kitti.CALIB_KEYS, strict=True))
    back = kitti.read_calib(path)
    for key, _ in kitti.CALIB_KEYS:
        np.testing.assert_allclose(getattr(back, key), getattr(calib, key), rtol=1e-12, atol=1e-15)
    path.write_text("\n".join(ln for ln in lines if not ln.startswith("Tr_velo_to_cam")))
    with pytest.raises(InputError, match="lacks Tr_velo_to_cam"):
        kitti.read_calib(path)
    path.write_text(lines[2].replace(lines[2].split()[-1], "x"))
    with pytest.raises(InputError, match=r":1: P2 holds a value that is not a number"):
        kitti.read_calib(path)


def test_label_lines_have_kittis_columns_and_read_back(tmp_path):
    car = kitti.KittiObject("Car", 0.0, 1, -1.5708, (100.0, 150.25, 300.5, 250.0), h=1.52, w=1.8, l=4.1,
                            location=(-2.0, 1.73, 9.7312), rotation_y=-1.8708)
    line = kitti.format_label(car)
    assert line == "Car 0.00 1 -1.57 100.00 150.25 300.50 250.00 1.52 1.80 4.10 -2.00 1.73 9.73 -1.87"
    scored = kitti.KittiObject(**{**car.__dict__, "score": 0.87654})
    assert len(kitti.format_label(scored, decimals=4).split()) == 16
    care = kitti.dont_care((1.0, 2.0, 3.0, 4.0))
    assert kitti.format_label(care).split()[1:4] == ["-1.00", "-1", "-10.00"]
    assert kitti.format_label(kitti.KittiObject("Car", -0.001, 0, 0, (0, 0, 0, 0), 1, 1, 1, (0, 0, 0), 0))\
        .split()[1] == "0.00"
    path = tmp_path / "000000.txt"
    path.write_text("\n".join(kitti.format_label(o, 4) for o in (car, scored, care)) + "\n")
    back = kitti.read_labels(path)
    assert [o.type for o in back] == ["Car", "Car", "DontCare"] and back[2].dont_care
    assert back[0].score is None and back[1].score == pytest.approx(0.8765)
    np.testing.assert_allclose(back[0].location, car.location)
    assert back[0].occluded == 1 and back[0].rotation_y == pytest.approx(-1.8708)
    path.write_text("Car 0 0 0 1 2 3 4\n")
    with pytest.raises(InputError, match=r":1: 8 columns"):
        kitti.read_labels(path)


def test_velodyne_bin_round_trips(tmp_path):
    pts = np.array([[1.5, -2.25, 0.125, 0.5], [60.0, 0.0, -1.75, 1.0]], dtype=np.float32)
    path = tmp_path / "000000.bin"
    kitti.write_velodyne(path, pts)
    assert path.stat().st_size == 2 * 16
    back = kitti.read_velodyne(path)
    assert back.dtype == np.float32 and np.array_equal(back, pts)
    path.write_bytes(path.read_bytes()[:-4])
    with pytest.raises(InputError, match="not a whole number of 16-byte points"):
        kitti.read_velodyne(path)


def _kitti_folder(root, stems, labelled):
    data = root / "training"
    for sub in ("velodyne", "calib", "label_2"):
        (data / sub).mkdir(parents=True)
    calib = kitti.format_calib(hand_calib())
    for i, stem in enumerate(stems):
        kitti.write_velodyne(data / "velodyne" / f"{stem}.bin", np.full((i + 1, 4), 0.5, dtype=np.float32))
        (data / "calib" / f"{stem}.txt").write_text(calib)
        if stem in labelled:
            (data / "label_2" / f"{stem}.txt").write_text(kitti.format_label(kitti.dont_care((0, 0, 5, 5))) + "\n")


def test_kitti_folder_lists_frames_splits_and_unlabelled_frames(tmp_path):
    _kitti_folder(tmp_path, ["000002", "000000", "000001"], labelled={"000000", "000001"})
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "train.txt").write_text("000000\n000001\n")
    (tmp_path / "ImageSets" / "test.txt").write_text("000002\n")
    folder = kitti.KittiFolder(tmp_path)
    assert folder.stems == ["000000", "000001", "000002"] and len(folder) == 3
    assert folder.splits == {"train": ["000000", "000001"], "test": ["000002"]}
    test_frame = folder.frame("000002")
    assert test_frame.objects is None and test_frame.points.shape == (1, 4) and test_frame.image_path is None
    assert not folder.has_labels("000002") and folder.has_labels("000000")
    assert [o.type for o in folder.frame("000001").objects] == ["DontCare"]
    np.testing.assert_allclose(folder.frame("000000").calib.P2, hand_calib().P2)
    # A folder holding velodyne/ directly reads the same.
    assert kitti.KittiFolder(tmp_path / "training").stems == folder.stems
    with pytest.raises(InputError, match="no frame '000009'"):
        folder.frame("000009")
    with pytest.raises(InputError, match="not a KITTI folder"):
        kitti.KittiFolder(tmp_path / "ImageSets")


# ------------------------------------------------------------------------------ the export of real episodes

#: docs/exports.md's class table (cosim -> KITTI); the classes it leaves out are not here.
DOC_CLASSES = {"car": "Car", "van": "Van", "truck": "Truck", "bus": "Tram", "motorcycle": "Cyclist",
               "bicycle": "Cyclist", "pedestrian": "Pedestrian", "static_obstacle": "Misc"}


@pytest.fixture(scope="module")
def full_export(export_episode, tmp_path_factory) -> Path:
    """tests/conftest.py's full-rig episode (LiDAR noise and motion distortion off, off-axis LiDAR mounts),
    exported with the defaults (the vehicles) but every other tick."""
    from cosim.exporters.export import ExportOptions, run_export

    out = tmp_path_factory.mktemp("kitti_full")
    run_export(export_episode, "kitti", out, ExportOptions(every=2))
    return out


@pytest.fixture(scope="module")
def smeared_export(smeared_episode, tmp_path_factory) -> Path:
    """The default LiDARs (noise, motion distortion), every agent (a drone: no front camera)."""
    from cosim.exporters.export import run_export

    out = tmp_path_factory.mktemp("kitti_smeared")
    run_export(smeared_episode, "kitti", out, agents="all")
    return out


def frames_of(root: Path) -> list[dict]:
    with (root / "training" / "frames.csv").open() as f:
        return list(csv.DictReader(f))


def map_from_velo(tick, agent: str, kind: str) -> np.ndarray:
    """docs/exports.md: the velodyne frame is the LiDAR's own for vehicles, the level frame at the LiDAR with
    its heading for RSUs and drones."""
    lidar = tick.transforms.to_root(f"{agent}/lidar")
    if kind == "vehicle":
        return lidar
    x = lidar[:3, 0] if np.hypot(*lidar[:2, 0]) > 1e-6 else tick.transforms.to_root(f"{agent}/base_link")[:3, 0]
    out = np.eye(4)
    out[:3, :3] = _rot(2, math.atan2(x[1], x[0]))
    out[:3, 3] = lidar[:3, 3]
    return out


def labelled(root: Path, stem: str) -> list[tuple[kitti.KittiObject, int]]:
    objs = kitti.read_labels(root / "training" / "label_2" / f"{stem}.txt")
    tracks = [int(t) for t in (root / "training" / "label_tracks" / f"{stem}.txt").read_text().split()]
    assert len(objs) == len(tracks)
    return list(zip(objs, tracks, strict=True))


@pytest.mark.integration
def test_the_layout_has_one_frame_per_vehicle_and_tick(full_export, export_episode):
    with open_episode(export_episode) as ep:
        vehicles = [a for a in ep.agents if a.startswith("vehicle_")]
        n_ticks, cams = ep.n_ticks, ep.tick(0).calibration(vehicles[0], "front")
    rows = frames_of(full_export)
    ticks = range(0, n_ticks, 2)
    assert [r["stem"] for r in rows] == [f"{i:06d}" for i in range(len(vehicles) * len(ticks))]
    # each agent's drive is a run of consecutive stems, in tick order
    assert [(r["agent_id"], int(r["tick"])) for r in rows] == [(a, t) for a in vehicles for t in ticks]
    assert {r["image"] for r in rows} == {"front"}
    training = full_export / "training"
    for sub, ext in (("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt"), ("image_2", "png"),
                     ("velodyne_labels", "npy"), ("label_tracks", "txt")):
        assert sorted(p.stem for p in (training / sub).glob(f"*.{ext}")) == [r["stem"] for r in rows], sub
    folder = kitti.KittiFolder(full_export)
    assert folder.stems == [r["stem"] for r in rows]
    assert folder.splits == {"train": folder.stems, "val": [], "test": []}
    with Image.open(training / "image_2" / "000000.png") as im:
        assert im.size == (cams.width, cams.height) and im.mode == "RGB"
    assert not (full_export / ".cosim-partial").exists()


def _check_labels(root: Path, source: Path) -> int:
    """Every frame's labels against the episode's /labels/objects and visibility; the number of boxes."""
    n = 0
    folder = kitti.KittiFolder(root)
    with open_episode(source) as ep:
        for row in frames_of(root):
            agent = row["agent_id"]
            tick = ep.tick(int(row["tick"]), topics=["/tf", "/labels/objects", f"/{agent}/visibility"])
            labels = tick.labels
            index = {int(t): i for i, t in enumerate(labels.track_ids)}
            seen = {o["track_id"]: o["lidar_points"] for o in tick[f"/{agent}/visibility"]["objects"]}
            ego = next((a.get("track_id") for a in labels.agents if a["agent_id"] == agent), None)
            frame = folder.frame(row["stem"])
            pairs = labelled(root, row["stem"])
            boxes = [(o, t) for o, t in pairs if not o.dont_care]
            # DontCare last, as in KITTI's files (OpenPCDet relies on it)
            assert not any(o.dont_care for o, _ in pairs[:len(boxes)])
            want = {int(t) for t, c in zip(labels.track_ids, labels.classes, strict=True)
                    if c in DOC_CLASSES and seen.get(int(t), 0) > 0 and int(t) != ego}
            assert {t for _, t in boxes} == want, row["stem"]
            assert {t for o, t in pairs if o.dont_care} <= {int(t) for t in labels.track_ids} - want
            velo = kitti.boxes_to_velo([o for o, _ in boxes], frame.calib)
            m = map_from_velo(tick, agent, row["agent_kind"])
            for (obj, track), box in zip(boxes, velo, strict=True):
                i = index[track]
                assert obj.type == DOC_CLASSES[labels.classes[i]]
                np.testing.assert_allclose(m[:3, :3] @ box[:3] + m[:3, 3], labels.centers_m[i], atol=1e-3)
                np.testing.assert_allclose(box[3:6], labels.sizes_m[i], atol=1e-3)
                heading = m[:3, :3] @ [math.cos(box[6]), math.sin(box[6]), 0.0]
                assert abs(kitti.wrap_rad(math.atan2(heading[1], heading[0]) - labels.yaws_rad[i])) < 1e-4
                assert 0.0 <= obj.truncated <= 1.0 and obj.occluded in (0, 1, 2)
                n += 1
    return n


@pytest.mark.integration
def test_labels_read_back_equal_cosims_boxes(full_export, export_episode, smeared_export, smeared_episode):
    assert _check_labels(full_export, export_episode) > 100
    assert _check_labels(smeared_export, smeared_episode) > 50


def _shares_in_boxes(root: Path, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per labelled object of every frame: the share of its LiDAR returns (by instance id) inside its
    exported box grown by ``margin_m``, and their number."""
    folder = kitti.KittiFolder(root)
    shares, counts = [], []
    for stem in folder.stems:
        frame = folder.frame(stem)
        ids = np.load(root / "training" / "velodyne_labels" / f"{stem}.npy")["instance_id"]
        assert len(ids) == len(frame.points)
        boxes = [(o, t) for o, t in labelled(root, stem) if not o.dont_care]
        velo = kitti.boxes_to_velo([o for o, _ in boxes], frame.calib)
        for (_, track), box in zip(boxes, velo, strict=True):
            own = frame.points[ids == track, :3]
            if len(own):
                shares.append(kitti.points_in_boxes(own, box[None], margin_m).mean())
                counts.append(len(own))
    return np.array(shares), np.array(counts)


@pytest.mark.integration
def test_each_objects_points_fall_in_its_box(full_export, smeared_export):
    # Instantaneous, noiseless sweeps: every return on its box, to the 1/128 m the episode stores.
    shares, _ = _shares_in_boxes(full_export, 0.01)
    assert len(shares) > 100 and shares.min() == 1.0
    # The default LiDAR (2 cm range noise, motion compensated to the tick): within 5 cm.
    shares, counts = _shares_in_boxes(smeared_export, 0.05)
    assert len(shares) > 50
    assert (shares * counts).sum() / counts.sum() > 0.99 and shares[counts >= 10].min() > 0.8


@pytest.mark.integration
def test_calib_puts_lidar_points_on_their_pixels_and_2d_boxes_around_them(full_export, export_episode):
    """A return on an object, projected with P2 R0_rect Tr_velo_to_cam and rounded (KITTI's pixel centres are
    at integers), lands on a pixel of that object in the episode's front instance image, and inside the label's
    2D box. (Not every one: the camera sits 1 m behind and 0.3 m below the LiDAR and sees other sides of things,
    and a quarter-size image's edges are coarse; 0.5 px off, the share falls from 0.90 to 0.87, 1 px off to 0.82.)"""
    folder = kitti.KittiFolder(full_export)
    hits = total = 0
    with open_episode(export_episode) as ep:
        for row in frames_of(full_export)[::2]:
            stem = row["stem"]
            tick = ep.tick(int(row["tick"]), topics=f"/{row['agent_id']}/front/instance")
            frame = folder.frame(stem)
            inst = tick.instance(row["agent_id"], "front").array
            ids = np.load(full_export / "training" / "velodyne_labels" / f"{stem}.npy")["instance_id"]
            c = frame.calib
            cam = (np.c_[frame.points[:, :3], np.ones(len(ids))] @ (np.c_[c.R0_rect, np.zeros(3)] @
                   np.r_[c.Tr_velo_to_cam, [[0, 0, 0, 1]]]).T)
            uvw = np.c_[cam, np.ones(len(cam))] @ c.P2.T
            front = uvw[:, 2] > 0.5
            uv = uvw[front, :2] / uvw[front, 2:]
            col, line = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            ok = (col >= 0) & (col < inst.shape[1]) & (line >= 0) & (line < inst.shape[0])
            on = ids[front][ok] > 0
            hits += int((inst[line[ok], col[ok]][on] == ids[front][ok][on]).sum())
            total += int(on.sum())
            for obj, track in labelled(full_export, stem):
                mine = ok & (ids[front] == track)
                if obj.dont_care or obj.truncated > 0 or not mine.any():
                    continue
                assert (uv[mine] >= obj.bbox[:2] - 1.0).all() and (uv[mine] <= obj.bbox[2:] + 1.0).all()
    assert total > 500 and hits / total > 0.88


@pytest.mark.integration
def test_agents_without_a_front_camera_get_the_default_front_cameras_calib(smeared_export):
    rows = frames_of(smeared_export)
    assert {r["agent_kind"] for r in rows} == {"vehicle", "rsu", "drone"}
    drone = next(r for r in rows if r["agent_kind"] == "drone")
    assert drone["image"] == "none"
    calib = kitti.read_calib(smeared_export / "training" / "calib" / f"{drone['stem']}.txt")
    f = 640.0 / math.tan(math.radians(55.0))  # the default rig's front camera: 1280 x 720 px, 110 deg
    np.testing.assert_allclose(calib.P2, [[f, 0, 639.5, 0], [0, f, 359.5, 0], [0, 0, 1, 0]])
    assert all(np.array_equal(getattr(calib, p), calib.P2) for p in ("P0", "P1", "P3"))
    # looking along the drone's heading: the optical axis is the velodyne x (the level frame's)
    np.testing.assert_allclose(calib.Tr_velo_to_cam[2, :3], [1, 0, 0], atol=1e-3)
    with Image.open(smeared_export / "training" / "image_2" / f"{drone['stem']}.png") as im:
        assert im.size == (1280, 720) and im.getextrema() == ((0, 0), (0, 0), (0, 0))


@pytest.mark.integration
def test_a_batch_gives_the_imagesets_and_parallel_frames_equal_serial_ones(export_episode, full_export, tmp_path):
    from cosim.exporters.export import ExportOptions, run_export

    from cosim.batch.manifest import Manifest
    from cosim.io.manifest import sha256_file

    batch = tmp_path / "batch"
    with Manifest(batch / "manifest.jsonl") as m:
        for split in ("train", "val"):
            (batch / split).mkdir(parents=True)
            f = batch / split / f"{split}-0000.mcap"
            shutil.copy(export_episode, f)
            m.append({"episode": f"{split}-0000", "split": split, "file": f"{split}/{f.name}", "status": "done",
                      "sha256": sha256_file(f), "size_bytes": f.stat().st_size})
    out = tmp_path / "out"
    result = run_export(batch, "kitti", out, ExportOptions(every=5), workers=2)
    assert result.agent_frames == 10
    folder = kitti.KittiFolder(out)
    rows = frames_of(out)
    assert folder.splits["train"] == [r["stem"] for r in rows if r["episode"] == "train-0000"]
    assert folder.splits["val"] == [r["stem"] for r in rows if r["episode"] == "val-0000"]
    assert len(folder.splits["train"]) == 5 and folder.splits["test"] == []
    serial = {(r["agent_id"], r["tick"]): r["stem"] for r in frames_of(full_export)}
    for r in rows:
        old = serial[(r["agent_id"], r["tick"])]
        for sub, ext in (("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt"), ("image_2", "png")):
            a = (out / "training" / sub / f"{r['stem']}.{ext}").read_bytes()
            assert a == (full_export / "training" / sub / f"{old}.{ext}").read_bytes(), (sub, r)
    again = run_export(batch, "kitti", out, ExportOptions(every=5))
    assert again.skipped == (out,) and again.agent_frames == 0


def test_the_egos_are_chosen_by_kind_and_an_episode_without_one_is_an_input_error():
    from cosim.exporters.kitti import ego_agents

    agents = ["vehicle_0", "vehicle_1", "rsu_0", "drone_0"]
    kinds = {a: a.rsplit("_", 1)[0] for a in agents}
    lidar = set(agents) - {"vehicle_1"}
    assert ego_agents(agents, kinds, lidar, None, "ep") == ["vehicle_0"]
    assert ego_agents(agents, kinds, lidar, "all", "ep") == ["vehicle_0", "rsu_0", "drone_0"]
    assert ego_agents(agents, kinds, lidar, "drone,rsus", "ep") == ["rsu_0", "drone_0"]
    assert ego_agents(agents, kinds, lidar, "drone_0", "ep") == ["drone_0"]
    with pytest.raises(InputError, match=r"ep: no agent with a LiDAR matches --agents vehicles"):
        ego_agents(["rsu_0", "drone_0"], {"rsu_0": "rsu", "drone_0": "drone"}, {"rsu_0", "drone_0"}, None, "ep")
    with pytest.raises(InputError, match="unknown kind 'boats'"):
        ego_agents(agents, kinds, lidar, "vehicles,boats", "ep")


def test_occlusion_counts_the_returns_nearer_than_the_object_in_its_window():
    from cosim.exporters.kitti import Polar, occluded_share, occlusion_level

    from cosim.classes import SEMANTIC_ID

    box = np.array([10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0])  # its near face at x = 8 m, y within +-1 m
    own = np.c_[np.full(10, 8.0), np.linspace(-0.9, 0.9, 10), np.full(10, -1.0)]
    wall = np.c_[np.full(5, 5.0), np.linspace(-0.5, 0.5, 5), np.full(5, -0.6)]  # in the window, nearer
    road = np.c_[np.full(3, 6.5), np.zeros(3), np.full(3, -1.3)]  # in the window, nearer, but ground
    behind = np.c_[np.full(4, 20.0), np.zeros(4), np.full(4, -1.0)]  # in the window, farther
    aside = np.c_[np.full(4, 5.0), np.full(4, 4.0), np.full(4, -0.6)]  # nearer, outside the window
    xyz = np.r_[own, wall, road, behind, aside]
    ids = np.r_[np.full(10, 7), np.full(5, 1_000_001), np.zeros(3), np.zeros(4), np.full(4, 9)].astype(np.uint32)
    classes = np.r_[np.full(10, SEMANTIC_ID["car"]), np.full(5, SEMANTIC_ID["building"]),
                    np.full(3, SEMANTIC_ID["road"]), np.full(8, SEMANTIC_ID["building"])].astype(np.uint8)
    share = occluded_share(Polar.of(xyz), ids, classes, box, 7)
    assert share == pytest.approx(5 / 15) and occlusion_level(share) == 1
    assert occluded_share(Polar.of(own), ids[:10], classes[:10], box, 7) == 0.0
    assert occluded_share(Polar.of(xyz), ids, classes, box, 8) == 1.0
    assert [occlusion_level(v) for v in (0.0, 0.19, 0.2, 0.59, 0.6, 1.0)] == [0, 0, 1, 1, 2, 2]


def test_2d_boxes_and_truncation_from_the_projected_3d_box():
    from cosim.exporters.kitti import image_box

    calib = hand_calib()
    box = np.array([[20.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0]])  # straight ahead
    bbox, truncated = image_box(kitti.box_corners_velo(box)[0], calib, 1240, 380)
    assert truncated == 0.0
    # the near face (x = 18 m, y = +-1 m) is the widest: u = 620 + 700 (-+1 + 0.06) / (18 - 0.27)
    np.testing.assert_allclose(bbox[[0, 2]], [620 + 700 * (-1.0 + 0.06) / 17.73, 620 + 700 * (1.0 + 0.06) / 17.73])
    behind = box.copy()
    behind[0, 0] = -20.0
    bbox, truncated = image_box(kitti.box_corners_velo(behind)[0], calib, 1240, 380)
    assert bbox.tolist() == [0.0, 0.0, 0.0, 0.0] and truncated == 1.0
    side = box.copy()
    side[0, :2] = [3.0, 3.0]  # beside the camera, half of it left of the image
    bbox, truncated = image_box(kitti.box_corners_velo(side)[0], calib, 1240, 380)
    assert bbox[0] == 0.0 and 0.0 < truncated < 1.0 and bbox[2] < 1239.0


def test_an_out_folder_holding_someone_elses_kitti_folders_is_refused(tmp_path):
    from cosim.exporters.export import run_export

    out = tmp_path / "kitti"
    (out / "training" / "velodyne").mkdir(parents=True)
    with pytest.raises(InputError, match="holds training/ that no cosim KITTI export wrote"):
        run_export(tmp_path / "no-such.mcap", "kitti", out)
    assert sorted(p.name for p in out.iterdir()) == ["training"]


def test_agents_is_refused_for_the_formats_that_export_every_agent(tmp_path):
    from cosim.exporters.export import run_export

    with pytest.raises(InputError, match="--agents chooses the egos of --format kitti; opv2v exports every agent"):
        run_export(tmp_path / "no-such.mcap", "opv2v", tmp_path / "out", agents="all")
    assert not (tmp_path / "out").exists()


@pytest.mark.integration
@pytest.mark.parametrize("case", ["out is a file", "no such agent"])
def test_bad_input_exits_2_with_one_line_and_writes_nothing(case, smeared_episode, tmp_path):
    """(An unknown --agents kind takes the same way out: the unit test above checks its message.)"""
    out = tmp_path / "out"
    args = {"no such agent": ["--agents", "vehicle_9"], "out is a file": []}[case]
    if case == "out is a file":
        out.write_text("not a folder")
    r = run_cli("export", str(smeared_episode), "--format", "kitti", "--out", str(out), "-q", *args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert {"no such agent": "vehicle_9", "out is a file": "out"}[case] in lines[0]
    assert out.is_file() if case == "out is a file" else not out.exists() or not any(out.iterdir())
