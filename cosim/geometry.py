"""Frames, rotations and unit conversions (docs/conventions.md sections 1, 2 and 4), in one place.

World frame ``map`` is ENU in metres; body frames are FLU; camera optical frames are x right,
y down, z forward. Quaternions are (x, y, z, w). Yaw is about +z from +x, in radians.
"""

from __future__ import annotations

import math

import numpy as np

FT_TO_M = 0.3048  # [m / ft]
M_TO_FT = 1.0 / FT_TO_M


def sumo_front_to_center(
    front_x: float, front_y: float, angle_deg: float, length_m: float
) -> tuple[float, float, float]:
    """SUMO's front-bumper position and compass heading to box centre (x, y) and ENU yaw [rad].

    SUMO's angle is degrees clockwise from north; ENU yaw is counter-clockwise from east.
    """
    a = math.radians(angle_deg)
    cx = front_x - 0.5 * length_m * math.sin(a)
    cy = front_y - 0.5 * length_m * math.cos(a)
    return cx, cy, wrap_angle(math.radians(90.0 - angle_deg))


def wrap_angle(a_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (a_rad + math.pi) % (2.0 * math.pi) - math.pi


def quat_from_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of intrinsic Z-Y-X (yaw, pitch, roll) Euler angles [rad]."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def rpy_from_quat(q: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """Inverse of :func:`quat_from_rpy`: (roll, pitch, yaw) [rad]."""
    x, y, z, w = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quat_multiply(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    """Hamilton product a * b of (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def rotation_matrix(q: tuple[float, float, float, float]) -> np.ndarray:
    """3x3 rotation matrix (float64) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_matrix(m: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix."""
    t = m[0, 0] + m[1, 1] + m[2, 2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return (float(x), float(y), float(z), float(w))


def ned_to_enu(v: tuple[float, float, float]) -> tuple[float, float, float]:
    """Vector from NED (north, east, down) to ENU (east, north, up)."""
    n, e, d = v
    return (e, n, -d)


def enu_to_ned(v: tuple[float, float, float]) -> tuple[float, float, float]:
    """Vector from ENU to NED."""
    e, n, u = v
    return (n, e, -u)


#: Rotation taking FLU body axes to a camera optical frame looking along body +x
#: (optical x right = body -y, optical y down = body -z, optical z forward = body +x).
OPTICAL_FROM_FLU = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


# ------------------------------------------------------------------------------------- camera lens
# The camera model of docs/episode_format.md 3.6: a point (x, y, z) of a camera's optical frame lands on
# pixel K [distort(x / z, y / z, D), 1], with pixel (u, v) covering [u, u + 1) x [v, v + 1).


def distort(xy: np.ndarray, D) -> np.ndarray:
    """Brown-Conrady distortion of normalised image points (N, 2) (x / z, y / z), ``D`` = (k1, k2, p1,
    p2, k3) as OpenCV and ROS ``plumb_bob`` define it."""
    k1, k2, p1, p2, k3 = (float(v) for v in D)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return np.stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                     y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], axis=1)


def undistort(xy_d: np.ndarray, D, iterations: int = 30) -> np.ndarray:
    """The normalised points (N, 2) that :func:`distort` takes to ``xy_d`` (fixed-point iteration)."""
    xy = xy_d.copy()
    for _ in range(iterations):
        xy = xy + (xy_d - distort(xy, D))
    return xy


def has_distortion(D) -> bool:
    """True when ``D`` (None, or Brown-Conrady coefficients of any length) bends rays: a non-zero value."""
    return D is not None and bool(np.any(np.asarray(D, np.float64)))


#: [m] optical z below which a point counts as behind the camera in :func:`project_to_image`.
NEAR_Z_M = 1e-6


def project_to_image(points_optical: np.ndarray, K: np.ndarray, D=None) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) [u, v] of points (N, 3) in a camera's optical frame (x right, y down,
    z forward), through the lens ``D`` (Brown-Conrady k1, k2, p1, p2, k3, the calibration's ``D``; None
    or zeros: a pinhole), and whether each point lies in front of the camera (N,) bool.

    The one projection of recorded camera data: pixel (col, row) covers u in [col, col + 1), v in
    [row, row + 1). Points behind the camera get finite but meaningless coordinates.
    """
    p = np.asarray(points_optical, np.float64).reshape(-1, 3)
    front = p[:, 2] > NEAR_Z_M
    z = np.where(front, p[:, 2], 1.0)
    xy = p[:, :2] / z[:, None]
    if has_distortion(D):
        d = np.asarray(D, np.float64).ravel()
        if len(d) != 5:
            raise ValueError(f"D must be the 5 plumb_bob coefficients (k1, k2, p1, p2, k3), got {len(d)}: {d}")
        xy = distort(xy, d)
    K = np.asarray(K, np.float64).reshape(3, 3)
    uv = np.stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]], axis=1)
    return uv, front
