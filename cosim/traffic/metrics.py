"""Physical checks of traffic output: bird's-eye overlaps and where box centres lie.

Pure functions over :class:`~cosim.protocol.VehicleState` lists, used by tests and benchmarks.
"""

from __future__ import annotations

import math

import numpy as np

from cosim.protocol import VehicleState


def bev_corners(s: VehicleState) -> np.ndarray:
    """Bird's-eye box corners (4, 2) [m], counter-clockwise."""
    c, si = math.cos(s.yaw_rad), math.sin(s.yaw_rad)
    hl, hw = 0.5 * s.size_m[0], 0.5 * s.size_m[1]
    local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    return local @ np.array([[c, si], [-si, c]]) + np.array(s.center_m[:2])


def _clip(subject: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Part of convex polygon ``subject`` left of the directed line a -> b (Sutherland-Hodgman step)."""
    if len(subject) == 0:
        return subject
    d = b - a
    side = d[0] * (subject[:, 1] - a[1]) - d[1] * (subject[:, 0] - a[0])
    out = []
    n = len(subject)
    for i in range(n):
        p, q = subject[i], subject[(i + 1) % n]
        sp, sq = side[i], side[(i + 1) % n]
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            t = sp / (sp - sq)
            out.append(p + t * (q - p))
    return np.array(out).reshape(-1, 2)


def convex_overlap_area(p: np.ndarray, q: np.ndarray) -> float:
    """Area [m^2] of the intersection of two convex CCW polygons (N, 2), (M, 2)."""
    poly = p
    for i in range(len(q)):
        poly = _clip(poly, q[i], q[(i + 1) % len(q)])
        if len(poly) < 3:
            return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)))


def max_pairwise_overlap(states: list[VehicleState]) -> tuple[float, tuple[str, str] | None]:
    """Largest bird's-eye overlap [m^2] between two vehicles of one tick, and the pair."""
    if len(states) < 2:
        return 0.0, None
    centres = np.array([s.center_m[:2] for s in states])
    radii = np.array([0.5 * math.hypot(s.size_m[0], s.size_m[1]) for s in states])
    corners = [bev_corners(s) for s in states]
    best, pair = 0.0, None
    for i in range(len(states)):
        d = np.linalg.norm(centres[i + 1 :] - centres[i], axis=1)
        for j in np.nonzero(d < radii[i + 1 :] + radii[i])[0] + i + 1:
            a = convex_overlap_area(corners[i], corners[j])
            if a > best:
                best, pair = a, (states[i].sumo_id, states[j].sumo_id)
    return best, pair
