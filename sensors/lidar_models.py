"""The renderer's side of the datasheet LiDAR models (docs/lidar_models.md): ring tables and intensity transfers.

The presets themselves (the numbers of each sheet) are scenario data, :mod:`cosim.scenario.lidar_presets`;
the loader expands ``sensors.<kind>.lidar.model`` into :class:`LidarSpec` fields. Here:

- :func:`ring_elevations_deg`: a spinning LiDAR's ring elevations, the sheet's table when the spec has
  one (``elevations_deg``), else evenly spaced over the vertical field of view (the generic rig);
- intensity transfers (a registry, :func:`register_transfer`): from cosim's physical return, the
  range-normalised reflectivity ``I = (rho_d cos(alpha) + rho_r) exp(-2 beta R)`` in [0, 1] of
  :func:`cosim.sensors.lidar.intensity_model`, to what the sensor reports, stored in [0, 1]:

  - ``linear``: ``I`` itself (the generic rig; the bytes of every episode before the presets);
  - ``calibrated_100``: Velodyne's (VLP-16, VLP-32C), Ouster's and Hesai's calibrated reflectivity byte:
    0..100 is the diffuse reflectance in percent, 101..255 retro-reflectors; stored as byte / 255, so the
    stored count is the sensor's byte;
  - ``livox_150``: Livox's byte: 0..150 diffuse (0..100 %), 151..255 retro-reflectors; stored as byte / 255;
  - ``kitti``: KITTI's remission from the HDL-64E S2, which reports the raw return strength, not a
    range-normalised reflectivity: the received power ``I (R0 / R)^2`` (R0 = :data:`KITTI_REF_RANGE_M`)
    through a compressive response, ``KITTI_GAIN * (I (R0 / R)^2) ** KITTI_EXPONENT`` (the two numbers fitted
    to KITTI's intensity histogram on a town scene, docs/realism.md); retro-reflectors from
    :data:`KITTI_RETRO_FLOOR` up to 1.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cosim.registry import Registry
from cosim.scenario.model import LidarSpec

#: ``(intensity (N,) float64 in [0, 1], retro (N,) bool, range_m (N,) float64) -> reported (N,) in [0, 1]``
Transfer = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]

#: KITTI remission = KITTI_GAIN * (I (KITTI_REF_RANGE_M / R)^2) ** KITTI_EXPONENT (diffuse returns); the gain and
#: exponent fitted on the town scene (benchmarks/lidar_realism.py --fit-kitti, docs/realism.md)
KITTI_GAIN = 0.44
KITTI_EXPONENT = 0.32
KITTI_REF_RANGE_M = 20.0  # [m]
KITTI_MIN_RANGE_M = 1.0  # [m] ranges below count as this (the response saturates anyway)
#: retro-reflectors' remission in KITTI: from this value up to 1 with their return strength
KITTI_RETRO_FLOOR = 0.7


#: intensity transfers by name (one of ``LidarSpec.intensity_transfer``); add one with ``@register_transfer(name)``
TRANSFERS: Registry[Transfer] = Registry("intensity transfer")
register_transfer = TRANSFERS.register


def transfer(name: str) -> Transfer:
    return TRANSFERS.get(name)


def needs_retro(spec: LidarSpec) -> bool:
    """Whether the spec's transfer tells retro-reflectors apart (the renderer then finds which returns are)."""
    return spec.intensity_transfer != "linear"


def report_intensity(spec: LidarSpec, intensity: np.ndarray, retro: np.ndarray | None,
                     range_m: np.ndarray | None) -> np.ndarray:
    """What the sensor of ``spec`` reports (N,) float64 in [0, 1] for physical returns ``intensity`` (N,);
    ``retro`` (N,) bool: returns from retro-reflective surfaces (None: none); ``range_m`` (N,) [m]."""
    i = np.clip(np.asarray(intensity, np.float64), 0.0, 1.0)
    if spec.intensity_transfer == "linear":
        return i
    n = len(i)
    r = np.zeros(n, bool) if retro is None else np.asarray(retro, bool)
    rng = np.zeros(n) if range_m is None else np.asarray(range_m, np.float64)
    return np.clip(transfer(spec.intensity_transfer)(i, r, rng), 0.0, 1.0)


@register_transfer("linear")
def linear(i: np.ndarray, retro: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    return i


def _byte_scale(i: np.ndarray, retro: np.ndarray, diffuse_max: int) -> np.ndarray:
    """A reflectivity byte / 255: diffuse returns 0..``diffuse_max`` for 0..100 % reflectance, retro-reflectors
    ``diffuse_max`` + 1 .. 255 by their return strength."""
    byte = np.where(retro, diffuse_max + 1 + (254 - diffuse_max) * i, diffuse_max * i)
    return np.rint(byte) / 255.0


@register_transfer("calibrated_100")
def calibrated_100(i: np.ndarray, retro: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    return _byte_scale(i, retro, 100)


@register_transfer("livox_150")
def livox_150(i: np.ndarray, retro: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    return _byte_scale(i, retro, 150)


@register_transfer("kitti")
def kitti(i: np.ndarray, retro: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    power = i * (KITTI_REF_RANGE_M / np.maximum(range_m, KITTI_MIN_RANGE_M)) ** 2
    diffuse = KITTI_GAIN * power ** KITTI_EXPONENT
    return np.where(retro, KITTI_RETRO_FLOOR + (1.0 - KITTI_RETRO_FLOOR) * i, diffuse)


def ring_elevations_deg(spec: LidarSpec) -> np.ndarray:
    """Ring elevations (C,) float64 [deg], ring 0 the lowest: the spec's table, else evenly spaced from
    ``lower_fov_deg`` to ``upper_fov_deg``."""
    if spec.elevations_deg is not None:
        return np.asarray(spec.elevations_deg, np.float64)
    return np.linspace(spec.lower_fov_deg, spec.upper_fov_deg, spec.channels)
