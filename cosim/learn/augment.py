"""Training augmentations of ``cosim learn`` in numpy alone: the global transforms, point drop and intensity
jitter of the LiDAR detection toolboxes, the sensor-height jitter, and ground-truth sampling (written for this
project from the descriptions in the SECOND (Yan et al., 2018) and PointPillars (Lang et al., 2019) papers;
docs/learnability.md, "Augmentation").

Every function takes points ``(N, 4+)`` float32 (x, y, z [m], intensity in 0..1, then anything) and boxes
``(M, 7)`` ([x, y, z, l, w, h, yaw]: centre [m], size [m], yaw [rad] about z) in one frame whose z axis is
up: the ego LiDAR frame (FLU, the sensor at the origin), or for intermediate fusion an agent's bird's-eye
frame (its x, y and heading, the ego's z). Nothing is changed in place. Randomness comes only from the
``numpy.random.Generator`` given, so a training step's batch depends on (seed, step) alone
(:func:`cosim.learn.train.step_batch`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Spherical bins of the occlusion of pasted objects (azimuth, elevation) [deg]: a scene point is hidden when a
#: pasted point in its bin is nearer the sensor. About one HDL-64E azimuth step and two of its ring spacings.
OCCLUSION_BIN_DEG: tuple[float, float] = (0.4, 1.0)
#: A pasted object needs ground returns around it: at least this many within 1 m of its footprint.
GROUND_MIN_POINTS = 3
#: Anything standing in a pasted object's footprint (grown by 0.2 m) higher than this above the ground
#: [m] makes the place not free (a wall, a pole, a bush, another object).
STANDING_M = 0.3
#: The ego vehicle's own footprint at the origin (l, w [m]), never a place to paste on.
EGO_FOOTPRINT_M: tuple[float, float] = (5.0, 2.2)


def rotate(points: np.ndarray, boxes: np.ndarray, angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Points and boxes turned by ``angle_rad`` about the frame's z axis (global rotation); the boxes' yaw
    grows by the angle."""
    points, boxes = points.copy(), boxes.copy()
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    for a in (points, boxes):
        x, y = a[:, 0].copy(), a[:, 1].copy()
        a[:, 0] = c * x - s * y
        a[:, 1] = s * x + c * y
    boxes[:, 6] += angle_rad
    return points, boxes


def scale(points: np.ndarray, boxes: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """Points and boxes scaled by ``factor`` about the frame's origin (global scaling): x, y, z of points and
    centres and the boxes' sizes; a point inside a box stays inside it."""
    points, boxes = points.copy(), boxes.copy()
    points[:, :3] *= np.asarray(factor, points.dtype)
    boxes[:, :6] *= factor
    return points, boxes


def translate(points: np.ndarray, boxes: np.ndarray, offset_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and box centres moved by ``offset_m`` (3,) [m] (global translation; the sensor-height jitter is
    the offset (0, 0, dz): the sensor stands dz lower against the scene)."""
    points, boxes = points.copy(), boxes.copy()
    off = np.asarray(offset_m, np.float64).reshape(3)
    points[:, :3] += off.astype(points.dtype)
    boxes[:, :3] += off
    return points, boxes


def drop_points(points: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """The points (N, 4+) less each one with probability ``share`` (random point drop; order kept)."""
    if share <= 0 or len(points) == 0:
        return points.copy()
    return points[rng.random(len(points)) >= share]


def jitter_intensity(points: np.ndarray, factor: float, noise: float, rng: np.random.Generator) -> np.ndarray:
    """The points with intensity (column 3) multiplied by ``factor``, plus Gaussian noise of standard deviation
    ``noise`` per point (drawn only when ``noise`` > 0), clipped to 0..1."""
    out = points.copy()
    i = out[:, 3].astype(np.float64) * factor
    if noise > 0:
        i = i + rng.normal(0.0, noise, len(out))
    out[:, 3] = np.clip(i, 0.0, 1.0)
    return out


def transform_poses(poses: np.ndarray, factor: float, offset_m: np.ndarray) -> np.ndarray:
    """Bird's-eye poses (J, 3: yaw, x, y of each agent's frame in the ego's) after the scene is scaled by
    ``factor`` about the ego's origin, then moved by ``offset_m`` (3,): an agent's cloud, in its own frame, is
    scaled by the same factor and keeps its x, y (p_ego = R p_agent + t, so f p_ego + d = R (f p_agent) +
    f t + d); the z of the offset moves every cloud, the poses have none."""
    out = np.asarray(poses, np.float64).copy()
    out[:, 1:3] = out[:, 1:3] * factor + np.asarray(offset_m, np.float64).reshape(3)[:2]
    return out


def points_in_boxes(points: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """(N, M) bool: point n inside box m (its rotated footprint and z extent), grown by ``margin_m``."""
    if len(boxes) == 0 or len(points) == 0:
        return np.zeros((len(points), len(boxes)), bool)
    d = points[:, None, :3].astype(np.float64) - boxes[None, :, :3]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    along = d[..., 0] * c + d[..., 1] * s
    across = -d[..., 0] * s + d[..., 1] * c
    return ((np.abs(along) <= boxes[:, 3] / 2 + margin_m) & (np.abs(across) <= boxes[:, 4] / 2 + margin_m)
            & (np.abs(d[..., 2]) <= boxes[:, 5] / 2 + margin_m))


def _in_footprint(xy: np.ndarray, box: np.ndarray, margin_m: float) -> np.ndarray:
    d = xy[:, :2].astype(np.float64) - box[:2]
    c, s = math.cos(box[6]), math.sin(box[6])
    return ((np.abs(d[:, 0] * c + d[:, 1] * s) <= box[3] / 2 + margin_m)
            & (np.abs(-d[:, 0] * s + d[:, 1] * c) <= box[4] / 2 + margin_m))


def _corners(boxes: np.ndarray) -> np.ndarray:
    """(M, 4, 2) bird's-eye corners of boxes (M, 7)."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    hl, hw = boxes[:, 3] / 2, boxes[:, 4] / 2
    sx = np.array([1, 1, -1, -1])[None]
    sy = np.array([1, -1, -1, 1])[None]
    x = boxes[:, 0:1] + sx * hl[:, None] * c[:, None] - sy * hw[:, None] * s[:, None]
    y = boxes[:, 1:2] + sx * hl[:, None] * s[:, None] + sy * hw[:, None] * c[:, None]
    return np.stack([x, y], axis=2)


def bev_overlap(a: np.ndarray, b: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """(M, K) bool: the bird's-eye footprints of boxes ``a`` (M, 7) and ``b`` (K, 7), each grown by
    ``margin_m`` on every side, overlap (separating axes: exact for rectangles)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)), bool)
    grow = np.array([0, 0, 0, 2 * margin_m, 2 * margin_m, 0, 0])
    ca, cb = _corners(a + grow)[:, None], _corners(b + grow)[None]  # (M, 1, 4, 2), (1, K, 4, 2)
    apart = np.zeros((len(a), len(b)), bool)
    for yaws in (a[:, 6][:, None] + np.zeros(len(b))[None], np.zeros(len(a))[:, None] + b[:, 6][None]):
        for turn in (0.0, math.pi / 2):
            ax = np.stack([np.cos(yaws + turn), np.sin(yaws + turn)], axis=-1)[:, :, None, :]  # (M, K, 1, 2)
            pa, pb = (ca * ax).sum(-1), (cb * ax).sum(-1)  # (M, K, 4)
            apart |= (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~apart


@dataclass
class GtDatabase:
    """Labelled objects and their points, cut from training samples (ground-truth sampling).

    ``boxes`` (K, 7) in the ego LiDAR frame of the sample each object was cut from, ``labels`` (K,) class
    indices, ``points`` K arrays (n, 4+) of the points inside each box in that frame, ``sources`` (K,) an id of
    the (episode, tick) it came from and ``ticks`` those ids by (episode, tick): an object is never pasted into
    a sample of its own tick, where it stands already, seen by another ego."""

    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    labels: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    points: list[np.ndarray] = field(default_factory=list)
    sources: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    ticks: dict[tuple[str, int], int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def build(cls, samples: Any, min_points: int = 5) -> GtDatabase:
        """The objects of every sample of ``samples`` (``len``, ``item(i)``: single-agent samples, one cloud
        and one target set) with at least ``min_points`` points inside their box, in sample order."""
        boxes, labels, points, sources = [], [], [], []
        ticks: dict[tuple[str, int], int] = {}
        for i in range(len(samples)):
            item = samples.item(i)
            src = ticks.setdefault((item["episode"], item["tick"]), len(ticks))
            cloud = item["clouds"][0]
            b, lab = item["targets"][0]
            inside = points_in_boxes(cloud, b)
            for m in range(len(b)):
                if inside[:, m].sum() >= min_points:
                    boxes.append(np.asarray(b[m], np.float64))
                    labels.append(int(lab[m]))
                    points.append(cloud[inside[:, m]].copy())
                    sources.append(src)
        return cls(np.asarray(boxes, np.float64).reshape(-1, 7), np.asarray(labels, np.int64), points,
                   np.asarray(sources, np.int64), ticks)

    def source_of(self, item: dict[str, Any]) -> int:
        """The id of a sample's (episode, tick) in :attr:`sources` (-1: a tick no object came from)."""
        return self.ticks.get((item["episode"], item["tick"]), -1)


def paste_objects(db: GtDatabase, points: np.ndarray, boxes: np.ndarray, labels: np.ndarray, count: int,
                  rng: np.random.Generator, source: int = -1, occlude: bool = True
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth sampling: up to ``count`` objects of ``db`` pasted into one sample (points (N, 4+), boxes
    (M, 7), labels (M,) in the ego LiDAR frame), each where it stood in its own sample (the same range and
    bearing from the sensor, so its points keep the pattern the LiDAR gives there), at a free place only:

    - its footprint (grown by 0.1 m) overlaps no box of the sample, no object pasted before it and not the
      ego's own footprint;
    - the sample has ground returns around it (:data:`GROUND_MIN_POINTS` within 1 m of the footprint, below
      its bottom + 0.5 m) and nothing standing in it (no point higher than :data:`STANDING_M` above that
      ground within 0.2 m of the footprint, up to its roof + 0.3 m);
    - it is moved in z onto that ground (the median height of those returns).

    The sample's points inside a pasted box are removed, and, with ``occlude``, so are the points a pasted
    object hides from the sensor (in a spherical bin of :data:`OCCLUSION_BIN_DEG` that holds a pasted point
    nearer the sensor). The pasted object's own points are kept whole. Candidates are ``4 count`` draws from the
    database (with replacement); ``source``: the id of this sample's tick (objects of it are skipped). Returns
    the points (the sample's kept, then the pasted ones), boxes and labels (the sample's, then the pasted)."""
    if count <= 0 or len(db) == 0:
        return points.copy(), boxes.copy(), labels.copy()
    obstacles = [np.asarray(boxes, np.float64).reshape(-1, 7),
                 np.array([[0.0, 0.0, 0.0, EGO_FOOTPRINT_M[0], EGO_FOOTPRINT_M[1], 1.0, 0.0]])]
    keep = np.ones(len(points), bool)
    pasted_boxes, pasted_labels, pasted_points = [], [], []
    cells = _Cells(points[:, :2])
    for c in rng.integers(len(db), size=4 * count):
        if len(pasted_boxes) >= count:
            break
        if db.sources[c] == source:
            continue
        box = db.boxes[c].copy()
        if bev_overlap(box[None], np.concatenate(obstacles), 0.1).any():
            continue
        idx = cells.near(box[0], box[1], math.hypot(box[3], box[4]) / 2 + 1.0)  # every point within 1 m of it
        sub = points[idx]
        z = sub[:, 2].astype(np.float64)
        bottom = box[2] - box[5] / 2
        low = _in_footprint(sub, box, 1.0) & (z < bottom + 0.5) & (z > bottom - 1.0)
        if low.sum() < GROUND_MIN_POINTS:
            continue
        ground = float(np.median(z[low]))
        standing = (_in_footprint(sub, box, 0.2) & (z > ground + STANDING_M) & (z < ground + box[5] + 0.3))
        if standing.any():
            continue
        dz = ground - bottom
        box[2] += dz
        obj = db.points[c].copy()
        obj[:, 2] += np.float32(dz)
        keep[idx[points_in_boxes(sub, box[None], 0.05)[:, 0]]] = False
        obstacles.append(box[None])
        pasted_boxes.append(box)
        pasted_labels.append(db.labels[c])
        pasted_points.append(obj)
    if not pasted_boxes:
        return points.copy(), boxes.copy(), labels.copy()
    obj_all = np.concatenate(pasted_points)
    if occlude:
        keep &= ~_hidden(points, obj_all)
    return (np.concatenate([points[keep], obj_all.astype(points.dtype)]),
            np.concatenate([np.asarray(boxes, np.float64).reshape(-1, 7), np.array(pasted_boxes)]),
            np.concatenate([labels, np.array(pasted_labels, labels.dtype)]))


class _Cells:
    """Points (N, 2+) hashed into square cells of ``size_m`` of x, y, for the points near a place."""

    def __init__(self, xy: np.ndarray, size_m: float = 4.0):
        self.size_m = size_m
        c = np.floor(xy[:, :2].astype(np.float64) / size_m).astype(np.int64) + (1 << 20)
        key = (c[:, 0] << 21) + c[:, 1]
        self.order = np.argsort(key, kind="stable")
        self.keys = key[self.order]

    def near(self, x: float, y: float, radius_m: float) -> np.ndarray:
        """(K,) indices of the points in the cells that the square of half side ``radius_m`` around (x, y)
        touches (every point within ``radius_m``, and some more), ascending."""
        lo = [math.floor((v - radius_m) / self.size_m) + (1 << 20) for v in (x, y)]
        hi = [math.floor((v + radius_m) / self.size_m) + (1 << 20) for v in (x, y)]
        parts = [self.order[np.searchsorted(self.keys, (cx << 21) + lo[1]):
                            np.searchsorted(self.keys, (cx << 21) + hi[1], side="right")]
                 for cx in range(lo[0], hi[0] + 1)]
        return np.sort(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def _spherical(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) int64 bin keys of :data:`OCCLUSION_BIN_DEG` and (N,) ranges [m] of points seen from the origin."""
    p = points[:, :3].astype(np.float64)
    rng_m = np.linalg.norm(p, axis=1)
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0])) + 180.0
    el = np.degrees(np.arcsin(np.clip(p[:, 2] / np.maximum(rng_m, 1e-9), -1.0, 1.0))) + 90.0
    ia = np.floor(az / OCCLUSION_BIN_DEG[0]).astype(np.int64)
    ie = np.floor(el / OCCLUSION_BIN_DEG[1]).astype(np.int64)
    return ie * 100_000 + ia, rng_m


def _hidden(scene: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """(N,) bool: scene points behind a point of ``obj`` in the same spherical bin (farther from the sensor
    than the nearest object point of that bin)."""
    if len(scene) == 0 or len(obj) == 0:
        return np.zeros(len(scene), bool)
    ko, ro = _spherical(obj)
    keys, first = np.unique(ko, return_inverse=True)
    nearest = np.full(len(keys), np.inf)
    np.minimum.at(nearest, first, ro)
    ks, rs = _spherical(scene)
    pos = np.searchsorted(keys, ks).clip(max=len(keys) - 1)
    return (keys[pos] == ks) & (rs > nearest[pos])
