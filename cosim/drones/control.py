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
    _mix_inv_rows: tuple[tuple[float, ...], ...] = field(init=False)
    _inertia_f: tuple[float, float, float] = field(init=False)

    def __post_init__(self) -> None:
        self._mix_inv = np.linalg.inv(mixer_matrix(self.frame))
        self._mix_inv_rows = tuple(tuple(row) for row in self._mix_inv.tolist())
        self._inertia_f = tuple(float(v) for v in self.frame.inertia_kgm2)

    def update(self, s: BodyState, ref: Reference) -> np.ndarray:
        """Rotor thrust commands (4,) [N] that drive ``s`` toward ``ref``.

        Written in plain float arithmetic: this runs for every drone at every physics step, and numpy's
        per-call overhead on 3-vectors cost more than the arithmetic itself.
        """
        lim, k, fr, dt = self.limits, self.gains, self.frame, self.dt_s
        px, py, pz = s.position_m.tolist()
        vx, vy, vz = s.velocity_mps.tolist()
        rx, ry, rz = ref.position_m.tolist()
        fvx, fvy, fvz = ref.velocity_mps.tolist()
        fax, fay, faz = ref.accel_mps2.tolist()
        # Position -> velocity.
        cx = fvx + k.pos[0] * (rx - px)
        cy = fvy + k.pos[0] * (ry - py)
        cz = fvz + k.pos[1] * (rz - pz)
        n = math.hypot(cx, cy)
        if n > lim.max_speed_mps:
            cx, cy = cx * lim.max_speed_mps / n, cy * lim.max_speed_mps / n
        cz = min(max(cz, -lim.max_descent_mps), lim.max_climb_mps)
        # Velocity -> acceleration (PI with clamped integrator).
        ex, ey, ez = cx - vx, cy - vy, cz - vz
        ix, iy, iz = self.vel_integral.tolist()
        ix = min(max(ix + ex * dt, -4.0), 4.0)
        iy = min(max(iy + ey * dt, -4.0), 4.0)
        iz = min(max(iz + ez * dt, -4.0), 4.0)
        self.vel_integral[:] = (ix, iy, iz)
        ax = fax + k.vel[0] * ex + k.vel_i[0] * ix
        ay = fay + k.vel[0] * ey + k.vel_i[0] * iy
        az = faz + k.vel[1] * ez + k.vel_i[1] * iz
        n = math.hypot(ax, ay)
        if n > lim.max_accel_mps2:
            ax, ay = ax * lim.max_accel_mps2 / n, ay * lim.max_accel_mps2 / n
        az = min(max(az, -lim.max_vert_accel_mps2), lim.max_vert_accel_mps2)
        # Drag feed-forward at the commanded velocity (still air assumed; the integrator learns the wind).
        speed = math.sqrt(cx * cx + cy * cy + cz * cz)
        drag = (0.5 * RHO_KGPM3 * fr.drag_area_m2 * speed + fr.drag_linear_nspm) / fr.mass_kg
        ax, ay, az = ax + drag * cx, ay + drag * cy, az + drag * cz
        # Acceleration -> thrust vector, tilt-limited.
        fx, fy, fz = fr.mass_kg * ax, fr.mass_kg * ay, fr.mass_kg * (az + G_MPS2)
        f_xy = math.hypot(fx, fy)
        max_xy = fz * math.tan(lim.max_tilt_rad)
        if f_xy > max_xy:
            fx, fy = fx * max_xy / f_xy, fy * max_xy / f_xy
        n = math.sqrt(fx * fx + fy * fy + fz * fz)
        zx, zy, zz = fx / n, fy / n, fz / n
        # Yaw setpoint moves toward the reference at the yaw-rate limit.
        r = s.rotation.tolist()
        if self.yaw_setpoint_rad is None:
            self.yaw_setpoint_rad = math.atan2(r[1][0], r[0][0])
        step = lim.max_yaw_rate_radps * dt
        dyaw = wrap_angle(ref.yaw_rad - self.yaw_setpoint_rad)
        self.yaw_setpoint_rad = wrap_angle(self.yaw_setpoint_rad + min(max(dyaw, -step), step))
        hx, hy = math.cos(self.yaw_setpoint_rad), math.sin(self.yaw_setpoint_rad)
        # y_des = z_des x heading, x_des = y_des x z_des
        yx, yy, yz = -zz * hy, zz * hx, zx * hy - zy * hx
        n = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / n, yy / n, yz / n
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        rd = ((xx, yx, zx), (xy, yy, zy), (xz, yz, zz))  # columns x_des, y_des, z_des
        thrust = fx * r[0][2] + fy * r[1][2] + fz * r[2][2]
        # Attitude -> body rate (geometric error on SO(3)): e = vee(Rd^T R - R^T Rd) / 2.
        def dot_cols(a: tuple, i: int, b: list, j: int) -> float:
            return a[0][i] * b[0][j] + a[1][i] * b[1][j] + a[2][i] * b[2][j]

        e0 = 0.5 * (dot_cols(rd, 2, r, 1) - dot_cols(r, 2, rd, 1))
        e1 = 0.5 * (dot_cols(rd, 0, r, 2) - dot_cols(r, 0, rd, 2))
        e2 = 0.5 * (dot_cols(rd, 1, r, 0) - dot_cols(r, 1, rd, 0))
        w0c, w1c = -k.att[0] * e0, -k.att[0] * e1
        w2c = min(max(-k.att[1] * e2, -lim.max_yaw_rate_radps), lim.max_yaw_rate_radps)
        # Rate -> torque: tau = J alpha + w x (J w).
        w0, w1, w2 = s.rate_radps.tolist()
        j0, j1, j2 = self._inertia_f
        a0, a1, a2 = k.rate[0] * (w0c - w0), k.rate[0] * (w1c - w1), k.rate[1] * (w2c - w2)
        h0, h1, h2 = j0 * w0, j1 * w1, j2 * w2
        torque = (j0 * a0 + w1 * h2 - w2 * h1, j1 * a1 + w2 * h0 - w0 * h2, j2 * a2 + w0 * h1 - w1 * h0)
        return self.mix(thrust, torque)

    def mix(self, thrust_n: float, torque_nm) -> np.ndarray:
        """Rotor thrusts (4,) [N] for a collective thrust and body torque (3,); yaw gives way first."""
        tmax = self.frame.rotor_max_thrust_n
        thrust_n = min(max(thrust_n, 0.0), 4.0 * tmax)
        tx, ty, tz = (float(v) for v in torque_nm)
        rows = self._mix_inv_rows
        t_noyaw = [m[0] * thrust_n + m[1] * tx + m[2] * ty for m in rows]
        yaw_part = [m[3] * tz for m in rows]
        t = [a + b for a, b in zip(t_noyaw, yaw_part, strict=True)]
        if min(t) < 0.0 or max(t) > tmax:
            if min(t_noyaw) >= 0.0 and max(t_noyaw) <= tmax:
                # Largest share of the yaw torque that keeps every rotor in range.
                scale = 1.0
                for base, dy in zip(t_noyaw, yaw_part, strict=True):
                    if dy > 0:
                        scale = min(scale, (tmax - base) / dy)
                    elif dy < 0:
                        scale = min(scale, -base / dy)
                scale = max(scale, 0.0)
                t = [a + scale * b for a, b in zip(t_noyaw, yaw_part, strict=True)]
            else:
                t = t_noyaw
        return np.array([min(max(v, 0.0), tmax) for v in t])
