"""Undo LiDAR motion distortion (docs/episode_format.md 3.4) with the recorded poses.

A sweep's points are each measured in the sensor frame of their firing, ``t_offset_ns`` (<= 0) before
the sweep's end, which is the message's (and the tick's) time. :func:`deskew` moves every point into
the sensor frame at the sweep's end with the model the renderer uses: the platform moves with its
velocity and turns with its body rates, constant over the sweep. :func:`deskew_tick` takes both from
the episode: the pose from ``/tf``, the velocity from ``/labels/objects``, the body rates from the
agent's ``/<agent>/imu`` when it has one (an IMU's rates carry its bias and noise; zero without one).
Points of other moving objects keep their own motion: deskewing corrects the ego motion only.
:func:`objects_to_tick` also moves the points of each labelled moving object by its recorded velocity
from the firing time to the sweep's end, as if every object had stood at its tick pose during the sweep.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _turn(v: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (N, 3) rotated by the rotation vectors ``rotvec`` (N, 3) (Rodrigues)."""
    theta = np.linalg.norm(rotvec, axis=1, keepdims=True)
    k = rotvec / np.where(theta > 0, theta, 1.0)
    c, s = np.cos(theta), np.sin(theta)
    return v * c + np.cross(k, v) * s + k * (k * v).sum(axis=1, keepdims=True) * (1.0 - c)


def deskew(xyz: np.ndarray, t_offset_ns: np.ndarray, base_to_map: np.ndarray, lidar_to_base: np.ndarray,
           velocity_mps: Any = (0.0, 0.0, 0.0), angular_rate_radps: Any = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Points (N, 3) float64 [m] in the sensor frame at the sweep's end.

    ``xyz`` (N, 3) as stored (each in the sensor frame of its firing); ``t_offset_ns`` (N,) <= 0;
    ``base_to_map`` (4, 4) ``map <- <agent>/base_link`` at the sweep's end; ``lidar_to_base`` (4, 4)
    ``base_link <- lidar``; ``velocity_mps`` (3,) in map; ``angular_rate_radps`` (3,) body (FLU).
    """
    xyz = np.asarray(xyz, np.float64)
    tau = np.asarray(t_offset_ns, np.float64)[:, None] * 1e-9
    rb, p = base_to_map[:3, :3], base_to_map[:3, 3]
    rm, m = lidar_to_base[:3, :3], lidar_to_base[:3, 3]
    turn = np.asarray(angular_rate_radps, np.float64)[None, :] * tau
    in_body = _turn(xyz @ rm.T + m, turn)  # the point in the body frame at the sweep's end orientation
    in_map = p + np.asarray(velocity_mps, np.float64) * tau + in_body @ rb.T
    return (in_map - (p + rb @ m)) @ (rb @ rm)


def deskew_tick(tick: Any, agent: str) -> np.ndarray:
    """:func:`deskew` of ``tick.points(agent)`` with the tick's recorded poses (module docstring)."""
    cloud = tick.points(agent)
    if "t_offset_ns" not in cloud.fields:
        return cloud.xyz
    tf = tick.transforms
    base_to_map = tf.to_root(f"{agent}/base_link")
    lidar_to_base = np.linalg.inv(base_to_map) @ tf.to_root(cloud.frame_id)
    velocity = next((a.get("velocity_mps", (0.0, 0.0, 0.0)) for a in tick.labels.agents if a["agent_id"] == agent),
                    (0.0, 0.0, 0.0))
    imu_topic = f"/{agent}/imu"
    rates = tick[imu_topic]["angular_velocity_radps"] if imu_topic in tick else (0.0, 0.0, 0.0)
    return deskew(cloud.xyz, cloud.points["t_offset_ns"], base_to_map, lidar_to_base, velocity, rates)


def objects_to_tick(xyz: np.ndarray, t_offset_ns: np.ndarray, instance_id: np.ndarray, sensor_to_map: np.ndarray,
                    velocities_mps: dict[int, Any]) -> np.ndarray:
    """Points (N, 3) in the sensor frame at the sweep's end (:func:`deskew`'s output), each point of an object
    in ``velocities_mps`` (track id -> velocity (3,) in map) moved by that velocity x (0 - its ``t_offset_ns``):
    where that surface is at the sweep's end (the renderer moves actors with their velocity, constant over the
    sweep, in time slices: what is left is the slice's half width times the speed)."""
    out = np.array(xyz, np.float64, copy=True)
    to_sensor = np.asarray(sensor_to_map, np.float64)[:3, :3].T
    moving = sorted((int(t), v) for t, v in velocities_mps.items() if np.any(v))
    if not moving:
        return out
    tracks = np.array([t for t, _ in moving], np.int64)
    shift = np.array([to_sensor @ np.asarray(v, np.float64) for _, v in moving])  # (M, 3) per track, in the sensor
    ids = np.asarray(instance_id).astype(np.int64)
    at = np.minimum(np.searchsorted(tracks, ids), len(tracks) - 1)  # one lookup for all points, not one pass a track
    sel = tracks[at] == ids
    out[sel] -= (np.asarray(t_offset_ns, np.float64) * 1e-9)[sel, None] * shift[at[sel]]
    return out


def objects_to_tick_of(tick: Any, agent: str, xyz: np.ndarray) -> np.ndarray:
    """:func:`objects_to_tick` of ``xyz`` (``tick.points(agent)``, compensated by :func:`deskew_tick`) with the
    tick's labelled velocities."""
    cloud = tick.points(agent)
    if "t_offset_ns" not in cloud.fields:
        return xyz
    lab = tick.labels
    velocities = {int(t): v for t, v in zip(lab.track_ids, lab.velocities_mps, strict=True)}
    return objects_to_tick(xyz, cloud.points["t_offset_ns"], cloud.points["instance_id"],
                           tick.transforms.to_root(cloud.frame_id), velocities)
