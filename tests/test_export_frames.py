"""Unit tests of the CARLA conventions (exporters/carla_frames.py) and the export file writers."""

from __future__ import annotations

import io
import json
import logging
import math

import numpy as np
import open3d as o3d
import pytest
from cosim.exporters import carla_frames as cf
from cosim.exporters.export import FORMATS, ExportFormat, get_format, register_format, sequence_name
from cosim.exporters.export_io import (
    SPARSE_PNG_LEVEL,
    depth_png,
    jpeg_components,
    npz_bytes,
    pcd_binary,
    png_bytes,
)
from PIL import Image

from cosim.errors import InputError
from cosim.geometry import quat_from_rpy, rotation_matrix
from tests.helpers import batch_folder
from tests.helpers import cli_in_process as cli

F = np.diag([1.0, -1.0, 1.0])


def loader_x_to_world(pose):
    """``x_to_world`` as OpenCOOD writes it out element by element (transformation_utils.py)."""
    x, y, z, roll, yaw, pitch = pose
    cy, sy = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    cr, sr = np.cos(np.radians(roll)), np.sin(np.radians(roll))
    cp, sp = np.cos(np.radians(pitch)), np.sin(np.radians(pitch))
    m = np.identity(4)
    m[:3, 3] = (x, y, z)
    m[0, 0], m[0, 1], m[0, 2] = cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr
    m[1, 0], m[1, 1], m[1, 2] = sy * cp, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr
    m[2, 0], m[2, 1], m[2, 2] = sp, -cp * sr, cp * cr
    return m


def test_enu_to_carla_pose_is_f_r_f_over_random_angles():
    rng = np.random.default_rng(7)
    for _ in range(500):
        roll, pitch, yaw = rng.uniform(-math.pi, math.pi), rng.uniform(-1.5, 1.5), rng.uniform(-math.pi, math.pi)
        r = rotation_matrix(quat_from_rpy(roll, pitch, yaw))
        p = rng.uniform(-500, 500, 3)
        pose = cf.carla_pose(p, r)
        # the documented rule: y -> -y, roll -> roll, pitch -> -pitch, yaw -> -yaw (degrees)
        assert pose == pytest.approx([p[0], -p[1], p[2], math.degrees(roll), -math.degrees(yaw),
                                      -math.degrees(pitch)], abs=1e-9)
        m = loader_x_to_world(pose)
        assert np.allclose(m[:3, :3], F @ r @ F, atol=1e-12)
        assert np.allclose(m[:3, 3], F @ p)
        assert np.allclose(cf.carla_matrix(pose), m, atol=1e-12)


@pytest.mark.parametrize("pitch_deg", [90.0, -90.0])
def test_a_nadir_pose_still_rebuilds_its_rotation(pitch_deg):
    for yaw in (-170.0, -30.0, 0.0, 45.0, 120.0):
        for roll in (0.0, 25.0):
            r = rotation_matrix(quat_from_rpy(math.radians(roll), math.radians(pitch_deg), math.radians(yaw)))
            pose = cf.carla_pose((1.0, 2.0, 3.0), r)
            assert np.allclose(loader_x_to_world(pose)[:3, :3], F @ r @ F, atol=1e-7)


def test_relative_poses_sum_back_to_the_world_pose_as_the_loader_adds_them():
    rng = np.random.default_rng(1)
    agent, sensor = rng.uniform(-180, 180, 6).tolist(), rng.uniform(-180, 180, 6).tolist()
    rel = cf.relative_pose(sensor, agent)
    assert [r + a for r, a in zip(rel, agent, strict=True)] == pytest.approx(sensor, abs=1e-9)


def test_boxes_location_plus_center_is_the_centre_and_extent_is_half():
    r = rotation_matrix(quat_from_rpy(0.1, -0.2, 2.0))
    loc, centre = cf.box_location_center((10.0, 20.0, 1.0), r, (4.0, 2.0, 1.5))
    assert np.add(loc, centre) == pytest.approx([10.0, -20.0, 1.0])
    assert cf.half_extent((4.0, 2.0, 1.5)) == [2.0, 1.0, 0.75]
    level_loc, level_centre = cf.box_location_center((0.0, 0.0, 0.75), np.eye(3), (4.0, 2.0, 1.5))
    assert level_centre == pytest.approx([0.0, 0.0, 0.75]) and level_loc == pytest.approx([0.0, 0.0, 0.0])
    assert cf.speed_kmh((3.0, 4.0, 0.0)) == pytest.approx(18.0) and cf.speed_mps((3.0, 4.0, 0.0)) == 5.0


def test_points_flip_y_and_the_extrinsic_maps_lidar_points_into_the_unreal_camera_frame():
    assert cf.carla_points(np.array([[1.0, 2.0, 3.0]])).tolist() == [[1.0, -2.0, 3.0]]
    lidar = np.eye(4)
    lidar[:3, 3] = (0.5, 0.2, 1.9)
    cam = np.eye(4)
    cam[:3, :3] = rotation_matrix(quat_from_rpy(0.0, 0.0, math.radians(90.0)))  # looking left (+y FLU)
    cam[:3, 3] = (0.0, 0.0, 1.6)
    e = cf.lidar_to_camera(lidar, cam)
    # a point 10 m to the left of the camera (FLU), i.e. y = -10 + ... in CARLA's LiDAR frame
    p_map = np.array([0.0, 10.0, 1.6, 1.0])
    p_lidar_carla = cf.carla_points((np.linalg.inv(lidar) @ p_map)[None, :3])[0]
    assert (e @ np.r_[p_lidar_carla, 1.0])[:3] == pytest.approx([10.0, 0.0, 0.0])  # straight ahead


def test_depth_and_id_rgb24_round_trip():
    d = np.array([[0.5, 12.345, np.nan], [999.0, 0.0, 65.536]])
    back = cf.decode_depth_rgb24(cf.encode_depth_rgb24(d))
    assert back[0, 2] == pytest.approx(1000.0)
    assert np.allclose(np.delete(back.ravel(), 2), np.delete(np.nan_to_num(d, nan=1000.0).ravel(), 2), atol=1e-4)
    ids = np.array([[0, 7, 1_000_123]])
    rgb = cf.encode_id_rgb24(ids).astype(np.int64)
    assert (rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2]).tolist() == ids.tolist()
    with pytest.raises(ValueError):
        cf.encode_id_rgb24(np.array([-1]))


def test_the_binary_pcd_reads_back_through_open3d_exactly_with_intensity_in_red(tmp_path):
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-150, 150, (2000, 3)).astype(np.float32)
    xyz[0] = (-9999.9994, 0.0004, 123456.7)  # float32 holds what the ASCII form's millimetres could not
    intensity = rng.uniform(0, 1, 2000)
    intensity[:3] = (0.0, 1.0, 0.5 / 255)
    path = tmp_path / "a.pcd"
    data = pcd_binary(xyz, intensity)
    assert b"DATA binary\n" in data[:300] and len(data) - data.index(b"DATA binary\n") - 12 == 16 * len(xyz)
    path.write_bytes(data)
    pcd = o3d.io.read_point_cloud(str(path))
    assert np.array_equal(np.asarray(pcd.points), xyz.astype(np.float64))
    colours = np.asarray(pcd.colors)
    assert np.abs(colours[:, 0] - intensity).max() <= 0.5 / 255 + 1e-9
    assert np.array_equal(np.rint(colours[:, 0] * 255), np.rint(intensity * 255))  # the 8-bit code, as before
    assert (colours[:, 1:] == 0).all()
    assert pcd_binary(xyz, intensity) == data  # deterministic
    with pytest.raises(ValueError, match="finite"):
        pcd_binary(np.array([[np.nan, 0.0, 0.0]]), np.zeros(1))


def test_npz_labels_read_back_with_np_load_and_are_byte_deterministic():
    rng = np.random.default_rng(4)
    arrays = {"class_id": rng.integers(0, 30, 5000).astype(np.uint8),
              "instance_id": rng.integers(0, 2_000_000, 5000).astype(np.uint32),
              "ring": rng.integers(0, 128, 5000).astype(np.uint16)}
    data = npz_bytes(arrays)
    assert npz_bytes(arrays) == data
    with np.load(io.BytesIO(data)) as back:
        assert back.files == list(arrays)
        for name, a in arrays.items():
            assert back[name].dtype == a.dtype and np.array_equal(back[name], a)


def test_the_depth_png_kernel_gives_the_bytes_of_the_numpy_reference():
    """``depth_png`` (one compiled pass) equals ``png_bytes(encode_depth_rgb24(...))`` byte for byte, NaN, infinities,
    negatives and depths beyond the far plane included, and decodes back to the depth within one code."""
    rng = np.random.default_rng(5)
    d = rng.uniform(-5.0, 1200.0, (37, 53)).astype(np.float32)
    d[rng.random(d.shape) < 0.1] = np.nan
    d[0, :6] = [np.inf, -np.inf, 0.0, 999.99994, 1000.0, 0.5 / cf.DEPTH_LEVELS * cf.DEPTH_FAR_M]
    assert depth_png(d) == png_bytes(cf.encode_depth_rgb24(d), SPARSE_PNG_LEVEL)
    back = cf.decode_depth_rgb24(np.asarray(Image.open(io.BytesIO(depth_png(d)))))
    ok = np.isfinite(d) & (d >= 0) & (d <= cf.DEPTH_FAR_M)
    assert np.abs(back[ok] - d[ok]).max() <= cf.DEPTH_FAR_M / cf.DEPTH_LEVELS
    assert (back[np.isnan(d)] == cf.DEPTH_FAR_M).all()


def test_jpeg_components_reads_the_frame_header():
    from cosim.sensors.encoding import encode_jpeg

    assert jpeg_components(encode_jpeg(np.zeros((16, 24, 3), np.uint8))) == 3
    grey = io.BytesIO()
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(grey, "JPEG")
    assert jpeg_components(grey.getvalue()) == 1
    assert jpeg_components(b"\x89PNG\r\n\x1a\n") == 0 and jpeg_components(b"\xff\xd8\xff") == 0


def test_the_format_registry_lists_known_formats_and_refuses_duplicates():
    assert get_format("airv2x").name == "airv2x" and get_format("opv2v").split_dir("val") == "validate"
    assert get_format("kitti").name == "kitti"
    with pytest.raises(InputError, match="known: airv2x, kitti, opv2v"):
        get_format("nuscenes")

    class Duplicate(ExportFormat):
        name = "airv2x"

    with pytest.raises(ValueError, match="registered twice"):
        register_format(Duplicate)
    assert FORMATS["airv2x"] is not Duplicate


def test_sequence_names_look_like_date_times_and_follow_the_content():
    a, b = sequence_name("0" * 64), sequence_name("f" * 64)
    for n in (a, b):
        assert len(n) == 19 and [len(x) for x in n.split("_")] == [4, 2, 2, 2, 2, 2]
    assert a != b and sequence_name("0" * 64) == a


# ------------------------------------------------------------------------------ a batch folder without splits


def test_export_of_a_sweep_without_splits_says_its_folder_is_not_read_and_names_the_sweep(synthetic_episodes, tmp_path,
                                                                                          caplog, capsys):
    from cosim.exporters.export import run_export

    root = batch_folder(tmp_path / "batch", synthetic_episodes[:1], ["all"], sweep="night_sweep")
    with caplog.at_level(logging.WARNING, logger="cosim.exporters.export"):
        result = run_export(root, "airv2x", tmp_path / "x")
    (seq,) = result.written
    assert seq.parent.name == "all"
    assert any("neither loader reads" in m and "--split" in m for m in caplog.messages), caplog.messages
    cond = json.loads((seq / "conditions.json").read_text())
    assert cond["scenario"] == cond["sweep"] == "night_sweep" and cond["episode"] == "night_sweep-0000"
    assert cond["base_scenario"] == "synthetic"
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cosim.exporters.export"):
        status, out, err = cli(capsys, "export", str(root), "--format", "airv2x", "--out", str(tmp_path / "y"),
                               "--split", "train")
    assert status == 0 and (tmp_path / "y" / "train").is_dir() and "1 sequence(s) written" in out, err
    assert not any("neither loader" in m for m in caplog.messages)
    assert "export airv2x: agent-frame 6 of 6 (100 %), " in err, err  # stderr not a terminal: a plain line
