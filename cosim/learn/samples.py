"""What ``cosim learn`` trains on, from a tick's *record*, in numpy alone (no MCAP, no torch): the setup of a
model, the record of one tick (:func:`learn_record`), one sample per ego (:func:`make_item`), the per-episode
cache of records (:class:`CachedEpisodes`) and the flips of training.

A record holds what every ego's sample of one tick needs: the agents, their LiDAR poses in ``map``, each
agent's sweep (compensated as :attr:`Setup.lidar` says, then rounded to 1 cm: :func:`quantise`), how many
returns each agent has on each labelled track, the labels, and the ``/comm/links`` delivery probabilities and
delays.
:class:`cosim.learn.data.Samples` makes records from MCAP through :class:`cosim.io.dataset.CooperativeDataset`,
or reads them from a cache written by ``cosim learn cache``; both give the same samples, bit for bit (tested).

A sample is one (episode, tick, ego vehicle). Its inputs depend on the fusion mode (docs/learnability.md):

- ``none``: the ego's own points (one cloud);
- ``early``: the ego's points and every collaborator's, in the ego LiDAR frame, as one cloud;
- ``late``: one cloud per agent in the ego LiDAR frame, each detected alone, boxes merged;
- ``intermediate``: one cloud per agent in that agent's bird's-eye frame (its x, y and heading, the ego's
  z), with the pose of that frame in the ego's (``poses``: yaw, x, y); the model encodes each into its own
  BEV map, warps the maps into the ego frame and fuses them per cell.

A :class:`Perturb` makes the collaboration as deployed (docs/learnability.md, "Collaboration as deployed"): each
collaborator's pose with a Gaussian error, its data from an earlier tick with its pose of that tick, its message
lost; every draw is seeded by (seed, episode, tick, agents), so the same seed gives the same perturbation.
"""

from __future__ import annotations

import hashlib
import json
import math
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError
from cosim.eval.predictions import SETTINGS
from cosim.geometry import rotation_matrix
from cosim.learn.grid import Grid

FUSIONS: tuple[str, ...] = ("none", "late", "early", "intermediate")
#: How intermediate fusion merges the agents' BEV maps per cell: max (F-Cooper) or attention (AttFuse).
FUSES: tuple[str, ...] = ("max", "attention")
#: Pillar encoders of intermediate fusion: one for all agents, one per agent kind (HEAL's point), or one per
#: LiDAR (:func:`lidar_sensor`: its preset, or its kind's own LiDAR) of the training data.
ENCODERS: tuple[str, ...] = ("shared", "kind", "sensor")
#: Learning-rate schedules of training (cosim.learn.train._lr).
SCHEDULES: tuple[str, ...] = ("cosine", "onecycle")
#: Agent kinds in the order of the per-kind encoders.
KINDS: tuple[str, ...] = ("vehicle", "rsu", "drone")
#: LiDAR motion compensation (as cosim.io.dataset.LIDAR_MODES, which a test checks).
LIDAR_MODES: tuple[str, ...] = ("tick", "objects", "raw")
#: The paper's vehicle classes (as cosim.eval.dataset.VEHICLE_CLASSES, which a test checks).
VEHICLE_CLASSES: tuple[str, ...] = ("car", "van", "truck", "bus", "motorcycle", "bicycle")
#: Communication range per agent kind (as cosim.io.dataset.PAPER_COMM_RANGE_M, which a test checks).
COMM_RANGE_M: dict[str, float] = {"vehicle": 120.0, "rsu": 120.0, "drone": 180.0}
#: Margin around the ego's own box inside which points are dropped from every cloud (collaborators see the
#: ego's body; it is never ground truth, so a model would learn a vehicle there that scores as a false positive).
EGO_MARGIN_M = 0.3
#: Points are stored (and, uncached, rounded) to this step: 1 cm, int16 in the agent's LiDAR frame.
QUANTUM_M = 0.01
_QMAX = 32767
#: Bytes a collaborator sends per ego frame (docs/learnability.md, "Bytes sent"): early fusion, a point as float32
#: x, y, z, intensity; intermediate fusion, a pillar of its BEV feature map as float32 channels and int16 row,
#: column (:func:`pillar_bytes`); late fusion, a box as 7 float32 (centre, size, yaw), a float32 score, a uint8 class.
POINT_BYTES = 16
BOX_BYTES = 33


def pillar_bytes(width: int) -> int:
    """Bytes of one pillar of an intermediate-fusion feature map of ``width`` channels, as sent."""
    return 4 * width + 4


@dataclass(frozen=True)
class Perturb:
    """How each collaborator's message reaches the ego (the ego's own data is never perturbed):

    - ``pose_m``, ``pose_deg``: standard deviations of a Gaussian error on the collaborator's pose in ``map``
      (x and y [m], yaw [deg]: V2X-ViT's and CoAlign's protocol), with which its data is placed in the ego frame;
    - ``latency_ms``: its data from that long before the ego's tick (a whole number of ticks), or with
      ``latency_links`` its ``/comm/links`` link's own ``delay_ms`` rounded up to ticks; placed with the pose
      the message carried (the collaborator's at that earlier tick); labels stay the ego tick's;
    - ``loss``: the message lost with this probability, or with ``loss_links`` with one minus its link's
      ``delivery`` (what ``--delivery`` did);
    - ``seed``: the draws' seed.
    """

    pose_m: float = 0.0
    pose_deg: float = 0.0
    latency_ms: int = 0
    latency_links: bool = False
    loss: float = 0.0
    loss_links: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        for name, v in (("pose noise POS_M", self.pose_m), ("pose noise ROT_DEG", self.pose_deg)):
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"--pose-noise: {name} must be a finite number >= 0, got {v!r}")
        if not (isinstance(self.latency_ms, int) and self.latency_ms >= 0):
            raise InputError(f"--latency: a whole number of milliseconds >= 0 or 'links', got {self.latency_ms!r}")
        if not (math.isfinite(self.loss) and 0.0 <= self.loss <= 1.0):
            raise InputError(f"--loss: a probability from 0 to 1 or 'links', got {self.loss!r}")
        if self.latency_links and self.latency_ms:
            raise InputError("--latency: give milliseconds or 'links', not both")
        if self.loss_links and self.loss:
            raise InputError("--loss: give a probability or 'links', not both")

    def __bool__(self) -> bool:
        return self != Perturb(seed=self.seed)

    @property
    def latency(self) -> bool:
        return bool(self.latency_ms) or self.latency_links

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Perturb:
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    def describe(self) -> str:
        """The perturbation in the words of the flags (``none`` when there is none)."""
        parts = []
        if self.pose_m or self.pose_deg:
            parts.append(f"pose noise {self.pose_m:g} m, {self.pose_deg:g} deg")
        if self.latency:
            parts.append("latency links" if self.latency_links else f"latency {self.latency_ms} ms")
        if self.loss or self.loss_links:
            parts.append("loss links" if self.loss_links else f"loss {self.loss:g}")
        return ", ".join(parts) + f" (seed {self.seed})" if parts else "none"


@dataclass(frozen=True)
class Setup:
    """What a model is trained for: fusion mode, collaborating agent kinds (a :data:`SETTINGS` name),
    object classes, grid, the collaborators' perturbation (:class:`Perturb`), the target rule, LiDAR
    compensation, and for intermediate fusion how maps are fused and encoded: ``sensors`` names the LiDARs of
    ``encoders`` sensor, one pillar encoder each, in order (:func:`sensor_vocabulary`)."""

    fusion: str = "none"
    agents: str = "ego"
    classes: tuple[str, ...] = VEHICLE_CLASSES
    grid: Grid = field(default_factory=Grid)
    perturb: Perturb = field(default_factory=Perturb)
    min_points: int = 1
    lidar: str = "tick"
    fuse: str = "max"
    encoders: str = "shared"
    #: The LiDAR's height above the road [m] in the training data (cosim: the rig's mount; a KITTI folder: given
    #: or estimated); scans from another height are moved to it (cosim.learn.kitti). None: not recorded.
    lidar_height_m: float | None = None
    sensors: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.fusion not in FUSIONS:
            raise InputError(f"unknown fusion {self.fusion!r}; choose one of {', '.join(FUSIONS)}")
        if self.agents not in SETTINGS:
            raise InputError(f"unknown agents {self.agents!r}; choose one of {', '.join(SETTINGS)}")
        if self.fusion == "none" and self.agents != "ego":
            raise InputError(f"fusion none uses the ego alone: --agents must be ego, not {self.agents!r} "
                             "(choose --fusion late, early or intermediate to collaborate)")
        if self.fusion != "none" and self.agents == "ego":
            raise InputError(f"fusion {self.fusion} needs collaborators: give --agents vehicles, vehicles+rsus, "
                             "vehicles+drones or all")
        if not self.classes:
            raise InputError("a model needs at least one object class")
        if self.lidar not in LIDAR_MODES:
            raise InputError(f"unknown lidar compensation {self.lidar!r}; choose one of {', '.join(LIDAR_MODES)}")
        if self.fuse not in FUSES:
            raise InputError(f"unknown fuse {self.fuse!r}; choose one of {', '.join(FUSES)}")
        if self.encoders not in ENCODERS:
            raise InputError(f"unknown encoders {self.encoders!r}; choose one of {', '.join(ENCODERS)}")
        if self.sensors and self.encoders != "sensor":
            raise InputError(f"sensors {', '.join(self.sensors)} name per-sensor encoders: give encoders sensor")

    def to_dict(self) -> dict[str, Any]:
        return {"fusion": self.fusion, "agents": self.agents, "classes": list(self.classes),
                "grid": self.grid.to_dict(), "perturb": self.perturb.to_dict(), "min_points": self.min_points,
                "lidar": self.lidar, "fuse": self.fuse, "encoders": self.encoders,
                "lidar_height_m": self.lidar_height_m, "sensors": list(self.sensors)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Setup:
        # checkpoints from before the compensation option were trained on raw sweeps; from before the
        # perturbations, with a /comm/links delivery flag (now loss links)
        perturb = Perturb.from_dict(d["perturb"]) if "perturb" in d else Perturb(loss_links=bool(d.get("delivery")))
        return cls(d["fusion"], d["agents"], tuple(d["classes"]), Grid.from_dict(d["grid"]), perturb,
                   int(d["min_points"]), d.get("lidar", "raw"), d.get("fuse", "max"), d.get("encoders", "shared"),
                   d.get("lidar_height_m"), tuple(d.get("sensors", ())))

    def with_agents(self, fusion: str | None, agents: str | None) -> Setup:
        fusion = fusion or self.fusion
        return replace(self, fusion=fusion, agents=agents or ("ego" if fusion == "none" else self.agents))


def kind_of(agent: str) -> str:
    return agent.rsplit("_", 1)[0]


def lidar_sensor(resolved: dict[str, Any], agent: str) -> str | None:
    """The name of an agent's LiDAR for the per-sensor encoders, from its episode's resolved scenario: its
    preset (``lidar.model``: ``vlp16``...), else its kind (``vehicle``...) when it carries its kind's LiDAR
    (``sensors.<kind>.lidar``), else ``custom-`` and a digest of its fields; None without a LiDAR."""
    from cosim.scenario.model import rig_data_of

    lidar = rig_data_of(resolved, agent).get("lidar")
    if not lidar:
        return None
    if lidar.get("model"):
        return str(lidar["model"])
    kind = kind_of(agent)
    if lidar == ((resolved.get("sensors") or {}).get(kind) or {}).get("lidar"):
        return kind
    digest = hashlib.sha256(json.dumps(lidar, sort_keys=True).encode()).hexdigest()[:8]
    return f"custom-{digest}"


def sensor_vocabulary(lidars: Iterable[dict[str, str | None]]) -> tuple[str, ...]:
    """The per-sensor encoders' LiDARs of some episodes' ``{agent: sensor}`` maps: the agent kinds first
    (:data:`KINDS`, so a LiDAR unknown to a model can fall back to its kind's), then the other names sorted."""
    names = {s for m in lidars for s in m.values() if s}
    return tuple(k for k in KINDS if k in names) + tuple(sorted(names - set(KINDS)))


def encoder_index(agent: str, setup: Setup, lidars: dict[str, str | None] | None) -> int:
    """The pillar encoder of an agent's points: its kind's (:data:`KINDS`), or with ``encoders`` sensor its
    LiDAR's in ``setup.sensors`` (``lidars``: the episode's ``{agent: sensor}``), falling back to its kind's
    for a LiDAR the model was not trained on (0 for an agent without one: it has no pillars); InputError when
    neither is among the model's."""
    kind = kind_of(agent)
    if setup.encoders != "sensor":
        return KINDS.index(kind) if kind in KINDS else 0
    if lidars is not None and agent in lidars and lidars[agent] is None:
        return 0
    name = (lidars or {}).get(agent) or kind
    for candidate in (name, kind):
        if candidate in setup.sensors:
            return setup.sensors.index(candidate)
    raise InputError(f"{agent}'s LiDAR {name!r} has no encoder in this model, nor has its kind: it was trained "
                     f"with the LiDARs {', '.join(setup.sensors)}")


def quantise(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) [m] as int16 steps of :data:`QUANTUM_M` and the mask of the points kept (those within
    +-327 m of the sensor: beyond any LiDAR's range)."""
    q = np.round(np.asarray(xyz, np.float64) / QUANTUM_M)
    keep = (np.abs(q) <= _QMAX).all(axis=1)
    return q[keep].astype(np.int16), keep


def dequantise(q: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity from int16 steps and uint8 intensity counts."""
    out = np.empty((len(q), 4), np.float32)
    out[:, :3] = q.astype(np.float32) * np.float32(QUANTUM_M)
    out[:, 3] = intensity.astype(np.float32) / np.float32(255.0)
    return out


def learn_record(rec: dict[str, Any], links: Any = None, tick_ns: int | None = None) -> dict[str, Any]:
    """The learn record of a :meth:`cosim.io.dataset.CooperativeDataset.read_tick` record (and the tick's
    ``/comm/links`` :class:`~cosim.comm.message.LinkSet`, or None; the episode's ``tick_ns``): points rounded to
    1 cm with intensity in counts of 1/255 (as stored), per-agent hit counts per track instead of per-point ids,
    each link's delivery probability (``links``) and delay (``link_delay_ms``) by ``"<tx>><rx>"``."""
    points, intensity, hits = [], [], []
    for cloud, inst in zip(rec["lidar"], rec["lidar_instance"], strict=True):
        q, keep = quantise(cloud[:, :3])
        points.append(q)
        intensity.append(np.round(cloud[keep, 3].astype(np.float64) * 255.0).astype(np.uint8))
        tracks, counts = np.unique(inst, return_counts=True)  # every return, as cosim eval's visibility counts
        hits.append(np.stack([tracks, counts]).astype(np.int64))
    out = {k: rec[k] for k in ("tick", "t_ns", "agents", "map_from", "label_track_ids", "label_classes",
                               "label_centers", "label_rotations", "label_sizes", "agent_tracks")}
    out.update({"points": points, "intensity": intensity, "hits": hits, "tick_ns": tick_ns})
    out["links"] = (None if links is None else
                    {f"{a}>{b}": float(p) for a, b, p in zip(links.tx, links.rx, links.delivery, strict=True)})
    out["link_delay_ms"] = (None if links is None else
                            {f"{a}>{b}": float(d) for a, b, d in zip(links.tx, links.rx, links.delay_ms, strict=True)})
    return out


def crop_record(rec: dict[str, Any], egos: list[str], grid: Grid) -> dict[str, Any]:
    """The record with only the points that some ego's sample can use: those inside ``grid``'s range in the
    frame of at least one ego, computed as :func:`make_item` moves them (so every sample is unchanged; the
    hit counts stay those of the whole sweep)."""
    agents = rec["agents"]
    map_from = dict(zip(agents, rec["map_from"], strict=True))
    out = dict(rec)
    out["points"], out["intensity"] = [], []
    for i, a in enumerate(agents):
        p = dequantise(rec["points"][i], rec["intensity"][i])
        keep = np.zeros(len(p), bool)
        for ego in egos:
            t = np.linalg.inv(map_from[ego]) @ map_from[a]
            xyz = p[:, :3] @ t[:3, :3].T.astype(np.float32) + t[:3, 3].astype(np.float32)
            keep |= grid.in_range(xyz)
        out["points"].append(rec["points"][i][keep])
        out["intensity"].append(rec["intensity"][i][keep])
    return out


def delivered(episode: str, tick: int, tx: str, rx: str, probability: float, seed: int = 0) -> bool:
    """Whether the message of ``tx`` to ``rx`` sent at ``tick`` arrives, with ``probability``: one uniform draw
    seeded by (episode, tick, link) and ``seed`` (seed 0: the draw ``--delivery`` made before seeds)."""
    key = f"{episode}|{tick}|{tx}|{rx}" + (f"|{seed}" if seed else "")
    return bool(np.random.default_rng(zlib.crc32(key.encode())).random() < probability)


def pose_error(perturb: Perturb, episode: str, tick: int, agent: str) -> tuple[float, float, float]:
    """The error (dx [m], dy [m], dyaw [rad]) on ``agent``'s pose at ``tick``: Gaussian with ``perturb``'s
    standard deviations, seeded by (seed, episode, tick, agent), so every ego that receives the message gets the
    same error."""
    rng = np.random.default_rng([perturb.seed, zlib.crc32(f"{episode}|{tick}|{agent}|pose".encode())])
    dx, dy, dyaw = rng.normal(0.0, 1.0, 3)
    return float(dx * perturb.pose_m), float(dy * perturb.pose_m), float(dyaw * math.radians(perturb.pose_deg))


def with_pose_error(pose: np.ndarray, dx: float, dy: float, dyaw: float) -> np.ndarray:
    """A 4x4 pose ``map <- frame`` moved by (dx, dy) [m] along map x, y and turned by ``dyaw`` [rad] about the
    vertical through its own origin."""
    c, s = math.cos(dyaw), math.sin(dyaw)
    out = np.array(pose, np.float64)
    out[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ out[:3, :3]
    out[0, 3] += dx
    out[1, 3] += dy
    return out


def latency_ticks(perturb: Perturb, rec: dict[str, Any], tx: str, rx: str) -> int:
    """How many ticks before ``rec``'s the message of ``tx`` to ``rx`` was captured: ``latency_ms`` in ticks, or
    the link's ``delay_ms`` at that tick rounded up to ticks (InputError without ``/comm/links``)."""
    if not perturb.latency:
        return 0
    tick_ns = rec.get("tick_ns")
    if not tick_ns:
        raise InputError("--latency needs the episodes' tick length: cache the data again with this cosim")
    if not perturb.latency_links:
        return perturb.latency_ms * 1_000_000 // int(tick_ns)
    delays = rec.get("link_delay_ms")
    if delays is None:
        raise InputError("--latency links needs /comm/links with delays: episodes with comm.enabled, cached again "
                         "with this cosim")
    return math.ceil(round(delays.get(f"{tx}>{rx}", 0.0) * 1_000_000) / int(tick_ns))


def inside_box(xy: np.ndarray, boxes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """(N, M) bool: point n (x, y) lies inside the bird's-eye footprint of box m ([x, y, z, l, w, h, yaw]),
    grown by ``margin_m`` on every side."""
    d = xy[:, None, :2] - boxes[None, :, :2]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    along = d[..., 0] * c + d[..., 1] * s
    across = -d[..., 0] * s + d[..., 1] * c
    return (np.abs(along) <= boxes[:, 3] / 2 + margin_m) & (np.abs(across) <= boxes[:, 4] / 2 + margin_m)


def agent_grid(grid: Grid) -> Grid:
    """The square grid of an agent's own BEV map in intermediate fusion: wide enough for every point of
    the ego's area seen from an agent up to the longest communication range away."""
    reach = math.hypot(max(map(abs, grid.x_range)), max(map(abs, grid.y_range))) + max(COMM_RANGE_M.values())
    half = math.ceil(reach / grid.pillar_m) * grid.pillar_m
    return replace(grid, x_range=(-half, half), y_range=(-half, half), max_pillars=10 ** 7)


def bev_pose(lidar_to_ego: np.ndarray) -> np.ndarray:
    """(yaw, x, y) of an agent's bird's-eye frame in the ego frame (its heading and position; z stays
    the ego's)."""
    return np.array([math.atan2(lidar_to_ego[1, 0], lidar_to_ego[0, 0]), lidar_to_ego[0, 3], lidar_to_ego[1, 3]])


def to_bev_frame(cloud: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """A cloud (N, 4) in the ego frame, moved into the bird's-eye frame of ``pose`` (yaw, x, y)."""
    c, s = math.cos(pose[0]), math.sin(pose[0])
    dx = cloud[:, 0] - np.float32(pose[1])
    dy = cloud[:, 1] - np.float32(pose[2])
    out = cloud.copy()
    out[:, 0] = np.float32(c) * dx + np.float32(s) * dy
    out[:, 1] = -np.float32(s) * dx + np.float32(c) * dy
    return out


def make_item(rec: dict[str, Any], ego: str, setup: Setup, episode: str,
              history: Callable[[int], dict[str, Any] | None] | None = None,
              lidars: dict[str, str | None] | None = None) -> dict[str, Any]:
    """The sample of ego ``ego`` from a learn record: ``episode`` (id), ``tick``, ``ego``, ``clouds`` (list
    of (N, 4) float32), ``sources`` (the agents of each cloud), ``targets`` (boxes (M, 7), class indices (M,)
    per target set: one per cloud for late fusion, else one), ``sent`` (the points each collaborator of
    ``sources`` sends: its cloud inside the ego's range), and for intermediate fusion ``poses`` (J, 3) and
    ``encoder`` (J,) (each agent's pillar encoder, :func:`encoder_index`; ``lidars`` the episode's
    ``{agent: sensor}`` for encoders sensor). ``setup.perturb`` perturbs each collaborator's message;
    with latency, ``history(tick)`` gives the learn record of an earlier tick of the episode (None: not at hand)."""
    agents = rec["agents"]
    map_from = dict(zip(agents, rec["map_from"], strict=True))
    ego_from_map = np.linalg.inv(map_from[ego])
    ego_xyz = map_from[ego][:3, 3]
    kinds = set(SETTINGS[setup.agents])
    chosen = [ego] + [a for a in agents if a != ego and kind_of(a) in kinds
                      and np.linalg.norm(map_from[a][:3, 3] - ego_xyz) <= COMM_RANGE_M.get(kind_of(a), np.inf)]
    use = chosen[:1] if setup.fusion == "none" else chosen
    sent_by = {ego: rec}  # each agent's record: the one of the tick its message was captured
    if setup.perturb and len(use) > 1:
        use, sent_by = _arrived(rec, ego, use, setup.perturb, episode, history)
    boxes, track_ids, classes = _boxes(rec, ego_from_map, setup)
    own = [i for i, t in enumerate(track_ids) if t == rec["agent_tracks"].get(ego)]
    ego_box = boxes[own[0]] if own else None
    if own:  # the ego's own box: never a target (nor ground truth in cosim eval)
        rest = [i for i in range(len(boxes)) if i != own[0]]
        boxes, track_ids, classes = boxes[rest], track_ids[rest], [classes[i] for i in rest]
    clouds_by_agent, poses, sent, hits_by_agent = [], [], [], []
    pose_noise = setup.perturb.pose_m or setup.perturb.pose_deg
    for a in use:
        src = sent_by.get(a, rec)
        i = src["agents"].index(a)
        pose = src["map_from"][i]
        if a != ego and pose_noise:
            pose = with_pose_error(pose, *pose_error(setup.perturb, episode, int(src["tick"]), a))
        t = ego_from_map @ pose
        p = dequantise(src["points"][i], src["intensity"][i])
        xyz = p[:, :3] @ t[:3, :3].T.astype(np.float32) + t[:3, 3].astype(np.float32)
        cloud = setup.grid.crop(np.concatenate([xyz, p[:, 3:4]], axis=1).astype(np.float32))
        sent.append(len(cloud))
        if ego_box is not None:  # the ego knows its own body: collaborators' returns on it are not an object
            cloud = cloud[~inside_box(cloud[:, :2], ego_box[None], EGO_MARGIN_M)[:, 0]]
        clouds_by_agent.append(cloud)
        poses.append(bev_pose(t))
        hits_by_agent.append(src["hits"][i])
    groups = [[k] for k in range(len(use))] if setup.fusion == "late" else [list(range(len(use)))]
    labels = np.array([setup.classes.index(c) for c in classes], np.int64)
    item: dict[str, Any] = {"episode": episode, "tick": int(rec["tick"]), "ego": ego, "clouds": [],
                            "sources": [], "targets": [], "sent": sent[1:]}
    for g in groups:
        hits: dict[int, int] = {}
        for k in g:
            for track, n in hits_by_agent[k].T.tolist():
                hits[track] = hits.get(track, 0) + n
        seen = np.array([hits.get(int(t), 0) >= setup.min_points for t in track_ids], bool)
        if len(boxes):
            seen &= setup.grid.box_inside(boxes[:, :2])
        item["targets"].append((boxes[seen].astype(np.float64), labels[seen]))
        if setup.fusion != "intermediate":
            item["clouds"].append(np.concatenate([clouds_by_agent[k] for k in g], axis=0))
            item["sources"].append([use[k] for k in g])
    if setup.fusion == "intermediate":
        item["clouds"] = [to_bev_frame(c, p) for c, p in zip(clouds_by_agent, poses, strict=True)]
        item["sources"] = [[a] for a in use]
        item["poses"] = np.array(poses, np.float64).reshape(-1, 3)
        item["encoder"] = np.array([encoder_index(a, setup, lidars) for a in use], np.int64)
    return item


def _arrived(rec: dict[str, Any], ego: str, use: list[str], perturb: Perturb, episode: str,
             history: Callable[[int], dict[str, Any] | None] | None) -> tuple[list[str], dict[str, dict[str, Any]]]:
    """The agents of ``use`` (the ego first) whose message reaches the ego at ``rec``'s tick under ``perturb``,
    and the record each message was captured in: ``latency_ticks`` earlier (none before the episode's first
    tick), then lost with ``perturb.loss`` or one minus its link's delivery at the tick it was sent."""
    tick = int(rec["tick"])
    kept, sent_by = [ego], {ego: rec}
    for a in use[1:]:
        k = latency_ticks(perturb, rec, a, ego)
        if tick - k < 0:  # captured before the episode began: nothing has arrived yet
            continue
        src = rec if k == 0 else (history(tick - k) if history is not None else None)
        if src is None:
            raise InputError(f"episode {episode}: the record of tick {tick - k} ({k} ticks before {tick}) is not at "
                             "hand for --latency: cache every tick (cosim learn cache --every 1) or read the episodes")
        if perturb.loss_links:
            if src["links"] is None:
                raise InputError(f"episode {episode} has no /comm/links (comm.enabled false): no --loss links")
            p_arrive = src["links"].get(f"{a}>{ego}", 0.0)
        else:
            p_arrive = 1.0 - perturb.loss
        if p_arrive < 1.0 and not delivered(episode, tick - k, a, ego, p_arrive, perturb.seed):
            continue
        kept.append(a)
        sent_by[a] = src
    return kept, sent_by


def _boxes(rec: dict[str, Any], ego_from_map: np.ndarray, setup: Setup) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The labelled boxes of the setup's classes with centres in the grid's range (z included), in the ego
    frame (as cosim.io.dataset.CooperativeDataset's, ego's box included)."""
    g = setup.grid
    lo = np.array([g.x_range[0], g.y_range[0], g.z_range[0]])
    hi = np.array([g.x_range[1], g.y_range[1], g.z_range[1]])
    boxes, keep = [], []
    for i, _track in enumerate(rec["label_track_ids"]):
        if rec["label_classes"][i] not in setup.classes:
            continue
        c = ego_from_map[:3, :3] @ rec["label_centers"][i] + ego_from_map[:3, 3]
        if not ((c >= lo) & (c <= hi)).all():
            continue
        r = ego_from_map[:3, :3] @ rotation_matrix(tuple(float(c) for c in rec["label_rotations"][i]))
        boxes.append([*c, *rec["label_sizes"][i], np.arctan2(r[1, 0], r[0, 0])])
        keep.append(i)
    return (np.asarray(boxes, np.float32).reshape(-1, 7),
            np.asarray([int(rec["label_track_ids"][i]) for i in keep], np.int64),
            [rec["label_classes"][i] for i in keep])


def augment(cloud: np.ndarray, boxes: np.ndarray, flip_x: bool, flip_y: bool, turn: float = 0.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """Mirror a cloud and its boxes about the x axis (y -> -y) and/or the y axis (x -> -x), then turn them by
    ``turn`` [rad] about the z axis (global rotation: boxes at every yaw, not mostly along the ego's axes)."""
    cloud, boxes = cloud.copy(), boxes.copy()
    if flip_y:
        cloud[:, 1] *= -1
        boxes[:, 1] *= -1
        boxes[:, 6] *= -1
    if flip_x:
        cloud[:, 0] *= -1
        boxes[:, 0] *= -1
        boxes[:, 6] = np.pi - boxes[:, 6]
    if turn:
        c, s = np.float32(math.cos(turn)), np.float32(math.sin(turn))
        for a in (cloud, boxes):
            x, y = a[:, 0].copy(), a[:, 1].copy()
            a[:, 0] = c * x - s * y
            a[:, 1] = s * x + c * y
        boxes[:, 6] += turn
    return cloud, boxes


def augment_poses(poses: np.ndarray, flip_x: bool, flip_y: bool, turn: float = 0.0) -> np.ndarray:
    """The bird's-eye poses (yaw, x, y) of the agents' frames after the scene is mirrored and turned as
    :func:`augment` does it; each agent's cloud, in its own frame, is mirrored and turned the same way (a
    mirror M turns R(yaw) into M R(yaw) = R(-yaw) M; a turn Q keeps the yaw, Q R(yaw) = R(yaw) Q, and
    turns the position)."""
    out = poses.copy()
    if flip_y:
        out[:, 0] *= -1
        out[:, 2] *= -1
    if flip_x:
        out[:, 0] *= -1
        out[:, 1] *= -1
    if turn:
        c, s = math.cos(turn), math.sin(turn)
        x, y = out[:, 1].copy(), out[:, 2].copy()
        out[:, 1] = c * x - s * y
        out[:, 2] = s * x + c * y
    return out


# ---------------------------------------------------------------------------------------- the cache

CACHE_FORMAT = 1


def cache_meta_path(root: Path) -> Path:
    return Path(root) / "cache.json"


def write_episode_cache(path: Path, records: list[dict[str, Any]]) -> None:
    """One episode's learn records as one ``.npz`` (numpy only, uncompressed: an epoch reads it at disk
    speed): every array of every record under ``<tick>/<key>``, the rest as JSON."""
    arrays: dict[str, np.ndarray] = {}
    meta = []
    for rec in records:
        t = rec["tick"]
        arrays[f"{t}/map_from"] = rec["map_from"]
        for i in range(len(rec["agents"])):
            arrays[f"{t}/points/{i}"] = rec["points"][i]
            arrays[f"{t}/intensity/{i}"] = rec["intensity"][i]
            arrays[f"{t}/hits/{i}"] = rec["hits"][i]
        for k in ("label_track_ids", "label_centers", "label_rotations", "label_sizes"):
            arrays[f"{t}/{k}"] = rec[k]
        meta.append({"tick": t, "t_ns": rec["t_ns"], "agents": rec["agents"], "label_classes": rec["label_classes"],
                     "agent_tracks": rec["agent_tracks"], "links": rec["links"], "tick_ns": rec.get("tick_ns"),
                     "link_delay_ms": rec.get("link_delay_ms")})
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)


class CachedEpisodes:
    """The records of a cache folder written by ``cosim learn cache`` (``cache.json`` with the episodes,
    splits and settings; one ``.npz`` per episode); numpy only."""

    def __init__(self, root: Path | str):
        self.root = Path(root)
        path = cache_meta_path(self.root)
        if not path.is_file():
            raise InputError(f"{self.root}: no cache.json: not a cache folder of cosim learn cache")
        self.meta = json.loads(path.read_text())
        if self.meta.get("format") != CACHE_FORMAT:
            raise InputError(f"{path}: not a cosim learn cache of format {CACHE_FORMAT}")
        self._open: dict[str, Any] = {}
        self._index: dict[str, dict[int, dict[str, Any]]] = {}

    @property
    def lidar(self) -> str:
        return self.meta["lidar"]

    def episodes(self, split: str | None = None) -> list[dict[str, Any]]:
        return [e for e in self.meta["episodes"] if split is None or e["split"] == split]

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_open": {}, "_index": {}}

    def _npz(self, episode: str) -> Any:
        if episode not in self._open:
            e = next((e for e in self.meta["episodes"] if e["id"] == episode), None)
            if e is None:
                raise InputError(f"{self.root}: episode {episode} is not in the cache")
            z = np.load(self.root / e["file"])
            self._open[episode] = z
            index = {m["tick"]: m for m in json.loads(z["meta"].tobytes())}
            # caches from before the perturbations lack the tick's length: the ticks' times give it
            tick_ns = next((m["t_ns"] // m["tick"] for m in index.values() if m["tick"] > 0), None)
            for m in index.values():
                m.setdefault("tick_ns", tick_ns)
                m.setdefault("link_delay_ms", None)
            self._index[episode] = index
        return self._open[episode]

    def tick_ns(self, episode: str) -> int | None:
        """The episode's tick length [ns] (None for an episode of a single cached tick from before it was kept)."""
        self._npz(episode)
        return next(iter(self._index[episode].values()))["tick_ns"]

    def ticks(self, episode: str) -> list[int]:
        self._npz(episode)
        return sorted(self._index[episode])

    def record(self, episode: str, tick: int) -> dict[str, Any]:
        z = self._npz(episode)
        m = self._index[episode].get(tick)
        if m is None:
            raise InputError(f"{self.root}: tick {tick} of episode {episode} is not in the cache "
                             f"(cached every {self.meta['every']} ticks)")
        n = len(m["agents"])
        rec = dict(m)
        rec["map_from"] = z[f"{tick}/map_from"]
        for k in ("label_track_ids", "label_centers", "label_rotations", "label_sizes"):
            rec[k] = z[f"{tick}/{k}"]
        rec["points"] = [z[f"{tick}/points/{i}"] for i in range(n)]
        rec["intensity"] = [z[f"{tick}/intensity/{i}"] for i in range(n)]
        rec["hits"] = [z[f"{tick}/hits/{i}"] for i in range(n)]
        return rec

    def close(self) -> None:
        for z in self._open.values():
            z.close()
        self._open, self._index = {}, {}
