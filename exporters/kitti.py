"""The KITTI object layout (what OpenPCDet, mmdetection3d and most single-agent LiDAR toolboxes read);
docs/exports.md ("KITTI") describes every file and convention. The file formats are :mod:`cosim.io.kitti`'s.

```
<out>/ImageSets/train.txt val.txt test.txt      the stems of each split (from the batch's manifest)
<out>/training/velodyne/<stem>.bin              float32 x y z reflectance, LiDAR frame, compensated to the tick
              label_2/<stem>.txt                KITTI's 15 columns, rectified (front camera) frame
              calib/<stem>.txt                  P0..P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo
              image_2/<stem>.png                the front camera (black, of the virtual camera's size, without one)
              velodyne_labels/<stem>.npy        class_id, instance_id, ring of every point, in the .bin's order
              label_tracks/<stem>.txt           the track id of each label line (0 for none)
              frames.csv                        stem -> split, episode, tick, agent
```

One frame per ego agent (vehicles by default, ``agents``) and exported tick; stems count from 000000 over the
sources in path order, then each ego in the episode's agent order, then its ticks: each agent's drive is a
run of consecutive stems. Unlike the sequence formats, the whole export is one folder: it is written under
``<out>/.cosim-partial/kitti`` and moved into place when complete, with a marker naming every source.
"""

from __future__ import annotations

import csv
import functools
import json
import logging
import math
import multiprocessing
import shutil
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import yaml
from cosim.exporters.export import (
    AGENT_KINDS,
    LOADER_SPLITS,
    MARKER,
    PARTIAL_DIR,
    AgentView,
    ExportFormat,
    ExportOptions,
    ExportResult,
    Source,
    TickView,
    _replace_dir,
    agent_frames,
    find_sources,
    is_complete,
    register_format,
    sequence_info,
    sequence_names,
)
from cosim.exporters.export_io import json_text, npy_bytes, png_bytes, write_bytes

import cosim
from cosim.classes import SEMANTIC_ID
from cosim.errors import InputError
from cosim.geometry import OPTICAL_FROM_FLU, quat_from_rpy, rotation_matrix
from cosim.io import kitti as kf
from cosim.io import open_episode
from cosim.io.decode import quat_to_matrix
from cosim.io.deskew import deskew_tick, objects_to_tick_of

log = logging.getLogger(__name__)

#: cosim object class -> KITTI type. A bus is a Tram (KITTI has no bus; a tram is the long, tall, boxy vehicle
#: it labels, and Car detectors ignore both); a bicycle or motorcycle carries its rider (docs/assets.md), as
#: KITTI's Cyclist does; a static obstacle (cone, barrier) is Misc. Drones are left out: nothing airborne is
#: in KITTI, and a ground detector must not learn boxes in the air.
KITTI_CLASS: dict[str, str] = {
    "car": "Car", "van": "Van", "truck": "Truck", "bus": "Tram", "motorcycle": "Cyclist", "bicycle": "Cyclist",
    "pedestrian": "Pedestrian", "static_obstacle": "Misc",
}
#: ``--agents`` words: plural or singular kinds, ``all``.
AGENT_WORDS: dict[str, tuple[str, ...]] = {
    "all": AGENT_KINDS, **{k: (k,) for k in AGENT_KINDS}, **{f"{k}s": (k,) for k in AGENT_KINDS},
}
DEFAULT_AGENTS = "vehicles"
#: Decimals of the label files (KITTI's own are 2): boxes read back to 0.05 mm and 5e-5 rad.
LABEL_DECIMALS = 4
#: Semantic classes a LiDAR point on the ground has: never an occluder (the road in front of a car is not).
GROUND_CLASSES = frozenset(SEMANTIC_ID[c] for c in ("road", "lane_marking", "sidewalk", "terrain"))
#: [m] a point of another thing counts as an occluder when it is this much nearer than the object's own nearest.
OCCLUDER_MARGIN_M = 0.3
#: Occluded share (of the returns in the object's angular window) below which KITTI's occlusion is 0, then 1;
#: from the second on it is 2 (largely occluded). 3 (unknown) is never written.
OCCLUSION_LEVELS = (0.2, 0.6)
#: [m] near plane the boxes are clipped at before projection.
NEAR_M = 0.1
#: What a frame reads of its ego's topics (the other agents' and cameras' are never decoded).
EGO_TOPICS = ("lidar", "imu", "visibility", "front/image", "front/calibration")
VELODYNE_LABELS_DTYPE = np.dtype([("class_id", "<u1"), ("instance_id", "<u4"), ("ring", "<u2")])
FRAMES_COLUMNS = ("stem", "split", "source_file", "source_sha256", "episode", "tick", "t_ns", "agent_id",
                  "agent_kind", "track_id", "image")


# ------------------------------------------------------------------------------------- agents


def parse_agents(spec: str | None) -> tuple[frozenset[str], frozenset[str]]:
    """``--agents`` -> (kinds, agent ids): comma-separated words of :data:`AGENT_WORDS` (``vehicles``,
    ``rsu``, ``all``...) and agent ids (``vehicle_0``). Raises InputError on anything else."""
    kinds: set[str] = set()
    ids: set[str] = set()
    for word in (spec or DEFAULT_AGENTS).split(","):
        w = word.strip()
        if w in AGENT_WORDS:
            kinds.update(AGENT_WORDS[w])
        elif w.rpartition("_")[0] in AGENT_KINDS and w.rpartition("_")[2].isdigit():
            ids.add(w)
        else:
            raise InputError(f"--agents: unknown kind {w!r}; give all, vehicles, rsus, drones (or the singular), "
                             "or agent ids such as vehicle_0, comma-separated")
    return frozenset(kinds), frozenset(ids)


def ego_agents(agents: Sequence[str], kinds: dict[str, str], with_lidar: set[str], spec: str | None,
               source: str) -> list[str]:
    """The agents of an episode (in its order) that ``spec`` chooses and that have a LiDAR; InputError when
    none is left (an episode without vehicles, by default)."""
    want_kinds, want_ids = parse_agents(spec)
    out = [a for a in agents if (kinds[a] in want_kinds or a in want_ids) and a in with_lidar]
    if not out:
        have = ", ".join(f"{a} ({'LiDAR' if a in with_lidar else 'no LiDAR'})" for a in agents) or "none"
        raise InputError(f"{source}: no agent with a LiDAR matches --agents {spec or DEFAULT_AGENTS} "
                         f"(the episode's agents: {have})")
    return out


# ------------------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class FrontCamera:
    """The camera labels refer to: the agent's ``front`` camera, or a virtual one with the rig's default
    front geometry. ``K`` (3, 3) in KITTI's pixel convention (pixel centres at integers), ``map_from_optical``
    (4, 4) at the tick, ``view`` the real camera's images (None: virtual)."""

    K: np.ndarray
    width: int
    height: int
    map_from_optical: np.ndarray
    view: Any = None


def _mount_matrix(xyz_m: Sequence[float], rpy_deg: Sequence[float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation_matrix(quat_from_rpy(*(math.radians(a) for a in rpy_deg)))
    out[:3, 3] = xyz_m
    return out


def virtual_front(scenario: dict[str, Any], agent_id: str) -> dict[str, Any]:
    """The front camera's spec (width, height, fov_deg, mount) of the agent's rig in the episode (its own rig
    or its kind's, :func:`cosim.scenario.model.rig_data_of`), or the default vehicle rig's
    (cosim/scenario/model.py) when that rig has none."""
    from cosim.scenario.model import CameraSpec, default_vehicle_rig, rig_data_of

    cams = rig_data_of(scenario, agent_id).get("cameras") or []
    spec = next((CameraSpec(**c) for c in cams if c.get("name") == "front"), None)
    spec = spec or next(c for c in default_vehicle_rig().cameras if c.name == "front")
    return {"width": spec.width, "height": spec.height, "fov_deg": spec.fov_deg,
            "xyz_m": tuple(spec.mount.xyz_m), "rpy_deg": tuple(spec.mount.rpy_deg)}


def front_camera(agent: AgentView, names: Sequence[str], virtual: dict[str, Any]) -> FrontCamera:
    """The agent's :class:`FrontCamera` at the tick."""
    to_kitti = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])  # pixel [u, u+1) -> centre u
    if "front" in names:
        cam = agent.cameras(["front"])[0]
        return FrontCamera(to_kitti @ cam.K, cam.width, cam.height,
                           agent.tick.transforms.to_root(f"{agent.agent_id}/front/optical"), cam)
    w, h = virtual["width"], virtual["height"]
    f = 0.5 * w / math.tan(math.radians(virtual["fov_deg"]) / 2.0)
    k = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    body_from_optical = np.eye(4)
    body_from_optical[:3, :3] = OPTICAL_FROM_FLU.T
    return FrontCamera(to_kitti @ k, w, h,
                       agent.map_from_base @ _mount_matrix(virtual["xyz_m"], virtual["rpy_deg"]) @ body_from_optical)


def frame_calib(camera: FrontCamera, map_from_velo: np.ndarray, map_from_imu: np.ndarray) -> kf.KittiCalib:
    """The frame's calib: P0..P3 all ``K [I | 0]`` (one camera: the rectified frame is the front camera's
    optical frame), R0_rect identity, Tr_velo_to_cam = optical <- velodyne, Tr_imu_to_velo = velodyne <- IMU."""
    p = np.c_[camera.K, np.zeros(3)]
    velo_to_cam = kf.rigid_inverse(camera.map_from_optical) @ map_from_velo
    imu_to_velo = kf.rigid_inverse(map_from_velo) @ map_from_imu
    return kf.KittiCalib(P0=p, P1=p, P2=p, P3=p, R0_rect=np.eye(3), Tr_velo_to_cam=velo_to_cam[:3],
                         Tr_imu_to_velo=imu_to_velo[:3])


def image_box(corners_velo: np.ndarray, calib: kf.KittiCalib, width: int, height: int) -> tuple[np.ndarray, float]:
    """A box's 2D box in image 2 and its truncation, from its (8, 3) velodyne corners: the box is clipped at
    the near plane (z = :data:`NEAR_M` in the camera) and projected (its image is the hull of the projected
    vertices); the 2D box is that hull's bounds clipped to the image, (0, 0, 0, 0) when nothing of it is in the
    image; truncation = the share of the unclipped bounds' area outside the image (1 when none is inside)."""
    cam = calib.velo_to_rect(corners_velo)
    edges = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
    verts = [cam[cam[:, 2] >= NEAR_M]]
    for i, j in edges:
        a, b = cam[i], cam[j]
        if (a[2] - NEAR_M) * (b[2] - NEAR_M) < 0:
            t = (NEAR_M - a[2]) / (b[2] - a[2])
            verts.append((a + t * (b - a))[None])
    pts = np.concatenate(verts)
    none = np.zeros(4)
    if len(pts) == 0:
        return none, 1.0
    uv, _ = calib.rect_to_image(pts)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    clipped = np.r_[np.maximum(lo, 0.0), np.minimum(hi, [width - 1.0, height - 1.0])]
    full = float(np.prod(np.maximum(hi - lo, 1e-9)))
    inside = float(np.prod(np.maximum(clipped[2:] - clipped[:2], 0.0)))
    if inside <= 0.0:
        return none, 1.0
    return clipped, float(np.clip(1.0 - inside / full, 0.0, 1.0))


@dataclass(frozen=True)
class Polar:
    """A cloud's points seen from the LiDAR: azimuth and elevation [rad], range [m], each (N,)."""

    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    range_m: np.ndarray

    @classmethod
    def of(cls, xyz_m: np.ndarray) -> Polar:
        horizontal = np.hypot(xyz_m[:, 0], xyz_m[:, 1])
        return cls(np.arctan2(xyz_m[:, 1], xyz_m[:, 0]), np.arctan2(xyz_m[:, 2], horizontal),
                   np.hypot(horizontal, xyz_m[:, 2]))


def occluded_share(polar: Polar, instance_id: np.ndarray, class_id: np.ndarray, box: np.ndarray,
                   track: int) -> float:
    """Share of the LiDAR returns in a box's angular window (its corners' azimuth and elevation span seen from
    the LiDAR) that hit something else nearer than the object's own nearest return (less
    :data:`OCCLUDER_MARGIN_M`); ground returns never count. 0: nothing in front of it; 1: no return of its own."""
    own = instance_id == track
    if not own.any():
        return 1.0
    corners = Polar.of(kf.box_corners_velo(box[None])[0])
    az_c = math.atan2(box[1], box[0])
    rel = kf.wrap_rad(corners.azimuth_rad - az_c)
    p_rel = kf.wrap_rad(polar.azimuth_rad - az_c)
    window = ((p_rel >= rel.min()) & (p_rel <= rel.max()) & (polar.elevation_rad >= corners.elevation_rad.min())
              & (polar.elevation_rad <= corners.elevation_rad.max()))
    near = polar.range_m[own].min() - OCCLUDER_MARGIN_M
    occluders = int((window & ~own & (polar.range_m < near) & ~np.isin(class_id, list(GROUND_CLASSES))).sum())
    return occluders / (int(own.sum()) + occluders)


def occlusion_level(share: float) -> int:
    """KITTI's occlusion (0 fully visible, 1 partly, 2 largely occluded) of an :func:`occluded_share`."""
    return 0 if share < OCCLUSION_LEVELS[0] else 1 if share < OCCLUSION_LEVELS[1] else 2


# ------------------------------------------------------------------------------------- one frame


@dataclass(frozen=True)
class Frame:
    """What one frame's files hold, before they are written."""

    points: np.ndarray  # (N, 4) float32 x y z reflectance, velodyne frame
    point_labels: np.ndarray  # (N,) VELODYNE_LABELS_DTYPE
    objects: list[kf.KittiObject]
    tracks: list[int]  # per label line
    calib: kf.KittiCalib
    camera: FrontCamera


def cloud_xyz(agent: AgentView) -> np.ndarray:
    """(N, 3) float64 the sweep's points in :attr:`AgentView.map_from_cloud`, compensated to the tick as
    the other exports' clouds are (``raw_lidar``, ``objects_at_tick``: :class:`ExportOptions`)."""
    pts = agent.points
    xyz = (np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64) if agent.raw_lidar
           else deskew_tick(agent.tick, agent.agent_id))
    if agent.objects_at_tick and not agent.raw_lidar:
        xyz = objects_to_tick_of(agent.tick, agent.agent_id, xyz)
    lidar, cloud = agent.map_from_lidar, agent.map_from_cloud
    if cloud is not lidar:
        xyz = xyz @ (cloud[:3, :3].T @ lidar[:3, :3]).T
    return np.asarray(xyz, dtype=np.float64)


def build_frame(view: TickView, agent: AgentView, virtual: dict[str, Any]) -> Frame:
    """One ego agent's frame at the tick: its cloud, the labels of every object it has a LiDAR return on (in
    track order), then DontCare for the mapped objects it has none on that show in the front image; calib,
    camera."""
    map_from_velo = agent.map_from_cloud
    imu_frame = f"{agent.agent_id}/imu"
    tf = agent.tick.transforms
    map_from_imu = tf.to_root(imu_frame) if imu_frame in set(tf.frames) else agent.map_from_base
    camera = front_camera(agent, view.camera_names[agent.agent_id], virtual)
    calib = frame_calib(camera, map_from_velo, map_from_imu)
    xyz = cloud_xyz(agent)
    pts = agent.points
    points = np.c_[xyz, pts["intensity"]].astype(np.float32)
    point_labels = np.zeros(len(pts), VELODYNE_LABELS_DTYPE)
    for f in VELODYNE_LABELS_DTYPE.names or ():
        if f in (pts.dtype.names or ()):
            point_labels[f] = pts[f]
    labels = view.labels
    seen = agent.visibility()
    velo_from_map = kf.rigid_inverse(map_from_velo)
    polar = Polar.of(xyz)
    objects: list[kf.KittiObject] = []
    tracks: list[int] = []
    regions: list[tuple[kf.KittiObject, int]] = []  # DontCare, written after every object (below)
    for i in np.argsort(labels.track_ids, kind="stable"):
        track, name = int(labels.track_ids[i]), labels.classes[i]
        if name not in KITTI_CLASS or track == agent.track_id:
            continue
        rot = velo_from_map[:3, :3] @ quat_to_matrix(labels.rotations[i])
        centre = velo_from_map[:3, :3] @ labels.centers_m[i] + velo_from_map[:3, 3]
        length, width, height = (float(v) for v in labels.sizes_m[i])
        box = np.array([*centre, length, width, height, math.atan2(rot[1, 0], rot[0, 0])])
        bbox, truncated = image_box(kf.box_corners_velo(box[None])[0], calib, camera.width, camera.height)
        if int(seen.get(track, {}).get("lidar_points", 0)) <= 0:
            if bbox[2] > bbox[0] and bbox[3] > bbox[1]:
                regions.append((kf.dont_care(bbox), track))
            continue
        loc, ry = kf.boxes_from_velo(box[None], calib)
        occ = occlusion_level(occluded_share(polar, point_labels["instance_id"], point_labels["class_id"], box,
                                             track))
        alpha = float(kf.wrap_rad(ry[0] - math.atan2(loc[0, 0], loc[0, 2])))
        objects.append(kf.KittiObject(KITTI_CLASS[name], truncated, occ, alpha, bbox, h=height, w=width, l=length,
                                      location=loc[0], rotation_y=float(ry[0])))
        tracks.append(track)
    # KITTI's files list DontCare last, and OpenPCDet's info script relies on it (it takes the first lines up to
    # the number of other objects as the boxes)
    return Frame(points, point_labels, objects + [o for o, _ in regions], tracks + [t for _, t in regions], calib,
                 camera)


def write_frame(root: Path, stem: str, frame: Frame) -> None:
    """A frame's files under ``root`` (the partial ``training/``)."""
    write_bytes(root / "velodyne" / f"{stem}.bin", np.ascontiguousarray(frame.points, "<f4").tobytes())
    write_bytes(root / "velodyne_labels" / f"{stem}.npy", npy_bytes(frame.point_labels))
    text = "".join(kf.format_label(o, LABEL_DECIMALS) + "\n" for o in frame.objects)
    write_bytes(root / "label_2" / f"{stem}.txt", text.encode())
    write_bytes(root / "label_tracks" / f"{stem}.txt", "".join(f"{t}\n" for t in frame.tracks).encode())
    write_bytes(root / "calib" / f"{stem}.txt", kf.format_calib(frame.calib).encode())
    cam = frame.camera
    write_bytes(root / "image_2" / f"{stem}.png", cam.view.rgb_png() if cam.view is not None
                else black_png(cam.width, cam.height))


@functools.lru_cache(maxsize=4)
def black_png(width: int, height: int) -> bytes:
    """A black RGB PNG: image_2 of a frame without a front camera (the toolboxes' info scripts read the shape)."""
    return png_bytes(np.zeros((height, width, 3), np.uint8))


# ------------------------------------------------------------------------------------- driver


@dataclass(frozen=True)
class Plan:
    """One source's part of the export: its egos, ticks and the stem of each (ego, tick)."""

    source: Source
    sequence: str
    egos: tuple[str, ...]
    ticks: tuple[int, ...]
    first_stem: int

    def stem(self, ego: str, tick: int) -> str:
        return f"{self.first_stem + self.egos.index(ego) * len(self.ticks) + self.ticks.index(tick):06d}"

    @property
    def n_frames(self) -> int:
        return len(self.egos) * len(self.ticks)


def _export_kitti_chunk(plan: Plan, options: ExportOptions, root: str, ticks: tuple[int, ...]) -> list[dict]:
    """Write ``ticks`` of one source's egos under the partial ``root/training``; the frames.csv rows."""
    rows = []
    training = Path(root) / "training"
    with open_episode(plan.source.path) as ep:
        seq = sequence_info(ep, plan.source, plan.sequence, options.every)
        scenario = yaml.safe_load(ep.attachment("scenario.yaml")) if "scenario.yaml" in ep.attachments else {}
        virtual = {a: virtual_front(scenario or {}, a) for a in plan.egos}
        topics = ["/tf", "/labels/objects"] + [f"/{a}/{what}" for a in plan.egos for what in EGO_TOPICS]
        topics = [t for t in topics if t in ep.topics]
        for view in agent_frames(ep, seq, ticks, options.raw_lidar, options.objects_at_tick, topics):
            by_id = {a.agent_id: a for a in view.agents}
            for ego in plan.egos:
                agent = by_id[ego]
                frame = build_frame(view, agent, virtual[ego])
                stem = plan.stem(ego, view.index)
                write_frame(training, stem, frame)
                rows.append({"stem": stem, "split": plan.source.split, "source_file": plan.source.path.name,
                             "source_sha256": plan.source.sha256,
                             "episode": plan.source.episode or plan.source.path.stem,
                             "tick": view.index, "t_ns": view.tick.t_ns, "agent_id": ego, "agent_kind": agent.kind,
                             "track_id": "" if agent.track_id is None else agent.track_id,
                             "image": "front" if frame.camera.view is not None else "none"})
    return rows


def _plans(sources: Sequence[Source], every: int, agents: str | None) -> list[Plan]:
    plans = []
    first = 0
    for src, name in zip(sources, sequence_names(sources), strict=True):
        with open_episode(src.path) as ep:
            seq = sequence_info(ep, src, name, every)
            with_lidar = {a for a in seq.agents if f"/{a}/lidar" in ep.topics}
            egos = ego_agents(seq.agents, seq.kinds, with_lidar, agents, str(src.path))
        plans.append(Plan(src, name, tuple(egos), seq.ticks, first))
        first += plans[-1].n_frames
    return plans


def kitti_marker(sources: Sequence[Source], options: ExportOptions, agents: str | None) -> dict[str, Any]:
    return {"format": "kitti", "agents": agents or DEFAULT_AGENTS, "options": options.model_dump(),
            "sources": [{"sha256": s.sha256, "size_bytes": s.size_bytes, "split": s.split} for s in sources],
            "cosim": cosim.__version__}


def run_kitti_export(source: Path, out: Path, options: ExportOptions, *, split: str | None = None,
                     workers: int = 1, progress: Callable[[int, int], None] | None = None,
                     agents: str | None = None) -> ExportResult:
    """Export SOURCE (an episode or a batch folder) as one KITTI object folder ``out`` (the module's layout).
    ``agents`` chooses the egos (:func:`parse_agents`; vehicles by default). The export is written under
    ``out/.cosim-partial/kitti`` and moved to ``out/training`` and ``out/ImageSets`` when complete, replacing
    an earlier export (never folders of those names that no export of cosim's wrote: an InputError); an export
    whose marker names the same sources and options is skipped."""
    out = Path(out)
    parse_agents(agents)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: a file, not a folder (the KITTI export is a folder)")
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    theirs = [sub for sub in ("training", "ImageSets") if (out / sub).exists()]
    if theirs and not _ours(out):
        raise InputError(f"--out {out}: holds {' and '.join(theirs)}/ that no cosim KITTI export wrote (no "
                         f"{MARKER} of one); give a new or empty folder (the export replaces these folders whole)")
    sources = find_sources(Path(source), split)
    marker = kitti_marker(sources, options, agents)
    if is_complete(out, marker) and (out / "training").is_dir():
        log.info("%s: complete KITTI export of these sources already there; skipped", out)
        return ExportResult((), (out,), 0)
    plans = _plans(sources, options.every, agents)
    for unread in sorted({s.split for s in sources} - LOADER_SPLITS):
        log.warning("%d episode(s) of split %r go to ImageSets/%s.txt, which the toolboxes do not read; give "
                    "--split train, val or test to choose one", sum(s.split == unread for s in sources), unread, unread)
    partial = out / PARTIAL_DIR / "kitti"
    if partial.exists():
        shutil.rmtree(partial)
    (partial / "training").mkdir(parents=True)
    total = sum(p.n_frames for p in plans)
    done = 0
    if progress:
        progress(0, total)
    size = max(1, math.ceil(max(len(p.ticks) for p in plans) / workers))
    tasks = [(p, tuple(p.ticks[i:i + size])) for p in plans for i in range(0, len(p.ticks), size)]
    rows: list[dict] = []

    def finished(plan: Plan, chunk_rows: list[dict]) -> None:
        nonlocal done
        rows.extend(chunk_rows)
        done += len(chunk_rows)
        if progress:
            progress(done, total)

    if workers == 1 or len(tasks) <= 1:
        for plan, chunk in tasks:
            finished(plan, _export_kitti_chunk(plan, options, str(partial), chunk))
    else:
        ctx = multiprocessing.get_context("spawn")  # never fork after Open3D / zstd threads (architecture.md)
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            pending: dict[Future, Plan] = {pool.submit(_export_kitti_chunk, plan, options, str(partial), chunk): plan
                                           for plan, chunk in tasks}
            while pending:
                ready, _ = wait(pending, return_when=FIRST_COMPLETED)
                for f in ready:
                    finished(pending.pop(f), f.result())
    rows.sort(key=lambda r: r["stem"])
    text = frames_csv(rows)
    write_bytes(partial / "training" / "frames.csv", text.encode())
    splits = sorted({*LOADER_SPLITS, *(s.split for s in sources)})
    for name in splits:
        stems = [r["stem"] for r in rows if r["split"] == name]
        write_bytes(partial / "ImageSets" / f"{name}.txt", "".join(f"{s}\n" for s in stems).encode())
    (out / MARKER).unlink(missing_ok=True)
    for sub in ("training", "ImageSets"):
        _replace_dir(partial / sub, out / sub)
    shutil.rmtree(out / PARTIAL_DIR)
    write_bytes(out / MARKER, json_text(marker).encode())
    log.info("exported %d frame(s) of %d episode(s) -> %s", len(rows), len(sources), out)
    return ExportResult((out,), (), done)


def _ours(out: Path) -> bool:
    """Whether ``out`` holds a KITTI export of cosim's (its marker), which a new export may replace."""
    try:
        return json.loads((out / MARKER).read_text()).get("format") == "kitti"
    except (OSError, ValueError, AttributeError):
        return False


def frames_csv(rows: Sequence[dict]) -> str:
    """frames.csv's text: :data:`FRAMES_COLUMNS`, one row per frame in stem order."""
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=FRAMES_COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


@register_format
class KittiFormat(ExportFormat):
    """``cosim export --format kitti``: the whole export is one KITTI folder, so it runs its own driver
    (:func:`run_kitti_export`) instead of the per-sequence one."""

    name: ClassVar[str] = "kitti"
    driver = staticmethod(run_kitti_export)
