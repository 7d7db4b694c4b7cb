"""The detector's bird's-eye grid in numpy: pillars from points (the voxeliser), centre-heatmap targets
from boxes, and boxes back from the head's maps. No torch here.

Frames and units are the ego LiDAR frame's (FLU, metres, radians; docs/episode_format.md).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

#: ``cosim eval``'s evaluation area, half extents x, y [m] (cosim.eval.dataset.AREA_HALF_M, which a test checks;
#: not imported, so that this module needs numpy alone).
AREA_HALF_M: tuple[float, float] = (140.8, 40.0)
#: Point features per point in a pillar: x, y, z, intensity, offsets to the pillar's point mean (3) and to
#: the pillar's centre (2).
POINT_FEATURES = 9
#: Regression channels per output cell: dx, dy (offset in cells), z, log l, log w, log h, sin 2 yaw, cos 2 yaw
#: (the box's axis, which a LiDAR return fixes: a car seen from one side looks alike both ways) and the
#: direction (a logit, target 1 where the heading is the axis angle in (-pi/2, pi/2], 0 where it is that + pi).
REG_CHANNELS = 9
#: The first channels of :data:`REG_CHANNELS`, trained by L1; the last, the direction, by cross-entropy.
L1_CHANNELS = 8


@dataclass(frozen=True)
class Grid:
    """Detection range and pillar size. ``stride``: output cells per pillar side (the head's maps are
    ``ny / stride`` x ``nx / stride``). The default range is ``cosim eval``'s evaluation area (x +-140.8,
    y +-40 m): a smaller one leaves the far objects that collaborators see, which the evaluation counts,
    undetectable. ``max_pillars`` is above the default grid's cell count, so no pillar is dropped."""

    x_range: tuple[float, float] = (-AREA_HALF_M[0], AREA_HALF_M[0])
    y_range: tuple[float, float] = (-AREA_HALF_M[1], AREA_HALF_M[1])
    z_range: tuple[float, float] = (-3.0, 1.0)
    pillar_m: float = 0.8
    max_points: int = 32
    max_pillars: int = 40000  # MAX_PILLARS
    stride: int = 2

    @property
    def nx(self) -> int:
        return round((self.x_range[1] - self.x_range[0]) / self.pillar_m)

    @property
    def ny(self) -> int:
        return round((self.y_range[1] - self.y_range[0]) / self.pillar_m)

    @property
    def out_shape(self) -> tuple[int, int]:
        return math.ceil(self.ny / self.stride), math.ceil(self.nx / self.stride)

    @property
    def cell_m(self) -> float:
        return self.pillar_m * self.stride

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Grid:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    def crop(self, points: np.ndarray) -> np.ndarray:
        """The points (N, >=3) inside the range."""
        return points[self.in_range(points)]

    def in_range(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: points (N, >=3) inside the range."""
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        return ((x >= self.x_range[0]) & (x < self.x_range[1]) & (y >= self.y_range[0]) & (y < self.y_range[1])
                & (z >= self.z_range[0]) & (z < self.z_range[1]))

    def covers(self, other: Grid) -> bool:
        """Whether ``other``'s range (x, y and z) lies inside this grid's (any pillar size): points cropped
        to this grid hold every point of ``other``."""
        return all(a[0] <= b[0] and b[1] <= a[1] for a, b in ((self.x_range, other.x_range),
                                                              (self.y_range, other.y_range),
                                                              (self.z_range, other.z_range)))

    def box_inside(self, centers: np.ndarray) -> np.ndarray:
        return ((centers[:, 0] >= self.x_range[0]) & (centers[:, 0] < self.x_range[1])
                & (centers[:, 1] >= self.y_range[0]) & (centers[:, 1] < self.y_range[1]))


#: ``--pillar-m`` below which a grid is refused (PointPillars' finest is 0.16 m).
MIN_PILLAR_M = 0.1
#: The cap on pillars of the default grid, kept as the floor of a finer one's (:func:`make_grid`).
MAX_PILLARS = 40000


def make_grid(pillar_m: float = 0.8, x_range: tuple[float, float] | None = None,
              y_range: tuple[float, float] | None = None) -> Grid:
    """The detector's grid with ``pillar_m`` pillars over ``x_range``, ``y_range`` [m] of the ego LiDAR frame
    (default: the evaluation area, :data:`AREA_HALF_M`; a KITTI-like front view is x (0, 70.4), y (-40, 40)).
    Each extent must be a whole number of pillars (an even number, so that the head's stride-2 cells tile
    it). ``max_pillars`` is the larger of :data:`MAX_PILLARS` and the cell count: no pillar is ever dropped.
    Raises InputError naming the problem."""
    from cosim.errors import InputError

    x_range = tuple(float(v) for v in (x_range or (-AREA_HALF_M[0], AREA_HALF_M[0])))
    y_range = tuple(float(v) for v in (y_range or (-AREA_HALF_M[1], AREA_HALF_M[1])))
    if not (math.isfinite(pillar_m) and pillar_m >= MIN_PILLAR_M):
        raise InputError(f"--pillar-m {pillar_m:g}: pillars must be at least {MIN_PILLAR_M:g} m")
    for name, (lo, hi) in (("x", x_range), ("y", y_range)):
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise InputError(f"--range-m: the {name} range {lo:g} to {hi:g} m is empty (give low < high)")
        n = (hi - lo) / pillar_m
        if abs(n - round(n)) > 1e-6 or round(n) % 2:
            raise InputError(f"--range-m: the {name} range {lo:g} to {hi:g} m is {n:.6g} pillars of {pillar_m:g} m; "
                             "it must be an even whole number of them")
    g = Grid(x_range=x_range, y_range=y_range, pillar_m=float(pillar_m))
    return Grid(x_range=x_range, y_range=y_range, pillar_m=float(pillar_m), max_pillars=max(MAX_PILLARS, g.nx * g.ny))


def voxelise(points: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pillars of a point cloud (N, 4: x, y, z, intensity) in the grid's frame, as a sparse list of points.

    Returns ``features`` (K, 9) float32, the kept points pillar after pillar (``counts[0]`` points of the
    first pillar, then the second's, ...), ``coords`` (P, 2) int64 (row iy, column ix) and ``counts`` (P,)
    points per pillar (<= max_points, sum K). Points are kept in their given order within a pillar; a pillar
    with more than ``max_points`` keeps ``max_points`` of them evenly spaced through that order (so every agent
    of a merged cloud keeps its share); when more than ``max_pillars`` pillars are occupied, the fullest are
    kept (ties by grid index), so the result depends only on the points.
    """
    pts = grid.crop(np.asarray(points, np.float32))
    m = grid.max_points
    if len(pts) == 0:
        return np.zeros((0, POINT_FEATURES), np.float32), np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    ix = np.floor((pts[:, 0] - grid.x_range[0]) / grid.pillar_m).astype(np.int64).clip(0, grid.nx - 1)
    iy = np.floor((pts[:, 1] - grid.y_range[0]) / grid.pillar_m).astype(np.int64).clip(0, grid.ny - 1)
    flat = iy * grid.nx + ix
    order = np.argsort(flat, kind="stable")
    flat_s, pts_s = flat[order], pts[order]
    uniq, counts = np.unique(flat_s, return_counts=True)
    if len(uniq) > grid.max_pillars:
        keep = np.lexsort((uniq, -counts))[: grid.max_pillars]
        keep.sort()
        point_sel = np.repeat(np.isin(np.arange(len(uniq)), keep), counts)
        uniq, counts = uniq[keep], counts[keep]
        flat_s, pts_s = flat_s[point_sel], pts_s[point_sel]
    # a pillar with more than m points keeps m of them evenly spaced through its points' order (the j-th kept
    # is the floor(j n / m)-th): with the ego's cloud first, the first m would drop every collaborator's point
    # wherever the ego's fill the pillar
    if counts.max() > m:
        total = np.repeat(counts, counts)
        rank = np.arange(len(flat_s)) - np.repeat(np.cumsum(counts) - counts, counts)
        ok = (total <= m) | ((rank * m) % total < m)
        pts_s = pts_s[ok]
    n = np.minimum(counts, m)
    pillar = np.repeat(np.arange(len(uniq)), n)
    first = np.cumsum(n) - n
    mean = np.add.reduceat(pts_s[:, :3].astype(np.float64), first, axis=0) / n[:, None]
    cy, cx = np.divmod(uniq, grid.nx)
    centre = np.stack([grid.x_range[0] + (cx + 0.5) * grid.pillar_m, grid.y_range[0] + (cy + 0.5) * grid.pillar_m],
                      axis=1)
    feats = np.empty((len(pts_s), POINT_FEATURES), np.float32)
    feats[:, :4] = pts_s[:, :4]
    feats[:, 4:7] = pts_s[:, :3] - mean.astype(np.float32)[pillar]
    feats[:, 7:9] = pts_s[:, :2] - centre[pillar]
    return feats, np.stack([cy, cx], axis=1).astype(np.int64), n.astype(np.int64)


def warp_index(coords: np.ndarray, poses: np.ndarray, present: np.ndarray, grid: Grid, agent: Grid
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intermediate fusion's index warp: for every ego cell of ``grid`` and every agent j of its sample, the
    pillar of agent j (in ``agent``'s grid, in agent j's frame) whose cell holds the ego cell's centre moved
    into that frame (nearest cell, any yaw).

    ``coords`` (P, 3) [map, row, column] of the pillars, map = b x J + j; ``poses`` (B, J, 3) yaw, x, y of
    agent j's frame in the ego's; ``present`` (B, J). Returns the hits only, ordered by cell, then agent:
    ``cell`` (H,) the ego cell (b x ny x nx + row x nx + column), ``pillar`` (H,) the pillar's row of
    ``coords`` and ``ego`` (H,) bool: the hit is the sample's first agent's (the ego's own map).
    """
    j = present.shape[1]
    cx = grid.x_range[0] + (np.arange(grid.nx, dtype=np.float64) + 0.5) * grid.pillar_m
    cy = grid.y_range[0] + (np.arange(grid.ny, dtype=np.float64) + 0.5) * grid.pillar_m
    keys = (coords[:, 0] * agent.ny + coords[:, 1]) * agent.nx + coords[:, 2]
    order = np.argsort(keys, kind="stable")
    keys_s = keys[order]
    cells, pillars, egos = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0, bool)]
    for m in np.flatnonzero(present.reshape(-1)):
        yaw, x, y = poses.reshape(-1, 3)[m]
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = cx[None, :] - x, cy[:, None] - y
        col = np.floor((c * dx + s * dy - agent.x_range[0]) / agent.pillar_m).astype(np.int64)  # the ego cell's
        row = np.floor((-s * dx + c * dy - agent.y_range[0]) / agent.pillar_m).astype(np.int64)  # centre in j's
        inside = ((col >= 0) & (col < agent.nx) & (row >= 0) & (row < agent.ny)).reshape(-1)
        query = (m * agent.ny + row.reshape(-1)) * agent.nx + col.reshape(-1)
        pos = np.searchsorted(keys_s, query).clip(max=max(len(keys_s) - 1, 0))
        hit = np.flatnonzero(inside & (keys_s[pos] == query)) if len(keys_s) else np.zeros(0, np.int64)
        cells.append(m // j * grid.ny * grid.nx + hit)
        pillars.append(order[pos[hit]])
        egos.append(np.full(len(hit), m % j == 0))
    cell = np.concatenate(cells)
    order = np.argsort(cell, kind="stable")
    return cell[order], np.concatenate(pillars)[order], np.concatenate(egos)[order]


def gaussian_radius(length_cells: float, width_cells: float, min_overlap: float = 0.1) -> float:
    """CenterNet's radius: how far a corner may move while the box keeps ``min_overlap`` IoU (three cases,
    the smallest root)."""
    h, w = length_cells, width_cells
    b1 = h + w
    c1 = w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1 ** 2 - 4 * c1)) / 2
    b2 = 2 * (h + w)
    c2 = (1 - min_overlap) * w * h
    r2 = (b2 + math.sqrt(b2 ** 2 - 16 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (h + w)
    c3 = (min_overlap - 1) * w * h
    r3 = (b3 + math.sqrt(b3 ** 2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def targets(boxes: np.ndarray, labels: np.ndarray, grid: Grid, n_classes: int, max_objects: int = 128
            ) -> dict[str, np.ndarray]:
    """Training targets of one sample: ``heatmap`` (K, H, W) with a Gaussian peak of 1 at each box centre
    in its class's channel, and up to ``max_objects`` regression targets ``reg`` (O, 9) at cells ``index``
    (O,) (flat row * W + column), ``mask`` (O,) marking the used rows. The yaw is the doubled angle's sine and
    cosine plus a direction target of 1 or 0 (:data:`REG_CHANNELS`)."""
    h, w = grid.out_shape
    heat = np.zeros((n_classes, h, w), np.float32)
    reg = np.zeros((max_objects, REG_CHANNELS), np.float32)
    index = np.zeros(max_objects, np.int64)
    mask = np.zeros(max_objects, np.float32)
    cell = grid.cell_m
    yy, xx = np.mgrid[0:h, 0:w]
    n = 0
    for box, k in zip(boxes, labels, strict=True):
        if n >= max_objects:
            break
        fx = (box[0] - grid.x_range[0]) / cell
        fy = (box[1] - grid.y_range[0]) / cell
        cx, cy = int(fx), int(fy)
        if not (0 <= cx < w and 0 <= cy < h):
            continue
        radius = max(1.0, gaussian_radius(box[3] / cell, box[4] / cell))
        sigma = (2 * radius + 1) / 6
        r = math.ceil(radius)
        y0, y1, x0, x1 = max(0, cy - r), min(h, cy + r + 1), max(0, cx - r), min(w, cx + r + 1)
        g = np.exp(-((xx[y0:y1, x0:x1] - cx) ** 2 + (yy[y0:y1, x0:x1] - cy) ** 2) / (2 * sigma ** 2))
        np.maximum(heat[k, y0:y1, x0:x1], g.astype(np.float32), out=heat[k, y0:y1, x0:x1])
        axis = 0.5 * math.atan2(math.sin(2 * box[6]), math.cos(2 * box[6]))
        reg[n] = [fx - cx, fy - cy, box[2], math.log(box[3]), math.log(box[4]), math.log(box[5]),
                  math.sin(2 * box[6]), math.cos(2 * box[6]), float(math.cos(box[6] - axis) > 0)]
        index[n] = cy * w + cx
        mask[n] = 1.0
        n += 1
    return {"heatmap": heat, "reg": reg, "index": index, "mask": mask}


def decode(heat: np.ndarray, reg: np.ndarray, grid: Grid, score_min: float = 0.1, top_k: int = 100
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes from one sample's head output: ``heat`` (K, H, W) probabilities, already reduced to local
    maxima (others 0), ``reg`` (9, H, W): the yaw is the axis angle, turned by pi where the direction logit is
    not above 0. Returns boxes (N, 7) [x, y, z, l, w, h, yaw], scores (N,),
    class indices (N,), best first."""
    _k, h, w = heat.shape
    flat = heat.reshape(-1)
    cand = np.nonzero(flat >= score_min)[0]
    cand = cand[np.argsort(-flat[cand], kind="stable")][:top_k]
    cls, rest = np.divmod(cand, h * w)
    cy, cx = np.divmod(rest, w)
    r = reg[:, cy, cx]
    cell = grid.cell_m
    x = grid.x_range[0] + (cx + r[0]) * cell
    y = grid.y_range[0] + (cy + r[1]) * cell
    size = np.exp(np.clip(r[3:6], -3.0, 3.5))
    axis = 0.5 * np.arctan2(r[6], r[7])
    yaw = np.where(r[8] > 0, axis, np.where(axis > 0, axis - np.pi, axis + np.pi))  # in (-pi, pi]
    boxes = np.stack([x, y, r[2], size[0], size[1], size[2], yaw], axis=1).astype(np.float64)
    return boxes.reshape(-1, 7), flat[cand].astype(np.float64), cls.astype(np.int64)
