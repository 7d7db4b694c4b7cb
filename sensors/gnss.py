"""GNSS receiver: the antenna's map position as a WGS-84 fix, with Gaussian noise.

The map frame is a local tangent plane (ENU) at the world's geo origin; the fix uses the
ellipsoid's meridian and prime-vertical radii there (error below 1 mm over a few km).

A sensor kind of :mod:`cosim.sensors.kinds` (``RigSpec.gnss``, ``/<agent>/gnss`` as ``foxglove.LocationFix``),
registered with :mod:`cosim.sensors.sensor_kind`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

from cosim.scenario.model import GnssSpec

from .sensor_kind import SensorContext, SensorKind, register_sensor_kind

WGS84_A_M = 6_378_137.0
WGS84_E2 = 6.69437999014e-3


@dataclass(frozen=True)
class GnssFrame:
    """A fix: latitude/longitude [deg], altitude [m] above the ellipsoid, and the ENU position
    covariance (3, 3) [m^2] (row-major as in foxglove.LocationFix: east, north, up)."""

    agent_id: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    covariance_m2: tuple[float, ...]


def enu_to_geodetic(xyz_m, origin: tuple[float, float, float]) -> tuple[float, float, float]:
    """Map (ENU) point [m] to (lat [deg], lon [deg], alt [m]) around ``origin`` (lat, lon, alt)."""
    lat0, lon0, alt0 = origin
    phi = math.radians(lat0)
    s = math.sin(phi)
    w = math.sqrt(1 - WGS84_E2 * s * s)
    r_n = WGS84_A_M / w  # prime vertical radius
    r_m = WGS84_A_M * (1 - WGS84_E2) / w**3  # meridian radius
    x, y, z = (float(c) for c in xyz_m)
    lat = lat0 + math.degrees(y / (r_m + alt0))
    lon = lon0 + math.degrees(x / ((r_n + alt0) * math.cos(phi)))
    return lat, lon, alt0 + z


def render_gnss(agent_id: str, spec: GnssSpec, antenna_map_m: np.ndarray, origin, rng: np.random.Generator,
                noise: bool = True) -> GnssFrame:
    """One fix of the antenna at ``antenna_map_m`` (3,) [m]; vertical noise is 1.5x horizontal."""
    sigma = np.array([spec.noise_m, spec.noise_m, 1.5 * spec.noise_m])
    e = rng.standard_normal(3) * sigma if noise else np.zeros(3)
    lat, lon, alt = enu_to_geodetic(np.asarray(antenna_map_m, np.float64) + e, origin)
    cov = np.diag(sigma**2)
    return GnssFrame(agent_id, lat, lon, alt, tuple(float(c) for c in cov.ravel()))


def gnss_message(agent_id: str, g: GnssFrame, t_ns: int) -> LocationFix:
    msg = LocationFix(frame_id=f"{agent_id}/gnss", latitude=g.latitude_deg, longitude=g.longitude_deg,
                      altitude=g.altitude_m, position_covariance_type=LocationFix.DIAGONAL_KNOWN)
    msg.timestamp.FromNanoseconds(int(t_ns))
    msg.position_covariance.extend(g.covariance_m2)
    return msg


def _render(ctx: SensorContext) -> GnssFrame:
    return render_gnss(ctx.agent.agent_id, ctx.spec, np.asarray(ctx.agent.position_m), ctx.world.geo_origin,
                       ctx.rng, ctx.noise)


register_sensor_kind(SensorKind("gnss", _render, gnss_message))
