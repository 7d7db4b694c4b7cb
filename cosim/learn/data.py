"""Training and prediction samples of ``cosim learn``: records of ticks read through
:class:`cosim.io.dataset.CooperativeDataset` (or from a cache written by ``cosim learn cache``), made into
samples by :mod:`cosim.learn.samples`. No torch here.

Collaborators are the agents of the chosen kinds (:data:`cosim.eval.predictions.SETTINGS`: ``vehicles``,
``vehicles+rsus``, ``vehicles+drones``, ``all``) within the paper's communication range of the ego (120 m
for vehicles and RSUs, 180 m for drones). The setup's :class:`~cosim.learn.samples.Perturb` perturbs what
reaches the ego of each collaborator's message (pose error, latency, loss: docs/learnability.md, "Collaboration
as deployed"); with latency, a sample also reads the records of earlier ticks.

Every cloud loses its points on the ego's own body (inside the ego's box, grown by :data:`EGO_MARGIN_M`):
collaborators see the ego, which is never ground truth. Training targets of a cloud are the boxes of the
model's classes with at least ``min_points`` LiDAR returns from the agents whose points make that cloud
(the "visible" ground truth of ``cosim eval --visible-only``).
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from cosim.errors import InputError
from cosim.eval.dataset import EpisodeRef
from cosim.learn.grid import Grid
from cosim.learn.samples import (  # noqa: F401  (the names the rest of cosim learn and its tests use)
    CACHE_FORMAT,
    EGO_MARGIN_M,
    FUSIONS,
    CachedEpisodes,
    Perturb,
    Setup,
    augment,
    cache_meta_path,
    crop_record,
    inside_box,
    learn_record,
    lidar_sensor,
    make_item,
    sensor_vocabulary,
    write_episode_cache,
)
from cosim.learn.samples import delivered as _delivered  # noqa: F401

#: Learn records a :class:`Samples` keeps at hand: the egos of a tick and, with a latency, the earlier ticks.
_RECORDS_KEPT = 8


def episode_lidars(ref: EpisodeRef) -> dict[str, str | None]:
    """Each agent's LiDAR in an episode as the per-sensor encoders name it (:func:`lidar_sensor`), from the
    resolved scenario the episode carries (an episode without one: every agent its kind's LiDAR). Read once
    per file and process: a training names its episodes' LiDARs for its encoders, then its samples do."""
    return _episode_lidars(Path(ref.path))


@functools.cache
def _episode_lidars(path: Path) -> dict[str, str | None]:
    import yaml

    from cosim.io.reader import open_episode

    with open_episode(path) as ep:
        resolved = yaml.safe_load(ep.attachment("scenario.yaml")) if "scenario.yaml" in ep.attachments else None
        agents = list(ep.agents)
    if not resolved:
        return {a: a.rsplit("_", 1)[0] for a in agents}
    return {a: lidar_sensor(resolved, a) for a in agents}


def with_sensors(setup: Setup, refs: list[EpisodeRef]) -> Setup:
    """``setup`` with the LiDARs of ``refs`` (the training and validation episodes) as its per-sensor encoders
    when its encoders are ``sensor``; else unchanged."""
    if setup.encoders != "sensor":
        return setup
    sensors = sensor_vocabulary(episode_lidars(r) for r in refs)
    if not sensors:
        raise InputError(f"--encoders sensor: no agent of the {len(refs)} training and validation episode(s) "
                         "carries a LiDAR")
    return replace(setup, sensors=sensors)


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


class McapRecords:
    """Learn records (:func:`cosim.learn.samples.learn_record`) of episodes read from their MCAP files."""

    def __init__(self, refs: list[EpisodeRef], lidar: str, every: int):
        from cosim.io.dataset import CooperativeDataset

        self.refs = {r.id: r for r in refs}
        self.ds = CooperativeDataset([r.path for r in refs], every=every, lidar=lidar)
        self.ids = {r.path: r.id for r in refs}
        self.keys = [(self.ids[k.episode], k.tick, k.ego) for k in self.ds.keys]
        self._links: dict[str, Any] = {}

    def record(self, episode: str, tick: int) -> dict[str, Any]:
        path = self.refs[episode].path
        links = None
        ep = self.ds._episode(path)
        if "/comm/links" in ep.topics:
            links = ep.tick(tick, topics=["/comm/links"]).links()
        return learn_record(self.ds.read_tick(path, tick), links, ep.tick_ns)

    def __getstate__(self) -> dict[str, Any]:
        return dict(self.__dict__)

    def tick_ns(self, episode: str) -> int | None:
        return self.ds._episode(self.refs[episode].path).tick_ns

    def close(self) -> None:
        self.ds.close()


class CacheRecords:
    """Learn records of episodes read from a ``cosim learn cache`` folder (no MCAP)."""

    def __init__(self, cache: CachedEpisodes, refs: list[EpisodeRef] | list[str], every: int, lidar: str,
                 self_grid: Grid):
        self.cache = cache
        if cache.lidar != lidar:
            raise InputError(f"{cache.root} holds sweeps compensated as {cache.lidar!r}, not {lidar!r}: "
                             f"give --lidar {cache.lidar} or cache the data again")
        if not Grid.from_dict(cache.meta["grid"]).covers(self_grid):
            raise InputError(f"{cache.root} was cropped to a smaller range than the model's grid: cache the data again")
        ids = [r if isinstance(r, str) else r.id for r in refs]
        cached_every = self.every = int(cache.meta["every"])
        if every % cached_every:
            raise InputError(f"{cache.root} holds every {cached_every}-th tick: --every must be a multiple of it")
        self.keys = []
        for e in ids:
            entry = next((x for x in cache.meta["episodes"] if x["id"] == e), None)
            if entry is None:
                raise InputError(f"{cache.root}: episode {e} is not in the cache")
            self.keys += [(e, t, ego) for t in range(0, entry["n_ticks"], every) for ego in entry["egos"]]

    def record(self, episode: str, tick: int) -> dict[str, Any]:
        return self.cache.record(episode, tick)

    def tick_ns(self, episode: str) -> int | None:
        return self.cache.tick_ns(episode)

    def close(self) -> None:
        self.cache.close()


class Samples:
    """The samples of some episodes for one :class:`Setup` (every ``every``-th tick, every ego vehicle).

    ``item(i)`` gives ``episode`` (id), ``tick``, ``ego``, ``clouds`` (list of (N, 4) float32 x, y, z,
    intensity: one cloud, or one per agent for late and intermediate fusion), ``sources`` (the agents of
    each cloud), ``targets`` (boxes (M, 7) and class indices (M,) per target set), and for intermediate fusion
    ``poses`` and ``encoder`` (:func:`cosim.learn.samples.make_item`). With ``cache`` (a folder of
    ``cosim learn cache``), records come from it and no sensor data is read from MCAP (per-sensor encoders
    read each episode's scenario).
    """

    def __init__(self, refs: list[EpisodeRef], setup: Setup, every: int = 1, cache: Path | str | None = None):
        if not refs:
            raise InputError("no episodes to read")
        self.refs = refs
        self.setup = setup
        if cache is not None:
            self.src: Any = CacheRecords(CachedEpisodes(cache), refs, every, setup.lidar, setup.grid)
        else:
            self.src = McapRecords(refs, setup.lidar, every)
        if len(self.src.keys) == 0:
            raise InputError(f"no samples in {len(refs)} episode(s): they have no connected vehicles to serve as ego")
        if setup.perturb.latency:
            self._check_latency(setup.perturb)
        self._records: dict[tuple[str, int], dict[str, Any]] = {}
        self.lidars = {r.id: episode_lidars(r) for r in refs} if setup.encoders == "sensor" else {}

    def _check_latency(self, perturb: Perturb) -> None:
        """InputError unless every episode's earlier ticks that ``perturb``'s latency asks for can be read: a
        latency in ms a whole number of each episode's ticks, and in the cache's ticks when read from one."""
        cached_every = getattr(self.src, "every", 1)
        if perturb.latency_links and cached_every > 1:
            raise InputError(f"--latency links takes each link's own delay in ticks: it needs every tick, and the "
                             f"cache holds one tick in {cached_every} (cosim learn cache --every 1)")
        for ref in self.refs:
            tick_ns = self.src.tick_ns(ref.id)
            if perturb.latency_links or not tick_ns:
                continue
            ticks, rest = divmod(perturb.latency_ms * 1_000_000, tick_ns)
            if rest:
                raise InputError(f"--latency {perturb.latency_ms}: not a whole number of ticks of episode {ref.id} "
                                 f"({tick_ns / 1e6:g} ms a tick): give a multiple of {tick_ns / 1e6:g} ms")
            if ticks % cached_every:
                raise InputError(f"--latency {perturb.latency_ms}: {ticks} tick{'s' if ticks > 1 else ''}, but the "
                                 f"cache holds one tick in {cached_every}: give a multiple of {cached_every} ticks "
                                 "or cache every tick (cosim learn cache --every 1)")

    def __len__(self) -> int:
        return len(self.src.keys)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_records": {}}

    def close(self) -> None:
        self.src.close()

    def _record(self, episode: str, tick: int) -> dict[str, Any] | None:
        """The learn record of a tick, kept while it is among the last few read (the egos of a tick share its
        record; a latency reads earlier ones again); None for a tick the source does not hold."""
        key = (episode, tick)
        if key not in self._records:
            if len(self._records) >= _RECORDS_KEPT:
                del self._records[next(iter(self._records))]
            try:
                self._records[key] = self.src.record(episode, tick)
            except InputError:
                if not self.setup.perturb.latency:
                    raise
                return None
        return self._records[key]

    def item(self, index: int) -> dict[str, Any]:
        episode, tick, ego = self.src.keys[index]
        history = (lambda t: self._record(episode, t)) if self.setup.perturb.latency else None
        return make_item(self._record(episode, tick), ego, self.setup, episode, history, self.lidars.get(episode))


def write_cache(refs: list[EpisodeRef], out: Path, lidar: str, every: int,
                progress: Any = None) -> dict[str, Any]:
    """Cache the learn records of every ``every``-th tick of the episodes into ``out`` (one ``.npz`` per
    episode and ``cache.json``); an episode already cached with the same settings is kept."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta_path = cache_meta_path(out)
    grid = Grid()
    meta: dict[str, Any] = {"format": CACHE_FORMAT, "lidar": lidar, "every": every, "grid": grid.to_dict(),
                            "episodes": []}
    if meta_path.is_file():
        old = json.loads(meta_path.read_text())
        if (old.get("format"), old.get("lidar"), old.get("every")) != (CACHE_FORMAT, lidar, every):
            raise InputError(f"{out} holds a cache of lidar {old.get('lidar')!r}, every {old.get('every')}: "
                             "choose another --out")
        meta = old
    done = {e["id"] for e in meta["episodes"]}
    t0 = time.perf_counter()
    for n, r in enumerate(refs):
        if r.id in done:
            continue
        src = McapRecords([r], lidar, every)
        ticks = sorted({t for _e, t, _ego in src.keys})
        egos = [a for a in src.ds._agents[r.path] if a.rsplit("_", 1)[0] in src.ds.ego_kinds]
        records = [crop_record(src.record(r.id, t), egos, grid) for t in ticks]
        src.close()
        rel = Path(r.split) / f"{r.id}.npz"
        (out / rel.parent).mkdir(parents=True, exist_ok=True)
        write_episode_cache(out / rel, records)
        meta["episodes"].append({"id": r.id, "split": r.split, "file": str(rel), "egos": egos, "n_ticks": r.n_ticks,
                                 "conditions": r.conditions, "object_classes": list(r.object_classes)})
        meta_path.write_text(json.dumps(meta, indent=1) + "\n")
        if progress:
            progress(n + 1, len(refs), r.id)
    return {"episodes": len(meta["episodes"]), "s": time.perf_counter() - t0,
            "bytes": sum((out / e["file"]).stat().st_size for e in meta["episodes"])}
