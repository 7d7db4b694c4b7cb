"""Keeping drones apart: altitude layers planned before take-off, and a yield rule in flight.

Two drones stay at least ``agents.drone_separation_m`` apart (centre to centre, 3D):

- **Layers** (:func:`plan_layers`): drones whose ways can come horizontally within the separation
  (plus :data:`REGION_MARGIN_M`) fly at altitudes at least :func:`layer_gap` apart. A hover drone's
  way is its point, a patrol's its loop; an escort follows a vehicle anywhere, so it shares the
  airspace of every other drone. In index order, each drone keeps its planned altitude when that is
  free, else takes the lowest free altitude above it (never lower: the planned altitude clears the
  buildings).
- **Yielding** (:func:`yield_plan`): escorts climb over buildings in flight, so a layer alone does not
  hold. Once per tick, each drone finds the drones it yields to (hover before patrol before escort,
  then by index) that can come within the separation plus :data:`REGION_MARGIN_M` horizontally in
  the next :data:`LOOKAHEAD_S` (closest approach of straight-line motion); their layers become
  forbidden altitude bands. Its reference is raised out of every band, and while it is still inside
  one it holds its horizontal position (climb first, then go on).
- **Not climbing past a drone close by**: a drone that would climb toward a drone it yields to, above it
  and horizontally within :data:`KEEP_OUT_M` (an escort whose vehicle passes under a hovering drone),
  first backs away horizontally to :data:`KEEP_OUT_M` plus :data:`KEEP_OUT_HYSTERESIS_M`, climbing no
  higher than the other drone's band (or its present altitude inside it); there it holds and climbs.

Pure functions over numpy arrays; map frame ENU, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cosim.drones.control import Reference

REGION_MARGIN_M = 5.0  # [m] added to the separation when deciding whether two ways can meet
LAYER_MARGIN_M = 3.0  # [m] added to the separation between layers (altitude tracking, gusts)
LOOKAHEAD_S = 6.0  # [s] how far ahead the yield rule looks for a closest approach
KEEP_OUT_M = 20.0  # [m] horizontal radius around a drone inside which a yielding drone does not climb past it
KEEP_OUT_HYSTERESIS_M = 3.0  # [m] how much farther it backs away before it climbs
KEEP_OUT_BELOW_M = 5.0  # [m] below a band's lower edge, a drone inside KEEP_OUT_M already counts as close
#: yield order by strategy: a drone yields to every drone of a lower rank (then of a lower index)
RANK = {"hover": 0, "patrol": 1, "escort": 2}


def layer_gap(separation_m: float) -> float:
    """[m] vertical distance between two layers that share airspace."""
    return separation_m + LAYER_MARGIN_M if separation_m > 0 else 0.0


def _segments(way: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start points and vectors (M, 2) of the closed polyline ``way`` (N, 2) (a point: one zero segment)."""
    way = np.asarray(way, dtype=np.float64).reshape(-1, 2)
    if len(way) == 1:
        return way, np.zeros((1, 2))
    return way, np.roll(way, -1, axis=0) - way


def way_distance(a: np.ndarray, b: np.ndarray) -> float:
    """[m] smallest horizontal distance between two closed polylines or points (N, 2), sampled every
    metre or closer along ``a``'s segments (exact for points and straight legs up to that step)."""
    pa, da = _segments(a)
    pb, db = _segments(b)
    best = np.inf
    for p, d in zip(pa, da, strict=True):
        n = max(2, int(np.ceil(np.hypot(d[0], d[1]))) + 1)
        pts = p + np.linspace(0.0, 1.0, n)[:, None] * d  # (n, 2)
        rel = pts[:, None, :] - pb[None, :, :]  # (n, M, 2)
        len2 = np.maximum(np.einsum("ij,ij->i", db, db), 1e-12)
        u = np.clip(np.einsum("nmj,mj->nm", rel, db) / len2, 0.0, 1.0)
        gap = rel - u[..., None] * db[None, :, :]
        best = min(best, float(np.sqrt(np.min(np.einsum("nmj,nmj->nm", gap, gap)))))
    return best


def plan_layers(z_m: list[float], ways: list[np.ndarray | None], separation_m: float) -> list[float]:
    """Flight altitudes [m]: ``z_m[i]`` or the lowest higher one at least :func:`layer_gap` from every
    earlier drone whose way comes within the separation plus :data:`REGION_MARGIN_M` (``None``: an
    escort, anywhere)."""
    gap = layer_gap(separation_m)
    out: list[float] = []
    for i, z in enumerate(z_m):
        if gap <= 0:
            out.append(z)
            continue
        shared = [
            out[j]
            for j in range(i)
            if ways[i] is None or ways[j] is None or way_distance(ways[i], ways[j]) < separation_m + REGION_MARGIN_M
        ]
        candidates = sorted({z, *(zj + gap for zj in shared if zj + gap > z)})
        out.append(next(c for c in candidates if all(abs(c - zj) >= gap - 1e-9 for zj in shared)))
    return out


@dataclass
class Yield:
    """What one drone must respect during the next tick: forbidden altitude bands (low, high) [m]."""

    bands: list[tuple[float, float]] = field(default_factory=list)
    hold: bool = False  # inside a band now: hold the horizontal position until out of it
    gap_m: float = 0.0  # the layer gap (half a band's height)
    #: the nearest drone it yields to that is above it, vertically close and horizontally within
    #: KEEP_OUT_M + KEEP_OUT_HYSTERESIS_M (see yield_plan): its position (3,) and horizontal distance [m]
    near: tuple[np.ndarray, float] | None = None

    def apply(self, ref: Reference, position_m: np.ndarray) -> Reference:
        """``ref`` raised out of every band; held horizontally at ``position_m`` when ``hold``. A drone that
        would climb while ``near`` is set holds horizontally, or within :data:`KEEP_OUT_M` backs away
        (climbing no higher than the near drone's band, or its present altitude inside it)."""
        if not self.bands:
            return ref
        z = float(ref.position_m[2])
        moved = True
        while moved:
            moved = False
            for lo, hi in self.bands:
                if lo < z < hi:
                    z, moved = hi, True
        zero = np.zeros(3)
        if self.near is not None and z > position_m[2]:
            other, h = self.near
            if h >= KEEP_OUT_M:
                return Reference(np.array([position_m[0], position_m[1], z]), zero, zero, ref.yaw_rad)
            away = position_m[:2] - other[:2]
            u = away / h if h > 1e-6 else np.array([1.0, 0.0])
            xy = other[:2] + (KEEP_OUT_M + KEEP_OUT_HYSTERESIS_M) * u
            z = min(z, max(float(position_m[2]), float(other[2]) - self.gap_m))
            return Reference(np.array([xy[0], xy[1], z]), zero, zero, ref.yaw_rad)
        if not self.hold and z == ref.position_m[2]:
            return ref
        if self.hold:
            return Reference(np.array([position_m[0], position_m[1], z]), zero, zero, ref.yaw_rad)
        pos = ref.position_m.copy()
        pos[2] = z
        vel, acc = ref.velocity_mps.copy(), ref.accel_mps2.copy()
        vel[2] = acc[2] = 0.0
        return Reference(pos, vel, acc, ref.yaw_rad)


def closest_approach_m(p: np.ndarray, v: np.ndarray, horizon_s: float) -> float:
    """[m] smallest horizontal distance over [0, ``horizon_s``] of relative position ``p`` (2,) moving
    at relative velocity ``v`` (2,)."""
    vv = float(v @ v)
    t = 0.0 if vv < 1e-9 else min(max(-float(p @ v) / vv, 0.0), horizon_s)
    q = p + t * v
    return float(np.hypot(q[0], q[1]))


def yield_plan(
    positions_m: np.ndarray, velocities_mps: np.ndarray, strategies: list[str], separation_m: float
) -> list[Yield]:
    """One :class:`Yield` per drone from every drone's position and velocity (N, 3) and strategy name."""
    n = len(strategies)
    out = [Yield() for _ in range(n)]
    if separation_m <= 0:
        return out
    gap = layer_gap(separation_m)
    order = {i: (RANK.get(s, len(RANK)), i) for i, s in enumerate(strategies)}
    for i in range(n):
        for j in range(n):
            if order[j] >= order[i]:
                continue
            rel_p = positions_m[j, :2] - positions_m[i, :2]
            rel_v = velocities_mps[j, :2] - velocities_mps[i, :2]
            if closest_approach_m(rel_p, rel_v, LOOKAHEAD_S) >= separation_m + REGION_MARGIN_M:
                continue
            zj = float(positions_m[j, 2])
            out[i].bands.append((zj - gap, zj + gap))
            dz = float(positions_m[i, 2]) - zj
            if abs(dz) < separation_m + 1.0:
                out[i].hold = True
            h = float(np.hypot(rel_p[0], rel_p[1]))
            close = h < KEEP_OUT_M + KEEP_OUT_HYSTERESIS_M and -gap - KEEP_OUT_BELOW_M < dz < 0.0
            if close and (out[i].near is None or h < out[i].near[1]):
                out[i].near = (positions_m[j].copy(), h)
                out[i].gap_m = gap
    return out


def closest_pair(positions_m: np.ndarray) -> tuple[float, int, int]:
    """Smallest 3D distance [m] between two of ``positions_m`` (N, 3), N >= 2, and the pair (i < j)."""
    d = np.linalg.norm(positions_m[:, None, :] - positions_m[None, :, :], axis=2)
    d[np.tril_indices(len(positions_m))] = np.inf
    k = int(np.argmin(d))
    i, j = divmod(k, len(positions_m))
    return float(d[i, j]), i, j
