"""Label fit, the ``boxes`` check of ``cosim validate``: sensor data agrees with the label boxes.

- LiDAR: every return with an object's instance id lies inside that object's box, within
  :data:`LIDAR_TOLERANCE_M` plus :data:`NOISE_SIGMAS` times the LiDAR's range noise. A sweep with
  motion distortion is first moved into the sensor frame at the tick (:func:`cosim.io.deskew.deskew`,
  the agent's velocity from the labels, its body rates from its IMU when it has one) and each return is
  compared with the box moved by the object's velocity to the return's firing time, as the renderer
  moved it (docs/episode_format.md 3.4).
- Cameras: every pixel of an object's instance id lies inside the object's box projected through the
  camera's calibration (lens included), within :data:`PIXEL_TOLERANCE` pixels; objects not wholly in
  front of the camera are skipped.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cosim.geometry import rotation_matrix
from cosim.io.deskew import deskew
from cosim.io.format import STATIC_INSTANCE_MIN

#: [m] how far a LiDAR return may lie outside its object's box, besides the range noise (positions are
#: stored to 1/128 m, the renderer's meshes touch their boxes within 1 cm)
LIDAR_TOLERANCE_M = 0.1
#: the range noise allowed, in standard deviations of the LiDAR's ``range_noise_m``
NOISE_SIGMAS = 4.0
#: [px] how far an instance pixel may lie outside its object's projected box
PIXEL_TOLERANCE = 1.5
#: samples along each of a box's 12 edges when projecting it (a lens bends the edges)
EDGE_SAMPLES = 8


def object_boxes(objs: dict[str, Any]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """track id -> (centre (3,), half size (3,), rotation map <- body (3, 3), velocity (3,)) of ``/labels/objects``."""
    out = {}
    for o in objs.get("objects", []):
        try:
            out[int(o["track_id"])] = (np.asarray(o["center_m"], np.float64), np.asarray(o["size_m"], np.float64) / 2,
                                       rotation_matrix(tuple(float(q) for q in o["rotation"])),
                                       np.asarray(o["velocity_mps"], np.float64))
        except (KeyError, TypeError, ValueError):
            continue  # reported by the labels check
    return out


def lidar_excess(cloud: Any, lidar_to_map: np.ndarray, base_to_map: np.ndarray, velocity: Any, rates: Any,
                 boxes: dict) -> dict[int, tuple[float, int, int]]:
    """Per object hit by the sweep ``cloud`` (:class:`cosim.io.decode.PointCloud`): (how far [m] its
    returns reach outside its box at most, how many lie outside by more than :data:`LIDAR_TOLERANCE_M`,
    how many returns it has)."""
    ids = cloud.points["instance_id"].astype(np.int64) if "instance_id" in cloud.fields else np.zeros(0, np.int64)
    keep = (ids > 0) & (ids < STATIC_INSTANCE_MIN)
    if not keep.any():
        return {}
    xyz = cloud.xyz[keep]
    tau = np.zeros(len(xyz))
    if "t_offset_ns" in cloud.fields:
        t_off = cloud.points["t_offset_ns"][keep]
        if np.any(t_off):
            lidar_to_base = np.linalg.inv(base_to_map) @ lidar_to_map
            xyz = deskew(xyz, t_off, base_to_map, lidar_to_base, velocity, rates)
            tau = t_off.astype(np.float64) * 1e-9
    pts = xyz @ lidar_to_map[:3, :3].T + lidar_to_map[:3, 3]
    ids = ids[keep]
    out = {}
    for tid in np.unique(ids):
        box = boxes.get(int(tid))
        if box is None:
            continue  # a dangling id: the labels check reports it
        c, half, rot, v = box
        sel = ids == tid
        local = (pts[sel] - c - tau[sel, None] * v) @ rot
        over = (np.abs(local) - half).max(axis=1)
        out[int(tid)] = (float(over.max()), int(np.count_nonzero(over > LIDAR_TOLERANCE_M)), int(sel.sum()))
    return out


def _unit_box_samples() -> np.ndarray:
    """Points (12 x EDGE_SAMPLES, 3) along the edges of the box [-1, 1]^3 (its corners among them)."""
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    edges = [(i, j) for i in range(8) for j in range(i + 1, 8) if np.abs(corners[i] - corners[j]).sum() == 2]
    s = np.linspace(0.0, 1.0, EDGE_SAMPLES)[:, None]
    return np.concatenate([corners[i] + s * (corners[j] - corners[i]) for i, j in edges])


_UNIT_BOX_SAMPLES = _unit_box_samples()


def _box_samples(c: np.ndarray, half: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """Points (12 x EDGE_SAMPLES, 3) along the edges of a box, in map."""
    return (_UNIT_BOX_SAMPLES * half) @ rot.T + c


def instance_ids(instance: np.ndarray) -> tuple[np.ndarray, ...]:
    """The object ids (0 < id < ``STATIC_INSTANCE_MIN``) of an instance image (H, W) or (H, W, C), sorted, and
    their pixel extents: first column, last column + 1, first row, last row + 1 (one pass,
    :func:`cosim.pixel_kernels.instance_extents`)."""
    from cosim.pixel_kernels import instance_extents

    img = np.asarray(instance)
    if img.ndim == 3:
        img = img[..., 0]
    return instance_extents(img, 0, STATIC_INSTANCE_MIN)


def pixel_excess(instance: np.ndarray | tuple, calib: Any, optical_to_map: np.ndarray, boxes: dict) -> dict[int, float]:
    """Per object in the instance image (H, W) (or its :func:`instance_ids`): how many pixels its pixels reach
    outside its projected box at most (objects not wholly in front of the camera are left out)."""
    ids, lo_u, hi_u, lo_v, hi_v = instance if isinstance(instance, tuple) else instance_ids(instance)
    if not len(ids):
        return {}
    map_to_optical = np.linalg.inv(optical_to_map)
    out = {}
    for k, tid in enumerate(ids):
        box = boxes.get(int(tid))
        if box is None:
            continue
        pts = _box_samples(*box[:3]) @ map_to_optical[:3, :3].T + map_to_optical[:3, 3]
        if np.any(pts[:, 2] <= 0.05):
            continue  # partly behind the camera: its projection is unbounded
        uv, _ = calib.project(pts)
        (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
        out[int(tid)] = float(max(u0 - lo_u[k], hi_u[k] - u1, v0 - lo_v[k], hi_v[k] - v1))
    return out
