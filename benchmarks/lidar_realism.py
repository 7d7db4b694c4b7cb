"""Sim-to-real check of the vehicle LiDAR (docs/realism.md): cosim episodes against real KITTI scans.

    PYTHONPATH=. .venv/bin/python benchmarks/lidar_realism.py --episode generic.mcap --episode hdl64e.mcap \
        --kitti /tmp/kitti/training [--reference-hist 10.1,2.5,13.9,26.7,42.7,3.8,0.3] [--picture out.png]

Per source (each cosim episode, every connected vehicle's LiDAR on every tick; the real scans), one column:
points per scan; the elevation gap between neighbouring rings and the azimuth step (medians over rings); the
ground spacing of rings (the distance between neighbouring rings' circles on flat ground, near 10 m and
20 m); points per vehicle (car, van, truck, bus in the front 90 deg, as KITTI labels them) by range bin;
the intensity histogram over :data:`BINS` and its total-variation distance to the reference histogram
(``--reference-hist`` in %, else the first real folder's). ``--fit-kitti``: the gain and exponent of the ``kitti``
intensity transfer that bring episodes rendered with ``intensity_transfer: linear`` closest to the reference.
``--detector RUN[:HEIGHT_M]``: instead, a ``cosim learn`` model (ego only) run on the real frames: vehicles
found, missed and false positives in the front 90 deg (DontCare regions of the image excluded); on ``--kitti``
folders scored by ``cosim.learn.kitti`` (``cosim learn score``'s rules: recall by range, false positives per
frame, BEV AP).

Real scans are read from a KITTI object folder (``velodyne/*.bin``, ``label_2/*.txt``, ``calib/*.txt``) that
you put in a scratch folder; none ship with cosim. KITTI scans have no ring field: rings are split where the
azimuth wraps (the scan is stored ring by ring).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from cosim.io import open_episode

BINS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
RANGE_BINS = ((10.0, 30.0), (30.0, 40.0), (60.0, 80.0))
VEHICLES = {"car", "van", "truck", "bus"}
KITTI_VEHICLES = {"Car": "car", "Van": "van", "Truck": "truck", "Tram": "bus"}
FRONT_HALF_ANGLE_RAD = math.radians(45.0)


class Scan:
    """One sweep in its sensor frame: ``xyz`` (N, 3) [m], ``intensity`` (N,), ``ring`` (N,) int, and the
    vehicles seen (``boxes``: (M, 7) x, y, z centre, length, width, height, yaw in the sensor frame) with
    the points on each (``hits`` (M,) int, or None where the points per box are counted from the boxes)."""

    def __init__(self, xyz, intensity, ring, boxes, hits=None):
        self.xyz, self.intensity, self.ring, self.boxes, self.hits = xyz, intensity, ring, boxes, hits


# ------------------------------------------------------------------------------------------ cosim episodes


def cosim_scans(path: Path) -> tuple[str, list[Scan]]:
    """Every connected vehicle's sweep of every tick of an episode, with the vehicles it saw."""
    import yaml

    scans = []
    with open_episode(path) as ep:
        resolved = yaml.safe_load(ep.attachment("scenario.yaml"))
        lidar = resolved["sensors"]["vehicle"]["lidar"]
        label = f"{lidar.get('model', 'generic')} at {lidar['mount']['xyz_m'][2]:g} m"
        vehicles = [a for a in ep.agents if a.startswith("vehicle_")]
        for tick in ep.ticks():
            objs, tf = tick.labels, tick.transforms
            for agent in vehicles:
                if f"/{agent}/lidar" not in tick:
                    continue
                cloud = tick.points(agent)
                m = np.linalg.inv(tf.to_root(f"{agent}/lidar"))  # sensor <- map
                keep = [i for i, c in enumerate(objs.classes) if c in VEHICLES and objs.agent_ids[i] != agent]
                c = objs.centers_m[keep] @ m[:3, :3].T + m[:3, 3]
                yaw = objs.yaws_rad[keep] + math.atan2(m[1, 0], m[0, 0])
                boxes = np.column_stack([c, objs.sizes_m[keep], yaw]) if keep else np.zeros((0, 7))
                inst = cloud.points["instance_id"]
                ids, counts = np.unique(inst, return_counts=True)
                per = dict(zip(ids.tolist(), counts.tolist(), strict=True))
                hits = np.array([per.get(int(objs.track_ids[i]), 0) for i in keep], np.int64)
                scans.append(Scan(cloud.xyz, cloud.points["intensity"].astype(np.float64),
                                  cloud.points["ring"].astype(np.int64), boxes, hits))
    return label, scans


# ---------------------------------------------------------------------------------------------- KITTI


def _calib(path: Path) -> np.ndarray:
    """rect camera <- velodyne (4, 4) from a KITTI calib file."""
    rows = {}
    for line in path.read_text().splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            rows[k.strip()] = np.array([float(x) for x in v.split()])
    r0 = np.eye(4)
    r0[:3, :3] = rows["R0_rect"].reshape(3, 3)
    tr = np.eye(4)
    tr[:3, :] = rows["Tr_velo_to_cam"].reshape(3, 4)
    return r0 @ tr


def _kitti_boxes(label: Path, cam_from_velo: np.ndarray) -> np.ndarray:
    """Vehicle boxes (M, 7) in the velodyne frame from a KITTI label file (DontCare and others left out)."""
    velo_from_cam = np.linalg.inv(cam_from_velo)
    out = []
    for line in label.read_text().splitlines():
        f = line.split()
        if not f or f[0] not in KITTI_VEHICLES:
            continue
        h, w, ln, x, y, z, ry = (float(v) for v in f[8:15])
        c = velo_from_cam @ np.array([x, y - h / 2, z, 1.0])  # KITTI gives the bottom centre, y down
        out.append([c[0], c[1], c[2], ln, w, h, -ry - math.pi / 2])
    return np.array(out).reshape(-1, 7)


def kitti_rings(xyz: np.ndarray) -> np.ndarray:
    """Ring (N,) of KITTI points, stored ring by ring, each from azimuth 0 counter-clockwise round to 0: the
    azimuth wraps from +180 to -180 deg at the back, and the next ring starts at the first point at or past 0
    deg after that."""
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    back = np.nonzero(np.diff(az) < -math.pi)[0] + 1
    ahead = np.nonzero(az >= 0.0)[0]
    k = np.searchsorted(ahead, back)
    starts = np.unique(ahead[k[k < len(ahead)]])
    ring = np.zeros(len(xyz), np.int64)
    ring[starts] = 1
    return np.cumsum(ring)


def kitti_scans(folder: Path) -> list[Scan]:
    scans = []
    for binf in sorted((folder / "velodyne").glob("*.bin")):
        raw = np.fromfile(binf, np.float32).reshape(-1, 4)
        xyz = raw[:, :3].astype(np.float64)
        calib, label = folder / "calib" / f"{binf.stem}.txt", folder / "label_2" / f"{binf.stem}.txt"
        boxes = _kitti_boxes(label, _calib(calib)) if label.exists() and calib.exists() else np.zeros((0, 7))
        scans.append(Scan(xyz, raw[:, 3].astype(np.float64), kitti_rings(xyz), boxes))
    return scans


# --------------------------------------------------------------------------------------------- measures


def in_box(xyz: np.ndarray, box: np.ndarray, margin_m: float = 0.1, ground_m: float = 0.15) -> np.ndarray:
    """Points (N,) bool inside a box (x, y, z, l, w, h, yaw) grown by ``margin_m``, less its lowest ``ground_m``
    (the road under a labelled box is not the vehicle: cosim counts a vehicle's points by their instance)."""
    d = xyz - box[:3]
    c, s = math.cos(box[6]), math.sin(box[6])
    u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    return ((np.abs(u) <= box[3] / 2 + margin_m) & (np.abs(v) <= box[4] / 2 + margin_m)
            & (d[:, 2] >= -box[5] / 2 + ground_m) & (d[:, 2] <= box[5] / 2 + margin_m))


def points_per_vehicle(scans: list[Scan]) -> dict[tuple[float, float], list[int]]:
    """Points on each vehicle in the front 90 deg, by range bin of its centre (horizontal distance)."""
    out: dict[tuple[float, float], list[int]] = {b: [] for b in RANGE_BINS}
    for s in scans:
        for k, box in enumerate(s.boxes):
            if abs(math.atan2(box[1], box[0])) > FRONT_HALF_ANGLE_RAD:
                continue
            r = math.hypot(box[0], box[1])
            for lo, hi in RANGE_BINS:
                if lo <= r < hi:
                    n = int(s.hits[k]) if s.hits is not None else int(in_box(s.xyz, box).sum())
                    out[(lo, hi)].append(n)
    return out


def ring_geometry(scans: list[Scan], height_m: float) -> dict[str, float]:
    """Median elevation gap between neighbouring rings [deg] (5th, 95th percentile), median azimuth step [deg],
    and the ground gap between neighbouring rings' circles [m] near 10 and 20 m (from the ring elevations
    and the mount height: d = h / tan(-elevation))."""
    s = scans[0]
    elev, steps = [], []
    for r in np.unique(s.ring):
        p = s.xyz[s.ring == r]
        if len(p) < 50:
            continue
        e = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
        elev.append(np.median(e))
        az = np.sort(np.degrees(np.arctan2(p[:, 1], p[:, 0])))
        d = np.diff(az)
        steps.append(np.median(d[d > 1e-4]))
    elev = np.sort(np.array(elev))
    gaps = np.diff(elev)
    gaps = gaps[gaps > 0.05]  # two pieces of one ring
    if len(gaps) < 2:  # a scan cut to the camera's view (the rings cannot be told apart)
        nan = float("nan")
        return {"rings": len(elev), "gap_deg": nan, "gap_p5_deg": nan, "gap_p95_deg": nan, "az_step_deg": nan,
                "ground_gap_10m": nan, "ground_gap_20m": nan}
    down = elev[elev < -0.5]
    ground = height_m / np.tan(np.radians(-down))
    order = np.argsort(ground)
    g = ground[order]
    spacing = np.diff(g)

    def near(d_m: float) -> float:
        k = np.nonzero((g[:-1] >= d_m * 0.8) & (g[:-1] <= d_m * 1.2))[0]
        return float(np.median(spacing[k])) if len(k) else float("nan")

    return {"rings": len(elev), "gap_deg": float(np.median(gaps)), "gap_p5_deg": float(np.percentile(gaps, 5)),
            "gap_p95_deg": float(np.percentile(gaps, 95)), "az_step_deg": float(np.median(steps)),
            "ground_gap_10m": near(10.0), "ground_gap_20m": near(20.0)}


ROAD_BINS = ((0.0, 5.0), (10.0, 15.0), (20.0, 30.0), (30.0, 40.0))


def road_intensity(scans: list[Scan], height_m: float) -> list[float]:
    """Median intensity of ground returns (within 0.25 m of the road plane under the sensor) by horizontal
    range bin of :data:`ROAD_BINS` (nan where fewer than 20)."""
    xyz = np.concatenate([s.xyz for s in scans])
    i = np.concatenate([s.intensity for s in scans])
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    ground = xyz[:, 2] < -height_m + 0.25
    out = []
    for lo, hi in ROAD_BINS:
        k = ground & (r >= lo) & (r < hi)
        out.append(float(np.median(i[k])) if k.sum() >= 20 else float("nan"))
    return out


def histogram(scans: list[Scan]) -> np.ndarray:
    """Share of points (7,) in % per intensity bin of :data:`BINS`."""
    i = np.concatenate([s.intensity for s in scans])
    h = np.histogram(np.clip(i, 0.0, 1.0), BINS)[0]
    return 100.0 * h / max(1, h.sum())


def tv_distance(p_pct: np.ndarray, q_pct: np.ndarray) -> float:
    """Total-variation distance of two histograms given in %: half the summed absolute difference (0..1)."""
    p, q = np.asarray(p_pct) / np.sum(p_pct), np.asarray(q_pct) / np.sum(q_pct)
    return 0.5 * float(np.abs(p - q).sum())


def fit_kitti(scans: list[Scan], reference: np.ndarray, sample: int = 100_000) -> tuple[float, float, float]:
    """(gain, exponent, TV distance) of the ``kitti`` transfer (:mod:`cosim.sensors.lidar_models`) closest to
    ``reference`` over a grid, on ``sample`` returns drawn from ``scans`` (rendered with the linear transfer)."""
    from cosim.sensors.lidar_models import KITTI_MIN_RANGE_M, KITTI_REF_RANGE_M

    i = np.clip(np.concatenate([s.intensity for s in scans]), 1e-6, 1.0)
    r = np.concatenate([np.linalg.norm(s.xyz, axis=1) for s in scans])
    pick = np.random.default_rng(0).choice(len(i), min(sample, len(i)), replace=False)
    log_power = np.log(i[pick] * (KITTI_REF_RANGE_M / np.maximum(r[pick], KITTI_MIN_RANGE_M)) ** 2)
    best = (1.0, 1.0, 1.0)
    for gain in np.arange(0.30, 1.01, 0.02):
        for exp in np.arange(0.10, 0.80, 0.02):
            h = np.histogram(np.clip(gain * np.exp(exp * log_power), 0, 1), BINS)[0]
            tv = tv_distance(h, reference)
            if tv < best[2]:
                best = (round(float(gain), 2), round(float(exp), 2), tv)
    return best


# ------------------------------------------------------------------------------------ detector transfer

MATCH_M = 2.0  # [m] a detection within this of a vehicle's centre (bird's eye) finds it


#: cosim vehicles with fewer LiDAR points than this are not counted as missed (nor their detections as false)
MIN_POINTS_COSIM = 5


def _cosim_frames(episodes: list[Path]):
    """(cloud (N, 4), vehicles (M, 7), vehicles with too few points (K, 7), [], None) per sweep of episodes."""
    for path in episodes:
        for s in cosim_scans(path)[1]:
            cloud = np.column_stack([s.xyz, s.intensity]).astype(np.float32)
            seen = s.hits >= MIN_POINTS_COSIM
            yield cloud, s.boxes[seen], s.boxes[~seen], [], None


def detect(run: Path, frames, shift_z_m: float, score_min: float) -> dict[str, object]:
    """A ``cosim learn`` model (ego only) on ``frames`` (:func:`_cosim_frames`): vehicles in
    the front 90 deg and the model's range are found when a detection of score >= ``score_min`` lies within
    :data:`MATCH_M` (best score first, one detection per vehicle); other detections in the front 90 deg are
    false positives unless they fall in a DontCare rectangle of the image or on another labelled object (for
    KITTI: misc, pedestrians, cyclists; for cosim: vehicles with under :data:`MIN_POINTS_COSIM` points).
    ``shift_z_m`` moves the points up or down (a model trained at another mount height)."""
    from cosim.learn.train import device_of, load_run, predict_sample

    device = device_of("cpu")
    model, setup, _ = load_run(run, device)
    found = missed = false_pos = 0
    best_scores = []
    for pts, gt, others, dontcare, p2 in frames:
        cloud = pts.copy()
        cloud[:, 2] += shift_z_m
        boxes, scores, _cls = predict_sample(model, {"clouds": [cloud]}, setup, device, score_min=0.01)
        front = np.abs(np.arctan2(boxes[:, 1], boxes[:, 0])) <= FRONT_HALF_ANGLE_RAD
        boxes, scores = boxes[front], scores[front]
        gt_front = gt[(np.abs(np.arctan2(gt[:, 1], gt[:, 0])) <= FRONT_HALF_ANGLE_RAD)
                      & setup.grid.box_inside(gt[:, :2])]
        used = np.zeros(len(boxes), bool)
        for g in gt_front:
            d = np.hypot(boxes[:, 0] - g[0], boxes[:, 1] - g[1])
            near = np.nonzero((d <= MATCH_M) & ~used)[0]
            best_scores.append(round(float(scores[near].max()), 2) if len(near) else 0.0)
            hit = near[scores[near] >= score_min] if len(near) else near
            if len(hit):
                used[hit[np.argmax(scores[hit])]] = True
                found += 1
            else:
                missed += 1
        for k in np.nonzero(~used & (scores >= score_min))[0]:
            b = boxes[k]
            if len(others) and np.min(np.hypot(others[:, 0] - b[0], others[:, 1] - b[1])) <= MATCH_M:
                continue
            if p2 is not None and dontcare:
                u, v, w = p2 @ np.array([b[0], b[1], b[2], 1.0])
                if w > 0 and any(x0 <= u / w <= x1 and y0 <= v / w <= y1 for x0, y0, x1, y1 in dontcare):
                    continue
            false_pos += 1
    return {"found": found, "missed": missed, "false_positives": false_pos, "best_scores": best_scores}


def kitti_detect(run: Path, folder: Path, kitti_height_m: float, model_height_m: float | None,
                 score_min: float) -> dict[str, object]:
    """A ``cosim learn`` model on a KITTI folder, scored by :mod:`cosim.learn.kitti` (front 90 deg, 40 m, vehicles
    with >= 5 points): the scans at ``kitti_height_m`` moved to the model's height (``model_height_m``, else the
    one its checkpoint records)."""
    import dataclasses

    from cosim.learn.kitti import KittiSource, ScoreOptions, predict_source, score_source, with_class_names
    from cosim.learn.train import device_of, load_run

    device = device_of("cpu")
    model, setup, _ = load_run(run, device)
    if model_height_m is not None:
        setup = dataclasses.replace(setup, lidar_height_m=model_height_m)
    source = KittiSource(folder, height_m=kitti_height_m)
    preds = with_class_names(predict_source(model, setup, source, device), setup.classes)
    out = score_source(source, preds, ScoreOptions(fov="front90", min_score=score_min)).summary()
    out["shift_m"] = 0.0 if setup.lidar_height_m is None else kitti_height_m - setup.lidar_height_m
    return out


# -------------------------------------------------------------------------------------------- picture


def picture(sources: list[tuple[str, Scan]], out: Path) -> None:
    """BEV (top row) and range image (bottom row) of one scan per source, side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(sources), figsize=(6 * len(sources), 8.5),
                             gridspec_kw={"height_ratios": [3, 1]})
    for col, (name, s) in enumerate(sources):
        ax = axes[0, col]
        near = np.hypot(s.xyz[:, 0], s.xyz[:, 1]) < 50
        ax.scatter(s.xyz[near, 0], s.xyz[near, 1], s=0.2, c=np.clip(s.intensity[near], 0, 1), cmap="viridis",
                   vmin=0, vmax=1, rasterized=True)
        ax.set_xlim(-50, 50)
        ax.set_ylim(-50, 50)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: {len(s.xyz) / 1000:.0f} k points\n(colour: reported intensity 0..1)")
        ax.set_xlabel("x [m] (forward)")
        ax.set_ylabel("y [m]")
        ax = axes[1, col]
        rings, inverse = np.unique(s.ring, return_inverse=True)
        elev = np.arctan2(s.xyz[:, 2], np.hypot(s.xyz[:, 0], s.xyz[:, 1]))
        ring_elev = np.array([np.median(elev[inverse == k]) for k in range(len(rings))])
        row = np.argsort(np.argsort(-ring_elev))[inverse]  # row 0: the highest ring (KITTI stores it first)
        az = np.degrees(np.arctan2(s.xyz[:, 1], s.xyz[:, 0]))
        colm = np.clip(((180.0 - az) / 360.0 * 1024).astype(int), 0, 1023)
        img = np.full((len(rings), 1024), np.nan)
        img[row, colm] = np.linalg.norm(s.xyz, axis=1)
        ax.imshow(img, aspect="auto", cmap="turbo", vmin=0, vmax=60, interpolation="nearest")
        ax.set_title("range image (rows: rings, highest on top; colour: range 0-60 m)", fontsize=9)
        ax.set_xticks([0, 256, 512, 768, 1023], ["180", "90", "0", "-90", "-180"])
        ax.set_xlabel("azimuth [deg]")
    fig.tight_layout()
    fig.savefig(out, dpi=90)


# ------------------------------------------------------------------------------------------------ main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episode", type=Path, action="append", default=[], help="a cosim episode (repeatable)")
    ap.add_argument("--kitti", type=Path, action="append", default=[],
                    help="a KITTI object folder with velodyne/, label_2/, calib/ (repeatable: one column each)")
    ap.add_argument("--kitti-height-m", type=float, default=1.73, help="KITTI's LiDAR height above the road")
    ap.add_argument("--reference-hist", help="reference intensity histogram, 7 percentages over BINS")
    ap.add_argument("--fit-kitti", action="store_true", help="fit the kitti transfer to the reference")
    ap.add_argument("--picture", type=Path, help="write the side-by-side picture here")
    ap.add_argument("--detector", action="append", default=[], metavar="RUN[:HEIGHT_M]",
                    help="a cosim learn run (ego only) to try on the --kitti frames; HEIGHT_M: the LiDAR height it "
                         "was trained at (the real points are moved to it; default --kitti-height-m)")
    ap.add_argument("--score-min", type=float, default=0.3, help="detections below this score are not counted")
    args = ap.parse_args()
    if args.detector:
        for spec in args.detector:
            run, _, height = spec.partition(":")
            for folder in args.kitti:
                s = kitti_detect(Path(run), folder, args.kitti_height_m, float(height) if height else None,
                                 args.score_min)
                print(f"{run} on {folder} (cosim.learn.kitti, as cosim learn score scores it in the front 90 deg "
                      f"within 40 m: points moved {s['shift_m']:+.2f} m): {s['cars']} vehicles, recall "
                      f"{s['recall 0-40 m']} (0-20 m {s['recall 0-20 m']}, 20-40 m {s['recall 20-40 m']}), "
                      f"{s['false positives per frame']} false positives per frame at score >= {args.score_min:g}, "
                      f"BEV AP30 {s['AP30']:.1f} / AP50 {s['AP50']:.1f}")
            if args.episode:
                r = detect(Path(run), _cosim_frames(args.episode), 0.0, args.score_min)
                print(f"{run} on {', '.join(p.stem for p in args.episode)}: found {r['found']} of "
                      f"{r['found'] + r['missed']}, missed {r['missed']}, false positives {r['false_positives']} at "
                      f"score >= {args.score_min:g}")
        return

    sources: list[tuple[str, list[Scan], float]] = []
    for path in args.episode:
        label, scans = cosim_scans(path)
        height = float(label.rsplit(" at ", 1)[1].split()[0])
        sources.append((f"cosim {label} ({path.stem})", scans, height))
    reference = None
    for folder in args.kitti:
        scans = kitti_scans(folder)
        sources.append((f"KITTI HDL-64E ({', '.join(p.stem for p in sorted((folder / 'velodyne').glob('*.bin')))})",
                        scans, args.kitti_height_m))
        if reference is None:
            reference = histogram(scans)
    if args.reference_hist:
        reference = np.array([float(v) for v in args.reference_hist.split(",")])

    rows: dict[str, list[str]] = {}

    def put(key: str, value: str) -> None:
        rows.setdefault(key, []).append(value)

    for _name, scans, height in sources:
        n = np.array([len(s.xyz) for s in scans])
        put("points per scan (mean, min-max)", f"{n.mean() / 1000:.1f} k ({n.min() / 1000:.1f}-{n.max() / 1000:.1f})")
        g = ring_geometry(scans, height)
        put("rings seen", f"{g['rings']}")
        put("elevation gap between rings [deg]: median (p5-p95)",
            f"{g['gap_deg']:.2f} ({g['gap_p5_deg']:.2f}-{g['gap_p95_deg']:.2f})")
        put("azimuth step [deg]", f"{g['az_step_deg']:.3f}")
        put("ground gap between rings near 10 m / 20 m [m]", f"{g['ground_gap_10m']:.2f} / {g['ground_gap_20m']:.2f}")
        ppv = points_per_vehicle(scans)
        for (lo, hi), counts in ppv.items():
            cell = f"{np.median(counts):.0f} (n={len(counts)})" if counts else "none (n=0)"
            put(f"points per vehicle {lo:g}-{hi:g} m: median", cell)
        h = histogram(scans)
        put("intensity: mean", f"{np.mean(np.concatenate([s.intensity for s in scans])):.3f}")
        put("road intensity (median) at " + " / ".join(f"{lo:g}-{hi:g}" for lo, hi in ROAD_BINS) + " m",
            " / ".join(f"{v:.2f}" for v in road_intensity(scans, height)))
        put("intensity histogram [%]", " / ".join(f"{v:.1f}" for v in h))
        if reference is not None:
            put("TV distance to the reference histogram", f"{tv_distance(h, reference):.3f}")
        if args.fit_kitti and reference is not None and not _name.startswith("KITTI"):
            gain, exp, tv = fit_kitti(scans, reference)
            put("kitti transfer fitted: gain, exponent (TV)", f"{gain:g}, {exp:g} ({tv:.3f})")
    print("| quantity | " + " | ".join(s[0] for s in sources) + " |")
    print("|---" + "|---:" * len(sources) + "|")
    for key, values in rows.items():
        print(f"| {key} | " + " | ".join(values) + " |")
    if reference is not None:
        print(f"\nreference histogram [%]: {' / '.join(f'{v:.1f}' for v in reference)}")
    if args.picture:  # of each source, the scan with the most vehicles within 60 m
        def busiest(scans: list[Scan]) -> Scan:
            return max(scans, key=lambda s: int((np.hypot(s.boxes[:, 0], s.boxes[:, 1]) < 60).sum()))

        picture([(name.split(" (")[0], busiest(scans)) for name, scans, _ in sources[:3]], args.picture)
        print(f"picture: {args.picture}")


if __name__ == "__main__":
    main()
