"""Ego-centred bird's-eye-view semantic grid: static layers from the world, one layer per dynamic class.

The grid is level and yaw-aligned with the agent (x forward, y left), centred on ``base_link``:
cell (i, j) has its centre at x = -X + (j + 0.5) c, y = -Y + (i + 0.5) c for half extents (X, Y)
= ``SensorsSpec.bev_range_m`` and cell size c = ``SensorsSpec.bev_cell_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from cosim.classes import OBJECT_CLASSES
from cosim.geometry import rotation_matrix, rpy_from_quat
from cosim.snapshot import Actor, AgentState
from cosim.world.types import StaticLayout

#: Static layers in bit order (bit k of the world raster = layer k).
STATIC_LAYERS: tuple[str, ...] = (
    "road", "lane_marking", "sidewalk", "building", "vegetation", "terrain", "pole", "street_light", "rsu",
)
DYNAMIC_LAYERS: tuple[str, ...] = OBJECT_CLASSES
BEV_LAYERS: tuple[str, ...] = STATIC_LAYERS + DYNAMIC_LAYERS
_MAX_RASTER_CELLS = 6000  # per side; coarser cells beyond that


@dataclass(frozen=True)
class BevFrame:
    """``grid`` (ny, nx, L) uint8 0/1, layer k = :data:`BEV_LAYERS` [k]; row i = y, column j = x.

    ``origin_m`` (x, y, z) and ``yaw_rad`` place the grid's (centre) frame in map; ``cell_m`` [m].
    """

    agent_id: str
    grid: np.ndarray
    cell_m: float
    half_extent_m: tuple[float, float]
    origin_m: tuple[float, float, float]
    yaw_rad: float
    layers: tuple[str, ...] = BEV_LAYERS


@dataclass(frozen=True)
class StaticRaster:
    """World-aligned raster of static layer bits: ``bits`` (ny, nx) uint16, cell (i, j) covers
    [x0 + j res, +res) x [y0 + i res, +res) [m]."""

    bits: np.ndarray
    x0: float
    y0: float
    res_m: float

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ny, nx = self.bits.shape
        j = np.floor((x - self.x0) / self.res_m).astype(np.int64)
        i = np.floor((y - self.y0) / self.res_m).astype(np.int64)
        ok = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        out = np.zeros(x.shape, np.uint16)
        out[ok] = self.bits[i[ok], j[ok]]
        return out


def static_raster(layout: StaticLayout, cell_m: float, margin_m: float = 80.0) -> StaticRaster:
    """Rasterise every prism footprint of a static layer into its bit (PIL polygon fill)."""
    pts = [np.asarray(p.footprint) for p in layout.prisms if p.cls in STATIC_LAYERS]
    if not pts:
        return StaticRaster(np.zeros((1, 1), np.uint16), 0.0, 0.0, cell_m)
    allp = np.concatenate(pts)
    x0, y0 = allp.min(0) - margin_m
    x1, y1 = allp.max(0) + margin_m
    res = max(cell_m, (x1 - x0) / _MAX_RASTER_CELLS, (y1 - y0) / _MAX_RASTER_CELLS)
    nx, ny = math.ceil((x1 - x0) / res), math.ceil((y1 - y0) / res)
    bits = np.zeros((ny, nx), np.uint16)
    for k, layer in enumerate(STATIC_LAYERS):
        polys = [p for p in layout.prisms if p.cls == layer]
        if not polys:
            continue
        img = Image.new("1", (nx, ny), 0)
        draw = ImageDraw.Draw(img)
        for p in polys:
            fp = np.asarray(p.footprint)
            xy = [((x - x0) / res, (y - y0) / res) for x, y in fp]
            draw.polygon(xy, fill=1)
        bits |= (np.asarray(img, bool).astype(np.uint16) << k)
    return StaticRaster(bits, float(x0), float(y0), float(res))


def render_bev(agent: AgentState, raster: StaticRaster, actors: tuple[Actor, ...], cell_m: float,
               half_extent_m: tuple[float, float]) -> BevFrame:
    """The agent's BEV grid at this tick."""
    hx, hy = half_extent_m
    nx, ny = round(2 * hx / cell_m), round(2 * hy / cell_m)
    _, _, yaw = rpy_from_quat(agent.rotation)
    c, s = math.cos(yaw), math.sin(yaw)
    ox, oy, oz = agent.position_m
    gx = -hx + (np.arange(nx) + 0.5) * cell_m
    gy = -hy + (np.arange(ny) + 0.5) * cell_m
    mx = ox + c * gx[None, :] - s * gy[:, None]
    my = oy + s * gx[None, :] + c * gy[:, None]
    bits = raster.sample(mx, my)
    grid = np.zeros((ny, nx, len(BEV_LAYERS)), np.uint8)
    for k in range(len(STATIC_LAYERS)):
        grid[..., k] = (bits >> k) & 1
    reach = math.hypot(hx, hy)
    for a in actors:
        if a.cls not in DYNAMIC_LAYERS:
            continue
        dx, dy = a.center_m[0] - ox, a.center_m[1] - oy
        if math.hypot(dx, dy) > reach + max(a.size_m):
            continue
        # box centre and axes in the grid frame
        ex, ey = c * dx + s * dy, -s * dx + c * dy
        r = rotation_matrix(a.rotation)
        ayaw = math.atan2(r[1, 0], r[0, 0]) - yaw
        ca, sa = math.cos(ayaw), math.sin(ayaw)
        half_l, half_w = a.size_m[0] / 2, a.size_m[1] / 2
        ext = abs(ca) * half_l + abs(sa) * half_w, abs(sa) * half_l + abs(ca) * half_w
        j0 = max(0, int((ex - ext[0] + hx) / cell_m))
        j1 = min(nx, math.ceil((ex + ext[0] + hx) / cell_m))
        i0 = max(0, int((ey - ext[1] + hy) / cell_m))
        i1 = min(ny, math.ceil((ey + ext[1] + hy) / cell_m))
        if j0 >= j1 or i0 >= i1:
            continue
        px = gx[None, j0:j1] - ex
        py = gy[i0:i1, None] - ey
        lx = ca * px + sa * py
        ly = -sa * px + ca * py
        inside = (np.abs(lx) <= half_l) & (np.abs(ly) <= half_w)
        grid[i0:i1, j0:j1, len(STATIC_LAYERS) + DYNAMIC_LAYERS.index(a.cls)] |= inside.astype(np.uint8)
    return BevFrame(agent.agent_id, grid, cell_m, (hx, hy), (float(ox), float(oy), float(oz)), float(yaw))
