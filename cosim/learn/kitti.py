"""A KITTI-layout folder (``velodyne/``, ``label_2/``, ``calib/``, optionally ``image_2/``) as a ``cosim learn``
dataset of single-agent samples: real scans, or cosim's own KITTI export (docs/realism.md, "Scoring a model
on real scans"). No torch at import.

Each scan becomes a learn record (:func:`cosim.learn.samples.learn_record`'s structure: one agent ``ego`` at
the identity pose, its points rounded to 1 cm, intensity in counts of 1/255, points per labelled box as its
hits), so :func:`cosim.learn.samples.make_item` makes the samples and training and prediction run the code
path of cosim's episodes. A folder is one "episode" (its id: :func:`folder_id`); a scan is the "tick" of its
number (``000076.bin``: 76); the ego is ``ego``.

Rules (all in the velodyne frame: x forward, y left, z up, metres):

- **Labels.** KITTI ``Car`` and ``Van`` (and ``Truck``, ``Tram``, ``Cyclist`` when chosen:
  :data:`KITTI_CLASSES`) are the model's vehicle classes ``car``, ``van`` (``truck``, ``bus``, ``bicycle``).
  ``DontCare`` regions (image rectangles), ``Misc``, ``Pedestrian``, ``Person_sitting``, the unchosen types
  and labels with fewer than ``min_points`` points are neither targets nor false positives: a detection on one
  of them (overlapping it more than any scored box, or centred in a DontCare rectangle) is left out of scoring.
- **Field of view.** KITTI labels objects only inside the front camera's image, so scoring counts only
  boxes and predictions whose centre projects into ``image_2`` (through ``P2``; the image's width from its
  PNG, else :data:`KITTI_IMAGE_WIDTH_PX`) and lies within the range asked; ``fov="front90"`` takes the front
  90 deg instead. ``"all"`` scores cosim's own export as ``cosim eval`` scores its episodes: every direction
  within cosim eval's area (x +-140.8, y +-40 m), nothing left out (a detection that matches no label is
  false). Training crops each scan to the camera's view: unlabelled cars behind the car must not be taught as
  background.
- **Sensor height.** A model stores the height of the LiDAR above the road it was trained at
  (:attr:`cosim.learn.samples.Setup.lidar_height_m`; cosim's episodes: the rig's mount height). A scan from
  a sensor at height ``h`` is moved up by ``h - H`` for a model of height ``H`` (its road then lies where the
  model's did), and the predictions moved back. ``h`` is given (``--lidar-height-m``) or estimated from the
  ground (:func:`estimate_height_m`).
- **Intensity.** cosim stores intensity 0..1 in counts of 1/255; KITTI's reflectance is 0..1 too. A scan's
  reflectance is multiplied by ``intensity_scale`` (default 1), clipped to 0..1 and rounded to 1/255, so both
  sources reach the model on one scale.
- **Targets** in training: labelled boxes of the chosen types with at least ``Setup.min_points`` points inside
  (:func:`box_point_counts`), centre in the grid.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError
from cosim.eval.ap import THRESHOLDS, DetectionAccumulator
from cosim.eval.boxes import footprints, iou_matrix
from cosim.io.kitti import KittiFolder, boxes_to_velo, read_labels, read_velodyne
from cosim.learn.grid import AREA_HALF_M
from cosim.learn.samples import quantise

#: KITTI object types that can be targets, and the cosim class each becomes.
KITTI_CLASSES: dict[str, str] = {"Car": "car", "Van": "van", "Truck": "truck", "Tram": "bus", "Cyclist": "bicycle"}
#: The targets by default (KITTI's "Car" benchmark counts vans as not-false-positives; here they are cars).
DEFAULT_TYPES: tuple[str, ...] = ("Car", "Van")
#: Width of KITTI's rectified colour images [px] when a folder has no ``image_2`` (they are 1224-1242).
KITTI_IMAGE_WIDTH_PX = 1242
#: Fields of view of scoring (see the module doc).
FOVS: tuple[str, ...] = ("camera", "front90", "all")
FRONT_HALF_ANGLE_RAD = math.radians(45.0)
#: Range bands of recall [m] (horizontal distance of the box centre from the sensor).
BANDS_M: tuple[tuple[float, float], ...] = ((0.0, 20.0), (20.0, 40.0), (40.0, 60.0))
#: The ego's name in the records of a KITTI folder.
EGO = "ego"
#: A label line has 15 columns (16 with a score).
LABEL_COLUMNS = 15


# ------------------------------------------------------------------------------------------- reading


def folder_id(folder: Path) -> str:
    """The "episode" id of a KITTI folder: its name, with its parent's before it for ``training`` or
    ``testing`` (``kitti_object/training``)."""
    folder = Path(folder).resolve()
    return f"{folder.parent.name}/{folder.name}" if folder.name in ("training", "testing") else folder.name


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) [px] from a PNG's header, or None when it is not a PNG."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    return struct.unpack(">II", head[16:24])


@dataclass
class Scan:
    """One scan of a KITTI folder in the velodyne frame: ``points`` (N, 4) float32 (x, y, z, reflectance 0..1),
    ``boxes`` (M, 7) [x, y, z centre, l, w, h, yaw] of every labelled object but DontCare with their ``types``
    (M,), ``dontcare`` (K, 4) image rectangles [px], ``image_from_velo`` (3, 4) (P2 after rect <- velo) and
    the image's width [px]."""

    stem: str
    points: np.ndarray
    boxes: np.ndarray
    types: list[str]
    dontcare: np.ndarray
    image_from_velo: np.ndarray | None
    image_width_px: int

    @property
    def tick(self) -> int:
        return int(self.stem)


class KittiSource:
    """A KITTI-layout folder (:class:`cosim.io.kitti.KittiFolder`: the folder itself or one holding
    ``training/``) read as samples: its scans (``stems``; those of ``ImageSets/<split>.txt`` with ``split``),
    each as a :class:`Scan`; the sensor's height above the road ``height_m`` (given, else
    :func:`estimate_height_m` over up to 20 scans); ``intensity_scale`` (the reflectance factor); ``types``
    (the KITTI types that are targets). ``labels`` True: every scan needs its label file."""

    def __init__(self, folder: Path | str, height_m: float | None = None, intensity_scale: float = 1.0,
                 types: Sequence[str] = DEFAULT_TYPES, labels: bool = True, split: str | None = None):
        self.kitti = KittiFolder(folder)
        self.folder = self.kitti.data
        self.stems = list(self.kitti.stems)
        if split is not None:
            if split not in self.kitti.splits:
                raise InputError(f"{folder}: no ImageSets/{split}.txt (splits: "
                                 f"{', '.join(self.kitti.splits) or 'none'})")
            have = set(self.stems)
            self.stems = [s for s in self.kitti.splits[split] if s in have]
            if not self.stems:
                raise InputError(f"{folder}: split {split} lists no scan of velodyne/")
        bad = [s for s in self.stems if not s.isdigit()]
        if bad:
            raise InputError(f"{self.folder}: scan {bad[0]}.bin is not named by its number (as 000076.bin)")
        unknown = [t for t in types if t not in KITTI_CLASSES]
        if unknown or not types:
            raise InputError(f"KITTI types {', '.join(unknown) or 'none'}: choose from {', '.join(KITTI_CLASSES)}")
        if height_m is not None and not (math.isfinite(height_m) and 0.0 < height_m < 10.0):
            raise InputError(f"--lidar-height-m {height_m}: the sensor's height above the road must be a number "
                             "above 0 and below 10 m")
        if not (math.isfinite(intensity_scale) and intensity_scale > 0):
            raise InputError(f"--intensity-scale {intensity_scale}: must be a number above 0")
        self.labels = labels
        if labels:
            missing = [s for s in self.stems if not self.kitti.has_labels(s)]
            if missing:
                raise InputError(f"{self.folder}: no label_2/{missing[0]}.txt ({len(missing)} scans without one)")
            for stem in self.stems:  # every label and calib file read once, so that a bad one stops us here
                read_labels(self.folder / "label_2" / f"{stem}.txt")
                self.kitti.calib(stem)
        self.id = folder_id(self.folder) + (f":{split}" if split else "")
        self.types = tuple(types)
        self.intensity_scale = float(intensity_scale)
        self.height_given = height_m is not None
        self.height_m = float(height_m) if height_m is not None else self.estimate_height()

    def __len__(self) -> int:
        return len(self.stems)

    def frame(self, stem: str) -> Scan:
        f = self.kitti.frame(stem)
        objs = [o for o in (f.objects or []) if not o.dont_care]
        dontcare = np.array([o.bbox for o in (f.objects or []) if o.dont_care], np.float64).reshape(-1, 4)
        p2 = f.calib.P2 @ f.calib.cam_from_velo
        size = png_size(f.image_path) if f.image_path is not None else None
        return Scan(stem, f.points, boxes_to_velo(objs, f.calib), [o.type for o in objs], dontcare, p2,
                    size[0] if size else KITTI_IMAGE_WIDTH_PX)

    def estimate_height(self, scans: int = 20) -> float:
        step = max(1, len(self.stems) // scans)
        heights = [estimate_height_m(read_velodyne(self.folder / "velodyne" / f"{s}.bin"))
                   for s in self.stems[::step][:scans]]
        good = [h for h in heights if math.isfinite(h)]
        if not good:
            raise InputError(f"{self.folder}: cannot find the road in its scans: give --lidar-height-m")
        return round(float(np.median(good)), 3)


# ------------------------------------------------------------------------------------- geometry rules


def estimate_height_m(points: np.ndarray, inner_m: float = 4.0, outer_m: float = 20.0, cell_m: float = 2.0
                      ) -> float:
    """The sensor's height above the road [m] from one scan (N, >=3): the lowest point of each ``cell_m``
    cell with at least 5 points in the ring ``inner_m``..``outer_m`` around the sensor, a plane z = a x + b y + c
    fitted to those by least squares with the cells more than 0.15 m off the plane dropped (5 rounds: cars and
    kerbs raise some cells' lowest point), and ``-c``: the road's depth under the sensor. NaN with under 10 cells."""
    xyz = np.asarray(points, np.float64)[:, :3]
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    p = xyz[(r >= inner_m) & (r <= outer_m)]
    if len(p) < 50:
        return float("nan")
    key = np.floor(p[:, 0] / cell_m).astype(np.int64) * 100_003 + np.floor(p[:, 1] / cell_m).astype(np.int64)
    order = np.lexsort((p[:, 2], key))
    key_s, p_s = key[order], p[order]
    first = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
    counts = np.diff(np.r_[first, len(key_s)])
    low = p_s[first[counts >= 5]]
    if len(low) < 10:
        return float("nan")
    keep = low[:, 2] <= np.percentile(low[:, 2], 50) + 0.5  # walls and cars: far above the road's median
    coef = np.zeros(3)
    for _ in range(5):
        a = np.column_stack([low[keep, 0], low[keep, 1], np.ones(keep.sum())])
        coef = np.linalg.lstsq(a, low[keep, 2], rcond=None)[0]
        resid = low[:, 2] - (low[:, 0] * coef[0] + low[:, 1] * coef[1] + coef[2])
        new = np.abs(resid) <= 0.15
        if new.sum() < 10 or (new == keep).all():
            break
        keep = new
    return float(-coef[2])


def box_point_counts(xyz: np.ndarray, boxes: np.ndarray, margin_m: float = 0.1, ground_m: float = 0.15
                    ) -> np.ndarray:
    """Points (M,) inside each box (M, 7), grown by ``margin_m`` on every side but the bottom, less its lowest
    ``ground_m`` (the road under a labelled box is not the car; as benchmarks/lidar_realism.py counts)."""
    xyz = np.asarray(xyz, np.float64)[:, :3]
    return np.array([int(points_in_box(xyz, b, margin_m, ground_m).sum()) for b in boxes], np.int64)


def points_in_box(xyz: np.ndarray, b: np.ndarray, margin_m: float = 0.1, ground_m: float = 0.15) -> np.ndarray:
    """(N,) bool: which points ``xyz`` (N, 3) lie inside box ``b`` (7,) as :func:`box_point_counts` counts them."""
    d = np.asarray(xyz, np.float64)[:, :3] - b[:3]
    reach = math.hypot(b[3], b[4]) / 2 + margin_m
    out = (np.abs(d[:, 0]) <= reach) & (np.abs(d[:, 1]) <= reach)
    near = np.flatnonzero(out)
    d = d[near]
    c, s = math.cos(b[6]), math.sin(b[6])
    u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    out[near] = ((np.abs(u) <= b[3] / 2 + margin_m) & (np.abs(v) <= b[4] / 2 + margin_m)
                 & (d[:, 2] >= -b[5] / 2 + ground_m) & (d[:, 2] <= b[5] / 2 + margin_m))
    return out


def in_view(xyz: np.ndarray, frame: Scan, fov: str) -> np.ndarray:
    """(N,) bool: points or box centres (N, >=3, velodyne frame) inside the field of view ``fov``
    (:data:`FOVS`; ``camera`` without P2 is the front 90 deg; ``all``: cosim eval's evaluation area)."""
    xyz = np.asarray(xyz, np.float64)
    xyz = xyz.reshape(len(xyz), -1) if xyz.size else np.zeros((0, 3))
    if fov == "all":
        return (np.abs(xyz[:, 0]) <= AREA_HALF_M[0]) & (np.abs(xyz[:, 1]) <= AREA_HALF_M[1])
    if fov == "camera" and frame.image_from_velo is not None:
        uvw = np.column_stack([xyz[:, :3], np.ones(len(xyz))]) @ frame.image_from_velo.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u = uvw[:, 0] / uvw[:, 2]
        return (uvw[:, 2] > 0) & (u >= 0) & (u < frame.image_width_px)
    if fov not in FOVS:
        raise InputError(f"unknown field of view {fov!r}; choose one of {', '.join(FOVS)}")
    return np.abs(np.arctan2(xyz[:, 1], xyz[:, 0])) <= FRONT_HALF_ANGLE_RAD


def in_dontcare(xyz: np.ndarray, frame: Scan) -> np.ndarray:
    """(N,) bool: centres (N, 3) that project into a DontCare rectangle of the image."""
    out = np.zeros(len(xyz), bool)
    if frame.image_from_velo is None or not len(frame.dontcare) or not len(xyz):
        return out
    uvw = np.column_stack([np.asarray(xyz)[:, :3], np.ones(len(xyz))]) @ frame.image_from_velo.T
    front = uvw[:, 2] > 0
    u = np.where(front, uvw[:, 0] / np.where(front, uvw[:, 2], 1.0), -1e9)
    v = np.where(front, uvw[:, 1] / np.where(front, uvw[:, 2], 1.0), -1e9)
    for x0, y0, x1, y1 in frame.dontcare:
        out |= (u >= x0) & (u <= x1) & (v >= y0) & (v <= y1)
    return out


# ---------------------------------------------------------------------------------------- samples


def _quat_z(yaw: np.ndarray) -> np.ndarray:
    yaw = np.asarray(yaw, np.float64)
    z = np.zeros_like(yaw)
    return np.stack([z, z, np.sin(yaw / 2), np.cos(yaw / 2)], axis=1).reshape(-1, 4)


def kitti_record(source: KittiSource, frame: Scan, shift_z_m: float, crop_fov: str | None) -> dict[str, Any]:
    """The learn record of one scan (see the module doc): points moved up ``shift_z_m`` and cropped to the
    field of view ``crop_fov`` (None: all), reflectance scaled; the labels of the source's types as the
    record's objects (track ids 0..M-1 in label order, the points in each box as the ego's hits)."""
    pts = frame.points
    if crop_fov is not None:
        pts = pts[in_view(pts[:, :3], frame, crop_fov)]
    xyz = pts[:, :3].astype(np.float64)
    xyz[:, 2] += shift_z_m
    q, keep = quantise(xyz)
    intensity = np.round(np.clip(pts[keep, 3].astype(np.float64) * source.intensity_scale, 0.0, 1.0) * 255.0
                         ).astype(np.uint8)
    sel = [i for i, t in enumerate(frame.types) if t in source.types]
    boxes = frame.boxes[sel].copy()
    boxes[:, 2] += shift_z_m
    counts = box_point_counts(q.astype(np.float64) * 0.01, boxes)
    tracks = np.arange(len(sel), dtype=np.int64)
    return {"tick": frame.tick, "t_ns": 0, "agents": [EGO], "map_from": np.eye(4)[None],
            "label_track_ids": tracks, "label_classes": [KITTI_CLASSES[frame.types[i]] for i in sel],
            "label_centers": boxes[:, :3].reshape(-1, 3), "label_rotations": _quat_z(boxes[:, 6]),
            "label_sizes": boxes[:, 3:6].reshape(-1, 3), "agent_tracks": {}, "links": None,
            "points": [q], "intensity": [intensity], "hits": [np.stack([tracks, counts]).astype(np.int64)]}


def height_shift_m(source: KittiSource, model_height_m: float | None) -> float:
    """How far a source's points move up for a model trained at ``model_height_m`` (0 when it is unknown)."""
    return 0.0 if model_height_m is None else source.height_m - float(model_height_m)


class KittiRecords:
    """The records of KITTI sources for :class:`cosim.learn.data.Samples`: ``keys`` (folder id, scan number, ego)."""

    def __init__(self, sources: Sequence[KittiSource], model_height_m: float | None, crop_fov: str | None):
        ids = [s.id for s in sources]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise InputError(f"KITTI folders with the same id {dupes[0]}: give each folder once")
        self.sources = {s.id: s for s in sources}
        self.model_height_m = model_height_m
        self.crop_fov = crop_fov
        self.keys = []
        self._stem: dict[tuple[str, int], str] = {}
        for s in sources:
            for stem in s.stems:
                t = int(stem) if stem.isdigit() else None
                if t is None:
                    raise InputError(f"{s.folder}: scan {stem}.bin is not named by its number (000076.bin)")
                self._stem[(s.id, t)] = stem
                self.keys.append((s.id, t, EGO))

    def frame(self, episode: str, tick: int) -> Scan:
        return self.sources[episode].frame(self._stem[(episode, tick)])

    def record(self, episode: str, tick: int) -> dict[str, Any]:
        s = self.sources[episode]
        return kitti_record(s, self.frame(episode, tick), height_shift_m(s, self.model_height_m), self.crop_fov)

    def close(self) -> None:
        pass


def kitti_samples(sources: Sequence[KittiSource], setup: Any, crop_fov: str | None = "camera") -> Any:
    """:class:`cosim.learn.data.Samples` over KITTI sources for ``setup`` (fusion none): records from
    :class:`KittiRecords`, shifted to the setup's LiDAR height; ``refs`` are the sources."""
    from cosim.learn.data import Samples

    if setup.fusion != "none":
        raise InputError(f"a KITTI folder has one agent: its samples are for fusion none, not {setup.fusion}")
    missing = sorted({KITTI_CLASSES[t] for s in sources for t in s.types} - set(setup.classes))
    if missing:
        raise InputError(f"the model detects {', '.join(setup.classes)}: it has no class {', '.join(missing)} for "
                         "the KITTI types asked")
    samples = Samples.__new__(Samples)
    samples.refs = list(sources)
    samples.setup = setup
    samples.src = KittiRecords(sources, setup.lidar_height_m, crop_fov)
    samples._records = {}
    samples.lidars = {}  # one agent of one LiDAR: no per-sensor encoders
    return samples


# ---------------------------------------------------------------------------------------- scoring


@dataclass(frozen=True)
class ScoreOptions:
    """How predictions are scored on a KITTI folder: the field of view, AP and false positives within
    ``max_range_m`` (horizontal, of the box centre), labels with at least ``min_points`` points (the others
    ignored), recall and false positives at score >= ``min_score`` matched at BEV IoU >= ``iou``, recall by
    range band ``bands_m``, AP at ``thresholds`` (cosim eval's definition, :mod:`cosim.eval.ap`)."""

    fov: str = "camera"
    max_range_m: float = 40.0
    min_points: int = 5
    min_score: float = 0.3
    iou: float = 0.3
    bands_m: tuple[tuple[float, float], ...] = BANDS_M
    thresholds: tuple[float, ...] = THRESHOLDS
    ignore: bool = True  # leave out detections on DontCare, other types and labels under min_points (not for "all")
    #: which detections are scored (when they carry class names; not for ``fov="all"``, where every vehicle class
    #: counts as cosim eval counts them): "types" those of the classes the KITTI types map to (KITTI scores each
    #: class on its own detections: a bicycle detection is no false car), "all" every vehicle class's
    det_classes: str = "types"

    def __post_init__(self) -> None:
        if self.fov not in FOVS:
            raise InputError(f"--fov {self.fov}: choose one of {', '.join(FOVS)}")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0):
            raise InputError(f"--max-range-m {self.max_range_m}: must be a number above 0")
        if self.min_points < 0:
            raise InputError(f"--min-points {self.min_points}: must be >= 0")
        if not (math.isfinite(self.min_score) and 0.0 <= self.min_score <= 1.0):
            raise InputError(f"--min-score {self.min_score}: must be 0 to 1")
        if not (math.isfinite(self.iou) and 0.0 < self.iou <= 1.0):
            raise InputError(f"--iou {self.iou}: must be above 0 and at most 1")
        if self.det_classes not in DET_CLASSES:
            raise InputError(f"--det-classes {self.det_classes}: choose one of {', '.join(DET_CLASSES)}")


DET_CLASSES = ("types", "all")  # :attr:`ScoreOptions.det_classes`

#: The operating point of the report beside its fixed score: the recall within ``max_range_m`` (AP's matching at
#: the scoring IoU) at the lowest score cut that leaves at most this many false positives per frame, and that cut.
OPERATING_FP_PER_FRAME = 1.0
OPERATING_RECALL = "recall at 1 false positive per frame"
OPERATING_SCORE = "score at 1 false positive per frame"


@dataclass
class FrameScore:
    """What :func:`score_frame` finds in one scan (boxes in the velodyne frame, for pictures too)."""

    gt: np.ndarray  # (M, 7) scored labels within the bands' reach
    gt_range_m: np.ndarray  # (M,)
    found: np.ndarray  # (M,) bool: matched by a detection of score >= min_score
    det: np.ndarray  # (N, 7) detections in view and range, not ignored
    det_scores: np.ndarray  # (N,)
    det_tp: np.ndarray  # (N,) bool: matched (score >= min_score and IoU >= iou)
    ignored_gt: np.ndarray  # (K, 7) labels neither scored nor false positives
    points: int = 0


@dataclass
class KittiScore:
    """Scores of one KITTI folder over its scans."""

    options: ScoreOptions
    acc: DetectionAccumulator = field(default_factory=DetectionAccumulator)
    frames: int = 0
    band_gt: list[int] = field(default_factory=list)
    band_found: list[int] = field(default_factory=list)
    false_pos: int = 0
    cars: int = 0  # scored labels within max_range_m

    def summary(self) -> dict[str, Any]:
        o = self.options
        out: dict[str, Any] = {"frames": self.frames, "cars": self.cars}
        for thr in o.thresholds:
            r = self.acc.result(thr)
            out[f"AP{round(thr * 100)}"] = round(100.0 * r.ap, 2) if r.ap == r.ap else float("nan")
        found = gt = 0
        for (lo, hi), n, k in zip(o.bands_m, self.band_gt, self.band_found, strict=True):
            out[f"cars {lo:g}-{hi:g} m"] = n
            out[f"recall {lo:g}-{hi:g} m"] = round(k / n, 3) if n else float("nan")
            if hi <= o.max_range_m + 1e-9:
                found, gt = found + k, gt + n
        out[f"recall 0-{o.max_range_m:g} m"] = round(found / gt, 3) if gt else float("nan")
        out["false positives"] = self.false_pos
        out["false positives per frame"] = round(self.false_pos / self.frames, 3) if self.frames else float("nan")
        iou = o.iou if o.iou in o.thresholds else o.thresholds[0]
        recall, cut = self.acc.operating_point(iou, OPERATING_FP_PER_FRAME * self.frames)
        out[OPERATING_RECALL] = round(recall, 3) if recall == recall else float("nan")
        out[OPERATING_SCORE] = round(cut, 3) if math.isfinite(cut) else float("nan")
        return out


def score_frame(frame: Scan, types: Sequence[str], det_boxes: np.ndarray, det_scores: np.ndarray,
                o: ScoreOptions, acc: DetectionAccumulator | None = None, det_classes: Sequence[str] | None = None
                ) -> FrameScore:
    """Score one scan's detections (N, 7) with scores (N,) in the velodyne frame, and their class names (N,)
    when known (see the module doc and :class:`ScoreOptions`); AP's true and false positives go to ``acc``."""
    reach = max([o.max_range_m] + [hi for _lo, hi in o.bands_m])
    xyz = frame.points[:, :3]
    boxes = frame.boxes
    counts = box_point_counts(xyz, boxes) if len(boxes) else np.zeros(0, np.int64)
    rng = np.hypot(boxes[:, 0], boxes[:, 1]) if len(boxes) else np.zeros(0)
    view = in_view(boxes[:, :3], frame, o.fov) if len(boxes) else np.zeros(0, bool)
    target = np.array([t in types for t in frame.types], bool).reshape(-1)
    scored = target & (counts >= o.min_points) & view & (rng <= reach)
    ignored = ~scored & (view | ~target)  # others in view, and every non-target (a pedestrian anywhere)
    det_boxes = np.asarray(det_boxes, np.float64).reshape(-1, 7)
    det_scores = np.asarray(det_scores, np.float64).reshape(-1)
    d_rng = np.hypot(det_boxes[:, 0], det_boxes[:, 1])
    keep = in_view(det_boxes[:, :3], frame, o.fov) & (d_rng <= reach)
    if det_classes is not None and o.det_classes == "types" and o.fov != "all":
        keep &= np.isin(np.asarray(det_classes, dtype=object).reshape(-1), [KITTI_CLASSES[t] for t in types])
    det_boxes, det_scores, d_rng = det_boxes[keep], det_scores[keep], d_rng[keep]
    det_fp = footprints(det_boxes[:, :2], det_boxes[:, 3:5], det_boxes[:, 6])
    gt_fp = footprints(boxes[scored, :2], boxes[scored, 3:5], boxes[scored, 6])
    if o.ignore and o.fov != "all" and len(det_boxes):
        iou_gt = iou_matrix(det_fp, gt_fp).max(axis=1) if scored.any() else np.zeros(len(det_boxes))
        ig_fp = footprints(boxes[ignored, :2], boxes[ignored, 3:5], boxes[ignored, 6])
        iou_ig = iou_matrix(det_fp, ig_fp).max(axis=1) if ignored.any() else np.zeros(len(det_boxes))
        drop = (iou_ig > 0) & (iou_ig > iou_gt)
        drop |= in_dontcare(det_boxes, frame) & (iou_gt < o.iou)
        det_boxes, det_scores, d_rng, det_fp = det_boxes[~drop], det_scores[~drop], d_rng[~drop], det_fp[~drop]
    gt = boxes[scored]
    g_rng = rng[scored]
    if acc is not None:
        a_det, a_gt = d_rng <= o.max_range_m, g_rng <= o.max_range_m
        acc.add(det_fp[a_det], det_scores[a_det], gt_fp[a_gt])
    from cosim.learn.recall import _matches

    strong = det_scores >= o.min_score
    match = _matches(det_fp[strong], det_scores[strong], gt_fp, o.iou)
    det_tp = np.zeros(len(det_boxes), bool)
    det_tp[np.flatnonzero(strong)[match[match >= 0]]] = True
    return FrameScore(gt, g_rng, match >= 0, det_boxes, det_scores, det_tp,
                      boxes[ignored & (rng <= reach)], len(xyz))


def score_source(source: KittiSource, predictions: dict[int, tuple[np.ndarray, np.ndarray]], o: ScoreOptions,
                 frames: Iterable[str] | None = None, keep: list | None = None) -> KittiScore:
    """Score detections ``predictions`` (scan number -> boxes (N, 7), scores (N,), velodyne frame, and
    optionally class names (N,): :func:`with_class_names`) on a source's scans (``frames``: stems, default all;
    every one needs its predictions). ``keep``: a list that gets (stem, :class:`FrameScore`) of each scan (for
    pictures)."""
    out = KittiScore(o, DetectionAccumulator(o.thresholds), band_gt=[0] * len(o.bands_m),
                     band_found=[0] * len(o.bands_m))
    for stem in frames or source.stems:
        frame = source.frame(stem)
        if frame.tick not in predictions:
            raise InputError(f"no predictions for scan {stem} of {source.id}")
        boxes, scores, *named = predictions[frame.tick]
        fs = score_frame(frame, source.types, boxes, scores, o, out.acc, named[0] if named else None)
        out.frames += 1
        out.cars += int((fs.gt_range_m <= o.max_range_m).sum())
        for k, (lo, hi) in enumerate(o.bands_m):
            band = (fs.gt_range_m >= lo) & (fs.gt_range_m < hi)
            out.band_gt[k] += int(band.sum())
            out.band_found[k] += int((band & fs.found).sum())
        d_rng = np.hypot(fs.det[:, 0], fs.det[:, 1])
        out.false_pos += int(((fs.det_scores >= o.min_score) & ~fs.det_tp & (d_rng <= o.max_range_m)).sum())
        if keep is not None:
            keep.append((stem, fs))
    return out


def predictions_from_file(path: Path, source: KittiSource) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The vehicle detections of a prediction file (docs/evaluation.md) for one KITTI folder (its records of
    episode ``source.id``): scan number -> boxes (N, 7), scores (N,) in the velodyne frame, class names (N,)."""
    from cosim.eval.predictions import read_predictions
    from cosim.learn.samples import VEHICLE_CLASSES

    out = {}
    for r in read_predictions(Path(path)):
        if r.episode != source.id:
            continue
        veh = np.isin(np.asarray(r.classes, dtype=object), VEHICLE_CLASSES) if len(r.classes) else \
            np.zeros(0, bool)
        boxes = np.column_stack([r.centers_m, r.sizes_m, r.yaws_rad]).reshape(-1, 7)[veh]
        out[r.tick] = (boxes, r.scores[veh], np.asarray(r.classes, dtype=object).reshape(-1)[veh])
    if not out:
        raise InputError(f"{path}: no prediction records of the KITTI folder {source.id!r}")
    return out


SCORE_COLUMNS = ("frames", "cars", "recall 0-20 m", "recall 20-40 m", "recall 40-60 m", "false positives per frame",
                 "AP30", "AP50", "AP70", OPERATING_RECALL, OPERATING_SCORE)


def write_score(rows: list[dict[str, Any]], out: Path, o: ScoreOptions, title: str) -> tuple[Path, Path]:
    """``score.md`` and ``score.json`` of rows (one per folder, :meth:`KittiScore.summary` plus ``folder``)."""
    out.mkdir(parents=True, exist_ok=True)
    cols = tuple(c for c in ("predictions", "folder", *SCORE_COLUMNS) if any(c in r for r in rows))
    lines = [title, "", "| " + " | ".join(cols) + " |", "|---" + "|---:" * (len(cols) - 1) + "|"]
    lines += ["| " + " | ".join(_cell(r.get(c)) for c in cols) + " |" for r in rows]
    md = out / "score.md"
    md.write_text("\n".join(lines) + "\n")
    js = out / "score.json"
    js.write_text(json.dumps(finite({"options": options_dict(o), "rows": rows}), indent=1) + "\n")
    return md, js


def options_dict(o: ScoreOptions) -> dict[str, Any]:
    return {"fov": o.fov, "max_range_m": o.max_range_m, "min_points": o.min_points, "min_score": o.min_score,
            "iou": o.iou, "bands_m": [list(b) for b in o.bands_m], "ignore": o.ignore, "det_classes": o.det_classes}


def score_title(o: ScoreOptions) -> str:
    view = {"camera": "in the front camera's view", "front90": "in the front 90 deg", "all": "all around"}[o.fov]
    which = "every vehicle class's detections" if o.fov == "all" or o.det_classes == "all" else \
        "the detections of the target types' classes"
    return (f"Vehicles {view} with >= {o.min_points} points, {which}: recall at score >= {o.min_score:g} (BEV IoU >= "
            f"{o.iou:g}) by range, false positives per frame and BEV AP within {o.max_range_m:g} m "
            f"(cosim eval's AP); the recall within {o.max_range_m:g} m at the lowest score cut with at most "
            f"{OPERATING_FP_PER_FRAME:g} false positive per frame, and that cut")


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return "-" if v != v else f"{v:g}"
    return "-" if v is None else str(v)


# ----------------------------------------------------------------------------- with a model (torch, lazily)


def predict_source(model: Any, setup: Any, source: KittiSource, device: Any, progress: Any = None
                   ) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A model's detections on every scan of ``source``: scan number -> boxes (N, 7) in the source's velodyne
    frame (moved back from the model's height), scores (N,), class indices (N,). The whole scan goes in (the
    field of view is scoring's business)."""
    from cosim.learn.train import predict_sample

    samples = kitti_samples([source], setup, crop_fov=None)
    shift = height_shift_m(source, setup.lidar_height_m)
    out = {}
    was_training = model.training
    model.eval()
    for i in range(len(samples)):
        item = samples.item(i)
        boxes, scores, cls = predict_sample(model, item, setup, device)
        boxes = boxes.copy()
        boxes[:, 2] -= shift
        out[item["tick"]] = (boxes, scores, cls)
        if progress:
            progress(i + 1, len(samples))
    model.train(was_training)
    return out


def prediction_lines(source: KittiSource, setup: Any, preds: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
                     ) -> list[str]:
    """One prediction record (docs/evaluation.md) per scan: episode the folder's id, tick the scan's number,
    ego ``ego``, agents ``ego``, boxes in the velodyne frame."""
    from cosim.eval.predictions import record_json

    return [record_json(source.id, t, EGO, "ego", b[:, :3], b[:, 3:6], b[:, 6], [setup.classes[k] for k in c], s)
            for t, (b, s, c) in sorted(preds.items())]


def score_model(model: Any, setup: Any, sources: Sequence[KittiSource], device: Any, o: ScoreOptions
                ) -> list[KittiScore]:
    """Each source's :class:`KittiScore` of a model's detections."""
    return [score_source(s, with_class_names(predict_source(model, setup, s, device), setup.classes), o)
            for s in sources]


def with_class_names(preds: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]], classes: Sequence[str]
                     ) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`predict_source`'s detections with class names (the model's ``classes``) for their indices."""
    names = np.asarray(classes, dtype=object)
    return {t: (b, s, names[np.asarray(c, np.int64)]) for t, (b, s, c) in preds.items()}


def ap_of(scores: Sequence[KittiScore]) -> dict[str, float]:
    """AP30, AP50, AP70 (%) of several sources' scores together (their detections ranked as one list)."""
    acc = DetectionAccumulator(scores[0].options.thresholds)
    for s in scores:
        acc.merge(s.acc)
    out = {}
    for thr in (0.3, 0.5, 0.7):
        r = acc.result(thr)
        out[f"AP{round(thr * 100)}"] = round(100.0 * r.ap, 2) if r.ap == r.ap else float("nan")
    return out


def val_fn(sources: Sequence[KittiSource], setup: Any, device: Any, o: ScoreOptions) -> Any:
    """A validation function for :func:`cosim.learn.train.fit`: model -> AP30/AP50/AP70 on the sources."""
    return lambda model: ap_of(score_model(model, setup, sources, device, o))


def run_training(samples: Any, validate: Any, setup: Any, opts: Any, run: Path, resume: bool, device: Any,
                 show_progress: bool, init: Path | None, about: dict[str, Any]) -> dict[str, Any]:
    """:func:`cosim.learn.train.fit` on ready samples (a KITTI folder's, or cosim's validated on KITTI),
    ``init`` the run whose weights it starts from; ``about`` goes into summary.json."""
    from cosim.learn.train import CHECKPOINT, fit

    run = Path(run)
    if (run / CHECKPOINT).exists() and not resume:
        raise InputError(f"{run} already holds a training run: --resume continues it, or choose another --out")
    if resume and not (run / CHECKPOINT).exists():
        raise InputError(f"{run}: nothing to resume (no {CHECKPOINT})")
    try:
        summary = fit(samples, validate, setup, opts, run, resume=resume, device=device, show_progress=show_progress,
                      init=init)
    finally:
        samples.close()
    summary.update(about)
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def validate_checkpoints(run: Path, sources: Sequence[KittiSource], o: ScoreOptions, threads: int | None = None,
                         from_step: int = 0):
    """Score every ``checkpoint_<step>.pt`` of a run (and its last checkpoint) at steps >= ``from_step`` on
    KITTI sources, as :func:`cosim.learn.train.validate_checkpoints` does on episodes: each result appended
    to the run's ``log.jsonl`` as ``{"step", "val", "split": "kitti:<ids>", "every": 1}``, steps scored
    before skipped. Yields (step, AP dict)."""
    from cosim.learn.train import _append_log, unscored_checkpoints

    run = Path(run)
    split = "kitti:" + ",".join(s.id for s in sources)
    for model, setup, step, device in unscored_checkpoints(run, threads, lambda r: r.get("split") == split,
                                                           from_step):
        ap = ap_of(score_model(model, setup, sources, device, o))
        _append_log(run / "log.jsonl", {"step": step, "val": ap, "split": split, "every": 1})
        yield step, ap


def vehicle_lidar_heights_m(resolved: dict[str, Any]) -> list[float]:
    """The LiDAR mount heights above the road [m] of a resolved scenario's connected vehicles, each from its
    own rig (``agents.vehicles.rigs``) or the kind's (``sensors.vehicle``); camera-only vehicles give none."""
    from cosim.scenario.model import rig_data_of

    count = int(((resolved.get("agents") or {}).get("vehicles") or {}).get("count") or 0)
    heights = []
    for i in range(count):
        lidar = rig_data_of(resolved, f"vehicle_{i}").get("lidar")
        try:
            heights.append(float(lidar["mount"]["xyz_m"][2]))
        except (KeyError, TypeError, IndexError):
            continue
    return heights


def episodes_lidar_height_m(refs: Sequence[Any]) -> float | None:
    """The vehicles' LiDAR mount height above the road [m] of cosim episodes (each vehicle's rig's
    ``lidar.mount.xyz_m`` z in the resolved scenario; the vehicle's base_link is on the road): the median over
    the episodes' vehicles, None when none has a LiDAR."""
    import yaml

    from cosim.io import open_episode

    heights = []
    for r in refs:
        with open_episode(r.path) as ep:
            heights += vehicle_lidar_heights_m(yaml.safe_load(ep.attachment("scenario.yaml")) or {})
    return round(float(np.median(heights)), 3) if heights else None


def finite(v: Any) -> Any:
    """``v`` (dicts, lists, numbers) with NaN and infinities as None, for strict JSON."""
    if isinstance(v, dict):
        return {k: finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [finite(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v
