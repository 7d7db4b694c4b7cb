"""Traffic-light geometry: poles, mast arms and three-lamp heads at SUMO's signalised junctions.

The heads stand where :func:`cosim.world.traffic_lights.signal_heads` puts them (above each controlled
lane's stop line, facing its traffic; a pole at the approach's right kerb with an arm to each head).
The geometry is static (part of the episode's static mesh); what changes per tick is which lamp is
lit, :class:`SignalLamps`. A lit lamp is self-luminous: the cameras draw it at full brightness in its
colour whatever the sun, dusk or night (an LED signal outshines the daylit scene around it); an unlit
lamp is its dark lens.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.world.layout import ROAD_Z
from cosim.world.traffic_lights import HEAD_SIZE_M, LAMP_COLOURS, SignalHead

#: first static instance id of the signal heads (the layout's prisms count up from 1 000 000)
FIRST_HEAD_INSTANCE = 3_000_000
#: first static instance id of their poles
FIRST_POLE_INSTANCE = 3_500_000
#: [m] half the side of a lamp's square lens; lamps' centres above and below the head's centre
LAMP_HALF_M = 0.12
LAMP_PITCH_M = 0.32
#: linear RGB of a lit lamp (red, yellow, green); an unlit lens is this times UNLIT
LAMP_RGB = np.array([(1.0, 0.08, 0.04), (1.0, 0.62, 0.02), (0.10, 1.0, 0.45)], np.float32)
UNLIT = 0.12
HOUSING_RGB = (0.03, 0.03, 0.035)
POLE_RGB = (0.32, 0.33, 0.34)

BOX_TRIANGLES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                   [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], np.int64)


def oriented_box(center, yaw: float, half) -> np.ndarray:
    """The 8 corners (8, 3) of a box of half sizes ``half`` turned by ``yaw`` about +z around ``center``."""
    hx, hy, hz = half
    local = np.array([[-hx, -hy, -hz], [hx, -hy, -hz], [hx, hy, -hz], [-hx, hy, -hz],
                      [-hx, -hy, hz], [hx, -hy, hz], [hx, hy, hz], [-hx, hy, hz]])
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return local @ rot.T + np.asarray(center, np.float64)


@dataclass(frozen=True)
class SignalParts:
    """The signal geometry: ``vertices`` (V, 3), ``triangles`` (T, 3), per triangle ``semantic`` class name
    index (0 traffic_light, 1 pole), ``instance``, ``albedo`` (T, 3), ``reflectivity``; ``lamp_head`` and
    ``lamp_colour`` (T,) the head index and lamp (0 red, 1 yellow, 2 green) of lamp triangles, -1
    elsewhere; ``segments`` (S, 2, 3) the thin things' centre lines (poles, arms, lamp columns)."""

    vertices: np.ndarray
    triangles: np.ndarray
    pole: np.ndarray
    instance: np.ndarray
    albedo: np.ndarray
    reflectivity: np.ndarray
    lamp_head: np.ndarray
    lamp_colour: np.ndarray
    segments: np.ndarray


def signal_parts(heads: tuple[SignalHead, ...]) -> SignalParts:
    """The poles, arms, housings and lamps of ``heads`` (:class:`SignalParts`)."""
    verts: list[np.ndarray] = []
    rows: list[tuple[bool, int, tuple, float, int, int]] = []  # pole, instance, albedo, refl, head, colour
    segments: list[list[list[float]]] = []
    d, w, h = HEAD_SIZE_M
    poles: dict[tuple[float, float], int] = {}

    def add(corners: np.ndarray, pole: bool, inst: int, albedo, refl: float, head: int = -1, colour: int = -1):
        verts.append(corners)
        rows.extend([(pole, inst, albedo, refl, head, colour)] * 12)

    for k, hd in enumerate(heads):
        cx, cy, cz = hd.center_m
        top_z = cz + h / 2
        pkey = (round(hd.pole_xy[0], 2), round(hd.pole_xy[1], 2))
        if pkey not in poles:
            poles[pkey] = FIRST_POLE_INSTANCE + len(poles)
            px, py = hd.pole_xy
            half_h = (top_z + 0.3 - ROAD_Z[1]) / 2
            add(oriented_box((px, py, ROAD_Z[1] + half_h), hd.yaw_rad, (0.1, 0.1, half_h)), True, poles[pkey],
                POLE_RGB, 0.5)
            segments.append([[px, py, ROAD_Z[1]], [px, py, top_z + 0.3]])
        # the arm from the pole over to the head, just above it
        px, py = hd.pole_xy
        ax, ay = cx - px, cy - py
        length = math.hypot(ax, ay)
        if length > 0.05:
            add(oriented_box(((px + cx) / 2, (py + cy) / 2, top_z + 0.2), math.atan2(ay, ax),
                             (length / 2 + 0.06, 0.06, 0.06)), True, poles[pkey], POLE_RGB, 0.5)
            segments.append([[px, py, top_z + 0.2], [cx, cy, top_z + 0.2]])
        inst = FIRST_HEAD_INSTANCE + k
        add(oriented_box(hd.center_m, hd.yaw_rad, (d / 2, w / 2, h / 2)), False, inst, HOUSING_RGB, 0.08)
        fx, fy = math.cos(hd.yaw_rad), math.sin(hd.yaw_rad)
        for j in range(3):  # red on top
            lz = cz + LAMP_PITCH_M * (1 - j)
            centre = (cx + fx * (d / 2 + 0.015), cy + fy * (d / 2 + 0.015), lz)
            add(oriented_box(centre, hd.yaw_rad, (0.015, LAMP_HALF_M, LAMP_HALF_M)), False, inst,
                tuple(float(v) for v in LAMP_RGB[j] * UNLIT), 0.3, k, j)
        face = (cx + fx * (d / 2 + 0.03), cy + fy * (d / 2 + 0.03))
        segments.append([[*face, cz - LAMP_PITCH_M], [*face, cz + LAMP_PITCH_M]])
    n = len(verts)
    tris = (BOX_TRIANGLES[None] + 8 * np.arange(n)[:, None, None]).reshape(-1, 3) if n else np.zeros((0, 3), np.int64)
    return SignalParts(
        np.concatenate(verts).astype(np.float32) if n else np.zeros((0, 3), np.float32),
        tris.astype(np.uint32),
        np.array([r[0] for r in rows], bool),
        np.array([r[1] for r in rows], np.uint32),
        np.array([r[2] for r in rows], np.float32).reshape(-1, 3),
        np.array([r[3] for r in rows], np.float32),
        np.array([r[4] for r in rows], np.int64),
        np.array([r[5] for r in rows], np.int64),
        np.asarray(segments, np.float64).reshape(-1, 2, 3),
    )


class SignalLamps:
    """Which static triangles are lamps and how to light them per tick: ``rows`` are the lamp triangles'
    global indices, ``head`` and ``colour`` their head and lamp; ``ids`` the head ids in head order."""

    def __init__(self, first_row: int, parts: SignalParts, heads: tuple[SignalHead, ...]):
        lamp = np.nonzero(parts.lamp_head >= 0)[0]
        self.rows = first_row + lamp
        self.head = parts.lamp_head[lamp]
        self.colour = parts.lamp_colour[lamp]
        self.index = {hd.head_id: k for k, hd in enumerate(heads)}

    def lit(self, lights, exposure: float) -> tuple[np.ndarray, np.ndarray]:
        """Global triangle indices (N,) of the lamps lit by ``lights`` (the snapshot's
        :class:`cosim.snapshot.TrafficLight` tuple) and their linear colour (N, 3): the lamp's colour at
        the camera's full scale (``1 / exposure``), so it shows saturated in any light."""
        shown = np.full(len(self.index), -1, np.int64)
        for t in lights:
            k = self.index.get(t.light_id)
            if k is not None and t.state in LAMP_COLOURS:
                shown[k] = LAMP_COLOURS.index(t.state)
        on = shown[self.head] == self.colour
        return self.rows[on], np.ascontiguousarray(LAMP_RGB[self.colour[on]] / np.float32(max(exposure, 1e-6)))
