"""What a drone can fly into: the raised prisms of the static layout and the ground.

Two queries over the same obstacle set, both in map ENU metres:
- :meth:`Obstacles.hit` - exact test of a sphere (the drone) against the prism solids and the ground;
- :meth:`Obstacles.top_near` - highest obstacle top within a radius, from a precomputed max-height
  grid (conservative: footprints enter the grid by their bounding boxes), for altitude planning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.world.types import Prism, StaticLayout

MIN_OBSTACLE_HEIGHT_M = 0.3  # [m] prisms lower than this above the ground (road, markings) are not obstacles
GRID_CELL_M = 5.0  # [m] cell of the height grid


def _point_in_polygon(x: float, y: float, poly: np.ndarray) -> bool:
    """Even-odd test of (x, y) against a polygon (N, 2)."""
    xs, ys = poly[:, 0], poly[:, 1]
    xj, yj = np.roll(xs, 1), np.roll(ys, 1)
    crosses = (ys > y) != (yj > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = (xj - xs) * (y - ys) / (yj - ys) + xs
    return bool(np.count_nonzero(crosses & (x < x_at)) % 2)


def _distance_to_polygon_edges(x: float, y: float, poly: np.ndarray) -> float:
    """Distance [m] from (x, y) to the nearest edge of a polygon (N, 2)."""
    a = poly
    b = np.roll(poly, -1, axis=0)
    ab = b - a
    ap = np.array([x, y]) - a
    denom = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    t = np.clip(np.einsum("ij,ij->i", ap, ab) / denom, 0.0, 1.0)
    closest = a + ab * t[:, None]
    return float(np.min(np.hypot(closest[:, 0] - x, closest[:, 1] - y)))


def prism_label(p: Prism) -> str:
    """Human-readable name of an obstacle, for collision messages."""
    tag = f" {p.instance_id}" if p.instance_id else ""
    return f"{p.cls}{tag} (top {p.z1_m:.1f} m)"


@dataclass(frozen=True, slots=True)
class Obstacles:
    prisms: tuple[Prism, ...]
    boxes: np.ndarray  # (N, 6) xmin, ymin, xmax, ymax, z0, z1 [m]
    polys: tuple[np.ndarray, ...]  # (K, 2) footprints
    ground_z_m: float
    grid_origin: tuple[float, float]  # [m] x, y of cell (0, 0)'s lower corner
    grid: np.ndarray  # (nx, ny) float64: highest obstacle top whose bounding box meets the cell [m]

    @classmethod
    def from_layout(cls, layout: StaticLayout) -> Obstacles:
        prisms = tuple(p for p in layout.prisms if p.z1_m > layout.ground_z_m + MIN_OBSTACLE_HEIGHT_M)
        polys = tuple(np.asarray(p.footprint, dtype=np.float64).reshape(-1, 2) for p in prisms)
        if prisms:
            boxes = np.array(
                [
                    [q[:, 0].min(), q[:, 1].min(), q[:, 0].max(), q[:, 1].max(), p.z0_m, p.z1_m]
                    for p, q in zip(prisms, polys, strict=True)
                ]
            )
            x0, y0 = boxes[:, 0].min(), boxes[:, 1].min()
            nx = math.ceil((boxes[:, 2].max() - x0) / GRID_CELL_M) + 1
            ny = math.ceil((boxes[:, 3].max() - y0) / GRID_CELL_M) + 1
            grid = np.full((nx, ny), layout.ground_z_m)
            for b in boxes:
                i0, j0 = int((b[0] - x0) // GRID_CELL_M), int((b[1] - y0) // GRID_CELL_M)
                i1, j1 = int((b[2] - x0) // GRID_CELL_M), int((b[3] - y0) // GRID_CELL_M)
                cell = grid[i0 : i1 + 1, j0 : j1 + 1]
                np.maximum(cell, b[5], out=cell)
        else:
            boxes = np.zeros((0, 6))
            x0 = y0 = 0.0
            grid = np.full((1, 1), layout.ground_z_m)
        return cls(prisms, boxes, polys, layout.ground_z_m, (float(x0), float(y0)), grid)

    def top_near(self, x: float, y: float, radius_m: float) -> float:
        """Highest obstacle top [m] (or the ground) within about ``radius_m`` of (x, y); conservative."""
        x0, y0 = self.grid_origin
        nx, ny = self.grid.shape
        i0 = max(int((x - radius_m - x0) // GRID_CELL_M), 0)
        i1 = min(int((x + radius_m - x0) // GRID_CELL_M), nx - 1)
        j0 = max(int((y - radius_m - y0) // GRID_CELL_M), 0)
        j1 = min(int((y + radius_m - y0) // GRID_CELL_M), ny - 1)
        if i0 > i1 or j0 > j1:
            return self.ground_z_m
        return float(self.grid[i0 : i1 + 1, j0 : j1 + 1].max())

    def top_along(self, points_xy: np.ndarray, radius_m: float) -> float:
        """Highest obstacle top [m] within ``radius_m`` of any of ``points_xy`` (N, 2)."""
        return max((self.top_near(float(p[0]), float(p[1]), radius_m) for p in points_xy), default=self.ground_z_m)

    def hit(self, position_m: np.ndarray, radius_m: float) -> str | None:
        """What a sphere of ``radius_m`` at ``position_m`` (3,) overlaps: obstacle label, "ground" or None."""
        x, y, z = float(position_m[0]), float(position_m[1]), float(position_m[2])
        if z - radius_m <= self.ground_z_m:
            return "ground"
        if not len(self.boxes) or z - radius_m > self.top_near(x, y, radius_m):
            return None  # above everything around: the common case, one grid lookup
        b = self.boxes
        near = np.nonzero(
            (b[:, 0] - radius_m <= x)
            & (x <= b[:, 2] + radius_m)
            & (b[:, 1] - radius_m <= y)
            & (y <= b[:, 3] + radius_m)
            & (b[:, 4] - radius_m <= z)
            & (z <= b[:, 5] + radius_m)
        )[0]
        for i in near:
            poly = self.polys[i]
            inside = _point_in_polygon(x, y, poly)
            d_xy = 0.0 if inside else _distance_to_polygon_edges(x, y, poly)
            dz = max(b[i, 4] - z, z - b[i, 5], 0.0)
            if math.hypot(d_xy, dz) <= radius_m:
                return prism_label(self.prisms[i])
        return None
