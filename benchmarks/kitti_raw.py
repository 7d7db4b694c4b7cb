"""A KITTI raw drive (synced velodyne scans, the day's calib files, the drive's tracklets) as a KITTI object
folder that ``cosim learn --kitti`` reads (docs/realism.md, "Scoring a model on real scans"):

    PYTHONPATH=. .venv/bin/python benchmarks/kitti_raw.py \
        --drive /work/scratch/raw/data/2011_09_26/2011_09_26_drive_0001_sync \
        --calib /work/scratch/raw/data/2011_09_26 --out /work/scratch/kitti_raw_0001

writes ``OUT/training/{velodyne,label_2,calib}/<frame:06d>`` and ``OUT/ImageSets/``: ``trainval.txt`` (every
frame), ``val.txt`` (the last ``--val-share``, 0.2, of the frames: a held-out stretch of the drive to choose a
checkpoint on) and ``train.txt`` (the others).
KITTI data is non-commercial: write it to a scratch folder, never into the repository.

- **calib** (the same for every frame): ``P0``-``P3`` are the day's ``P_rect_00``-``P_rect_03``, ``R0_rect`` its
  ``R_rect_00``, ``Tr_velo_to_cam`` and ``Tr_imu_to_velo`` the ``R``, ``T`` of ``calib_velo_to_cam.txt`` and
  ``calib_imu_to_velo.txt`` (as KITTI's object benchmark builds its calib files).
- **labels**: each tracklet pose is a box in the velodyne frame (h, w, l; the translation is the box's bottom
  centre; yaw ``rz``), turned into a label line with :func:`cosim.io.kitti.boxes_from_velo`. As in KITTI's object
  labels, only poses inside the front camera's field of view are kept: the box centre projects into image 2
  (``S_rect_02`` wide) and the tracklet does not mark the pose out of the image or behind it (truncation 2, 3
  or 99). ``truncated``: 0 for a pose in the image, for a truncated one (1) the share of its projected 2D box
  outside the image; ``occluded``: the tracklet's 0 (visible), 1 (partly), 2 (fully), and 3 for its -1
  (unknown); the 2D box is the projected corners' bounds clipped to the image; ``alpha`` is rotation_y less the
  centre's bearing ``atan2(x, z)``. Object types as the tracklets name them (Car, Van, Cyclist, Tram...).
- **velodyne**: the drive's ``.bin`` scans, copied.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from cosim.errors import InputError
from cosim.io.kitti import (
    KittiCalib,
    KittiObject,
    box_corners_velo,
    boxes_from_velo,
    format_calib,
    format_label,
    wrap_rad,
)

#: Tracklet truncation values of a pose outside the image (out of it, behind it, to be ignored).
OUTSIDE = (2, 3, 99)


def _values(path: Path) -> dict[str, np.ndarray]:
    out = {}
    for line in path.read_text().splitlines():
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        try:
            out[key.strip()] = np.array([float(v) for v in rest.split()], np.float64)
        except ValueError:
            continue  # calib_time: a date
    return out


def raw_calib(day: Path) -> tuple[KittiCalib, tuple[int, int]]:
    """The object-style calib of a raw recording day's folder and image 2's size (width, height) [px]."""
    files = {n: day / f"calib_{n}.txt" for n in ("cam_to_cam", "velo_to_cam", "imu_to_velo")}
    for f in files.values():
        if not f.is_file():
            raise InputError(f"{day}: no {f.name}")
    cam = _values(files["cam_to_cam"])
    velo = _values(files["velo_to_cam"])
    imu = _values(files["imu_to_velo"])
    rt = lambda v: np.column_stack([v["R"].reshape(3, 3), v["T"].reshape(3)])  # noqa: E731
    calib = KittiCalib(P0=cam["P_rect_00"].reshape(3, 4), P1=cam["P_rect_01"].reshape(3, 4),
                       P2=cam["P_rect_02"].reshape(3, 4), P3=cam["P_rect_03"].reshape(3, 4),
                       R0_rect=cam["R_rect_00"].reshape(3, 3), Tr_velo_to_cam=rt(velo), Tr_imu_to_velo=rt(imu))
    w, h = cam["S_rect_02"]
    return calib, (int(w), int(h))


def read_tracklets(path: Path) -> list[dict]:
    """The tracklets of a ``tracklet_labels.xml``: type, h, w, l, first frame and the poses (tx, ty, tz, rz,
    truncation, occlusion) in the velodyne frame."""
    root = ET.parse(path).getroot()
    out = []
    for item in root.find("tracklets").findall("item"):
        poses = []
        for p in item.find("poses").findall("item"):
            poses.append({k: float(p.find(k).text) for k in ("tx", "ty", "tz", "rz")}
                         | {k: int(p.find(k).text) for k in ("truncation", "occlusion")})
        out.append({"type": item.find("objectType").text, "h": float(item.find("h").text),
                    "w": float(item.find("w").text), "l": float(item.find("l").text),
                    "first_frame": int(item.find("first_frame").text), "poses": poses})
    return out


def frame_labels(tracklets: list[dict], frame: int, calib: KittiCalib, size: tuple[int, int]) -> list[KittiObject]:
    """The label lines of one frame (see the module doc)."""
    width, height = size
    out = []
    for t in tracklets:
        k = frame - t["first_frame"]
        if not 0 <= k < len(t["poses"]):
            continue
        p = t["poses"][k]
        if p["truncation"] in OUTSIDE:
            continue
        box = np.array([[p["tx"], p["ty"], p["tz"] + t["h"] / 2, t["l"], t["w"], t["h"], p["rz"]]])
        loc, ry = boxes_from_velo(box, calib)
        centre_uv, depth = calib.rect_to_image(calib.velo_to_rect(box[:, :3]))
        if depth[0] <= 0 or not 0 <= centre_uv[0, 0] < width:
            continue
        uv, d = calib.rect_to_image(calib.velo_to_rect(box_corners_velo(box)[0]))
        uv = uv[d > 0]
        x0, y0 = uv.min(axis=0)
        x1, y1 = uv.max(axis=0)
        cx0, cy0, cx1, cy1 = max(x0, 0.0), max(y0, 0.0), min(x1, width - 1.0), min(y1, height - 1.0)
        full = max((x1 - x0) * (y1 - y0), 1e-9)
        inside = max(cx1 - cx0, 0.0) * max(cy1 - cy0, 0.0)
        truncated = 0.0 if p["truncation"] == 0 else float(np.clip(1.0 - inside / full, 0.0, 1.0))
        occluded = p["occlusion"] if p["occlusion"] in (0, 1, 2) else 3
        x, _y, z = loc[0]
        alpha = float(wrap_rad(ry[0] - math.atan2(x, z)))
        out.append(KittiObject(type=t["type"], truncated=truncated, occluded=occluded, alpha=alpha,
                               bbox=(cx0, cy0, cx1, cy1), h=t["h"], w=t["w"], l=t["l"], location=loc[0],
                               rotation_y=float(ry[0])))
    return out


def convert(drive: Path, day: Path, out: Path, val_share: float = 0.2) -> dict[str, int]:
    """Write the KITTI object folder ``out/training`` of a synced raw drive; returns counts."""
    if not 0.0 <= val_share < 1.0:
        raise InputError(f"--val-share {val_share}: the share of frames held out must be 0 to below 1")
    scans = sorted((drive / "velodyne_points" / "data").glob("*.bin"))
    if not scans:
        raise InputError(f"{drive}: no velodyne_points/data/*.bin")
    tracklets_path = drive / "tracklet_labels.xml"
    if not tracklets_path.is_file():
        raise InputError(f"{drive}: no tracklet_labels.xml")
    calib, size = raw_calib(day)
    tracklets = read_tracklets(tracklets_path)
    data = out / "training"
    for sub in ("velodyne", "label_2", "calib"):
        (data / sub).mkdir(parents=True, exist_ok=True)
    (out / "ImageSets").mkdir(parents=True, exist_ok=True)
    calib_text = format_calib(calib)
    stems, labels = [], 0
    for scan in scans:
        frame = int(scan.stem)
        stem = f"{frame:06d}"
        shutil.copyfile(scan, data / "velodyne" / f"{stem}.bin")
        (data / "calib" / f"{stem}.txt").write_text(calib_text)
        objs = frame_labels(tracklets, frame, calib, size)
        (data / "label_2" / f"{stem}.txt").write_text("".join(format_label(o, 4) + "\n" for o in objs))
        labels += len(objs)
        stems.append(stem)
    n_val = int(len(stems) * val_share)
    splits = {"trainval": stems, "train": stems[: len(stems) - n_val], "val": stems[len(stems) - n_val:]}
    for name, part in splits.items():
        (out / "ImageSets" / f"{name}.txt").write_text("".join(s + "\n" for s in part))
    return {"frames": len(stems), "labels": labels, "tracklets": len(tracklets), "val": n_val}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--drive", type=Path, required=True, help="the synced drive folder (velodyne_points/, "
                                                              "tracklet_labels.xml)")
    ap.add_argument("--calib", type=Path, required=True, help="the recording day's folder with calib_*.txt")
    ap.add_argument("--out", type=Path, required=True, help="the KITTI object folder to write (training/ in it)")
    ap.add_argument("--val-share", type=float, default=0.2, help="the last frames held out as ImageSets/val.txt")
    args = ap.parse_args(argv)
    try:
        n = convert(args.drive, args.calib, args.out, args.val_share)
    except InputError as exc:
        print(f"kitti_raw: error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.out}/training: {n['frames']} frames ({n['val']} of them in ImageSets/val.txt), {n['labels']} labels "
          f"in the front camera's view from {n['tracklets']} tracklets")
    return 0


if __name__ == "__main__":
    sys.exit(main())
