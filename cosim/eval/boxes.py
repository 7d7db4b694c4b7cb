"""Rotated boxes in bird's-eye view: footprints, IoU, frame changes.

A BEV box is (x, y, length, width, yaw): centre [m], size along its own x and y [m], yaw [rad] about
+z from +x of the frame it is given in. Footprints are (4, 2) corner arrays, counter-clockwise.
IoU is the area of the footprints' intersection over the area of their union (the definition of
the collaborative-perception literature: polygon intersection, no height); the intersection is
:func:`cosim.traffic.metrics.convex_overlap_area` (Sutherland-Hodgman clipping of convex polygons).
"""

from __future__ import annotations

import math

import numpy as np

from cosim.traffic.metrics import convex_overlap_area

_EPS = 1e-12


def footprints(centers_xy: np.ndarray, sizes_lw: np.ndarray, yaws_rad: np.ndarray) -> np.ndarray:
    """Corners (N, 4, 2) [m] of N boxes, counter-clockwise, from centres (N, 2), sizes (N, 2), yaws (N,)."""
    c = np.asarray(centers_xy, np.float64).reshape(-1, 2)
    s = np.asarray(sizes_lw, np.float64).reshape(-1, 2)
    yaw = np.asarray(yaws_rad, np.float64).reshape(-1)
    unit = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])  # CCW in the box frame
    local = unit[None, :, :] * s[:, None, :]
    cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x = cos * local[..., 0] - sin * local[..., 1] + c[:, None, 0]
    y = sin * local[..., 0] + cos * local[..., 1] + c[:, None, 1]
    return np.stack([x, y], axis=-1)


def polygon_area(poly: np.ndarray) -> float:
    """Signed area [m^2] of a simple polygon (K, 2) (positive when counter-clockwise); 0 for K < 3."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """BEV IoU (N, M) between footprints ``a`` (N, 4, 2) and ``b`` (M, 4, 2)."""
    a = np.asarray(a, np.float64).reshape(-1, 4, 2)
    b = np.asarray(b, np.float64).reshape(-1, 4, 2)
    out = np.zeros((len(a), len(b)))
    if len(a) == 0 or len(b) == 0:
        return out
    ca, cb = a.mean(axis=1), b.mean(axis=1)
    ra = np.linalg.norm(a - ca[:, None], axis=2).max(axis=1)
    rb = np.linalg.norm(b - cb[:, None], axis=2).max(axis=1)
    area_a = np.array([abs(polygon_area(p)) for p in a])
    area_b = np.array([abs(polygon_area(p)) for p in b])
    dist = np.linalg.norm(ca[:, None, :] - cb[None, :, :], axis=2)
    for i, j in zip(*np.nonzero(dist < ra[:, None] + rb[None, :]), strict=True):
        inter = convex_overlap_area(a[i], b[j])
        union = area_a[i] + area_b[j] - inter
        out[i, j] = inter / union if union > _EPS else 0.0
    return out


def yaw_from_matrix(r: np.ndarray) -> np.ndarray:
    """Yaw [rad] of rotation matrices (..., 3, 3): the heading of their x axis projected on the xy plane."""
    return np.arctan2(r[..., 1, 0], r[..., 0, 0])


def quat_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of unit quaternions (N, 4) in (x, y, z, w) order."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def to_frame(frame_from_map: np.ndarray, centers_m: np.ndarray, rotations: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) [m] and yaws (N,) [rad] of map boxes expressed in another frame (4x4 ``frame <- map``)."""
    c = np.asarray(centers_m, np.float64).reshape(-1, 3)
    r = frame_from_map[:3, :3] @ quat_matrices(rotations)
    return c @ frame_from_map[:3, :3].T + frame_from_map[:3, 3], yaw_from_matrix(r)


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi
