"""The KITTI object layout: cosim/io/kitti.py's readers and writers on hand-made numbers, and
``cosim export --format kitti`` on a real episode (docs/exports.md, "KITTI")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cosim.errors import InputError
from cosim.io import kitti

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
