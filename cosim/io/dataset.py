"""A map-style dataset over episodes for training without MCAP knowledge (no torch needed).

    from cosim.io.dataset import CooperativeDataset

    ds = CooperativeDataset(["out/a.mcap", "out/b.mcap"])        # one sample per (episode, tick, ego)
    sample = ds[0]
    sample["boxes"]      # (M, 7) float32 [x, y, z, l, w, h, yaw] in the ego LiDAR frame (FLU, metres, rad)
    sample["lidar"][i]   # (N_i, 4) float32 x, y, z, intensity of agent i, in agent i's LiDAR frame
    sample["lidar_to_ego"][i]                                    # (4, 4) ego LiDAR <- agent i's LiDAR

With ``cameras=True`` also, per agent i: ``images[i]`` (one array per camera), ``intrinsics[i]`` (n, 3, 3),
``distortions[i]`` (n, 5) Brown-Conrady D (zeros: pinhole; project points with
``cosim.geometry.project_to_image(points_optical, K, D)``) and ``camera_to_ego[i]`` (n, 4, 4, optical frames).

LiDAR motion compensation (``lidar``), as the exports do (docs/exports.md, :mod:`cosim.io.deskew`):
``"tick"`` (default) moves every point of a sweep into the sensor frame at the tick with the recorded
motion; ``"objects"`` also moves the points of each moving labelled object to where it is at the tick;
``"raw"`` gives the points as fired (each in the sensor frame of its firing time).

It is a plain sequence (``__len__``, ``__getitem__``) returning numpy arrays, so
``torch.utils.data.DataLoader(ds, batch_size=..., collate_fn=...)`` takes it as it is (samples hold
lists of different lengths: give a ``collate_fn``, see examples/train_loop.py). Episodes are opened
lazily in each process that reads them, so DataLoader workers each open their own files.

Defaults are the AirV2X-Perception paper's (section 4.2): detection range x in [-140.8, 140.8] m,
y in [-40, 40] m, z in [-3, 1] m around the ego LiDAR; agents within 120 m (vehicles, RSUs) or 180 m
(drones) of the ego take part. Frames and units are cosim's (docs/episode_format.md): right-handed,
x forward, y left, z up.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError
from cosim.io.decode import quat_to_matrix
from cosim.io.deskew import deskew_tick, objects_to_tick_of
from cosim.io.reader import Episode, open_episode

PAPER_LIDAR_RANGE_M = (-140.8, -40.0, -3.0, 140.8, 40.0, 1.0)
PAPER_COMM_RANGE_M = {"vehicle": 120.0, "rsu": 120.0, "drone": 180.0}
#: LiDAR motion compensation of a sample's sweeps (module docstring).
LIDAR_MODES: tuple[str, ...] = ("tick", "objects", "raw")


@dataclass(frozen=True)
class SampleKey:
    """Which sample an index is: episode file, tick, ego agent."""

    episode: Path
    tick: int
    ego: str


class CooperativeDataset:
    """Samples over (episode, tick, ego agent); see the module docstring for what a sample holds.

    ``ego_kinds``: agent kinds that serve as ego (default vehicles). ``classes``: object classes kept as
    boxes (default every object class of the episode). ``cameras``: also load every agent's images,
    intrinsics and camera poses. ``every``: keep ticks 0, every, 2 every... ``lidar``: motion compensation
    (:data:`LIDAR_MODES`). A sample is :meth:`assemble` of :meth:`read_tick` (the tick's record, the same
    for every ego), which lets a cache of records give the same samples without reading MCAP.
    """

    def __init__(self, episodes: Sequence[str | Path], *, ego_kinds: Sequence[str] = ("vehicle",),
                 classes: Sequence[str] | None = None, cameras: bool = False, every: int = 1,
                 lidar_range_m: Sequence[float] = PAPER_LIDAR_RANGE_M,
                 comm_range_m: dict[str, float] | None = None, include_ego_box: bool = False,
                 lidar: str = "tick"):
        if lidar not in LIDAR_MODES:
            raise InputError(f"unknown lidar compensation {lidar!r}; choose one of {', '.join(LIDAR_MODES)}")
        if every < 1:
            raise InputError(f"every must be >= 1, got {every}")
        if len(lidar_range_m) != 6:
            raise InputError(f"lidar_range_m needs 6 numbers (xmin, ymin, zmin, xmax, ymax, zmax), got {lidar_range_m}")
        self.paths = [Path(p) for p in episodes]
        self.ego_kinds = tuple(ego_kinds)
        self.classes = tuple(classes) if classes is not None else None
        self.cameras = cameras
        self.lidar_range_m = tuple(float(v) for v in lidar_range_m)
        self.comm_range_m = dict(comm_range_m or PAPER_COMM_RANGE_M)
        self.include_ego_box = include_ego_box
        self.lidar = lidar
        self.keys: list[SampleKey] = []
        self._agents: dict[Path, list[str]] = {}
        self._open: dict[Path, Episode] = {}
        self._pid = os.getpid()
        for path in self.paths:
            with open_episode(path) as ep:
                agents = list(ep.agents)
                self._agents[path] = agents
                egos = [a for a in agents if a.rsplit("_", 1)[0] in self.ego_kinds]
                self.keys.extend(SampleKey(path, k, e) for k in range(0, ep.n_ticks, every) for e in egos)

    def __len__(self) -> int:
        return len(self.keys)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_open"] = {}
        return state

    def _episode(self, path: Path) -> Episode:
        if self._pid != os.getpid():  # a DataLoader worker: never share file handles across processes
            self._open, self._pid = {}, os.getpid()
        if path not in self._open:
            self._open[path] = open_episode(path)
        return self._open[path]

    def close(self) -> None:
        for ep in self._open.values():
            ep.close()
        self._open = {}

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"sample {index} out of range: {len(self)} samples")
        key = self.keys[index]
        sample = self.assemble(self.read_tick(key.episode, key.tick), key.ego)
        if self.cameras:
            ep = self._episode(key.episode)
            topics = ["/tf"] + [f"/{a}/{c}/{what}" for a in sample["agents"] for c in ep.cameras(a)
                                for what in ("image", "calibration")]
            tick = ep.tick(key.tick, topics=topics)
            ego_from_map = np.linalg.inv(tick.transforms.to_root(self._lidar_frame(tick, key.ego)))
            sample.update(self._images(ep, tick, sample["agents"], ego_from_map))
        return sample

    @staticmethod
    def _lidar_frame(tick: Any, agent: str) -> str:
        return f"{agent}/lidar" if f"/{agent}/lidar" in tick else f"{agent}/base_link"

    def read_tick(self, episode: str | Path, tick_index: int) -> dict[str, Any]:
        """Everything the samples of one tick need, for every ego alike: ``agents``, ``map_from`` (A, 4, 4)
        ``map <- <agent>/lidar`` (or base_link without a LiDAR), per agent ``lidar`` (N, 4) float32 (x, y, z
        compensated per :attr:`lidar`, intensity), ``lidar_class`` and ``lidar_instance``, and the labels
        (``label_*``: track ids, classes, centres, quaternions and sizes in map; ``agent_tracks``)."""
        path = Path(episode)
        ep = self._episode(path)
        agents = self._agents[path]
        topics = ["/tf", "/labels/objects"] + [f"/{a}/lidar" for a in agents if f"/{a}/lidar" in ep.topics]
        if self.lidar != "raw":  # the body rates of deskew_tick
            topics += [f"/{a}/imu" for a in agents if f"/{a}/imu" in ep.topics]
        tick = ep.tick(tick_index, topics=topics)
        tf = tick.transforms
        rec: dict[str, Any] = {
            "episode": str(path), "tick": int(tick_index), "t_ns": int(tick.t_ns), "agents": list(agents),
            "map_from": np.stack([tf.to_root(self._lidar_frame(tick, a)) for a in agents]),
            "lidar": [], "lidar_class": [], "lidar_instance": [],
        }
        for a in agents:
            if f"/{a}/lidar" in tick:
                p = tick.points(a).points
                if self.lidar == "raw":
                    xyz = np.stack([p["x"], p["y"], p["z"]], axis=1)
                else:
                    xyz = deskew_tick(tick, a)
                    if self.lidar == "objects":
                        xyz = objects_to_tick_of(tick, a, xyz)
                cloud = np.empty((len(p), 4), np.float32)
                cloud[:, :3] = xyz
                cloud[:, 3] = p["intensity"]
                rec["lidar"].append(cloud)
                rec["lidar_class"].append(np.asarray(p["class_id"], np.uint8))
                rec["lidar_instance"].append(np.asarray(p["instance_id"], np.int64))
            else:
                rec["lidar"].append(np.zeros((0, 4), np.float32))
                rec["lidar_class"].append(np.zeros(0, np.uint8))
                rec["lidar_instance"].append(np.zeros(0, np.int64))
        labels = tick.labels
        rec.update({
            "label_track_ids": np.asarray(labels.track_ids, np.int64), "label_classes": list(labels.classes),
            "label_centers": np.asarray(labels.centers_m, np.float64).reshape(-1, 3),
            "label_rotations": np.asarray(labels.rotations, np.float64).reshape(-1, 4),
            "label_sizes": np.asarray(labels.sizes_m, np.float64).reshape(-1, 3),
            "agent_tracks": {a["agent_id"]: int(a["track_id"]) for a in labels.agents
                             if a.get("track_id") is not None},
        })
        return rec

    def assemble(self, rec: dict[str, Any], ego: str) -> dict[str, Any]:
        """The sample of ego ``ego`` from a tick's record (:meth:`read_tick`)."""
        agents = rec["agents"]
        map_from = dict(zip(agents, rec["map_from"], strict=True))
        ego_from_map = np.linalg.inv(map_from[ego])
        ego_xyz = map_from[ego][:3, 3]
        chosen = [ego] + [
            a for a in agents if a != ego
            and np.linalg.norm(map_from[a][:3, 3] - ego_xyz) <= self.comm_range_m.get(a.rsplit("_", 1)[0], np.inf)
        ]
        at = [agents.index(a) for a in chosen]
        sample: dict[str, Any] = {
            "episode": rec["episode"], "tick": rec["tick"], "t_ns": rec["t_ns"], "ego": ego, "agents": chosen,
            "lidar_to_ego": np.stack([ego_from_map @ map_from[a] for a in chosen]),
            "lidar": [rec["lidar"][i] for i in at], "lidar_class": [rec["lidar_class"][i] for i in at],
            "lidar_instance": [rec["lidar_instance"][i] for i in at],
        }
        sample.update(self._boxes(rec, ego_from_map, ego))
        return sample

    def _boxes(self, rec: dict[str, Any], ego_from_map: np.ndarray, ego: str) -> dict[str, np.ndarray]:
        ego_track = rec["agent_tracks"].get(ego)
        keep = []
        boxes = []
        lo, hi = np.array(self.lidar_range_m[:3]), np.array(self.lidar_range_m[3:])
        for i, track in enumerate(rec["label_track_ids"]):
            if self.classes is not None and rec["label_classes"][i] not in self.classes:
                continue
            if not self.include_ego_box and ego_track is not None and int(track) == int(ego_track):
                continue
            c = ego_from_map[:3, :3] @ rec["label_centers"][i] + ego_from_map[:3, 3]
            if not ((c >= lo) & (c <= hi)).all():
                continue
            r = ego_from_map[:3, :3] @ quat_to_matrix(rec["label_rotations"][i])
            boxes.append([*c, *rec["label_sizes"][i], np.arctan2(r[1, 0], r[0, 0])])
            keep.append(i)
        return {
            "boxes": np.asarray(boxes, np.float32).reshape(-1, 7),
            "track_ids": np.asarray([int(rec["label_track_ids"][i]) for i in keep], np.int64),
            "classes": [rec["label_classes"][i] for i in keep],
        }

    def _images(self, ep: Episode, tick: Any, agents: list[str], ego_from_map: np.ndarray) -> dict[str, Any]:
        out: dict[str, Any] = {"camera_names": [], "images": [], "intrinsics": [], "distortions": [],
                               "camera_to_ego": []}
        for a in agents:
            names = [c for c in ep.cameras(a) if f"/{a}/{c}/image" in tick]
            out["camera_names"].append(names)
            out["images"].append([tick.image(a, c).array for c in names])
            cals = [tick.calibration(a, c) for c in names]
            out["intrinsics"].append(np.stack([c.K for c in cals]) if names else np.zeros((0, 3, 3)))
            # the lens of each camera (plumb_bob k1, k2, p1, p2, k3; zeros: a pinhole), as
            # cosim.geometry.project_to_image takes it
            out["distortions"].append(np.array([c.D if c.distorted else np.zeros(5) for c in cals],
                                               np.float64).reshape(-1, 5))
            poses = [ego_from_map @ tick.transforms.to_root(f"{a}/{c}/optical") for c in names]
            out["camera_to_ego"].append(np.stack(poses) if poses else np.zeros((0, 4, 4)))
        return out
