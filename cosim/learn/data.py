"""Training and prediction samples of ``cosim learn``, read through :class:`cosim.io.dataset.CooperativeDataset`,
with the fusion modes. No torch here.

A sample is one (episode, tick, ego vehicle). Its *inputs* depend on the fusion mode:

- ``none``: the ego's own LiDAR points (one cloud);
- ``early``: the ego's points and those of every collaborator of the chosen agent kinds, each moved into
  the ego LiDAR frame, as one cloud;
- ``late``: one cloud per agent (the ego and each collaborator), each moved into the ego LiDAR frame but
  detected alone; the detections are then merged (:func:`cosim.learn.train.predict_sample`).

Collaborators are the agents of the chosen kinds (:data:`cosim.eval.predictions.SETTINGS`: ``vehicles``,
``vehicles+rsus``, ``vehicles+drones``, ``all``) within the paper's communication range of the ego (the
dataset's defaults: 120 m for vehicles and RSUs, 180 m for drones). With ``delivery`` on, each
collaborator's data reaches the ego only if its ``/comm/links`` link to the ego delivers at that tick
(drawn with the link's ``delivery`` probability, seeded by episode, tick and link, so it is repeatable).

Every cloud loses its points on the ego's own body (inside the ego's box, grown by :data:`EGO_MARGIN_M`):
collaborators see the ego, which is never ground truth. Training targets of a cloud are the boxes of the
model's classes with at least ``min_points`` LiDAR returns from the agents whose points make that cloud
(the "visible" ground truth of ``cosim eval --visible-only``).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError
from cosim.eval.dataset import VEHICLE_CLASSES, EpisodeRef
from cosim.eval.predictions import SETTINGS
from cosim.io.dataset import PAPER_COMM_RANGE_M, CooperativeDataset
from cosim.learn.grid import Grid

FUSIONS: tuple[str, ...] = ("none", "late", "early")
#: Margin around the ego's own box inside which points are dropped from every cloud (collaborators see the
#: ego's body; it is never ground truth, so a model would learn a vehicle there that scores as a false positive).
EGO_MARGIN_M = 0.3


@dataclass(frozen=True)
class Setup:
    """What a model is trained for: fusion mode, collaborating agent kinds (a :data:`SETTINGS` name),
    object classes, grid, ``/comm/links`` delivery, and the target rule."""

    fusion: str = "none"
    agents: str = "ego"
    classes: tuple[str, ...] = VEHICLE_CLASSES
    grid: Grid = field(default_factory=Grid)
    delivery: bool = False
    min_points: int = 1

    def __post_init__(self) -> None:
        if self.fusion not in FUSIONS:
            raise InputError(f"unknown fusion {self.fusion!r}; choose one of {', '.join(FUSIONS)}")
        if self.agents not in SETTINGS:
            raise InputError(f"unknown agents {self.agents!r}; choose one of {', '.join(SETTINGS)}")
        if self.fusion == "none" and self.agents != "ego":
            raise InputError(f"fusion none uses the ego alone: --agents must be ego, not {self.agents!r} "
                             "(choose --fusion late or early to collaborate)")
        if self.fusion != "none" and self.agents == "ego":
            raise InputError(f"fusion {self.fusion} needs collaborators: give --agents vehicles, vehicles+rsus, "
                             "vehicles+drones or all")
        if not self.classes:
            raise InputError("a model needs at least one object class")

    def to_dict(self) -> dict[str, Any]:
        return {"fusion": self.fusion, "agents": self.agents, "classes": list(self.classes),
                "grid": self.grid.to_dict(), "delivery": self.delivery, "min_points": self.min_points}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Setup:
        return cls(d["fusion"], d["agents"], tuple(d["classes"]), Grid.from_dict(d["grid"]), bool(d["delivery"]),
                   int(d["min_points"]))


def split_episodes(refs: list[EpisodeRef], split: str | None, role: str, dataset: Path | str) -> list[EpisodeRef]:
    """Episodes of ``split`` of a dataset's episodes ``refs`` (:func:`cosim.eval.dataset.load_dataset`).
    ``split`` None: the split named ``role`` (train, val, test) when the dataset has splits, else every
    episode (a folder of plain episodes has the one split ``all``)."""
    splits = sorted({r.split for r in refs})
    if split is None:
        if splits == ["all"]:
            return refs
        split = role
    chosen = [r for r in refs if r.split == split]
    if not chosen:
        raise InputError(f"{dataset}: no episode in split {split!r}; splits present: {', '.join(splits)}")
    return chosen


def check_classes(refs: list[EpisodeRef], classes: tuple[str, ...], what: str) -> None:
    """Every episode's class table must hold the model's classes."""
    for r in refs:
        missing = [c for c in classes if c not in r.object_classes]
        if missing:
            raise InputError(f"{what} is for classes {', '.join(classes)}, but episode {r.id} has no class "
                             f"{', '.join(missing)} (its classes: {', '.join(r.object_classes) or 'none'})")


def _kind(agent: str) -> str:
    return agent.rsplit("_", 1)[0]


def _delivered(episode: str, tick: int, tx: str, rx: str, probability: float) -> bool:
    seed = zlib.crc32(f"{episode}|{tick}|{tx}|{rx}".encode())
    return bool(np.random.default_rng(seed).random() < probability)


class Samples:
    """The samples of some episodes for one :class:`Setup` (every ``every``-th tick, every ego vehicle).

    ``item(i)`` gives ``episode`` (id), ``tick``, ``ego``, ``clouds`` (list of (N, 4) float32 x, y, z,
    intensity in the ego LiDAR frame: one cloud, or one per agent for late fusion), ``sources`` (the agents
    of each cloud), ``targets`` (per cloud: boxes (M, 7) and class indices (M,)).
    """

    def __init__(self, refs: list[EpisodeRef], setup: Setup, every: int = 1):
        if not refs:
            raise InputError("no episodes to read")
        self.refs = refs
        self.setup = setup
        self.ids = {r.path.resolve(): r.id for r in refs}
        kinds = set(SETTINGS[setup.agents])
        # agents out of the setting never take part: a negative range leaves them out of the samples
        comm = {k: (v if k in kinds else -1.0) for k, v in PAPER_COMM_RANGE_M.items()}
        # the ego's own box comes with the others so that the ego's body can be cut out of the clouds
        self.ds = CooperativeDataset([r.path for r in refs], classes=setup.classes, every=every, comm_range_m=comm,
                                     include_ego_box=True)
        if len(self.ds) == 0:
            raise InputError(f"no samples in {len(refs)} episode(s): they have no connected vehicles to serve as ego")
        self._links: dict[Path, Any] = {}

    def __len__(self) -> int:
        return len(self.ds)

    def close(self) -> None:
        self.ds.close()
        for ep in self._links.values():
            ep.close()
        self._links = {}

    def _delivered_agents(self, path: Path, episode: str, tick: int, ego: str, agents: list[str]) -> list[str]:
        from cosim.io import open_episode

        if path not in self._links:
            self._links[path] = open_episode(path)
        ep = self._links[path]
        if "/comm/links" not in ep.topics:
            raise InputError(f"episode {episode} has no /comm/links (comm.enabled false): train without --delivery")
        links = ep.tick(tick, topics=["/comm/links"]).links
        out = [ego]
        for a in agents[1:]:
            try:
                p = float(links.delivery[links.index(a, ego)])
            except KeyError:
                p = 0.0
            if _delivered(episode, tick, a, ego, p):
                out.append(a)
        return out

    def item(self, index: int) -> dict[str, Any]:
        s = self.ds[index]
        setup = self.setup
        path = Path(s["episode"]).resolve()
        episode = self.ids[path]
        agents = list(s["agents"])
        use = agents[:1] if setup.fusion == "none" else agents
        if setup.delivery and len(use) > 1:
            use = self._delivered_agents(path, episode, s["tick"], s["ego"], use)
        idx = [agents.index(a) for a in use]
        boxes, track_ids, classes = s["boxes"], s["track_ids"], list(s["classes"])
        own = np.nonzero(inside_box(np.zeros((1, 2)), boxes)[0])[0] if len(boxes) else np.zeros(0, np.int64)
        ego_box = boxes[own[0]] if len(own) else None
        if len(own):  # the ego's own box: never a target (nor ground truth in cosim eval)
            rest = np.setdiff1d(np.arange(len(boxes)), own[:1])
            boxes, track_ids, classes = boxes[rest], track_ids[rest], [classes[i] for i in rest]
        clouds_by_agent = []
        for i in idx:
            p = s["lidar"][i]
            t = s["lidar_to_ego"][i]
            xyz = p[:, :3] @ t[:3, :3].T.astype(np.float32) + t[:3, 3].astype(np.float32)
            cloud = np.concatenate([xyz, p[:, 3:4]], axis=1).astype(np.float32)
            if ego_box is not None:  # the ego knows its own body: collaborators' returns on it are not an object
                cloud = cloud[~inside_box(cloud[:, :2], ego_box[None], EGO_MARGIN_M)[:, 0]]
            clouds_by_agent.append(cloud)
        groups = [[k] for k in range(len(idx))] if setup.fusion == "late" else [list(range(len(idx)))]
        labels = np.array([setup.classes.index(c) for c in classes], np.int64)
        clouds, sources, targets = [], [], []
        for g in groups:
            clouds.append(setup.grid.crop(np.concatenate([clouds_by_agent[k] for k in g], axis=0)))
            sources.append([use[k] for k in g])
            inst = np.concatenate([s["lidar_instance"][idx[k]] for k in g])
            tracks, counts = np.unique(inst, return_counts=True)
            hits = dict(zip(tracks.tolist(), counts.tolist(), strict=True))
            seen = np.array([hits.get(int(t), 0) >= setup.min_points for t in track_ids], bool)
            if len(boxes):
                seen &= setup.grid.box_inside(boxes[:, :2])
            targets.append((boxes[seen].astype(np.float64), labels[seen]))
        return {"episode": episode, "tick": int(s["tick"]), "ego": s["ego"], "clouds": clouds, "sources": sources,
                "targets": targets}


def inside_box(xy: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """(N, M) bool: point n (x, y) lies inside the bird's-eye footprint of box m ([x, y, z, l, w, h, yaw]),
    grown by ``margin_m`` on every side."""
    d = xy[:, None, :2] - boxes[None, :, :2]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    along = d[..., 0] * c + d[..., 1] * s
    across = -d[..., 0] * s + d[..., 1] * c
    return (np.abs(along) <= boxes[:, 3] / 2 + margin_m) & (np.abs(across) <= boxes[:, 4] / 2 + margin_m)


def augment(cloud: np.ndarray, boxes: np.ndarray, flip_x: bool, flip_y: bool) -> tuple[np.ndarray, np.ndarray]:
    """Mirror a cloud and its boxes about the x axis (y -> -y) and/or the y axis (x -> -x)."""
    cloud, boxes = cloud.copy(), boxes.copy()
    if flip_y:
        cloud[:, 1] *= -1
        boxes[:, 1] *= -1
        boxes[:, 6] *= -1
    if flip_x:
        cloud[:, 0] *= -1
        boxes[:, 0] *= -1
        boxes[:, 6] = np.pi - boxes[:, 6]
    return cloud, boxes
