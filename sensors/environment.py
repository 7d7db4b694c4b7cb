"""Weather and lighting as the sensors feel them: extinction, sun, sky, artificial light, rain.

Fog follows Koschmieder's law: extinction ``beta = 3.0 / visibility`` [1/m] (5 % contrast at the
visibility distance); light and laser pulses travel through it with transmittance ``exp(-beta d)``
(two-way for LiDAR). Rain adds a weaker extinction ``beta_rain = 0.00045 * rate^0.63`` [1/m]
(rate in mm/h), LiDAR dropout, range noise and spurious near returns, and darkens the cameras.
Under rain the roads are wet (``Atmosphere.wet_roads``): the cameras draw them darker and glossy
(:mod:`cosim.sensors.surface`), with the constants below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.scenario.model import EnvironmentSpec

#: Street lamps and headlights: sodium-ish colour of artificial light (linear RGB), cameras and surfaces.
LAMP_RGB = np.array([1.0, 0.82, 0.55], np.float32)

#: Defaults when the scenario leaves them open.
DEFAULT_FOG_VISIBILITY_M = 100.0
DEFAULT_RAIN_RATE_MM_H = 10.0
CLEAR_VISIBILITY_M = 20_000.0

#: Wet surfaces under rain: diffuse albedo factor of a wet road (water fills the asphalt's pores:
#: about half as bright), of wet lane paint and of wet paving and roofs.
WET_ROAD_ALBEDO = 0.55
WET_MARKING_ALBEDO = 0.8
WET_PAVING_ALBEDO = 0.7
#: Water film on a wet road: Fresnel reflectance at normal incidence (water, Schlick's approximation),
#: Blinn-Phong exponent of its specular lobe (a rough film: highlights stretch towards the camera), and
#: the share of the road the film covers on paving and roofs (roads 1).
WET_F0 = 0.02
WET_SHININESS = 120.0
WET_FILM_PAVING = 0.5
#: [linear] radiance of a lit window at night (times the lighting's artificial level), warm white
WINDOW_RGB = (1.0, 0.78, 0.5)
WINDOW_RADIANCE = 0.35
#: share of windows lit at night
LIT_WINDOW_FRACTION = 0.35


@dataclass(frozen=True)
class Atmosphere:
    """Everything the LiDAR and camera models need from ``scenario.environment``."""

    weather: str
    lighting: str
    visibility_m: float  # [m] meteorological visibility (fog); CLEAR_VISIBILITY_M otherwise
    rain_rate_mm_h: float  # [mm/h]
    sun_dir: np.ndarray  # (3,) unit vector towards the sun, map ENU
    sun_rgb: np.ndarray  # (3,) direct light colour x intensity
    ambient_rgb: np.ndarray  # (3,) sky/ambient light on every surface
    sky_zenith: np.ndarray  # (3,) sky colour overhead (0..1)
    sky_horizon: np.ndarray  # (3,) sky colour at the horizon
    fog_rgb: np.ndarray  # (3,) colour that distant things fade to
    artificial: float  # 0..1 how strongly street lights and headlights shine (night 1, dusk 0.5)
    exposure: float  # camera gain
    wet_roads: bool = False  # rain: roads darker and glossy (WET_* constants)

    @property
    def casts_shadows(self) -> bool:
        """Whether the sun is strong and high enough for the cameras to trace its shadows."""
        return float(np.max(self.sun_rgb)) >= 0.05 and float(self.sun_dir[2]) > 0.02

    @property
    def beta_fog(self) -> float:
        """Fog extinction [1/m]."""
        return 3.0 / self.visibility_m if self.visibility_m < CLEAR_VISIBILITY_M else 0.0

    @property
    def beta_rain(self) -> float:
        """Rain extinction [1/m]."""
        return 0.00045 * self.rain_rate_mm_h**0.63 if self.rain_rate_mm_h > 0 else 0.0

    @property
    def beta(self) -> float:
        """Total extinction [1/m]."""
        return self.beta_fog + self.beta_rain


def _sun(elev_deg: float, azim_deg: float) -> np.ndarray:
    e, a = math.radians(elev_deg), math.radians(azim_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def sun_azimuth_deg(seed: int | None, lighting: str) -> float:
    """The sun's azimuth [deg] (ENU, counter-clockwise from east): drawn per episode from ``seed``
    (uniform over the circle), or the fixed default of ``lighting`` when ``seed`` is None."""
    if seed is None:
        return {"day": 210.0, "dusk": 260.0}.get(lighting, 120.0)
    return float(np.random.default_rng([seed, 0x5A11]).uniform(0.0, 360.0))


def atmosphere(env: EnvironmentSpec, seed: int | None = None) -> Atmosphere:
    """The sensor-side view of ``env``; ``seed`` (the scenario's) draws the sun's azimuth
    (:func:`sun_azimuth_deg`)."""
    v = np.asarray
    az = sun_azimuth_deg(seed, env.lighting)
    if env.lighting == "day":
        sun_dir, sun, amb = _sun(50, az), v([1.0, 0.97, 0.92]), v([0.38, 0.40, 0.45])
        zen, hor, art, expo = v([0.25, 0.45, 0.85]), v([0.70, 0.80, 0.92]), 0.0, 1.0
    elif env.lighting == "dusk":
        # a low sun (15 deg up): long shadows
        sun_dir, sun, amb = _sun(15, az), v([0.85, 0.50, 0.28]), v([0.16, 0.14, 0.18])
        zen, hor, art, expo = v([0.18, 0.20, 0.40]), v([0.85, 0.50, 0.30]), 0.5, 1.1
    else:
        sun_dir, sun, amb = _sun(30, az), v([0.006, 0.007, 0.010]), v([0.006, 0.007, 0.011])
        zen, hor, art, expo = v([0.002, 0.002, 0.008]), v([0.012, 0.012, 0.02]), 1.0, 1.0
    fog = np.clip(0.55 * hor + 0.45 * np.mean(hor), 0, 1)
    visibility = CLEAR_VISIBILITY_M
    rain = 0.0
    if env.weather == "cloudy":
        amb = amb * 1.15 + 0.5 * sun * max(sun_dir[2], 0.1)
        sun = sun * 0.15
        grey = np.mean(hor)
        zen, hor = 0.35 * zen + 0.65 * grey * v([0.9, 0.9, 0.95]), 0.3 * hor + 0.7 * grey
    elif env.weather == "foggy":
        visibility = env.fog_visibility_m or DEFAULT_FOG_VISIBILITY_M
        amb = amb * 1.2 + 0.4 * sun * max(sun_dir[2], 0.1)
        sun = sun * 0.25
        fog = np.clip(np.full(3, np.mean(hor)) * (0.75 if env.lighting == "day" else 0.8), 0, 1)
        zen = hor = fog
    elif env.weather == "rainy":
        rain = env.rain_rate_mm_h if env.rain_rate_mm_h is not None else DEFAULT_RAIN_RATE_MM_H
        amb = amb * 1.0 + 0.3 * sun * max(sun_dir[2], 0.1)
        sun = sun * 0.1
        grey = np.mean(hor) * 0.75
        zen, hor = np.full(3, grey * 0.85), np.full(3, grey)
        fog = np.full(3, grey)
    if env.fog_visibility_m is not None and env.weather != "foggy":
        visibility = env.fog_visibility_m
    if env.rain_rate_mm_h is not None and env.weather != "rainy":
        rain = env.rain_rate_mm_h
    return Atmosphere(
        env.weather, env.lighting, float(visibility), float(rain), sun_dir, v(sun, np.float64),
        v(amb, np.float64), v(zen, np.float64), v(hor, np.float64), v(fog, np.float64), art, expo, rain > 0,
    )
