"""Seeded wind at drone altitude: a steady mean wind plus turbulent gusts.

The mean wind has magnitude ``environment.wind_mps`` and a direction drawn once per episode; gusts
are a first-order Gauss-Markov (Ornstein-Uhlenbeck) process per axis, the time-domain form of a
Dryden spectrum with a fixed correlation time, drawn per drone. All draws come from the numpy
Generator handed in (seeded from the scenario seed); the wind is a pure function of that stream.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

GUST_TIME_S = 3.0  # [s] correlation time of the horizontal gusts (L / V for L ~ 30-100 m)
VERTICAL_GUST_SHARE = 0.5  # vertical gust std as a share of the horizontal one


@dataclass(slots=True)
class Wind:
    """Wind velocity [m/s] in map ENU, advanced one physics step at a time."""

    mean_mps: np.ndarray  # (3,) steady wind, ENU
    gust_std_mps: float
    dt_s: float
    rng: np.random.Generator
    gust_mps: np.ndarray  # (3,) current gust, ENU

    @classmethod
    def create(
        cls,
        speed_mps: float,
        direction_rad: float,
        gust_std_mps: float,
        dt_s: float,
        rng: np.random.Generator,
    ) -> Wind:
        """Mean wind blowing TOWARD ``direction_rad`` (ENU yaw); gust state drawn from its stationary law."""
        mean = np.array([speed_mps * math.cos(direction_rad), speed_mps * math.sin(direction_rad), 0.0])
        sigma = gust_std_mps * np.array([1.0, 1.0, VERTICAL_GUST_SHARE])
        gust = sigma * rng.standard_normal(3)
        return cls(mean, gust_std_mps, dt_s, rng, gust)

    def step(self) -> np.ndarray:
        """Advance the gusts by ``dt_s``; returns the wind velocity (3,) [m/s] ENU."""
        a = math.exp(-self.dt_s / GUST_TIME_S)
        sigma = self.gust_std_mps * np.array([1.0, 1.0, VERTICAL_GUST_SHARE])
        self.gust_mps = a * self.gust_mps + sigma * math.sqrt(1.0 - a * a) * self.rng.standard_normal(3)
        return self.mean_mps + self.gust_mps

    @property
    def velocity_mps(self) -> np.ndarray:
        return self.mean_mps + self.gust_mps
