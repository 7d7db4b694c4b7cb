"""IMU: specific force and angular rate in the body frame (FLU), with bias and white noise.

Biases are constant over an episode (drawn once per agent from the scenario seed, see
:func:`imu_biases`); noise is drawn per sample from the tick's generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.scenario.model import ImuSpec
from cosim.snapshot import AgentState


@dataclass(frozen=True)
class ImuFrame:
    """``linear_acceleration_mps2`` (3,) specific force and ``angular_velocity_radps`` (3,), body FLU;
    ``orientation`` (x, y, z, w) map <- body (ground truth attitude, as an AHRS would report)."""

    agent_id: str
    linear_acceleration_mps2: tuple[float, float, float]
    angular_velocity_radps: tuple[float, float, float]
    orientation: tuple[float, float, float, float]


def imu_biases(spec: ImuSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-episode accelerometer (3,) [m/s^2] and gyro (3,) [rad/s] biases."""
    return rng.standard_normal(3) * spec.accel_bias_mps2, rng.standard_normal(3) * spec.gyro_bias_radps


def render_imu(agent: AgentState, spec: ImuSpec, biases: tuple[np.ndarray, np.ndarray], rng: np.random.Generator,
               noise: bool = True) -> ImuFrame:
    acc = np.asarray(agent.specific_force_mps2, np.float64)
    gyr = np.asarray(agent.angular_rate_radps, np.float64)
    if noise:
        acc = acc + biases[0] + rng.standard_normal(3) * spec.accel_noise_mps2
        gyr = gyr + biases[1] + rng.standard_normal(3) * spec.gyro_noise_radps
    return ImuFrame(agent.agent_id, tuple(float(v) for v in acc), tuple(float(v) for v in gyr),
                    tuple(float(v) for v in agent.rotation))
