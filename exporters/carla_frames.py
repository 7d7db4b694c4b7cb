"""CARLA / Unreal conventions of the AirV2X-Perception and OPV2V loaders, each in one named function.

cosim's episodes are right-handed (``map`` ENU, bodies FLU, docs/episode_format.md); the loaders of
OpenCOOD (``DerrickXuNu/OpenCOOD``) and the AirV2X-Perception devkit (``taco-group/AirV2X-Perception``)
read CARLA's left-handed frames: x forward/east, **y right**, z up, metres. Every conversion from one
to the other happens here, nowhere else; docs/exports.md lists them with the reference file that fixes
each. A CARLA pose is six numbers ``[x, y, z, roll, yaw, pitch]`` with angles in degrees, read by
``opencood/utils/transformation_utils.py: x_to_world``.

With F = diag(1, -1, 1) (the y flip), a rigid transform T of cosim (map <- frame, both right-handed)
is F T F in CARLA's axes, applied to the world and to the frame alike. :func:`carla_pose` writes that
as the six pose numbers; :func:`carla_matrix` is the matrix the loaders build from them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

#: The y flip between right-handed (ENU / FLU) and CARLA's left-handed axes.
FLIP_Y = np.diag([1.0, -1.0, 1.0])
#: Rotation OpenCV camera axes (x right, y down, z forward) -> Unreal camera axes (x forward, y right,
#: z up), the axes of a CARLA camera's pose (``opencood/utils/camera_utils.py: ue4_to_lss``).
UE_FROM_OPENCV = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
KMH_PER_MPS = 3.6  # [km/h / (m/s)]
#: CARLA's RGB24 depth encoding: metres = (R + 256 G + 65536 B) / (2^24 - 1) * far plane.
DEPTH_FAR_M = 1000.0  # [m]
DEPTH_LEVELS = 2**24 - 1


def rpy_from_matrix(rot: np.ndarray) -> tuple[float, float, float]:
    """Intrinsic Z-Y-X Euler angles (roll, pitch, yaw) [rad] of a right-handed rotation (3, 3).

    At pitch = +-90 deg (a nadir camera) roll and yaw are not separable; roll is then 0 and yaw takes
    the whole rotation about the vertical, so the angles still rebuild ``rot`` exactly.
    """
    sp = -float(rot[2, 0])
    pitch = math.asin(max(-1.0, min(1.0, sp)))
    if abs(sp) > 1.0 - 1e-9:
        return 0.0, pitch, math.atan2(-float(rot[0, 1]), float(rot[1, 1]))
    return math.atan2(float(rot[2, 1]), float(rot[2, 2])), pitch, math.atan2(float(rot[1, 0]), float(rot[0, 0]))


def carla_pose(position_m: Sequence[float], rot: np.ndarray) -> list[float]:
    """``[x, y, z, roll, yaw, pitch]`` (m, deg) in CARLA's axes of a cosim pose (ENU position, rotation
    map <- frame with the frame FLU).

    The rule: y -> -y, roll -> roll, pitch -> -pitch, yaw -> -yaw (degrees), so that
    ``x_to_world(pose)`` (``opencood/utils/transformation_utils.py``) equals F T F.
    """
    roll, pitch, yaw = rpy_from_matrix(np.asarray(rot, np.float64))
    x, y, z = (float(v) for v in position_m)
    return [x, -y, z, math.degrees(roll), -math.degrees(yaw), -math.degrees(pitch)]


def carla_pose_of_matrix(t: np.ndarray) -> list[float]:
    """:func:`carla_pose` of a 4x4 transform map <- frame."""
    return carla_pose(t[:3, 3], t[:3, :3])


def carla_matrix(pose: Sequence[float]) -> np.ndarray:
    """The 4x4 transform CARLA world <- frame that ``x_to_world`` builds from a six-number pose
    (``opencood/utils/transformation_utils.py: x_to_world``): Rz(yaw) Ry(-pitch) Rx(-roll)."""
    x, y, z, roll, yaw, pitch = (float(v) for v in pose)
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    cr, sr = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    cp, sp = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    m[:3, :3] = [
        [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
        [sp, -cp * sr, cp * cr],
    ]
    return m


def flip_transform(t: np.ndarray) -> np.ndarray:
    """F T F: a right-handed 4x4 transform in CARLA's axes (both of its frames y-flipped)."""
    f = np.eye(4)
    f[1, 1] = -1.0
    return f @ t @ f


def carla_points(xyz: np.ndarray) -> np.ndarray:
    """Points (N, 3) from a FLU sensor frame into the same sensor's CARLA frame (y right): y -> -y.

    The point clouds the loaders read (``opencood/utils/pcd_utils.py: pcd_to_np``) are in the sensor's
    CARLA frame; writing FLU points unflipped is the y-axis error that made the AirV2X team
    regenerate their data (``correct_lidar_coordinate_system`` in the same file).
    """
    out = np.array(xyz, dtype=np.float64, copy=True)
    out[:, 1] *= -1.0
    return out


def relative_pose(sensor_pose: Sequence[float], agent_pose: Sequence[float]) -> list[float]:
    """A sensor's pose relative to its agent as the AirV2X loader composes it: component by component.

    ``opencood/utils/transformation_utils.py: get_abs_world_pose`` adds the relative pose to the
    agent's pose number by number (x + x, ..., yaw + yaw), not as transforms; so the relative pose is
    the component-wise difference of the two world poses, and the loader's sum gives back the
    sensor's world pose exactly.
    """
    return [float(s) - float(a) for s, a in zip(sensor_pose, agent_pose, strict=True)]


def half_extent(size_m: Sequence[float]) -> list[float]:
    """Box extent as the loaders read it: half length, half width, half height [m]
    (``opencood/utils/box_utils.py: create_bbx`` spans -extent .. +extent)."""
    return [0.5 * float(v) for v in size_m]


def box_location_center(center_m: Sequence[float], rot: np.ndarray, size_m: Sequence[float]) -> tuple[list[float],
                                                                                                        list[float]]:
    """``location`` (the actor origin: the middle of the box's bottom face) and ``center`` (the offset
    from it to the box centre, in world axes) in CARLA's axes, both [x, y, z] m.

    The loaders add the two without rotating the offset (``opencood/utils/box_utils.py:
    project_world_objects`` and ``project_world_objects_airv2x``), so the offset is written already
    rotated into the world; location + center is the box centre exactly.
    """
    offset = np.asarray(rot, np.float64) @ np.array([0.0, 0.0, 0.5 * float(size_m[2])])
    c = np.asarray(center_m, np.float64)
    loc = c - offset
    return [float(loc[0]), -float(loc[1]), float(loc[2])], [float(offset[0]), -float(offset[1]), float(offset[2])]


def speed_kmh(velocity_mps: Sequence[float]) -> float:
    """Speed [km/h], the unit of OPV2V's ``ego_speed`` and vehicles' ``speed``."""
    return float(np.linalg.norm(np.asarray(velocity_mps, np.float64))) * KMH_PER_MPS


def speed_mps(velocity_mps: Sequence[float]) -> float:
    """Speed [m/s], the unit of AirV2X's ``odometry.ego_speed`` and objects' ``speed``."""
    return float(np.linalg.norm(np.asarray(velocity_mps, np.float64)))


def lidar_to_camera(map_from_lidar: np.ndarray, map_from_camera: np.ndarray) -> np.ndarray:
    """The 4x4 ``extrinsic`` of both layouts: LiDAR-frame points (CARLA axes) into the camera frame in
    Unreal axes (x forward, y right, z up; no OpenCV swap). ``map_from_camera`` is the camera body
    frame (FLU, x along the optical axis).

    AirV2X (``opencood/utils/camera_utils.py: ue4_to_lss``) inverts it into camera -> LiDAR and then
    swaps to OpenCV axes; OpenCOOD's OPV2V files hold the same matrix (its docs call it camera-to-LiDAR).
    """
    return flip_transform(np.linalg.inv(map_from_camera) @ map_from_lidar)


def encode_depth_rgb24(depth_m: np.ndarray) -> np.ndarray:
    """Planar depth [m] (H, W), NaN = no hit, as CARLA's RGB24 depth image (H, W, 3) uint8:
    code = round(depth / 1000 m * (2^24 - 1)) = R + 256 G + 65536 B; no hit is the far plane (white).

    Read by ``opencood/utils/camera_utils.py: decode_depth_carla`` of the AirV2X devkit. Computed in
    float32 (one code, 60 um, at most off).
    """
    code = np.asarray(depth_m, np.float32) * np.float32(DEPTH_LEVELS / DEPTH_FAR_M)
    np.nan_to_num(code, copy=False, nan=DEPTH_LEVELS, posinf=DEPTH_LEVELS, neginf=0.0)
    np.clip(code, 0.0, DEPTH_LEVELS, out=code)
    np.rint(code, out=code)
    return _rgb24(code.astype("<u4"))


def _rgb24(code: np.ndarray) -> np.ndarray:
    """(H, W) little-endian uint32 codes < 2^24 as (H, W, 3) uint8: R = low byte, then G, B."""
    v = code.view(np.uint8).reshape(-1, 4)
    out = np.empty((v.shape[0], 3), np.uint8)
    for k in range(3):  # one 1-D strided copy per channel (a 3-D slice copy is 5x slower)
        out[:, k] = v[:, k]
    return out.reshape(*code.shape, 3)


def decode_depth_rgb24(rgb: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_depth_rgb24` [m] (the far plane stays 1000 m)."""
    a = np.asarray(rgb, np.uint32)
    return (a[..., 0] + 256 * a[..., 1] + 65536 * a[..., 2]).astype(np.float64) / DEPTH_LEVELS * DEPTH_FAR_M


def encode_id_rgb24(ids: np.ndarray) -> np.ndarray:
    """Non-negative integer ids (H, W) < 2^24 as RGB24 (id = R + 256 G + 65536 B), for instance masks."""
    a = np.asarray(ids)
    if a.size and (a.min() < 0 or a.max() > DEPTH_LEVELS):
        raise ValueError(f"ids must lie in [0, {DEPTH_LEVELS}], got {a.min()}..{a.max()}")
    return _rgb24(a.astype("<u4"))
