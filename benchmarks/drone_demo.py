"""Synthetic inputs for exercising the drone stack without SUMO or the world builder: a small
world of box buildings on a junction grid, and a car driving a route with turns.

Used by the acceptance report (:mod:`benchmarks.drone_report`) and the tests.
"""

from __future__ import annotations

import math

import numpy as np

from cosim.protocol import EscortTarget
from cosim.world.types import Junction, Prism, StaticLayout, World

GEO_ORIGIN = (37.3352, -121.8811, 20.0)  # lat [deg], lon [deg], alt [m]


def box(x0: float, y0: float, x1: float, y1: float, top_m: float, instance_id: int) -> Prism:
    """An axis-aligned building from the ground to ``top_m``."""
    return Prism("building", ((x0, y0), (x1, y0), (x1, y1), (x0, y1)), 0.0, top_m, instance_id)


def grid_net_xml(junctions: tuple[Junction, ...], spacing_m: float) -> bytes:
    """A minimal SUMO network: two-way single-lane roads between junctions ``spacing_m`` apart."""
    lines = ['<net version="1.20">']
    for a in junctions:
        for b in junctions:
            d = math.dist(a.position_m, b.position_m)
            if a is b or abs(d - spacing_m) > 1e-6:
                continue
            eid = f"{a.junction_id}_{b.junction_id}"
            shape = f"{a.position_m[0]},{a.position_m[1]} {b.position_m[0]},{b.position_m[1]}"
            lines.append(
                f'  <edge id="{eid}" from="{a.junction_id}" to="{b.junction_id}" priority="1">'
                f'<lane id="{eid}_0" index="0" speed="13.89" length="{d}" shape="{shape}"/></edge>'
            )
    for j in junctions:
        x, y = j.position_m
        lines.append(f'  <junction id="{j.junction_id}" type="{j.kind}" x="{x}" y="{y}" incLanes="" intLanes=""/>')
    lines.append("</net>")
    return "\n".join(lines).encode()


def demo_world(with_roads: bool = False) -> World:
    """400 m square; a 3x3 grid of junctions 100 m apart at x, y in {100, 200, 300}; three buildings
    between the roads (25 m, a 70 m tower, 15 m) and a flat road strip (not an obstacle). With
    ``with_roads`` it carries a SUMO network of two-way roads along the grid lines."""
    junctions = tuple(
        Junction(f"j{i}{j}", (100.0 * i + 100.0, 100.0 * j + 100.0), "priority") for i in range(3) for j in range(3)
    )
    prisms = (
        box(120, 120, 180, 180, 25.0, 1_000_001),
        box(220, 120, 280, 180, 70.0, 1_000_002),
        box(120, 220, 180, 280, 15.0, 1_000_003),
        Prism("road", ((0, 95), (400, 95), (400, 105), (0, 105)), 0.0, 0.02, 0),
    )
    net = grid_net_xml(junctions, 100.0) if with_roads else b""
    return World("urban", net, b"", (0.0, 0.0, 400.0, 400.0), junctions, (), StaticLayout(prisms), GEO_ORIGIN)


#: A route on the demo world's roads with five 90-degree turns.
DEMO_ROUTE = [(20.0, 100.0), (300.0, 100.0), (300.0, 300.0), (100.0, 300.0), (100.0, 200.0), (380.0, 200.0)]


class Drive:
    """A car's trajectory sampled every ``dt_s``: times (N,) [s], positions (N, 2) [m], yaws (N,) [rad],
    velocities (N, 2) [m/s], map frame."""

    def __init__(self, t: np.ndarray, pos: np.ndarray, yaw: np.ndarray, vel: np.ndarray, dt_s: float):
        self.t, self.pos, self.yaw, self.vel, self.dt_s = t, pos, yaw, vel, dt_s

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])

    def target_at(self, t_s: float, height_m: float = 1.5) -> EscortTarget:
        """The car's state at ``t_s`` (clamped to the drive) as the conductor would send it."""
        i = min(max(round(t_s / self.dt_s), 0), len(self.t) - 1)
        return EscortTarget(
            (float(self.pos[i, 0]), float(self.pos[i, 1]), 0.5 * height_m),
            float(self.yaw[i]),
            (float(self.vel[i, 0]), float(self.vel[i, 1]), 0.0),
        )


def synthetic_drive(
    corners: list[tuple[float, float]],
    v_max: float = 14.0,
    v_turn: float = 6.0,
    radius_m: float = 12.0,
    accel: float = 2.5,
    dt_s: float = 0.01,
) -> Drive:
    """A car driving a polyline route with rounded corners: straights at up to ``v_max``, corners
    (circular arcs of ``radius_m``) at ``v_turn``, braking/accelerating at ``accel``.

    Starts and ends at (nearly) rest; sampled every ``dt_s``.
    """
    c = np.array(corners, dtype=np.float64)
    pts, is_arc = [c[0]], [False]
    for i in range(1, len(c) - 1):
        a, b, n = c[i - 1], c[i], c[i + 1]
        d_in = (b - a) / np.linalg.norm(b - a)
        d_out = (n - b) / np.linalg.norm(n - b)
        turn = math.atan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], d_in @ d_out)
        cut = radius_m * math.tan(abs(turn) / 2)
        p_in, p_out = b - d_in * cut, b + d_out * cut
        pts.append(p_in)
        is_arc.append(False)
        centre = p_in + radius_m * math.copysign(1, turn) * np.array([-d_in[1], d_in[0]])
        a0 = math.atan2(*(p_in - centre)[::-1])
        for u in np.linspace(0, 1, 20)[1:]:
            ang = a0 + turn * u
            pts.append(centre + radius_m * np.array([math.cos(ang), math.sin(ang)]))
            is_arc.append(True)
        pts.append(p_out)
        is_arc.append(False)
    pts.append(c[-1])
    is_arc.append(False)
    # Densify to <= 2 m so the speed profile can rise and fall along the straights.
    dense, dense_arc = [pts[0]], [is_arc[0]]
    for i in range(1, len(pts)):
        n = max(1, math.ceil(np.linalg.norm(pts[i] - pts[i - 1]) / 2.0))
        for u in np.linspace(0, 1, n + 1)[1:]:
            dense.append(pts[i - 1] + u * (pts[i] - pts[i - 1]))
            dense_arc.append(is_arc[i] and is_arc[i - 1] if u < 1 else is_arc[i])
    p, is_arc = np.array(dense), dense_arc
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s_nodes = np.concatenate([[0.0], np.cumsum(seg)])
    # Speed limit per node, then forward/backward passes for the acceleration limit.
    v_lim = np.where(np.array(is_arc), v_turn, v_max)
    v_lim[0] = v_lim[-1] = 0.0
    for i in range(1, len(v_lim)):
        v_lim[i] = min(v_lim[i], math.sqrt(v_lim[i - 1] ** 2 + 2 * accel * seg[i - 1]))
    for i in range(len(v_lim) - 2, -1, -1):
        v_lim[i] = min(v_lim[i], math.sqrt(v_lim[i + 1] ** 2 + 2 * accel * seg[i]))
    v_lim[0] = 1.0
    # Integrate s(t).
    s_list = [0.0]
    s = 0.0
    while s < s_nodes[-1] - 0.5:
        v = max(float(np.interp(s, s_nodes, v_lim)), 0.5)
        s += v * dt_s
        s_list.append(s)
    times = np.arange(len(s_list)) * dt_s
    s_arr = np.minimum(np.array(s_list), s_nodes[-1])
    pos = np.column_stack([np.interp(s_arr, s_nodes, p[:, 0]), np.interp(s_arr, s_nodes, p[:, 1])])
    vel = np.gradient(pos, dt_s, axis=0)
    yaw = np.unwrap(np.arctan2(vel[:, 1], vel[:, 0]))
    return Drive(times, pos, yaw, vel, dt_s)
