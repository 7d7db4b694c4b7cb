"""Drone strategies: what each drone wants to do, as a moving reference for the shared controller.

- hover: hold a point (default above a junction) at a planned altitude;
- patrol: loop over waypoints with a speed profile that slows into corners and never runs ahead of
  a waypoint the drone has not reached;
- escort: hold an offset (target body frame) and altitude over a connected vehicle whose state
  arrives one tick late; the target is extrapolated with a constant turn-rate model.

Altitude planning: the flight altitude is the requested height above ground or, where higher, the
obstacle tops along the path (:class:`Obstacles`) plus ``clearance_m``; :func:`climb_first` keeps a
drone that is still below it from moving toward obstacles. Map frame ENU, metres.
"""

from __future__ import annotations

import itertools
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from cosim.drones.control import BodyState, Reference
from cosim.drones.obstacles import Obstacles
from cosim.geometry import wrap_angle
from cosim.protocol import EscortTarget

ZERO3 = np.zeros(3)
PATH_MARGIN_M = 10.0  # [m] lateral distance from the path inside which obstacles count for altitude
HOLD_RADIUS_M = 2.0  # [m] within this of its point a hovering drone is "hold"
TRACK_RADIUS_M = 5.0  # [m] within this of the offset point an escort is "tracking"
#: Share of the offset point's swing (turn rate x offset) fed forward to the controller. The turn rate
#: is estimated from yaws one tick old, so in short urban turns the full swing arrives late and throws
#: the drone outward as the turn ends; of 0, 0.5 and 1, half measured best in SUMO traffic and in
#: synthetic drives.
SWING_FEEDFORWARD = 0.5
GUARD_AHEAD_M = 30.0  # [m] how far ahead the climb-first rule looks
GUARD_MARGIN_M = 3.0  # [m] its margin, sideways and below
MAX_TARGET_YAW_RATE_RADPS = 2.0  # [rad/s] bound on the estimated turn rate (a yaw jump is not a turn)


def planned_altitude(obstacles: Obstacles, points_xy: np.ndarray, height_m: float, clearance_m: float | None) -> float:
    """Flight z [m]: ``height_m`` above the ground, raised to clear obstacle tops along ``points_xy``
    (N, 2) by ``clearance_m`` (None: no planning, fly at ``height_m`` whatever is there)."""
    z = obstacles.ground_z_m + height_m
    if clearance_m is None:
        return z
    return max(z, obstacles.top_along(points_xy, PATH_MARGIN_M) + clearance_m)


def polyline_points(points_xy: np.ndarray, step_m: float = 5.0) -> np.ndarray:
    """(M, 2) points every ``step_m`` or closer along the open polyline ``points_xy`` (N, 2)."""
    if len(points_xy) < 2:
        return np.asarray(points_xy, dtype=np.float64)
    parts = [
        np.linspace(a, b, max(2, int(np.linalg.norm(b - a) // step_m) + 2)) for a, b in itertools.pairwise(points_xy)
    ]
    return np.concatenate(parts)


def climb_first(ref: Reference, s: BodyState, obstacles: Obstacles) -> Reference:
    """Safety rule: a drone below its reference altitude that would fly into an obstacle at its
    current altitude stops moving horizontally and climbs first.

    "Into": an obstacle within ``GUARD_MARGIN_M`` of the next ``GUARD_AHEAD_M`` of the straight way
    to the reference reaches up to ``GUARD_MARGIN_M`` below the drone.
    """
    z = float(s.position_m[2])
    if ref.position_m[2] - z < 2.0:
        return ref
    p = s.position_m[:2]
    to_ref = ref.position_m[:2] - p
    dist = float(np.hypot(to_ref[0], to_ref[1]))
    ahead = p + to_ref * min(1.0, GUARD_AHEAD_M / dist) if dist > 1e-6 else p
    if obstacles.top_along(polyline_points(np.array([p, ahead]), 2.0), GUARD_MARGIN_M) + GUARD_MARGIN_M < z:
        return ref
    hold = np.array([p[0], p[1], ref.position_m[2]])
    return Reference(hold, ZERO3, ZERO3, ref.yaw_rad)


class Strategy(ABC):
    name: str

    @abstractmethod
    def start(self) -> tuple[np.ndarray, float]:
        """Where the drone starts, hovering: position (3,) map ENU [m] and yaw [rad]."""

    def start_velocity(self) -> np.ndarray:
        """The velocity (3,) map ENU [m/s] the drone starts with: its strategy's steady state (at rest here)."""
        return np.zeros(3)

    @abstractmethod
    def reference(self, t_s: float, s: BodyState) -> Reference:
        """The reference at time ``t_s`` given the drone's state; called once per physics step, in order."""

    @abstractmethod
    def label(self) -> str:
        """Short state of the strategy ("hold", "to_wp_3", "tracking", ...)."""

    @abstractmethod
    def fly_at(self, z_m: float) -> None:
        """Fly at map z ``z_m`` [m] (an altitude layer) instead of the planned one; never lower."""


@dataclass
class Hover(Strategy):
    point_m: np.ndarray  # (3,)
    yaw_rad: float = 0.0
    name: str = "hover"
    _label: str = "hold"

    def start(self) -> tuple[np.ndarray, float]:
        return self.point_m.copy(), self.yaw_rad

    def reference(self, t_s: float, s: BodyState) -> Reference:
        d = float(np.linalg.norm(s.position_m - self.point_m))
        self._label = "hold" if d <= HOLD_RADIUS_M else "approach"
        return Reference(self.point_m, ZERO3, ZERO3, self.yaw_rad)

    def label(self) -> str:
        return self._label

    def fly_at(self, z_m: float) -> None:
        self.point_m[2] = max(self.point_m[2], z_m)


def corner_speed(prev_dir: np.ndarray, next_dir: np.ndarray, cruise_mps: float) -> float:
    """Speed [m/s] to pass a corner between unit directions: cruise when straight, 1 m/s at 90 deg or more."""
    c = float(np.clip(prev_dir @ next_dir, -1.0, 1.0))
    turn = math.acos(c)
    share = max(0.0, 1.0 - turn / (0.5 * math.pi))
    return max(1.0, min(cruise_mps, cruise_mps * share * share))


@dataclass
class Patrol(Strategy):
    """Loop over ``waypoints_m`` (N, 3) closed polygon (last point not repeated)."""

    waypoints_m: np.ndarray
    cruise_mps: float
    reach_radius_m: float
    accel_mps2: float = 1.5  # planned along-path acceleration
    name: str = "patrol"

    def __post_init__(self) -> None:
        # Drop repeated points (a closing copy of the first one included): zero-length legs.
        pts = list(np.asarray(self.waypoints_m, dtype=np.float64))
        w = np.array([p for i, p in enumerate(pts) if i == 0 or np.linalg.norm(p - pts[i - 1]) > 1e-6])
        if len(w) > 1 and np.linalg.norm(w[-1] - w[0]) <= 1e-6:
            w = w[:-1]
        if len(w) < 2:
            raise ValueError(f"a patrol needs at least 2 distinct waypoints, got {self.waypoints_m.tolist()}")
        self.waypoints_m = w
        n = len(w)
        seg = np.roll(w, -1, axis=0) - w  # segment i: waypoint i -> i+1
        self._seg_len = np.linalg.norm(seg, axis=1)
        self._seg_dir = seg / self._seg_len[:, None]
        self._s_wp = np.concatenate([[0.0], np.cumsum(self._seg_len)])  # arc length at waypoint i (and loop end)
        self._loop_m = float(self._s_wp[-1])
        self._v_corner = np.array(
            [corner_speed(self._seg_dir[(i - 1) % n], self._seg_dir[i], self.cruise_mps) for i in range(n)]
        )
        self._s = 0.0  # unwrapped arc length of the reference
        self._s_dot = 0.0
        self._next = 1 % n  # next waypoint to reach (the drone starts on waypoint 0)
        self._next_s = float(self._s_wp[1])  # unwrapped arc length of that waypoint
        self._last_t: float | None = None
        self.reached: list[tuple[float, int]] = [(0.0, 0)]  # (t [s], waypoint index)

    def start(self) -> tuple[np.ndarray, float]:
        d = self._seg_dir[0]
        return self.waypoints_m[0].copy(), math.atan2(d[1], d[0])

    def start_velocity(self) -> np.ndarray:
        """On the route at the speed allowed there (cruise, or less braking into the first corner); the
        reference starts at that speed too."""
        v_c = float(self._v_corner[1 % len(self.waypoints_m)])
        v = min(self.cruise_mps, math.sqrt(v_c * v_c + 2.0 * self.accel_mps2 * float(self._seg_len[0])))
        self._s_dot = v
        return v * self._seg_dir[0]

    def _locate(self, s: float) -> tuple[int, float]:
        u = s % self._loop_m
        i = min(int(np.searchsorted(self._s_wp, u, side="right")) - 1, len(self.waypoints_m) - 1)
        return i, u - self._s_wp[i]

    def reference(self, t_s: float, s: BodyState) -> Reference:
        dt = 0.0 if self._last_t is None else t_s - self._last_t
        self._last_t = t_s
        n = len(self.waypoints_m)
        # Waypoint bookkeeping: the drone itself must come within the reach radius, in order (with a
        # margin: half the radius, so that sampled positions and gusts still count as reached).
        wp = self.waypoints_m[self._next]
        if math.hypot(s.position_m[0] - wp[0], s.position_m[1] - wp[1]) <= 0.5 * self.reach_radius_m:
            self.reached.append((t_s, self._next))
            self._next = (self._next + 1) % n
            self._next_s += float(self._seg_len[(self._next - 1) % n])
        # Speed profile: brake into the next corner, never more than cruise.
        i, along = self._locate(self._s)
        to_corner = self._seg_len[i] - along
        v_c = self._v_corner[(i + 1) % n]
        v_allowed = min(self.cruise_mps, math.sqrt(v_c * v_c + 2.0 * self.accel_mps2 * max(to_corner, 0.0)))
        # Governor: wait for a lagging drone.
        ref_now = self.waypoints_m[i] + along * self._seg_dir[i]
        lag = float(np.linalg.norm(ref_now - s.position_m))
        v_allowed *= min(1.0, max(0.0, 1.0 - (lag - 4.0) / 6.0))
        s_dot_new = min(v_allowed, self._s_dot + self.accel_mps2 * dt)
        s_new = self._s + s_dot_new * dt
        # Do not run past a waypoint the drone has not reached.
        if s_new > self._next_s:
            s_new = self._next_s
            s_dot_new = min(s_dot_new, v_c)
        a_t = (s_dot_new - self._s_dot) / dt if dt > 0 else 0.0
        self._s, self._s_dot = s_new, s_dot_new
        i, along = self._locate(self._s)
        d = self._seg_dir[i]
        pos = self.waypoints_m[i] + along * d
        return Reference(pos, s_dot_new * d, a_t * d, math.atan2(d[1], d[0]))

    def label(self) -> str:
        return f"to_wp_{self._next}"

    def fly_at(self, z_m: float) -> None:
        self.waypoints_m[:, 2] = np.maximum(self.waypoints_m[:, 2], z_m)


@dataclass
class Escort(Strategy):
    """Hold ``offset_m`` (forward, left) in the target's body frame at flight z ``z_m``."""

    offset_m: tuple[float, float]
    height_m: float
    clearance_m: float | None
    obstacles: Obstacles
    fallback_start_m: np.ndarray  # (3,) where to start when the target is not known at t=0
    name: str = "escort"

    def __post_init__(self) -> None:
        self._obs: tuple[float, np.ndarray, float, np.ndarray] | None = None  # t, centre, yaw, velocity
        self._yaw_rate = 0.0
        self._label = "lost"
        self._hold: np.ndarray | None = None
        self._z_m = self.fallback_start_m[2]
        self._drone_xy: np.ndarray | None = None  # where the drone was at the last reference

    def observe(self, t_s: float, target: EscortTarget | None) -> None:
        """The target's state at ``t_s`` (the previous tick), or None when the conductor sent none."""
        if target is None:
            self._obs = None
            self._label = "lost"
            return
        c = np.array(target.center_m, dtype=np.float64)
        v = np.array(target.velocity_mps, dtype=np.float64)
        if self._obs is not None and t_s > self._obs[0]:
            rate = wrap_angle(target.yaw_rad - self._obs[2]) / (t_s - self._obs[0])
            self._yaw_rate = min(max(rate, -MAX_TARGET_YAW_RATE_RADPS), MAX_TARGET_YAW_RATE_RADPS)
        self._obs = (t_s, c, float(target.yaw_rad), v)
        if self._label == "lost":
            self._label = "approach"
        q = self._predict(t_s)[0]
        ahead = np.array([q[:2] + v[:2] * tau for tau in (0.0, 2.0, 4.0, 6.0)])
        if self._drone_xy is not None:  # and the way from where the drone is
            ahead = np.vstack([ahead, polyline_points(np.array([self._drone_xy, q[:2]]))])
        self._z_m = planned_altitude(self.obstacles, ahead, self.height_m, self.clearance_m)

    def _predict(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Offset point position (3,), velocity (3,), acceleration (3,) and target yaw at ``t_s``."""
        assert self._obs is not None
        t0, c0, yaw0, v0 = self._obs
        dt = min(max(t_s - t0, 0.0), 1.0)
        w = self._yaw_rate
        speed = math.hypot(v0[0], v0[1])
        h0 = math.atan2(v0[1], v0[0]) if speed > 0.5 else yaw0
        h = h0 + w * dt
        if abs(w) > 1e-4:
            dp = speed / w * np.array([math.sin(h) - math.sin(h0), math.cos(h0) - math.cos(h)])
        else:
            dp = speed * dt * np.array([math.cos(h0), math.sin(h0)])
        p = c0[:2] + dp
        v = speed * np.array([math.cos(h), math.sin(h)])
        a = speed * w * np.array([-math.sin(h), math.cos(h)])
        yaw = yaw0 + w * dt
        cy, sy = math.cos(yaw), math.sin(yaw)
        o = np.array([cy * self.offset_m[0] - sy * self.offset_m[1], sy * self.offset_m[0] + cy * self.offset_m[1]])
        q = p + o
        q_dot = v + SWING_FEEDFORWARD * w * np.array([-o[1], o[0]])
        q_ddot = a - SWING_FEEDFORWARD * w * w * o
        return (
            np.array([q[0], q[1], self._z_m]),
            np.array([q_dot[0], q_dot[1], 0.0]),
            np.array([q_ddot[0], q_ddot[1], 0.0]),
            yaw,
        )

    def offset_point(self, target: EscortTarget) -> np.ndarray:
        """(2,) the commanded offset point of an exactly known target state."""
        cy, sy = math.cos(target.yaw_rad), math.sin(target.yaw_rad)
        fx, ly = self.offset_m
        return np.array([target.center_m[0] + cy * fx - sy * ly, target.center_m[1] + sy * fx + cy * ly])

    def start(self) -> tuple[np.ndarray, float]:
        if self._obs is None:
            return self.fallback_start_m.copy(), 0.0
        q, _, _, yaw = self._predict(self._obs[0])
        return q, yaw

    def start_velocity(self) -> np.ndarray:
        """The offset point's velocity (the target's, and the swing of the offset as it turns)."""
        return np.zeros(3) if self._obs is None else self._predict(self._obs[0])[1]

    def reference(self, t_s: float, s: BodyState) -> Reference:
        self._drone_xy = s.position_m[:2]
        if self._obs is None:
            if self._hold is None:
                self._hold = s.position_m.copy()
            self._label = "lost"
            return Reference(self._hold, ZERO3, ZERO3, math.atan2(s.rotation[1, 0], s.rotation[0, 0]))
        self._hold = None
        q, q_dot, q_ddot, yaw = self._predict(t_s)
        d = math.hypot(q[0] - s.position_m[0], q[1] - s.position_m[1])
        self._label = "tracking" if d <= TRACK_RADIUS_M else "approach"
        return Reference(q, q_dot, q_ddot, yaw)

    def label(self) -> str:
        return self._label

    def fly_at(self, z_m: float) -> None:
        """The layer becomes the lowest the escort flies (it still climbs over buildings)."""
        self.height_m = max(self.height_m, z_m - self.obstacles.ground_z_m)
        self.fallback_start_m[2] = max(self.fallback_start_m[2], z_m)
        self._z_m = max(self._z_m, z_m)


@dataclass
class GoTo(Strategy):
    """Fly a straight line from ``start_m`` to ``goal_m`` (both (3,)) at up to ``cruise_mps``, then hold.

    The reference moves along the line with a trapezoid speed profile (``accel_mps2``) that stops on the
    goal, and waits for a drone that lags behind it, as a patrol does. Used for the ``goto`` and ``land``
    actions of closed-loop clients (``name`` tells them apart in the labels).
    """

    start_m: np.ndarray
    goal_m: np.ndarray
    cruise_mps: float
    accel_mps2: float = 1.5
    name: str = "goto"
    arrived_label: str = "arrived"
    start_velocity_mps: np.ndarray | None = None  # (3,) the drone's velocity: a new goal does not stop it first

    def __post_init__(self) -> None:
        d = self.goal_m - self.start_m
        self._length_m = float(np.linalg.norm(d))
        self._dir = d / self._length_m if self._length_m > 1e-9 else ZERO3
        horizontal = math.hypot(d[0], d[1])
        self._yaw: float | None = math.atan2(d[1], d[0]) if horizontal > 1.0 else None
        self._s = 0.0
        v0 = 0.0 if self.start_velocity_mps is None else float(self.start_velocity_mps @ self._dir)
        self._s_dot = min(max(v0, 0.0), self.cruise_mps)
        self._last_t: float | None = None
        self._label = "approach"

    def start(self) -> tuple[np.ndarray, float]:
        return self.start_m.copy(), self._yaw or 0.0

    def reference(self, t_s: float, s: BodyState) -> Reference:
        dt = 0.0 if self._last_t is None else t_s - self._last_t
        self._last_t = t_s
        if self._yaw is None:
            self._yaw = math.atan2(s.rotation[1, 0], s.rotation[0, 0])  # pure climbs and descents keep the heading
        to_go = self._length_m - self._s
        v_allowed = min(self.cruise_mps, math.sqrt(2.0 * self.accel_mps2 * max(to_go, 0.0)))
        ref_now = self.start_m + self._s * self._dir
        lag = float(np.linalg.norm(ref_now - s.position_m))
        v_allowed *= min(1.0, max(0.0, 1.0 - (lag - 4.0) / 6.0))
        s_dot = min(v_allowed, self._s_dot + self.accel_mps2 * dt)
        self._s = min(self._length_m, self._s + s_dot * dt)
        a_t = (s_dot - self._s_dot) / dt if dt > 0 else 0.0
        self._s_dot = s_dot if self._s < self._length_m else 0.0
        done = self._s >= self._length_m
        near = float(np.linalg.norm(s.position_m - self.goal_m)) <= HOLD_RADIUS_M
        self._label = self.arrived_label if done and near else "approach"
        pos = self.goal_m if done else self.start_m + self._s * self._dir
        return Reference(pos, self._s_dot * self._dir, (0.0 if done else a_t) * self._dir, self._yaw)

    def label(self) -> str:
        return self._label

    def fly_at(self, z_m: float) -> None:
        """The goal is at least at ``z_m``; the line from the start is re-planned."""
        self.goal_m = np.array([self.goal_m[0], self.goal_m[1], max(float(self.goal_m[2]), z_m)])
        self.__post_init__()
