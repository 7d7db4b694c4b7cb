"""Ground truth for evaluation, read through :mod:`cosim.io`: episodes of a dataset and, per (tick, ego),
the labelled boxes in the ego's LiDAR frame with which agents see them.

A DATASET is one episode file, a batch folder with a manifest (``cosim batch``: episode ids, splits,
files) or a folder of episode files (ids = file stems, split ``all``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.errors import InputError
from cosim.eval.boxes import footprints, to_frame
from cosim.eval.predictions import SETTINGS
from cosim.io import open_episode

log = logging.getLogger(__name__)

#: The paper's vehicle classes, scored together as "vehicle" (by name: other object classes stay per class).
VEHICLE_CLASSES: tuple[str, ...] = ("car", "van", "truck", "bus", "motorcycle", "bicycle")
#: Conditions an episode is grouped by (keys of :attr:`EpisodeRef.conditions`), in table order.
CONDITIONS: tuple[str, ...] = ("lighting", "weather", "environment", "strategy")
#: Evaluation area in the ego LiDAR frame: half extents x, y [m] (the paper's [-140.8, 140.8] x [-40, 40]).
AREA_HALF_M: tuple[float, float] = (140.8, 40.0)
#: The AirV2X release's z band [m] in the ego LiDAR frame (``cav_lidar_range``), used by ``--compat airv2x``.
RELEASE_Z_BAND_M: tuple[float, float] = (-3.0, 1.0)


@dataclass(frozen=True)
class EpisodeRef:
    """One episode of a dataset: id, file, split and conditions (lighting, weather, environment, strategy)."""

    id: str
    path: Path
    split: str
    conditions: dict[str, str] = field(default_factory=dict)
    agents: tuple[str, ...] = ()
    n_ticks: int = 0
    object_classes: tuple[str, ...] = ()


@dataclass(frozen=True)
class VisibilityRule:
    """An agent sees an object with at least ``min_points`` LiDAR returns or ``min_pixels`` instance pixels
    (summed over its cameras) on it."""

    min_points: int = 1
    min_pixels: int = 1

    def seen(self, entry: dict) -> bool:
        return (int(entry.get("lidar_points", 0)) >= self.min_points
                or sum(int(v) for v in (entry.get("pixels") or {}).values()) >= self.min_pixels)


DEFAULT_RULE = VisibilityRule()


def strategy_label(strategies: list[str]) -> str:
    """One label per episode: its drones' strategy when they share one, ``mixed`` otherwise, ``none`` without drones."""
    kinds = sorted(set(strategies))
    return kinds[0] if len(kinds) == 1 else ("mixed" if kinds else "none")


def episode_ref(eid: str, path: Path, split: str) -> EpisodeRef:
    """Read an episode's metadata into an :class:`EpisodeRef`."""
    with open_episode(path) as ep:
        meta = ep.metadata
        cond = {
            "lighting": str(meta.get("lighting", "?")),
            "weather": str(meta.get("weather", "?")),
            "environment": str(meta.get("environment", "?")),
            "strategy": strategy_label(list(meta.get("strategies") or [])),
        }
        classes = tuple((ep.class_table or {}).get("object_classes", ()))
        return EpisodeRef(eid, path, split, cond, tuple(ep.agents), ep.n_ticks, classes)


def load_dataset(path: Path | str, split: str | None = None) -> list[EpisodeRef]:
    """The episodes of a DATASET (see the module doc), optionally only those of one split."""
    from cosim.io.manifest import latest_records, manifest_files

    path = Path(path)
    refs: list[tuple[str, Path, str]] = []
    if path.is_file():
        refs.append((path.stem, path, "all"))
    elif path.is_dir() and manifest_files(path):
        for rec in latest_records(path).values():
            if rec.get("status") != "done" or not rec.get("file"):
                continue
            f = path / rec["file"]
            if not f.is_file():
                log.warning("%s: manifest lists %s but the file is missing; skipped", path, f)
                continue
            refs.append((rec["episode"], f, str(rec.get("split", "all"))))
    elif path.is_dir():
        refs.extend((f.stem, f, "all") for f in sorted(path.rglob("*.mcap")))
    else:
        raise InputError(f"no dataset at {path}: give an episode file (.mcap) or a batch folder")
    if split is not None:
        splits = sorted({s for _, _, s in refs})
        refs = [r for r in refs if r[2] == split]
        if not refs:
            raise InputError(f"{path}: no episode in split {split!r}; splits present: {', '.join(splits) or 'none'}")
    if not refs:
        raise InputError(f"{path}: no finished episodes found")
    ids = [r[0] for r in refs]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        raise InputError(f"{path}: episode ids {', '.join(dupes)} appear twice (files with the same stem?)")
    return [episode_ref(eid, f, s) for eid, f, s in refs]


@dataclass(frozen=True)
class FrameTruth:
    """Ground truth of one (episode, tick, ego): M objects (every labelled actor but the ego itself).

    ``centers_m`` (M, 3), ``sizes_m`` (M, 3), ``yaws_rad`` (M,) in the ego LiDAR frame; ``in_area``
    (M,): centre inside the evaluation area; ``in_area_release`` (M,): all 8 corners inside the
    release's range (x, y area and z band); ``ego_box`` is the ego's own box (never ground truth);
    ``seen[setting]`` (M,): seen by an agent of that
    collaboration setting (None when the episode has no visibility topics); ``seen_by_agent``:
    agent id -> (M,) bool.
    """

    episode: str
    tick: int
    ego: str
    track_ids: np.ndarray
    classes: tuple[str, ...]
    centers_m: np.ndarray
    sizes_m: np.ndarray
    yaws_rad: np.ndarray
    in_area: np.ndarray
    in_area_release: np.ndarray
    seen: dict[str, np.ndarray] | None
    seen_by_agent: dict[str, np.ndarray] | None
    ego_from_map: np.ndarray  # 4x4
    ego_box: tuple[np.ndarray, np.ndarray, float, str] | None = None  # ego's own centre, size, yaw, class

    def footprints(self, mask: np.ndarray | None = None) -> np.ndarray:
        m = slice(None) if mask is None else mask
        return footprints(self.centers_m[m, :2], self.sizes_m[m, :2], self.yaws_rad[m])


def agent_kind(agent_id: str) -> str:
    return agent_id.rsplit("_", 1)[0]


def _corners_inside_release_range(centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    fp = footprints(centers[:, :2], sizes[:, :2], yaws)
    hx, hy = AREA_HALF_M
    xy_ok = (np.abs(fp[..., 0]) <= hx).all(axis=1) & (np.abs(fp[..., 1]) <= hy).all(axis=1)
    z0, z1 = RELEASE_Z_BAND_M
    z_ok = (centers[:, 2] - sizes[:, 2] / 2 >= z0) & (centers[:, 2] + sizes[:, 2] / 2 <= z1)
    return xy_ok & z_ok


def ego_frame_name(frames: set[str], ego: str) -> str:
    """``<ego>/lidar`` when the episode has it (sensors on), else ``<ego>/base_link``."""
    lidar = f"{ego}/lidar"
    return lidar if lidar in frames else f"{ego}/base_link"


def iter_truth(ref: EpisodeRef, egos: list[str] | None = None, rule: VisibilityRule = DEFAULT_RULE,
               ticks: set[int] | None = None) -> Iterator[FrameTruth]:
    """Ground truth per tick and ego of one episode (egos: given ids, default every vehicle agent)."""
    with open_episode(ref.path) as ep:
        agents = ep.agents
        use = [a for a in agents if agent_kind(a) == "vehicle"] if egos is None else egos
        missing = [e for e in use if e not in agents]
        if missing:
            raise InputError(f"{ref.id}: no agent {', '.join(missing)}; agents: {', '.join(agents)}")
        vis_topics = [f"/{a}/visibility" for a in agents if f"/{a}/visibility" in ep.topics]
        has_vis = len(vis_topics) == len(agents)
        for tick in ep.ticks(topics=["/labels/objects", "/tf", *vis_topics]):
            if ticks is not None and tick.index not in ticks:
                continue
            labels = tick.labels
            seen_tracks: dict[str, set[int]] = {}
            if has_vis:
                for a in agents:
                    seen_tracks[a] = {int(o["track_id"]) for o in tick.visibility(a).get("objects", [])
                                      if rule.seen(o)}
            for ego in use:
                keep = np.array([aid != ego for aid in labels.agent_ids], bool)
                frame = ego_frame_name(tick.transforms.frames, ego)
                ego_from_map = np.linalg.inv(tick.transforms.to_root(frame))
                centers, yaws = to_frame(ego_from_map, labels.centers_m[keep], labels.rotations[keep])
                own = np.nonzero(~keep)[0]
                ego_box = None
                if len(own):
                    oc, oy = to_frame(ego_from_map, labels.centers_m[own[:1]], labels.rotations[own[:1]])
                    ego_box = (oc[0], labels.sizes_m[own[0]], float(oy[0]), labels.classes[own[0]])
                sizes = labels.sizes_m[keep]
                tracks = labels.track_ids[keep]
                hx, hy = AREA_HALF_M
                in_area = (np.abs(centers[:, 0]) <= hx) & (np.abs(centers[:, 1]) <= hy)
                seen = by_agent = None
                if has_vis:
                    by_agent = {a: np.isin(tracks, list(s)) for a, s in seen_tracks.items()}
                    seen = {}
                    for name, kinds in SETTINGS.items():
                        members = [a for a in agents if a == ego or agent_kind(a) in kinds]
                        seen[name] = np.logical_or.reduce([by_agent[a] for a in members]) if members else \
                            np.zeros(len(tracks), bool)
                yield FrameTruth(
                    ref.id, tick.index, ego, tracks,
                    tuple(c for c, k in zip(labels.classes, keep, strict=True) if k),
                    centers, sizes, yaws, in_area, _corners_inside_release_range(centers, sizes, yaws),
                    seen, by_agent, ego_from_map, ego_box,
                )


def require_visibility(truth: FrameTruth, what: str) -> dict[str, np.ndarray]:
    """``truth.seen``; an :class:`InputError` naming the episode when it has no visibility topics."""
    if truth.seen is None:
        raise InputError(f"episode {truth.episode} has no /<agent>/visibility topics (labels-only episode, "
                         f"sensors.enabled: false?); {what} needs them: generate the data with sensors on")
    return truth.seen
