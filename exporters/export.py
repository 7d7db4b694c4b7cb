"""``cosim export``: episodes into the folder layouts that training code already reads (docs/exports.md).

A registry of formats (:data:`FORMATS`; ``airv2x`` and ``opv2v`` register themselves) and one driver,
:func:`run_export`, that every format shares:

- SOURCE is one episode or a batch folder (its manifest gives each episode's split);
- each episode becomes one sequence named like a date-time derived from the episode's sha256;
- a sequence is written under ``<out>/.cosim-partial/`` and renamed into place when complete, with a
  marker (:data:`MARKER`) holding the source's sha256 and size and the export options, so a complete
  export of the same source is skipped and a crash never leaves a folder that looks complete;
- the ticks of an episode are cut into chunks that ``workers`` processes write in parallel.

Episodes are read only through :mod:`cosim.io`. The conventions of the target formats live in
:mod:`cosim.exporters.carla_frames`.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import math
import multiprocessing
import os
import re
import shutil
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from cosim.exporters import carla_frames as cf
from cosim.exporters.export_io import (
    is_rgb8_png,
    jpeg_components,
    json_text,
    npz_bytes,
    pcd_binary,
    png_bytes,
    write_bytes,
)
from cosim.exporters.undistort import PinholeRemap, pinhole_remap
from pydantic import BaseModel, ConfigDict, Field

import cosim
from cosim.cli_args import check_output_folder
from cosim.errors import CosimError, InputError
from cosim.io import Episode, Objects, Tick, open_episode
from cosim.io.decode import parse_proto
from cosim.io.deskew import deskew_tick, objects_to_tick_of
from cosim.io.manifest import latest_records, sha256_file

log = logging.getLogger(__name__)

MARKER = ".cosim_export.json"
PARTIAL_DIR = ".cosim-partial"
#: The evaluation scripts take the first match of this anywhere in a file's path as the sequence.
DATE_LIKE = re.compile(r"\d{4}_\d{2}_\d{2}_\d{2}_\d{2}_\d{2}")
SEQUENCE_EPOCH = dt.datetime(2000, 1, 1)
SEQUENCE_SPAN_S = 20 * 365 * 86400  # sequence names fall in 2000..2019: plainly not recording times
BEV_CELL_M = 0.25  # [m] the AirV2X map resolution
BEV_PIXELS = 512  # per side: 128 m x 128 m centred on the agent
#: Per-point labels written beside each exported point cloud, in the PCD's point order.
LIDAR_LABELS_DTYPE = np.dtype([("class_id", "<u1"), ("instance_id", "<u4"), ("ring", "<u2")])
#: Threads per export process writing a tick's agents (PNG/zlib and numpy release the GIL).
AGENT_THREADS = min(4, os.cpu_count() or 1)
#: Agent kinds of cosim episodes (docs/episode_format.md section 2).
AGENT_KINDS = ("vehicle", "rsu", "drone")
#: cosim split names whose folders the loaders read (each format maps them to its own folder names)
LOADER_SPLITS = frozenset({"train", "val", "test"})
#: Agents whose clouds are exported in the level frame at the LiDAR (:func:`level_frame`): a drone tilts as it
#: accelerates and an RSU's LiDAR may be mounted tilted, while the loaders keep a box's yaw only in the LiDAR
#: frame. A vehicle keeps its LiDAR's frame: it stands on the road like the objects around it.
LEVEL_CLOUD_KINDS = ("rsu", "drone")


def level_frame(map_from_sensor: np.ndarray, map_from_base: np.ndarray) -> np.ndarray:
    """map <- the frame at the sensor's origin with z up and x along the sensor's heading (the horizontal
    part of its x axis; of the agent's x axis when the sensor looks straight up or down)."""
    x = map_from_sensor[:3, 0] if np.hypot(*map_from_sensor[:2, 0]) > 1e-6 else map_from_base[:3, 0]
    yaw = math.atan2(x[1], x[0])
    out = np.eye(4)
    out[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    out[:3, 3] = map_from_sensor[:3, 3]
    return out


class ExportOptions(BaseModel):
    """What an export writes, beyond the format's fixed content. Part of the completeness marker."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    every: int = Field(1, ge=1)  # keep ticks 0, every, 2 every, ...
    masks: bool = False  # semantic and instance images beside the camera images (AirV2X; costs export time)
    # LiDAR points as fired (each in the sensor frame of its firing time) instead of compensated to the tick's
    # sensor pose with the recorded motion (cosim.io.deskew; docs/exports.md)
    raw_lidar: bool = False
    # move the points of each moving labelled object to where it is at the tick, with its recorded velocity
    # (cosim.io.deskew.objects_to_tick; docs/exports.md), as CARLA's LiDAR (one instant per sweep) recorded both
    # datasets; False keeps the objects' own motion over the sweep (nuScenes-style); None: True unless raw_lidar
    objects_at_tick: bool | None = None
    # camera files as lossless PNG even where the episode stored JPEG (8 times the bytes; the same pixels)
    png_images: bool = False

    def resolved(self) -> ExportOptions:
        """These options with the defaults that depend on others filled in (what the marker records)."""
        if self.objects_at_tick is None:
            return self.model_copy(update={"objects_at_tick": not self.raw_lidar})
        return self


# ------------------------------------------------------------------------------------- registry


class ExportFormat:
    """One target layout. Subclasses set :attr:`name` and implement the three writers; they are
    constructed once per process and sequence and must not keep state between ticks."""

    name: ClassVar[str] = ""
    #: cosim split name -> the folder name this format's loaders expect.
    split_names: ClassVar[dict[str, str]] = {}
    #: A layout that is not one folder per sequence (KITTI's one folder of frames) runs its own driver, called
    #: with :func:`run_export`'s arguments; None: the shared one.
    driver: ClassVar[Callable[..., ExportResult] | None] = None

    def __init__(self, seq: SequenceInfo, options: ExportOptions, root: Path):
        self.seq = seq
        self.options = options
        self.root = root  # the partial folder that becomes <out>/<split>/<sequence>

    @classmethod
    def split_dir(cls, split: str) -> str:
        return cls.split_names.get(split, split)

    @classmethod
    def extra_roots(cls, split: str, sequence: str) -> list[Path]:
        """Folders outside ``<split>/<sequence>`` this format writes, relative to the export root; they are
        written under :meth:`staged` and renamed into place just before the sequence folder."""
        return []

    def staged(self, relative: Path) -> Path:
        """Where an :meth:`extra_roots` folder is written while the sequence is partial."""
        return self.root.parent / f"{self.root.name}.extra" / relative

    def write_sequence(self, ep: Episode) -> None:
        """Files once per sequence (conditions, protocol), written before any tick."""

    def warnings(self) -> list[str]:
        """What a user of this sequence's loader must know (one line each; ``cosim export`` prints them)."""
        return []

    def write_tick(self, view: TickView) -> None:
        raise NotImplementedError


FORMATS: dict[str, type[ExportFormat]] = {}


def register_format(cls: type[ExportFormat]) -> type[ExportFormat]:
    """Class decorator: add a format to :data:`FORMATS` (a second one of the same name is an error)."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    if cls.name in FORMATS and FORMATS[cls.name] is not cls:
        raise ValueError(f"export format {cls.name!r} is registered twice ({FORMATS[cls.name].__name__}, "
                         f"{cls.__name__})")
    FORMATS[cls.name] = cls
    return cls


def get_format(name: str) -> type[ExportFormat]:
    """The format registered as ``name`` (the built-in ones register when :mod:`cosim.exporters` is imported)."""
    try:
        return FORMATS[name]
    except KeyError:
        raise InputError(f"unknown export format {name!r}; known: {', '.join(sorted(FORMATS))}") from None


# ------------------------------------------------------------------------------------- sources


@dataclass(frozen=True)
class Source:
    """One episode to export: its file, split, sha256 and size."""

    path: Path
    split: str
    sha256: str
    size_bytes: int
    sweep: str | None = None  # the batch's sweep name and episode id (from its manifest), None for a file
    episode: str | None = None


def find_sources(source: Path, split: str | None = None) -> list[Source]:
    """The episodes of SOURCE: one ``.mcap`` file (split ``split`` or ``train``) or a batch folder, whose
    manifest gives each finished episode's split (``split`` then overrides it)."""
    source = Path(source)
    if source.is_file():
        return [Source(source, split or "train", sha256_file(source), source.stat().st_size)]
    if not source.is_dir():
        raise InputError(f"no episode file or batch folder at {source}")
    records = latest_records(source)
    if not records:
        raise InputError(f"{source} is a folder without a batch manifest (manifest*.jsonl); give an episode "
                         "file or a folder written by `cosim batch`")
    out = []
    for rec in records.values():
        path = source / str(rec.get("file", ""))
        if rec.get("status") != "done" or not path.is_file():
            log.warning("%s: episode %s is not finished (status %s); skipped", source, rec["episode"],
                        rec.get("status"))
            continue
        size = path.stat().st_size
        sha = rec.get("sha256") if rec.get("size_bytes") == size else None
        out.append(Source(path, split or str(rec.get("split") or "train"), sha or sha256_file(path), size,
                          rec.get("sweep"), rec.get("episode")))
    if not out:
        raise InputError(f"{source}: the manifest lists no finished episode")
    return sorted(out, key=lambda s: str(s.path))


def sequence_name(sha256: str) -> str:
    """A date-time-like name ``YYYY_MM_DD_HH_MM_SS`` derived from an episode's sha256 (the layouts'
    loaders parse sequence folders as date-times; this one is an identity, not a recording time)."""
    seconds = int(sha256[:15], 16) % SEQUENCE_SPAN_S
    return (SEQUENCE_EPOCH + dt.timedelta(seconds=seconds)).strftime("%Y_%m_%d_%H_%M_%S")


def sequence_names(sources: Sequence[Source]) -> list[str]:
    """:func:`sequence_name` of each source; a clash (another episode, same name) moves on by a second."""
    taken: dict[str, str] = {}
    names = []
    for s in sources:
        name = sequence_name(s.sha256)
        while name in taken and taken[name] != s.sha256:
            t = dt.datetime.strptime(name, "%Y_%m_%d_%H_%M_%S") + dt.timedelta(seconds=1)
            name = t.strftime("%Y_%m_%d_%H_%M_%S")
        taken[name] = s.sha256
        names.append(name)
    return names


# ------------------------------------------------------------------------------------- agents


@dataclass(frozen=True)
class SequenceInfo:
    """What every writer of a sequence needs to know beyond one tick."""

    name: str
    split: str
    source: Source
    ticks: tuple[int, ...]  # exported tick indices
    agents: tuple[str, ...]  # cosim agent ids
    kinds: dict[str, str]  # agent id -> vehicle | rsu | drone
    track_ids: dict[str, int | None]  # agent id -> its track id (None for RSUs)
    metadata: dict[str, Any] = field(repr=False)
    world: dict[str, Any] = field(repr=False)  # the world.json attachment

    def conditions(self) -> dict[str, Any]:
        """Weather, lighting, environment, drone strategies and agent counts (the devkit keeps none)."""
        md = self.metadata
        counts = {k: sum(1 for a in self.agents if self.kinds[a] == k) for k in AGENT_KINDS}
        return {
            "sequence": self.name,
            "weather": md.get("weather"),
            "lighting": md.get("lighting"),
            "environment": md.get("environment"),
            "strategies": list(md.get("strategies") or []),
            "agent_counts": counts,
            # the sweep an episode of a batch came from (its base scenario, e.g. ``paper``, is ``base_scenario``)
            "scenario": self.source.sweep or md.get("scenario"),
            "base_scenario": md.get("scenario"),
            "sweep": self.source.sweep,
            "episode": self.source.episode,
            "seed": md.get("seed"),
            "tick_hz": md.get("tick_hz"),
            "ticks": list(self.ticks),
            "source": {"file": self.source.path.name, "sha256": self.source.sha256,
                       "size_bytes": self.source.size_bytes},
            "agents": {a: {"kind": self.kinds[a], "track_id": self.track_ids[a]} for a in self.agents},
        }


def agent_kind(agent_id: str) -> str:
    kind = agent_id.rsplit("_", 1)[0]
    if kind not in AGENT_KINDS:
        raise CosimError(f"agent {agent_id!r} is of no known kind ({', '.join(AGENT_KINDS)})")
    return kind


def sequence_info(ep: Episode, source: Source, name: str, every: int) -> SequenceInfo:
    if not ep.metadata.get("sensors_enabled", False):
        raise InputError(f"{source.path}: a labels-only episode (sensors_enabled false); the dataset layouts "
                         "need LiDAR and camera data: generate it with sensors")
    first = ep.tick(0, topics="/labels/objects").labels
    tracks = {a["agent_id"]: a.get("track_id") for a in first.agents}
    agents = tuple(ep.agents)
    world = json.loads(ep.attachment("world.json")) if "world.json" in ep.attachments else {}
    return SequenceInfo(name, source.split, source, tuple(range(0, ep.n_ticks, every)), agents,
                        {a: agent_kind(a) for a in agents}, {a: tracks.get(a) for a in agents},
                        ep.metadata, world)


# ------------------------------------------------------------------------------------- tick view


@dataclass
class CameraView:
    """One camera of one agent at one tick; images are decoded on first use."""

    tick: Tick
    agent_id: str
    name: str
    map_from_camera: np.ndarray  # (4, 4) map <- camera body (FLU, x along the optical axis)
    K: np.ndarray  # (3, 3) pinhole intrinsic of every image this view gives
    width: int
    height: int
    #: Resampling of a distorting camera's images onto the pinhole ``K`` (docs/exports.md); None: a pinhole.
    lens: PinholeRemap | None = None

    def rgb_png(self) -> bytes:
        """The RGB image as an 8-bit RGB PNG: the episode's own bytes when they already are one (and the
        camera has no lens distortion to undo)."""
        raw = self.tick.raw(f"/{self.agent_id}/{self.name}/image")
        if raw.schema_name == "foxglove.CompressedImage" and self.lens is None:
            msg = parse_proto(raw.schema_name, raw.data, raw.schema_data)
            if msg.format == "png" and is_rgb8_png(msg.data):
                return bytes(msg.data)
        a = self.tick.image(self.agent_id, self.name).array
        rgb = np.ascontiguousarray(a[..., :3]) if a.ndim == 3 else np.stack([a] * 3, -1)
        return png_bytes(rgb if self.lens is None else self.lens.bilinear(rgb))

    def image_file(self, keep_jpeg: bool = True) -> bytes:
        """The RGB image as the layouts' camera file (named ``.png``): the episode's own JPEG bytes when it stored
        a 3-channel JPEG, the camera has no lens distortion to undo and ``keep_jpeg`` (the loaders open camera
        files with Pillow or OpenCV, which decode by content: the same pixels as a PNG of the decoded JPEG, at
        an eighth of its bytes and none of its encoding time; docs/exports.md); else :meth:`rgb_png`."""
        if keep_jpeg and self.lens is None:
            raw = self.tick.raw(f"/{self.agent_id}/{self.name}/image")
            if raw.schema_name == "foxglove.CompressedImage":
                msg = parse_proto(raw.schema_name, raw.data, raw.schema_data)
                if msg.format == "jpeg" and jpeg_components(msg.data) == 3:
                    return bytes(msg.data)
        return self.rgb_png()

    def has(self, what: str) -> bool:
        return f"/{self.agent_id}/{self.name}/{what}" in self.tick

    def depth_m(self) -> np.ndarray:
        d = self.tick.depth(self.agent_id, self.name).depth_m
        return d if self.lens is None else self.lens.nearest_of(d, np.nan)

    def semantic(self) -> np.ndarray:
        s = self.tick.semantic(self.agent_id, self.name).array
        return s if self.lens is None else self.lens.nearest_of(s, 0)

    def instance(self) -> np.ndarray:
        i = self.tick.instance(self.agent_id, self.name).array
        return i if self.lens is None else self.lens.nearest_of(i, 0)


@dataclass
class AgentView:
    """One agent at one tick, in cosim's frames (``map`` ENU)."""

    tick: Tick
    agent_id: str
    kind: str
    raw_lidar: bool
    track_id: int | None
    map_from_base: np.ndarray  # (4, 4)
    velocity_mps: np.ndarray  # (3,)
    extra: dict[str, Any]
    objects_at_tick: bool = False

    @cached_property
    def map_from_lidar(self) -> np.ndarray | None:
        """The LiDAR's own frame at the tick (map <- lidar), or None without a LiDAR."""
        if f"/{self.agent_id}/lidar" not in self.tick:
            return None
        pc = self.tick.points(self.agent_id)
        return self.tick.transforms.to_root(pc.frame_id)

    @cached_property
    def map_from_cloud(self) -> np.ndarray | None:
        """The frame the exported cloud, ``lidar_pose`` and camera extrinsics are in (map <- cloud): the
        LiDAR's own for vehicles; for RSUs and drones the level frame at the LiDAR with its heading
        (:func:`level_frame`), as both loaders turn boxes into yaw-only boxes in this frame."""
        lidar = self.map_from_lidar
        if lidar is None or self.kind not in LEVEL_CLOUD_KINDS:
            return lidar
        return level_frame(lidar, self.map_from_base)

    @cached_property
    def points(self) -> np.ndarray | None:
        """The sweep: structured array with ``x y z intensity class_id instance_id`` in the LiDAR frame."""
        return self.tick.points(self.agent_id).points if f"/{self.agent_id}/lidar" in self.tick else None

    def lidar_files(self) -> tuple[bytes, bytes]:
        """The sweep as a binary PCD in the CARLA axes of :attr:`map_from_cloud` (intensity in red) and its
        per-point labels (``.npz`` of the fields of :data:`LIDAR_LABELS_DTYPE`, one array each, same order).
        Points are compensated to the sensor pose at the tick (:func:`cosim.io.deskew.deskew_tick`) unless the
        export's ``raw_lidar`` asks for them as fired."""
        pts = self.points
        raw = np.stack([pts["x"], pts["y"], pts["z"]], axis=1)
        xyz = raw if self.raw_lidar else deskew_tick(self.tick, self.agent_id)
        if self.objects_at_tick and not self.raw_lidar:
            xyz = objects_to_tick_of(self.tick, self.agent_id, xyz)
        lidar, cloud = self.map_from_lidar, self.map_from_cloud
        if cloud is not lidar:
            xyz = xyz @ (cloud[:3, :3].T @ lidar[:3, :3]).T  # same origin: a rotation into the level frame
        names = pts.dtype.names or ()
        labels = {f: (pts[f] if f in names else np.zeros(len(pts))).astype(LIDAR_LABELS_DTYPE[f])
                  for f in LIDAR_LABELS_DTYPE.names or ()}
        return pcd_binary(cf.carla_points(xyz), pts["intensity"]), npz_bytes(labels)

    def cameras(self, names: Sequence[str]) -> list[CameraView]:
        out = []
        for name in names:
            if f"/{self.agent_id}/{name}/image" not in self.tick:
                continue
            cal = self.tick.calibration(self.agent_id, name)
            if cal.distorted and cal.distortion_model != "plumb_bob":
                raise CosimError(f"{self.agent_id} {name}: lens model {cal.distortion_model!r} (D = {cal.D.tolist()}); "
                                 "the export undistorts plumb_bob only")
            out.append(CameraView(self.tick, self.agent_id, name,
                                  self.tick.transforms.to_root(f"{self.agent_id}/{name}"),
                                  cal.K, cal.width, cal.height, pinhole_remap(cal.width, cal.height, cal.K, cal.D)))
        return out

    def visibility(self) -> dict[int, dict[str, Any]]:
        """track id -> {lidar_points, pixels} of what this agent sees (docs/episode_format.md 3.10)."""
        topic = f"/{self.agent_id}/visibility"
        if topic not in self.tick:
            return {}
        return {int(o["track_id"]): o for o in self.tick[topic].get("objects", [])}

    def optional(self, what: str) -> Any:
        """The decoded ``/<agent>/<what>`` message (``imu``, ``gnss``) or None."""
        return self.tick.get(f"/{self.agent_id}/{what}")


@dataclass
class TickView:
    """One tick of a sequence: labels, agents, and the sequence it belongs to."""

    seq: SequenceInfo
    tick: Tick
    camera_names: dict[str, list[str]]  # agent -> camera names in the file
    raw_lidar: bool = False  # ExportOptions.raw_lidar
    objects_at_tick: bool = False  # ExportOptions.objects_at_tick

    @property
    def index(self) -> int:
        return self.tick.index

    @cached_property
    def labels(self) -> Objects:
        return self.tick.labels

    @cached_property
    def agents(self) -> list[AgentView]:
        by_id = {a["agent_id"]: a for a in self.labels.agents}
        out = []
        for agent_id in self.seq.agents:
            a = by_id.get(agent_id, {})
            out.append(AgentView(
                self.tick, agent_id, self.seq.kinds[agent_id], self.raw_lidar, self.seq.track_ids[agent_id],
                self.tick.transforms.to_root(f"{agent_id}/base_link"),
                np.asarray(a.get("velocity_mps", (0.0, 0.0, 0.0)), np.float64), dict(a.get("extra") or {}),
                self.objects_at_tick,
            ))
        return out

    def for_each_agent(self, write: Callable[[AgentView], None]) -> None:
        """``write(agent)`` for every agent, in :data:`AGENT_THREADS` threads; each writes its own files."""
        _ = self.labels, self.agents, self.snapshot, _static_raster(self.seq)  # shared state first, once
        if AGENT_THREADS == 1:
            for agent in self.agents:
                write(agent)
            return
        with ThreadPoolExecutor(AGENT_THREADS) as pool:
            for f in [pool.submit(write, agent) for agent in self.agents]:
                f.result()

    def object_rotations(self) -> list[np.ndarray]:
        from cosim.io.decode import quat_to_matrix

        return [quat_to_matrix(q) for q in self.labels.rotations]

    @cached_property
    def snapshot(self) -> Any:
        return self.tick.snapshot()

    def bev_maps(self, agent: AgentView) -> dict[str, np.ndarray]:
        """The agent's BEV layers, 512 x 512 bool, 0.25 m per pixel, centred on its ``base_link``,
        level and yaw-aligned, in CARLA's image orientation: row = 256 - 4 x, column = 256 + 4 y with
        (x forward, y right) [m]. Keys: every static layer and object class name of cosim's BEV."""
        from cosim.sensors.bev import render_bev

        half = BEV_PIXELS * BEV_CELL_M / 2
        frame = render_bev(self.snapshot.agent(agent.agent_id), _static_raster(self.seq), self.snapshot.actors,
                           BEV_CELL_M, (half, half))
        # cosim's grid[i, j]: row i along +y (left), column j along +x (forward); CARLA's image[r, c]: row
        # along -x, column along +y_carla = -y; so image[r, c] = grid[n-1-c, n-1-r], every layer in one copy.
        g = frame.grid
        cells = np.ascontiguousarray(g).view(f"V{g.shape[2]}").reshape(g.shape[:2])  # one record per cell
        flipped = np.ascontiguousarray(cells[::-1, ::-1].T).view(np.uint8).reshape(g.shape[1], g.shape[0], -1)
        return {name: flipped[..., k].astype(bool) for k, name in enumerate(frame.layers)}


_RASTERS: dict[str, Any] = {}


def _static_raster(seq: SequenceInfo) -> Any:
    """The static BEV raster of the sequence's world (one per process and episode)."""
    from cosim.sensors.bev import static_raster

    from cosim.world.types import Prism, StaticLayout

    key = seq.source.sha256
    if key not in _RASTERS:
        prisms = tuple(Prism(p[0], tuple(tuple(q) for q in p[1]), p[2], p[3], p[4])
                       for p in seq.world.get("prisms", []))
        _RASTERS.clear()
        _RASTERS[key] = static_raster(StaticLayout(prisms, seq.world.get("ground_z_m", 0.0)), BEV_CELL_M)
    return _RASTERS[key]


def agent_frames(ep: Episode, seq: SequenceInfo, ticks: Sequence[int], raw_lidar: bool = False,
                 objects_at_tick: bool = False, topics: Sequence[str] | None = None) -> Iterator[TickView]:
    """A :class:`TickView` per exported tick in ``ticks`` (reads each tick once, in order), holding ``topics``
    (default all)."""
    cams = {a: ep.cameras(a) for a in seq.agents}
    wanted = set(ticks)
    if not wanted:
        return
    for tick in ep.ticks(topics, start=min(wanted), stop=max(wanted) + 1):
        if tick.index in wanted:
            yield TickView(seq, tick, cams, raw_lidar, objects_at_tick)


def export_topics(ep: Episode, options: ExportOptions) -> list[str]:
    """The episode's topics the AirV2X and OPV2V writers read: all but the agents' BEV grids (the maps are rendered
    from the tick's snapshot) and, without ``masks``, the semantic and instance images, which are most of an
    episode's bytes once decompressed (about four fifths of a default episode's)."""
    skipped = ("/bev",) if options.masks else ("/bev", "/semantic", "/instance")
    return [t for t in ep.topics if not t.endswith(skipped)]


# ------------------------------------------------------------------------------------- driver


@dataclass(frozen=True)
class ExportResult:
    """What :func:`run_export` did: sequences written and skipped, agent-frames written."""

    written: tuple[Path, ...]
    skipped: tuple[Path, ...]
    agent_frames: int
    #: Lines for the user about the written sequences (e.g. more agents than a loader reads by default).
    warnings: tuple[str, ...] = ()


def marker_content(fmt: str, source: Source, options: ExportOptions, seq_name: str) -> dict[str, Any]:
    return {"format": fmt, "sequence": seq_name, "source": {"sha256": source.sha256, "size_bytes": source.size_bytes},
            "options": options.model_dump(), "cosim": cosim.__version__}


def is_complete(folder: Path, expected: dict[str, Any]) -> bool:
    try:
        return json.loads((folder / MARKER).read_text()) == expected
    except (OSError, ValueError):
        return False


def _export_chunk(fmt: str, source: Source, seq_name: str, options: ExportOptions, root: str,
                  ticks: tuple[int, ...]) -> int:
    """Write ``ticks`` of one episode into the partial folder ``root`` (runs in a worker process)."""
    cls = get_format(fmt)
    with open_episode(source.path) as ep:
        seq = sequence_info(ep, source, seq_name, options.every)
        writer = cls(seq, options, Path(root))
        n = 0
        for view in agent_frames(ep, seq, ticks, options.raw_lidar, options.objects_at_tick,
                                 export_topics(ep, options)):
            writer.write_tick(view)
            n += len(seq.agents)
    return n


def _chunks(ticks: Sequence[int], n: int) -> list[tuple[int, ...]]:
    size = max(1, math.ceil(len(ticks) / max(1, n)))
    return [tuple(ticks[i : i + size]) for i in range(0, len(ticks), size)]


def check_output_dir(out: Path) -> None:
    check_output_folder(out)  # a file, or under one: one message before .cosim-partial is made
    m = DATE_LIKE.search(str(out.resolve()))
    if m:
        raise InputError(f"--out {out}: the path holds the date-like {m.group(0)!r}; the devkit's evaluation takes "
                         "the first date-time in a path as the sequence name, so keep them out of the export root")


def run_export(source: Path, fmt: str, out: Path, options: ExportOptions | None = None, *,
               split: str | None = None, workers: int = 1,
               progress: Callable[[int, int], None] | None = None, agents: str | None = None) -> ExportResult:
    """Export SOURCE (an episode or a batch folder) in format ``fmt`` under ``out``.

    Each episode is written in ``ceil(ticks / workers)``-tick chunks by ``workers`` processes into
    ``out/.cosim-partial/``, then renamed to ``out/<split>/<sequence>``; a sequence whose marker says
    it holds this source with these options is skipped. ``progress(done, total)`` counts agent-frames.
    """
    options = options or ExportOptions()
    cls = get_format(fmt)
    if options.raw_lidar and options.objects_at_tick:
        raise InputError("--objects-at-tick moves points of a compensated sweep; it cannot go with --raw-lidar")
    options = options.resolved()
    if cls.driver is not None:
        return cls.driver(Path(source), Path(out), options, split=split, workers=workers,
                          progress=progress, agents=agents)
    if agents is not None:
        raise InputError(f"--agents chooses the egos of --format kitti; {fmt} exports every agent")
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    out = Path(out)
    check_output_dir(out)
    sources = find_sources(Path(source), split)
    for unread in sorted({s.split for s in sources} - LOADER_SPLITS):
        log.warning("%d episode(s) of split %r are exported into %s, which neither loader reads (a sweep "
                    "without splits: puts its episodes in 'all'); give --split train, val or test to choose one",
                    sum(s.split == unread for s in sources), unread, out / cls.split_dir(unread))
    names = sequence_names(sources)
    jobs = []
    skipped: list[Path] = []
    warnings: list[str] = []
    total = 0
    for src, name in zip(sources, names, strict=True):
        final = out / cls.split_dir(src.split) / name
        marker = marker_content(fmt, src, options, name)
        if is_complete(final, marker):
            log.info("%s: complete export of %s already there; skipped", final, src.path.name)
            skipped.append(final)
            continue
        with open_episode(src.path) as ep:
            seq = sequence_info(ep, src, name, options.every)
            partial = out / PARTIAL_DIR / fmt / cls.split_dir(src.split) / name
            for stale in (partial, partial.parent / f"{name}.extra"):
                if stale.exists():
                    shutil.rmtree(stale)
            partial.mkdir(parents=True)
            writer = cls(seq, options, partial)
            writer.write_sequence(ep)
            warnings.extend(writer.warnings())
        jobs.append((src, name, seq, partial, final, marker))
        total += len(seq.ticks) * len(seq.agents)
    done = 0
    if progress:
        progress(0, total)
    tasks = [(j, chunk) for j in jobs for chunk in _chunks(j[2].ticks, workers)]
    remaining = {id(j): sum(1 for t in tasks if t[0] is j) for j in jobs}
    written: list[Path] = []

    def finished(job: tuple, n: int) -> None:
        nonlocal done
        done += n
        if progress:
            progress(done, total)
        remaining[id(job)] -= 1
        if remaining[id(job)] == 0:
            written.append(_finalise(cls, out, job))

    if workers == 1 or len(tasks) <= 1:
        for job, chunk in tasks:
            finished(job, _export_chunk(fmt, job[0], job[1], options, str(job[3]), chunk))
    else:
        ctx = multiprocessing.get_context("spawn")  # never fork after Open3D / zstd threads (architecture.md)
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            pending: dict[Future, tuple] = {
                pool.submit(_export_chunk, fmt, job[0], job[1], options, str(job[3]), chunk): job
                for job, chunk in tasks
            }
            while pending:
                ready, _ = wait(pending, return_when=FIRST_COMPLETED)
                for f in ready:
                    job = pending.pop(f)
                    finished(job, f.result())
    _tidy_partial(out)
    return ExportResult(tuple(written), tuple(skipped), done, tuple(warnings))


def _finalise(cls: type[ExportFormat], out: Path, job: tuple) -> Path:
    """Write the marker, then rename the extra folders and the sequence folder into place."""
    src, name, _seq, partial, final, marker = job
    write_bytes(partial / MARKER, json_text(marker).encode())
    for extra in cls.extra_roots(src.split, name):
        staged = partial.parent / f"{name}.extra" / extra
        if staged.exists():
            _replace_dir(staged, out / extra)
    _replace_dir(partial, final)
    extra_stage = partial.parent / f"{name}.extra"
    if extra_stage.exists():
        shutil.rmtree(extra_stage)
    log.info("exported %s -> %s", src.path.name, final)
    return final


def _replace_dir(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        old = dst.parent / f".{dst.name}.old"
        if old.exists():
            shutil.rmtree(old)
        dst.rename(old)
        src.rename(dst)
        shutil.rmtree(old)
    else:
        src.rename(dst)


def _tidy_partial(out: Path) -> None:
    """Remove empty folders left under ``out/.cosim-partial``."""
    base = out / PARTIAL_DIR
    if not base.exists():
        return
    for d in sorted((p for p in base.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        if not any(d.iterdir()):
            d.rmdir()
    if not any(base.iterdir()):
        base.rmdir()
