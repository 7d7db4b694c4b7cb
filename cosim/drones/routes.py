"""Where strategies fly when the scenario does not say: hover points and patrol loops from the world.

Pure functions of the world (and an index), so every run picks the same places.
"""

from __future__ import annotations

import math

import numpy as np

from cosim.world.types import Junction, World

#: SUMO junction types a drone should not be sent to (not a real crossing).
_MINOR_KINDS = frozenset({"dead_end", "internal"})


def world_centre(world: World) -> np.ndarray:
    """(2,) centre of the world bounds [m]."""
    xmin, ymin, xmax, ymax = world.bounds_m
    return np.array([0.5 * (xmin + xmax), 0.5 * (ymin + ymax)])


def ranked_junctions(world: World) -> list[Junction]:
    """Real crossings first (not dead ends), then by distance to the world centre, then by id."""
    c = world_centre(world)

    def key(j: Junction) -> tuple[int, float, str]:
        d = math.hypot(j.position_m[0] - c[0], j.position_m[1] - c[1])
        return (1 if j.kind in _MINOR_KINDS else 0, round(d, 6), j.junction_id)

    return sorted(world.junctions, key=key)


def hover_point(world: World, k: int) -> np.ndarray:
    """(2,) map x, y [m] of the ``k``-th hover drone: the k-th ranked junction (wrapping), else the centre."""
    js = ranked_junctions(world)
    if not js:
        return world_centre(world)
    return np.array(js[k % len(js)].position_m, dtype=np.float64)


def patrol_loop(world: World, k: int, loop_length_m: float) -> np.ndarray:
    """(N, 2) closed patrol loop (last point not repeated) of about ``loop_length_m`` for patrol drone ``k``.

    Around a centre junction (the k-th ranked one): one junction per 45-degree sector at about the
    radius of a circle of that perimeter, in counter-clockwise order; where fewer than 4 sectors have
    a junction, a square of that perimeter around the centre.
    """
    js = ranked_junctions(world)
    centre = np.array(js[k % len(js)].position_m) if js else world_centre(world)
    radius = loop_length_m / (2.0 * math.pi)
    picks: dict[int, tuple[float, np.ndarray]] = {}
    for j in js:
        d = np.asarray(j.position_m, dtype=np.float64) - centre
        r = math.hypot(d[0], d[1])
        if not 0.5 * radius <= r <= 1.6 * radius or j.kind in _MINOR_KINDS:
            continue
        sector = int((math.atan2(d[1], d[0]) + math.pi) / (2 * math.pi) * 8) % 8
        score = abs(r - radius)
        if sector not in picks or score < picks[sector][0]:
            picks[sector] = (score, centre + d)
    if len(picks) >= 4:
        return np.array([picks[s][1] for s in sorted(picks)])
    half = loop_length_m / 8.0
    return centre + np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
