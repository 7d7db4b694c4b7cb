"""The KITTI object layout (docs/exports.md, "KITTI"): calib, label and velodyne files, both ways, in numpy.

Frames, as KITTI defines them:

- **velodyne** (LiDAR): x forward, y left, z up, metres.
- **rectified camera** (``rect``): x right, y down, z forward (the optical frame of camera 0 after stereo
  rectification). ``R0_rect`` maps the unrectified camera-0 frame into it, ``Tr_velo_to_cam`` the velodyne
  frame into the unrectified one, so ``rect <- velo`` is ``R0_rect @ Tr_velo_to_cam``
  (:attr:`KittiCalib.cam_from_velo`). ``P0``..``P3`` project rectified points to pixels of camera 0..3.

A label line holds 15 columns (16 with a detector's score): type, truncated (0..1), occluded (0 visible,
1 partly, 2 largely, 3 unknown), alpha [rad], 2D box (left, top, right, bottom) [px] in image 2, h w l [m],
location (x, y, z) [m] of the box's **bottom** centre in the rectified frame, rotation_y [rad] about the
rectified y axis. ``DontCare`` lines mark regions with unlabelled objects: their 3D columns are -1 / -1000 / -10.

Box conversion follows KITTI's own (its raw-data devkit turns velodyne tracklets into labels this way):
the bottom centre is the velodyne centre lowered by h/2 along velodyne z and then transformed to ``rect``;
``rotation_y = -yaw - pi/2``, where yaw is about velodyne z from velodyne x. It is exact both ways for any
calib; rotation_y reads as an angle in the camera frame when the camera looks along velodyne x, as KITTI's
and cosim's front cameras do.

Nothing here imports cosim beyond :mod:`cosim.errors`: the module sits in ``cosim.io`` (layer 5) so that the
exporters and ``cosim learn`` share it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.errors import InputError

#: The calib keys in file order, and the shape of each.
CALIB_KEYS: tuple[tuple[str, tuple[int, int]], ...] = (
    ("P0", (3, 4)), ("P1", (3, 4)), ("P2", (3, 4)), ("P3", (3, 4)),
    ("R0_rect", (3, 3)), ("Tr_velo_to_cam", (3, 4)), ("Tr_imu_to_velo", (3, 4)),
)
#: Other spellings some KITTI-derived files use (the tracking benchmark, raw-data calib files).
_CALIB_ALIASES = {"R_rect": "R0_rect", "Tr_velo_cam": "Tr_velo_to_cam", "Tr_imu_velo": "Tr_imu_to_velo"}
#: The types KITTI's object benchmark labels, DontCare last.
KITTI_TYPES = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc", "DontCare")
#: The ImageSets split files a KITTI folder may hold.
SPLITS = ("train", "val", "test")


def _homogeneous(m: np.ndarray) -> np.ndarray:
    """(3, 3) or (3, 4) -> (4, 4) with the last row (0, 0, 0, 1)."""
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


def rigid_inverse(t: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform (or of any invertible affine one, via numpy)."""
    r = t[:3, :3]
    if np.allclose(r @ r.T, np.eye(3), atol=1e-9):
        out = np.eye(4)
        out[:3, :3] = r.T
        out[:3, 3] = -r.T @ t[:3, 3]
        return out
    return np.linalg.inv(t)


@dataclass(frozen=True)
class KittiCalib:
    """One frame's calib file. Projections ``P0``..``P3`` (3, 4) map rectified-camera points (homogeneous)
    to pixels of cameras 0..3 (P2 is the left colour camera, the one labels' 2D boxes refer to);
    ``R0_rect`` (3, 3) unrectified camera 0 -> rectified; ``Tr_velo_to_cam`` (3, 4) velodyne -> unrectified
    camera 0; ``Tr_imu_to_velo`` (3, 4) IMU (the vehicle's body) -> velodyne. All float64, metres."""

    P0: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    P3: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray
    Tr_imu_to_velo: np.ndarray

    def __post_init__(self):
        for key, shape in CALIB_KEYS:
            value = np.array(getattr(self, key), dtype=np.float64)
            if value.shape != shape:
                raise InputError(f"KITTI calib {key}: shape {value.shape}, expected {shape}")
            if not np.all(np.isfinite(value)):
                raise InputError(f"KITTI calib {key}: not finite")
            value.setflags(write=False)
            object.__setattr__(self, key, value)

    @property
    def cam_from_velo(self) -> np.ndarray:
        """(4, 4) rectified camera <- velodyne: ``R0_rect @ Tr_velo_to_cam``."""
        return _homogeneous(self.R0_rect) @ _homogeneous(self.Tr_velo_to_cam)

    @property
    def velo_from_cam(self) -> np.ndarray:
        """(4, 4) velodyne <- rectified camera, the inverse of :attr:`cam_from_velo`."""
        return rigid_inverse(self.cam_from_velo)

    @property
    def velo_from_imu(self) -> np.ndarray:
        """(4, 4) velodyne <- IMU."""
        return _homogeneous(self.Tr_imu_to_velo)

    def velo_to_rect(self, xyz_m: np.ndarray) -> np.ndarray:
        """(N, 3) velodyne points -> (N, 3) rectified-camera points [m]."""
        return _apply(self.cam_from_velo, xyz_m)

    def rect_to_velo(self, xyz_m: np.ndarray) -> np.ndarray:
        """(N, 3) rectified-camera points -> (N, 3) velodyne points [m]."""
        return _apply(self.velo_from_cam, xyz_m)

    def rect_to_image(self, xyz_m: np.ndarray, camera: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) rectified points -> ((N, 2) pixels (u right, v down) in camera ``camera``, (N,) depth [m],
        the third homogeneous coordinate; a point is in front of the camera where it is > 0)."""
        p = getattr(self, f"P{camera}")
        xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
        uvw = np.c_[xyz, np.ones(len(xyz))] @ p.T
        depth = uvw[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[:, :2] / depth[:, None]
        return uv, depth


def _apply(t: np.ndarray, xyz_m: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    return xyz @ t[:3, :3].T + t[:3, 3]


def read_calib(path: str | Path) -> KittiCalib:
    """Read a KITTI object calib file (``KEY: v v v ...`` lines). ``P0``, ``P1``, ``P3`` default to ``P2``
    and ``Tr_imu_to_velo`` to the identity where a file leaves them out; ``P2``, ``R0_rect`` and
    ``Tr_velo_to_cam`` are required. Raises InputError naming the file and key on anything else."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read KITTI calib ({exc})") from None
    values: dict[str, np.ndarray] = {}
    shapes = dict(CALIB_KEYS)
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        key = _CALIB_ALIASES.get(key.strip(), key.strip())
        if not sep:
            raise InputError(f"{path}:{n}: not a 'KEY: values' line")
        if key not in shapes:
            continue
        try:
            numbers = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise InputError(f"{path}:{n}: {key} holds a value that is not a number") from None
        if numbers.size != math.prod(shapes[key]):
            raise InputError(f"{path}:{n}: {key} has {numbers.size} values, expected {math.prod(shapes[key])}")
        values[key] = numbers.reshape(shapes[key])
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        if key not in values:
            raise InputError(f"{path}: KITTI calib lacks {key}")
    for key in ("P0", "P1", "P3"):
        values.setdefault(key, values["P2"])
    values.setdefault("Tr_imu_to_velo", np.eye(3, 4))
    try:
        return KittiCalib(**values)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def format_calib(calib: KittiCalib) -> str:
    """The calib file's text: the seven keys in KITTI's order, each value as ``%.12e`` (KITTI's own)."""
    lines = []
    for key, _ in CALIB_KEYS:
        lines.append(f"{key}: " + " ".join(f"{v:.12e}" for v in getattr(calib, key).ravel()))
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class KittiObject:
    """One label line. ``type`` one of :data:`KITTI_TYPES` (others are read as given); ``truncated`` 0..1
    (-1 for DontCare); ``occluded`` 0..3 (-1 for DontCare); ``alpha`` [rad] observation angle; ``bbox``
    (4,) left, top, right, bottom [px] in image 2; ``h``, ``w``, ``l`` [m]; ``location`` (3,) bottom centre
    in the rectified camera frame [m]; ``rotation_y`` [rad] about rectified y; ``score`` a detector's
    confidence or None for ground truth."""

    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox: np.ndarray
    h: float
    w: float
    l: float  # noqa: E741 (KITTI's name)
    location: np.ndarray
    rotation_y: float
    score: float | None = field(default=None)

    def __post_init__(self):
        for key, size in (("bbox", 4), ("location", 3)):
            value = np.array(getattr(self, key), dtype=np.float64).reshape(-1)
            if value.size != size:
                raise InputError(f"KITTI object {key}: {value.size} values, expected {size}")
            value.setflags(write=False)
            object.__setattr__(self, key, value)
        for key in ("truncated", "alpha", "h", "w", "l", "rotation_y"):
            object.__setattr__(self, key, float(getattr(self, key)))
        object.__setattr__(self, "occluded", int(self.occluded))
        if self.score is not None:
            object.__setattr__(self, "score", float(self.score))

    @property
    def dont_care(self) -> bool:
        """True for a DontCare region (no 3D box)."""
        return self.type == "DontCare"


def read_labels(path: str | Path) -> list[KittiObject]:
    """Every line of a label_2 file (DontCare included) in file order; 15 columns, or 16 with a score.
    Raises InputError naming the file and line on a malformed one."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read KITTI labels ({exc})") from None
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        cols = line.split()
        if not cols:
            continue
        if len(cols) not in (15, 16):
            raise InputError(f"{path}:{n}: {len(cols)} columns, a KITTI label has 15 (16 with a score)")
        try:
            v = [float(c) for c in cols[1:]]
        except ValueError:
            raise InputError(f"{path}:{n}: a column after the type is not a number") from None
        if not all(math.isfinite(x) for x in v):
            raise InputError(f"{path}:{n}: a column is not finite")
        out.append(KittiObject(type=cols[0], truncated=v[0], occluded=int(v[1]), alpha=v[2], bbox=v[3:7],
                               h=v[7], w=v[8], l=v[9], location=v[10:13], rotation_y=v[13],
                               score=v[14] if len(v) == 15 else None))
    return out


def format_label(obj: KittiObject, decimals: int = 2) -> str:
    """One label line (no newline): 15 columns, 16 with a score. ``decimals`` 2 is KITTI's own precision
    (occluded as an integer); cosim's export writes more so that boxes read back to well under 1 mm."""
    d = decimals
    nums = [obj.truncated, None, obj.alpha, *obj.bbox, obj.h, obj.w, obj.l, *obj.location, obj.rotation_y]
    cols = [obj.type] + [str(int(obj.occluded)) if v is None else _fixed(v, d) for v in nums]
    if obj.score is not None:
        cols.append(_fixed(obj.score, max(d, 4)))
    return " ".join(cols)


def _fixed(v: float, decimals: int) -> str:
    """``v`` with ``decimals`` decimals, never as ``-0.00``."""
    text = f"{v:.{decimals}f}"
    return text[1:] if text.startswith("-") and not text.strip("-0.") else text


def dont_care(bbox: Sequence[float]) -> KittiObject:
    """A DontCare region over ``bbox`` (left, top, right, bottom) [px], with KITTI's filler values."""
    return KittiObject(type="DontCare", truncated=-1.0, occluded=-1, alpha=-10.0, bbox=bbox, h=-1.0, w=-1.0,
                       l=-1.0, location=(-1000.0, -1000.0, -1000.0), rotation_y=-10.0)


def wrap_rad(a: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + math.pi) % (2.0 * math.pi) - math.pi


def boxes_to_velo(objects: Sequence[KittiObject], calib: KittiCalib) -> np.ndarray:
    """(M, 7) boxes in the velodyne frame: centre x, y, z [m], l, w, h [m] (l along the heading), yaw [rad]
    about velodyne z from velodyne x, wrapped to [-pi, pi). ``objects`` should hold no DontCare (filter with
    :attr:`KittiObject.dont_care`): their filler values give meaningless rows."""
    if not objects:
        return np.zeros((0, 7))
    loc = np.array([o.location for o in objects], dtype=np.float64)
    lwh = np.array([(o.l, o.w, o.h) for o in objects], dtype=np.float64)
    ry = np.array([o.rotation_y for o in objects], dtype=np.float64)
    centre = calib.rect_to_velo(loc)
    centre[:, 2] += lwh[:, 2] / 2.0
    return np.c_[centre, lwh, wrap_rad(-ry - math.pi / 2.0)]


def boxes_from_velo(boxes: np.ndarray, calib: KittiCalib) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`boxes_to_velo`: (M, 7) velodyne boxes -> ((M, 3) bottom-centre locations in the
    rectified camera frame [m], (M,) rotation_y [rad] wrapped to [-pi, pi))."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    bottom = b[:, :3].copy()
    bottom[:, 2] -= b[:, 5] / 2.0
    return calib.velo_to_rect(bottom), wrap_rad(-b[:, 6] - math.pi / 2.0)


def box_corners_velo(boxes: np.ndarray) -> np.ndarray:
    """(M, 7) velodyne boxes -> (M, 8, 3) corners [m]: bottom four then top four, each counter-clockwise
    from front-left seen from above."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    sx = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * 0.5
    sy = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * 0.5
    sz = np.array([-1, -1, -1, -1, 1, 1, 1, 1]) * 0.5
    local = np.stack([b[:, 3:4] * sx, b[:, 4:5] * sy, b[:, 5:6] * sz], axis=-1)
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    x = c * local[..., 0] - s * local[..., 1]
    y = s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y, local[..., 2]], axis=-1) + b[:, None, :3]


def points_in_boxes(xyz_m: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """(N, M) bool: point n lies inside box m (velodyne boxes as :func:`boxes_to_velo` gives, each grown by
    ``margin_m`` on every side)."""
    p = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    d = p[:, None, :] - b[None, :, :3]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    lx = c * d[..., 0] + s * d[..., 1]
    ly = -s * d[..., 0] + c * d[..., 1]
    return ((np.abs(lx) <= b[:, 3] / 2 + margin_m) & (np.abs(ly) <= b[:, 4] / 2 + margin_m)
            & (np.abs(d[..., 2]) <= b[:, 5] / 2 + margin_m))


def read_velodyne(path: str | Path) -> np.ndarray:
    """(N, 4) float32 x, y, z [m] in the velodyne frame and reflectance (KITTI: 0..1) of a ``.bin`` file."""
    path = Path(path)
    try:
        raw = np.fromfile(path, dtype="<f4")
    except OSError as exc:
        raise InputError(f"{path}: cannot read KITTI velodyne scan ({exc})") from None
    if raw.size % 4:
        raise InputError(f"{path}: {raw.size * 4} bytes is not a whole number of 16-byte points")
    return raw.reshape(-1, 4).astype(np.float32, copy=False)


def write_velodyne(path: str | Path, points: np.ndarray) -> None:
    """Write (N, 4) x, y, z [m], reflectance as little-endian float32 (KITTI's ``.bin``)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 4:
        raise ValueError(f"velodyne points must be (N, 4), got {pts.shape}")
    Path(path).write_bytes(np.ascontiguousarray(pts, dtype="<f4").tobytes())


@dataclass(frozen=True)
class KittiFrame:
    """One frame of a KITTI folder: ``points`` (N, 4) float32 velodyne x y z reflectance; ``objects`` its
    label lines (DontCare included), or None where the frame has no label file (test frames); ``calib``;
    ``image_path`` image_2's PNG where there is one."""

    stem: str
    points: np.ndarray
    objects: list[KittiObject] | None
    calib: KittiCalib
    image_path: Path | None


class KittiFolder:
    """A KITTI object folder: ``root`` holds ``training/`` (preferred) or ``testing/``, or is itself a
    folder holding ``velodyne/`` (with ``calib/``, and ``label_2/`` and ``image_2/`` where present).
    :attr:`stems` lists the frames (the velodyne files' stems, sorted); :attr:`splits` maps each of
    ``train``/``val``/``test`` to the stems ``ImageSets/<split>.txt`` lists (beside ``training/`` or in
    ``root``), for the files that exist."""

    def __init__(self, root: str | Path):
        root = Path(root)
        if not root.is_dir():
            raise InputError(f"{root}: not a folder (a KITTI folder holds training/ or velodyne/)")
        for cand in (root / "training", root, root / "testing"):
            if (cand / "velodyne").is_dir():
                self.data = cand
                break
        else:
            raise InputError(f"{root}: no velodyne/ folder in it or in its training/ (not a KITTI folder)")
        self.root = root
        self.stems: list[str] = sorted(p.stem for p in (self.data / "velodyne").glob("*.bin"))
        if not self.stems:
            raise InputError(f"{self.data / 'velodyne'}: no .bin scans")
        if not (self.data / "calib").is_dir():
            raise InputError(f"{self.data}: no calib/ folder")
        self.splits: dict[str, list[str]] = {}
        for base in (self.root, self.data.parent):
            for split in SPLITS:
                f = base / "ImageSets" / f"{split}.txt"
                if split not in self.splits and f.is_file():
                    self.splits[split] = [s for s in f.read_text().split() if s]

    def __len__(self) -> int:
        return len(self.stems)

    def has_labels(self, stem: str) -> bool:
        """Whether frame ``stem`` has a label file."""
        return (self.data / "label_2" / f"{stem}.txt").is_file()

    def calib(self, stem: str) -> KittiCalib:
        """Frame ``stem``'s calib."""
        return read_calib(self.data / "calib" / f"{stem}.txt")

    def frame(self, stem: str) -> KittiFrame:
        """Frame ``stem`` read whole (see :class:`KittiFrame`)."""
        if stem not in set(self.stems):
            raise InputError(f"{self.data}: no frame {stem!r} (no velodyne/{stem}.bin)")
        label = self.data / "label_2" / f"{stem}.txt"
        image = self.data / "image_2" / f"{stem}.png"
        return KittiFrame(stem=stem, points=read_velodyne(self.data / "velodyne" / f"{stem}.bin"),
                          objects=read_labels(label) if label.is_file() else None, calib=self.calib(stem),
                          image_path=image if image.is_file() else None)
