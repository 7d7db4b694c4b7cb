"""Guidance and control shared by every dynamics backend.

A cascade, each loop a few times faster than the one around it::

    position P (1.2/s) -> velocity PI (2.5/s) -> thrust vector and attitude (6/s) -> body rate (16/s)
    -> torque -> mixer -> 4 rotor thrust commands

with limits on horizontal and vertical speed, acceleration (which bounds the tilt), and yaw rate.
The drone tilts to accelerate: the thrust vector follows the commanded acceleration, so gusts,
motor lag and the loops' bandwidths show up as lag and overshoot, as on a real multirotor.
Frames: positions, velocities and accelerations in map ENU; rotations map <- body FLU; rates and
torques in body FLU. Runs at the physics rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cosim.drones.airframe import G_MPS2, RHO_KGPM3, ROTOR_SPIN, Airframe
from cosim.geometry import wrap_angle

E_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, slots=True)
class Limits:
    """Flight envelope the controller enforces."""

    max_speed_mps: float = 15.0  # horizontal
    max_climb_mps: float = 4.0
    max_descent_mps: float = 3.0
    max_accel_mps2: float = 7.0  # horizontal, before drag compensation
    max_vert_accel_mps2: float = 4.0
    max_tilt_rad: float = math.radians(40.0)
    max_yaw_rate_radps: float = math.radians(60.0)

    @classmethod
    def for_speed(cls, max_speed_mps: float, frame: Airframe) -> Limits:
        """Limits for a drone asked to fly up to ``max_speed_mps``: the tilt limit grows (40 to 55 deg)
        so that the thrust can still beat the drag at that speed with a 30 % margin for manoeuvre."""
        drag = (0.5 * RHO_KGPM3 * frame.drag_area_m2 * max_speed_mps + frame.drag_linear_nspm) * max_speed_mps
        tilt = math.atan2(1.3 * drag, frame.mass_kg * G_MPS2)
        return cls(max_speed_mps=max_speed_mps, max_tilt_rad=min(max(tilt, math.radians(40.0)), math.radians(55.0)))


@dataclass(frozen=True, slots=True)
class Gains:
    pos: tuple[float, float] = (1.2, 1.5)  # [1/s] horizontal, vertical
    vel: tuple[float, float] = (2.5, 4.0)  # [1/s]
    vel_i: tuple[float, float] = (0.8, 2.0)  # [1/s^2]
    att: tuple[float, float] = (6.0, 3.0)  # [1/s] roll/pitch, yaw
    rate: tuple[float, float] = (16.0, 8.0)  # [1/s] roll/pitch, yaw


@dataclass(frozen=True, slots=True)
class Reference:
    """What guidance asks for at one instant (map ENU)."""

    position_m: np.ndarray  # (3,)
    velocity_mps: np.ndarray  # (3,) feed-forward
    accel_mps2: np.ndarray  # (3,) feed-forward
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class BodyState:
    """Rigid-body state a backend reports, already in cosim frames and SI units."""

    position_m: np.ndarray  # (3,) map ENU [m]
    rotation: np.ndarray  # (3, 3) map <- body FLU
    velocity_mps: np.ndarray  # (3,) map ENU [m/s]
    rate_radps: np.ndarray  # (3,) body FLU [rad/s]
    specific_force_mps2: np.ndarray  # (3,) body FLU [m/s^2], what an IMU at the CG measures


def yaw_of(rotation: np.ndarray) -> float:
    """Heading [rad] of the body x axis projected on the map x/y plane."""
    return math.atan2(rotation[1, 0], rotation[0, 0])


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two (3,) vectors (numpy.cross is slow on tiny arrays)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _limit_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = math.hypot(v[0], v[1])
    return v * (limit / n) if n > limit else v


def mixer_matrix(frame: Airframe) -> np.ndarray:
    """(4, 4) matrix M with [T, tau_x, tau_y, tau_z] = M @ rotor_thrusts (body FLU)."""
    pos = frame.rotor_positions_m()
    return np.vstack([np.ones(4), pos[:, 1], -pos[:, 0], -ROTOR_SPIN * frame.rotor_torque_m])


@dataclass(slots=True)
class Controller:
    """Cascaded multirotor controller; ``update`` is called once per physics step of ``dt_s``."""

    frame: Airframe
    dt_s: float
    limits: Limits = field(default_factory=Limits)
    gains: Gains = field(default_factory=Gains)
    vel_integral: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_setpoint_rad: float | None = None
    _mix_inv: np.ndarray = field(init=False)
    _inertia: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self._mix_inv = np.linalg.inv(mixer_matrix(self.frame))
        self._inertia = np.array(self.frame.inertia_kgm2)

    def update(self, s: BodyState, ref: Reference) -> np.ndarray:
        """Rotor thrust commands (4,) [N] that drive ``s`` toward ``ref``."""
        lim, k = self.limits, self.gains
        # Position -> velocity.
        e_p = ref.position_m - s.position_m
        v_cmd = ref.velocity_mps + np.array([k.pos[0] * e_p[0], k.pos[0] * e_p[1], k.pos[1] * e_p[2]])
        v_cmd = _limit_norm(v_cmd, lim.max_speed_mps)
        v_cmd[2] = min(max(v_cmd[2], -lim.max_descent_mps), lim.max_climb_mps)
        # Velocity -> acceleration (PI with clamped integrator).
        e_v = v_cmd - s.velocity_mps
        self.vel_integral = np.clip(self.vel_integral + e_v * self.dt_s, -4.0, 4.0)
        kv = np.array([k.vel[0], k.vel[0], k.vel[1]])
        ki = np.array([k.vel_i[0], k.vel_i[0], k.vel_i[1]])
        a_cmd = ref.accel_mps2 + kv * e_v + ki * self.vel_integral
        a_cmd = _limit_norm(a_cmd, lim.max_accel_mps2)
        a_cmd[2] = min(max(a_cmd[2], -lim.max_vert_accel_mps2), lim.max_vert_accel_mps2)
        # Drag feed-forward at the commanded velocity (still air assumed; the integrator learns the wind).
        fr = self.frame
        speed = float(np.linalg.norm(v_cmd))
        a_cmd = a_cmd + (0.5 * RHO_KGPM3 * fr.drag_area_m2 * speed + fr.drag_linear_nspm) / fr.mass_kg * v_cmd
        # Acceleration -> thrust vector, tilt-limited.
        f = self.frame.mass_kg * (a_cmd + G_MPS2 * E_Z)
        f_xy = math.hypot(f[0], f[1])
        max_xy = f[2] * math.tan(lim.max_tilt_rad)
        if f_xy > max_xy:
            f[0] *= max_xy / f_xy
            f[1] *= max_xy / f_xy
        z_des = f / np.linalg.norm(f)
        # Yaw setpoint moves toward the reference at the yaw-rate limit.
        if self.yaw_setpoint_rad is None:
            self.yaw_setpoint_rad = yaw_of(s.rotation)
        step = lim.max_yaw_rate_radps * self.dt_s
        dyaw = wrap_angle(ref.yaw_rad - self.yaw_setpoint_rad)
        self.yaw_setpoint_rad = wrap_angle(self.yaw_setpoint_rad + min(max(dyaw, -step), step))
        x_c = np.array([math.cos(self.yaw_setpoint_rad), math.sin(self.yaw_setpoint_rad), 0.0])
        y_des = cross3(z_des, x_c)
        y_des /= np.linalg.norm(y_des)
        x_des = cross3(y_des, z_des)
        r_des = np.column_stack([x_des, y_des, z_des])
        r = s.rotation
        thrust = float(f @ r[:, 2])
        # Attitude -> body rate (geometric error on SO(3)).
        e_m = r_des.T @ r - r.T @ r_des
        e_r = 0.5 * np.array([e_m[2, 1], e_m[0, 2], e_m[1, 0]])
        w_cmd = -np.array([k.att[0] * e_r[0], k.att[0] * e_r[1], k.att[1] * e_r[2]])
        w_cmd[2] = min(max(w_cmd[2], -lim.max_yaw_rate_radps), lim.max_yaw_rate_radps)
        # Rate -> torque.
        w = s.rate_radps
        alpha = np.array([k.rate[0], k.rate[0], k.rate[1]]) * (w_cmd - w)
        torque = self._inertia * alpha + cross3(w, self._inertia * w)
        return self.mix(thrust, torque)

    def mix(self, thrust_n: float, torque_nm: np.ndarray) -> np.ndarray:
        """Rotor thrusts (4,) [N] for a collective thrust and body torque; yaw gives way first."""
        tmax = self.frame.rotor_max_thrust_n
        thrust_n = min(max(thrust_n, 0.0), 4.0 * tmax)
        wrench = np.array([thrust_n, torque_nm[0], torque_nm[1], torque_nm[2]])
        t = self._mix_inv @ wrench
        if t.min() < 0.0 or t.max() > tmax:
            wrench[3] = 0.0
            t_noyaw = self._mix_inv @ wrench
            yaw_part = t - t_noyaw
            if t_noyaw.min() >= 0.0 and t_noyaw.max() <= tmax:
                # Largest share of the yaw torque that keeps every rotor in range.
                scale = 1.0
                for base, dy in zip(t_noyaw, yaw_part, strict=True):
                    if dy > 0:
                        scale = min(scale, (tmax - base) / dy)
                    elif dy < 0:
                        scale = min(scale, -base / dy)
                t = t_noyaw + max(scale, 0.0) * yaw_part
            else:
                t = t_noyaw
        return np.clip(t, 0.0, tmax)
