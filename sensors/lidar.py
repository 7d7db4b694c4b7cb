"""Spinning LiDAR: one ray per (channel, azimuth) over a full sweep, cast at the tick's pose.

Output points are in the sensor frame ``<agent>/lidar`` (FLU at the mount). Intensity is the
surface reflectivity times the cosine of the incidence angle times the two-way atmospheric
transmittance. Weather (see :mod:`cosim.sensors.environment`): fog removes returns beyond the
visibility distance and thins those approaching it, dims the rest, and adds near-range backscatter;
rain adds dropout, range noise and spurious near returns from drops.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from cosim.scenario.model import LidarSpec

from .environment import Atmosphere
from .rig import Pose, rotate
from .scene import StaticHits, TickScene

MIN_RANGE_M = 0.3  # [m] returns closer than this are not reported (housing, mount)


@dataclass(frozen=True)
class LidarFrame:
    """One sweep. N returns; every array has length N and row i describes return i.

    ``points`` (N, 3) float32 [m] in the sensor frame; ``intensity`` (N,) float32 in [0, 1];
    ``ring`` (N,) uint16 (0 = lowest channel); ``class_id`` (N,) uint8 semantic id (0 for spurious
    weather returns); ``instance_id`` (N,) uint32 (track id, static instance id, or 0).
    """

    agent_id: str
    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])


@lru_cache(maxsize=16)
def beam_pattern(spec: LidarSpec) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions (C * A, 3) float64 in the sensor frame and ring index (C * A,) uint16.

    Channels are evenly spaced from ``lower_fov_deg`` (ring 0) to ``upper_fov_deg``; azimuths cover
    360 deg counter-clockwise from the sensor's +x at ``horizontal_resolution_deg``.
    """
    n_az = max(1, round(360.0 / spec.horizontal_resolution_deg))
    elev = np.radians(np.linspace(spec.lower_fov_deg, spec.upper_fov_deg, spec.channels))
    az = np.arange(n_az) * (2 * math.pi / n_az)
    e, a = np.meshgrid(elev, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    ring = np.repeat(np.arange(spec.channels, dtype=np.uint16), n_az)
    return d, ring


def render_lidar(
    agent_id: str,
    spec: LidarSpec,
    pose: Pose,
    scene: TickScene,
    atm: Atmosphere,
    rng: np.random.Generator,
    exclude_track: int | None = None,
    noise: bool = True,
    fixed: StaticHits | None = None,
) -> LidarFrame:
    """Cast one sweep from ``pose`` (map <- sensor) and apply the sensor and weather models.

    Random draws (in this order, always the full ray count so the stream does not depend on the
    scene): range noise, dropout, weather thinning, spurious returns. ``noise=False`` turns every
    random effect off (exact ranges, for tests). ``fixed``: the sensor's :class:`StaticHits` when
    it does not move between ticks (same result, the static world cast once).
    """
    d_sensor, ring = beam_pattern(spec)
    n = d_sensor.shape[0]
    d_map = rotate(d_sensor, pose.rotation)
    rays = np.empty((n, 6), np.float32)
    rays[:, :3] = pose.position_m
    rays[:, 3:] = d_map
    if fixed is None:
        t, gid = scene.cast(rays, exclude_track, MIN_RANGE_M)
    else:
        key = pose.rotation.tobytes() + pose.position_m.tobytes()
        t, gid = fixed.cast(scene, key, rays, exclude_track, MIN_RANGE_M)
    hit = t <= spec.range_m
    r = np.where(hit, t, 0.0).astype(np.float64)

    lab = scene.labels
    normals = np.take(lab["normal"], gid, axis=0)
    cos_inc = np.abs((normals * rays[:, 3:]).sum(axis=1))
    intensity = np.take(lab["reflectivity"], gid) * cos_inc
    if atm.beta > 0:
        intensity = intensity * np.exp(-2.0 * atm.beta * r)
    cls = np.take(lab["semantic"], gid)
    inst = np.take(lab["instance"], gid)

    if noise:
        u_noise = rng.standard_normal(n)
        u_drop = rng.random(n)
        u_weather = rng.random(n)
        u_spur = rng.random(n)
        u_spur_r = rng.random(n)
        rain = atm.rain_rate_mm_h
        sigma = spec.range_noise_m + 0.0015 * rain
        r = np.where(hit, r + sigma * u_noise, r)
        p_drop = spec.dropout + min(0.5, 0.004 * rain)
        hit &= u_drop >= p_drop
        if atm.beta_fog > 0:
            vis = atm.visibility_m
            # detection probability falls towards the visibility distance, zero beyond
            p_keep = np.clip(1.0 - (r / vis) ** 3, 0.0, 1.0) * (r <= vis)
            hit &= u_weather < p_keep
            p_back = min(0.2, 1.5 / vis)
            spur = u_spur < p_back
            spur_r = 0.5 + u_spur_r * min(6.0, 0.1 * vis)
        elif rain > 0:
            spur = u_spur < min(0.05, 0.0008 * rain)
            spur_r = 0.5 + u_spur_r * 9.5
        else:
            spur = np.zeros(n, bool)
            spur_r = np.zeros(n)
        spur &= ~hit | (spur_r < r)
        r = np.where(spur, spur_r, r)
        intensity = np.where(spur, 0.02 + 0.05 * u_spur_r, intensity)
        cls = np.where(spur, 0, cls)
        inst = np.where(spur, 0, inst)
        hit |= spur

    idx = np.nonzero(hit)[0]
    pts = (d_sensor[idx] * r[idx, None]).astype(np.float32)
    return LidarFrame(
        agent_id,
        pts,
        np.clip(intensity[idx], 0.0, 1.0).astype(np.float32),
        ring[idx],
        cls[idx].astype(np.uint8),
        inst[idx].astype(np.uint32),
    )
