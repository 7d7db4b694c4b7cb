"""Plane geometry for the static world: polygons, polyline offsets, rasterised masks.

Every polygon is an ``(N, 2)`` float64 array of map x/y [m] without a repeated last point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw, ImageFilter


def signed_area(poly: np.ndarray) -> float:
    """Shoelace area [m^2] of ``poly`` (N, 2); positive when counter-clockwise."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def ccw(poly: np.ndarray) -> np.ndarray:
    """``poly`` (N, 2) in counter-clockwise order, repeated last point and duplicates removed."""
    p = np.asarray(poly, dtype=np.float64)
    if len(p) > 1 and np.allclose(p[0], p[-1]):
        p = p[:-1]
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-6
    p = p[keep]
    return p[::-1].copy() if signed_area(p) < 0 else p


def rect(cx: float, cy: float, length_m: float, width_m: float, yaw_rad: float) -> np.ndarray:
    """Corners (4, 2) of a rectangle centred at (cx, cy), ``length_m`` along ``yaw_rad``, CCW."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    hl, hw = 0.5 * length_m, 0.5 * width_m
    local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.array([cx, cy])


def regular_polygon(cx: float, cy: float, radius_m: float, n: int = 8, phase_rad: float = 0.0) -> np.ndarray:
    """``n``-gon (n, 2) around (cx, cy), CCW."""
    a = phase_rad + np.arange(n) * (2.0 * math.pi / n)
    return np.stack([cx + radius_m * np.cos(a), cy + radius_m * np.sin(a)], axis=1)


def polyline_length(line: np.ndarray) -> float:
    """Length [m] of a polyline (N, 2)."""
    return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())


def resample(line: np.ndarray, start_m: float, end_m: float) -> np.ndarray:
    """Part of polyline ``line`` (N, 2) between arc lengths ``start_m`` and ``end_m``, as (M, 2)."""
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    start_m, end_m = max(0.0, start_m), min(s[-1], end_m)
    inner = [i for i in range(len(line)) if start_m < s[i] < end_m]
    pts = [point_at(line, start_m), *(line[i] for i in inner), point_at(line, end_m)]
    return np.array(pts)


def point_at(line: np.ndarray, pos_m: float) -> np.ndarray:
    """Point (2,) at arc length ``pos_m`` along polyline (N, 2), clamped to its ends."""
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    pos_m = min(max(pos_m, 0.0), s[-1])
    i = int(np.clip(np.searchsorted(s, pos_m, side="right") - 1, 0, len(seg) - 1))
    t = 0.0 if seg[i] < 1e-9 else (pos_m - s[i]) / seg[i]
    return line[i] + t * (line[i + 1] - line[i])


def direction_at(line: np.ndarray, pos_m: float) -> float:
    """Heading [rad, ENU] of polyline (N, 2) at arc length ``pos_m``."""
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    i = int(np.clip(np.searchsorted(s, pos_m, side="right") - 1, 0, len(seg) - 1))
    d = line[i + 1] - line[i]
    return math.atan2(d[1], d[0])


def offset_polyline(line: np.ndarray, offset_m: float) -> np.ndarray:
    """Polyline (N, 2) shifted ``offset_m`` to its left (negative: right), mitred at the joints."""
    p = np.asarray(line, dtype=np.float64)
    d = np.diff(p, axis=0)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    n[n < 1e-9] = 1e-9
    t = d / n
    normals = np.stack([-t[:, 1], t[:, 0]], axis=1)
    out = np.empty_like(p)
    out[0] = p[0] + offset_m * normals[0]
    out[-1] = p[-1] + offset_m * normals[-1]
    for i in range(1, len(p) - 1):
        m = normals[i - 1] + normals[i]
        norm = np.linalg.norm(m)
        if norm < 1e-6:
            out[i] = p[i] + offset_m * normals[i]
            continue
        m /= norm
        cos_half = max(0.3, float(np.dot(m, normals[i])))
        out[i] = p[i] + offset_m / cos_half * m
    return out


def strip(line: np.ndarray, width_m: float) -> np.ndarray:
    """CCW polygon of a band of ``width_m`` centred on polyline ``line`` (N, 2)."""
    left = offset_polyline(line, 0.5 * width_m)
    right = offset_polyline(line, -0.5 * width_m)
    return ccw(np.concatenate([right, left[::-1]], axis=0))


def points_in_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Bool (M,) whether each point (M, 2) lies inside polygon (N, 2) (boundary counts as inside)."""
    from matplotlib.path import Path as MplPath  # half a second to import: only the processes that need it

    return MplPath(poly).contains_points(points, radius=1e-9) | MplPath(poly[::-1]).contains_points(points, radius=1e-9)


@dataclass(frozen=True)
class Raster:
    """A boolean occupancy grid over the map: ``mask[row, col]`` covers
    x in [x0 + col * cell, x0 + (col + 1) * cell), y in [y0 + row * cell, ...)."""

    x0: float
    y0: float
    cell_m: float
    mask: np.ndarray  # (H, W) bool

    @classmethod
    def empty(cls, bounds_m: tuple[float, float, float, float], cell_m: float) -> Raster:
        xmin, ymin, xmax, ymax = bounds_m
        w = math.ceil((xmax - xmin) / cell_m) + 1
        h = math.ceil((ymax - ymin) / cell_m) + 1
        return cls(xmin, ymin, cell_m, np.zeros((h, w), dtype=bool))

    def with_polygons(self, polys: list[np.ndarray]) -> Raster:
        """A copy with every polygon (N, 2) filled in."""
        img = Image.fromarray(self.mask.astype(np.uint8) * 255, mode="L")
        draw = ImageDraw.Draw(img)
        for poly in polys:
            if len(poly) < 3:
                continue
            pix = (np.asarray(poly) - [self.x0, self.y0]) / self.cell_m
            draw.polygon([tuple(q) for q in pix.tolist()], fill=255, outline=255)
        return Raster(self.x0, self.y0, self.cell_m, np.asarray(img) > 0)

    def dilated(self, radius_m: float) -> Raster:
        """A copy grown by ``radius_m`` (square structuring element)."""
        k = 2 * math.ceil(radius_m / self.cell_m) + 1
        if k <= 1:
            return self
        img = Image.fromarray(self.mask.astype(np.uint8) * 255, mode="L").filter(ImageFilter.MaxFilter(k))
        return Raster(self.x0, self.y0, self.cell_m, np.asarray(img) > 0)

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Bool (M,) mask value at points (M, 2); outside the grid is False."""
        c = np.floor((points[:, 0] - self.x0) / self.cell_m).astype(int)
        r = np.floor((points[:, 1] - self.y0) / self.cell_m).astype(int)
        h, w = self.mask.shape
        ok = (c >= 0) & (c < w) & (r >= 0) & (r < h)
        out = np.zeros(len(points), dtype=bool)
        out[ok] = self.mask[r[ok], c[ok]]
        return out


class Occupancy:
    """A mutable occupancy grid for placing objects one after another without overlaps."""

    def __init__(self, bounds_m: tuple[float, float, float, float], cell_m: float) -> None:
        xmin, ymin, xmax, ymax = bounds_m
        self.x0, self.y0, self.cell_m = xmin, ymin, cell_m
        self.size = (math.ceil((xmax - xmin) / cell_m) + 1, math.ceil((ymax - ymin) / cell_m) + 1)
        self.img = Image.new("L", self.size, 0)
        self._draw = ImageDraw.Draw(self.img)

    def _pix(self, poly: np.ndarray) -> list[tuple[float, float]]:
        return [tuple(q) for q in ((np.asarray(poly) - [self.x0, self.y0]) / self.cell_m).tolist()]

    def add(self, poly: np.ndarray) -> None:
        self._draw.polygon(self._pix(poly), fill=255, outline=255)

    def add_mask(self, raster: Raster) -> None:
        """Mark every occupied cell of ``raster`` (same grid) as occupied."""
        self.img.paste(255, mask=Image.fromarray(raster.mask.astype(np.uint8) * 255, mode="L"))

    def free(self, poly: np.ndarray) -> bool:
        """True when polygon (N, 2) covers no occupied cell."""
        pix = np.asarray(self._pix(poly))
        x0, y0 = np.floor(pix.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(pix.max(axis=0)).astype(int) + 1
        region = np.asarray(self.img.crop((x0, y0, x1, y1))) > 0
        if not region.any():
            return True
        local = Image.new("L", (x1 - x0, y1 - y0), 0)
        ImageDraw.Draw(local).polygon([(x - x0, y - y0) for x, y in pix.tolist()], fill=255, outline=255)
        return not bool((region & (np.asarray(local) > 0)).any())

    def raster(self) -> Raster:
        return Raster(self.x0, self.y0, self.cell_m, np.asarray(self.img) > 0)
