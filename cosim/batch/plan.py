"""Planning: a sweep becomes a deterministic list of episodes, each with its id, split, parameters and seed.

The plan depends only on the sweep file, the size (count or hours) and the command-line overrides:
never on the number of workers, the backend or the order episodes finish in. An episode's seed is
derived from the sweep seed and the episode id, so growing a sweep keeps the episodes it already had.

Allocation: the total is shared between the splits by largest remainder over the split weights; in
each split the combinations of the axes get their episodes by :func:`balanced_allocation`: every
combination once when there is room (``cover_all``), and at any size each axis's levels in
proportion to their weights, so even a small preview is balanced.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from cosim.batch.sweep import MAX_EPISODES, Choice, Level, Sweep, SweepError, find_sweep, load_sweep
from cosim.errors import ScenarioError
from cosim.scenario.loader import YamlDoc, apply_override, find_scenario, load_with_extends, validate_doc

VARY_STREAM = 0x7A5  # random stream of the per-episode draws (``vary``)


@dataclass(frozen=True)
class Episode:
    """One planned episode. ``params`` are the values that differ between episodes of the sweep."""

    id: str
    index: int  # position in the full plan (sharding uses it)
    split: str
    labels: dict[str, str]  # axis name -> level label
    params: dict[str, Any]  # dotted scenario key -> value (axes, vary draws and the seed)
    seed: int
    duration_s: float  # simulated [s]
    scenario: dict[str, Any] = field(repr=False)  # the resolved, validated scenario data
    base_dir: str = field(repr=False)  # folder relative map files resolve against

    @property
    def fingerprint(self) -> str:
        """sha256 of the resolved scenario: a changed ``--set`` or base file means a different episode."""
        return hashlib.sha256(json.dumps(self.scenario, sort_keys=True).encode()).hexdigest()

    @property
    def file(self) -> str:
        """Path of the episode file relative to the output folder."""
        return f"{self.split}/{self.id}.mcap"

    @property
    def conditions(self) -> dict[str, str]:
        """``weather``, ``lighting`` and ``environment`` (the map kind) of the resolved scenario."""
        env = self.scenario.get("environment", {})
        return {"weather": str(env.get("weather", "?")), "lighting": str(env.get("lighting", "?")),
                "environment": str(self.scenario.get("map", {}).get("kind", "?"))}

    def describe(self, drawn_keys: Sequence[str] = ()) -> str:
        """One line of the dry run's plan: file, seed, duration, ``weather/lighting/environment`` and the
        values of ``drawn_keys`` (the sweep's ``vary`` keys) this episode drew, e.g.
        ``all/all-urban-0000.mcap  seed 17  2 s  rainy/dusk/urban  agents.vehicles.count=3``."""
        cond = "/".join(self.conditions.values())
        drawn = " ".join(f"{k}={json.dumps(self.params[k])}" for k in drawn_keys
                         if k in self.params and k not in _CONDITION_KEYS)
        return f"{self.file}  seed {self.seed}  {self.duration_s:g} s  {cond}" + (f"  {drawn}" if drawn else "")


#: Scenario keys :attr:`Episode.conditions` shows already.
_CONDITION_KEYS = frozenset({"environment.weather", "environment.lighting", "map.kind"})


@dataclass(frozen=True)
class Plan:
    sweep: Sweep
    episodes: tuple[Episode, ...]
    combinations: int
    warnings: tuple[str, ...] = ()
    shard: tuple[int, int] = (0, 1)

    @property
    def sim_seconds(self) -> float:
        return sum(e.duration_s for e in self.episodes)

    def sharded(self, index: int, count: int) -> Plan:
        """Episodes ``index, index + count, ...`` of this plan (round robin over the plan order)."""
        if count < 1 or not 0 <= index < count:
            raise SweepError(f"shard must be i/k with 0 <= i < k, got {index}/{count}", source="--shard")
        picked = tuple(e for e in self.episodes if e.index % count == index)
        return replace(self, episodes=picked, shard=(index, count))

    def only_splits(self, names: Sequence[str]) -> Plan:
        """The episodes of these splits only (e.g. the test split again at another tick rate): each keeps its
        id, seed and parameters, so the episodes are those of the whole plan."""
        unknown = [n for n in names if n not in self.sweep.split]
        if unknown:
            raise SweepError(f"no split {', '.join(map(repr, unknown))} in sweep {self.sweep.name!r} "
                             f"(its splits: {', '.join(self.sweep.split)})", source="--split")
        return replace(self, episodes=tuple(e for e in self.episodes if e.split in names))


def derive_seed(sweep_seed: int, episode_id: str) -> int:
    """Scenario seed of an episode: a hash of the sweep seed and the episode id, in [0, 2**31)."""
    digest = hashlib.sha256(f"{sweep_seed}/{episode_id}".encode()).digest()
    return int.from_bytes(digest[:8], "big") % (2**31)


def _tiebreak(seed: int, key: str) -> int:
    return int.from_bytes(hashlib.sha256(f"tie/{seed}/{key}".encode()).digest()[:8], "big")


def largest_remainder(total: int, weights: Sequence[float], keys: Sequence[str], seed: int = 0) -> list[int]:
    """Whole numbers summing to ``total`` proportional to ``weights`` (Hamilton's method).

    Equal remainders are ordered by a hash of ``keys`` so no key wins merely by coming first.
    """
    if total < 0:
        raise ValueError(f"total must be >= 0, got {total}")
    w = np.asarray(weights, dtype=float)
    quota = total * w / w.sum()
    out = np.floor(quota).astype(int)
    rest = total - int(out.sum())
    order = sorted(range(len(w)), key=lambda i: (-(quota[i] - out[i]), _tiebreak(seed, keys[i])))
    for i in order[:rest]:
        out[i] += 1
    return [int(x) for x in out]


def balanced_allocation(total: int, levels: Sequence[Sequence[float]], *, seed: int = 0,
                        cover_all: bool = True) -> list[int]:
    """Episodes per combination of the axes: ``total`` picks, each of the most under-represented one.

    ``levels[j]`` are the weights of axis j's levels; combinations are enumerated as by
    :func:`itertools.product` (last axis fastest) and returned in that order. Pick k goes to the
    combination whose levels (every axis) and whose own count lag furthest behind their weighted
    targets; with ``cover_all`` the first picks go to combinations not yet taken, so every
    combination appears once ``total`` allows. Ties are broken by a random order fixed by ``seed``.
    The picks never depend on ``total``: a larger total extends a smaller one (episodes are kept).
    """
    index = np.array(list(itertools.product(*(range(len(w)) for w in levels))), dtype=np.int64)
    n_comb = len(index)
    index = index.reshape(n_comb, len(levels))
    shares = [np.asarray(w, dtype=float) / float(np.sum(w)) for w in levels]
    joint = np.ones(n_comb)
    for j, share in enumerate(shares):
        joint *= share[index[:, j]]
    counts = np.zeros(n_comb, dtype=np.int64)
    marginal = [np.zeros(len(share)) for share in shares]
    priority = np.random.default_rng([seed, 0xA110C]).permutation(n_comb)
    for k in range(1, total + 1):
        score = counts + 1 - k * joint
        for j, share in enumerate(shares):
            score = score + (marginal[j] + 1 - k * share)[index[:, j]]
        if cover_all and k <= n_comb:
            score = np.where(counts == 0, score, np.inf)
        best = np.flatnonzero(score <= score.min() + 1e-9)
        pick = int(best[np.argmin(priority[best])])
        counts[pick] += 1
        priority[pick] += n_comb  # the next tie goes to another combination
        for j in range(len(levels)):
            marginal[j][index[pick, j]] += 1
    return [int(c) for c in counts]


def _resolve_base(name: str, sweep_dir: Path) -> Path:
    p = Path(name)
    cand = p if p.is_absolute() else sweep_dir / p
    if cand.is_file():
        return cand.resolve()
    return find_scenario(name).resolve()


def _assignment(key: str, value: Any) -> str:
    return f"{key}={json.dumps(value)}"


class _Builder:
    """Validates episode scenarios: each base parsed once, overrides applied with the loader's ``--set``."""

    def __init__(self, sweep_doc: YamlDoc | None, sweep_source: str, sweep_dir: Path):
        self.doc, self.source, self.dir = sweep_doc, sweep_source, sweep_dir
        self._bases: dict[str, tuple[Path, YamlDoc]] = {}

    def base(self, name: str, origin: tuple[str | int, ...]) -> tuple[Path, YamlDoc]:
        if name not in self._bases:
            try:
                path = _resolve_base(name, self.dir)
                self._bases[name] = (path, load_with_extends(path))
            except ScenarioError as exc:
                raise self._error(f"base scenario {name!r}: {exc}", origin) from None
        return self._bases[name]

    def _error(self, message: str, origin: tuple[str | int, ...]) -> SweepError:
        line = None
        if self.doc is not None:
            for n in range(len(origin), -1, -1):
                mark = self.doc.marks.get(tuple(origin[:n]))
                if mark is not None:
                    line = mark[1]
                    break
        return SweepError(message, path=".".join(str(p) for p in origin), line=line, source=self.source)

    def build(self, base: str, base_origin: tuple[str | int, ...],
              overrides: list[tuple[str, tuple[str | int, ...]]], what: str) -> tuple[dict[str, Any], float, str]:
        """Validate one scenario; returns (resolved data, duration_s, base folder)."""
        path, doc = self.base(base, base_origin)
        work = YamlDoc(copy.deepcopy(doc.data), dict(doc.marks))
        for assignment, origin in overrides:
            try:
                apply_override(work, assignment)
            except ScenarioError as exc:
                raise self._error(f"{what}: {exc.detail} ({assignment})", origin) from None
        try:
            loaded = validate_doc(work, path)
        except ScenarioError as exc:
            origin = next((o for a, o in reversed(overrides) if exc.path and
                           (exc.path == a.split("=", 1)[0] or exc.path.startswith(a.split("=", 1)[0] + "."))),
                          base_origin)
            raise self._error(f"{what}: {exc}", origin) from None
        return loaded.resolved, loaded.scenario.duration_s, str(path.parent)


def _common_overrides(sweep: Sweep, cli_set: Sequence[str]) -> list[tuple[str, tuple[str | int, ...]]]:
    out = [(_assignment(k, v), ("set", k)) for k, v in sweep.set.items()]
    out += [(a, ("--set",)) for a in cli_set]
    return out


def _draw(sweep: Sweep, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng([sweep.seed, seed, VARY_STREAM])
    out: dict[str, Any] = {}
    for key, spec in sweep.vary.items():
        if isinstance(spec, Choice):
            p = None
            if spec.weights is not None:
                w = np.asarray(spec.weights, dtype=float)
                p = w / w.sum()
            out[key] = spec.choice[int(rng.choice(len(spec.choice), p=p))]
        else:
            lo, hi = spec.uniform
            value = round(float(rng.uniform(lo, hi)), spec.decimals)
            out[key] = int(value) if spec.decimals == 0 else value
    return out


def episode_total(sweep: Sweep, nominal_duration_s: float, *, count: int | None = None,
                  hours: float | None = None, scale: float = 1.0) -> int:
    """How many episodes: ``count``, else ``hours`` of driving at the nominal episode length, times ``scale``."""
    if count is None and hours is None:
        count, hours = sweep.count, sweep.hours
    if count is not None:
        total = count * scale
    elif hours is not None:
        total = hours * 3600.0 * scale / nominal_duration_s
    else:
        total = math.prod(len(levels) for levels in sweep.all_axes().values()) * len(sweep.split) * scale
    if not total <= MAX_EPISODES:  # also NaN and infinity
        raise ValueError(f"{total:.6g} episodes cannot be planned: at most {MAX_EPISODES} per plan (split a larger "
                         "data set into several sweeps)")
    return max(1, round(total))


def plan_sweep(
    sweep: Sweep,
    *,
    sweep_dir: Path | str = ".",
    sweep_doc: YamlDoc | None = None,
    source: str = "sweep",
    count: int | None = None,
    hours: float | None = None,
    scale: float = 1.0,
    cli_set: Sequence[str] = (),
) -> Plan:
    """Expand a sweep into its episodes (validating every episode's scenario)."""
    if not 0 < scale < math.inf:
        raise SweepError(f"scale must be a finite number > 0, got {scale}", source="--scale")
    builder = _Builder(sweep_doc, source, Path(sweep_dir))
    common = _common_overrides(sweep, cli_set)
    _, nominal_s, _ = builder.build(sweep.default_base, ("base",), common, "the base scenario")
    try:
        total = episode_total(sweep, nominal_s, count=count, hours=hours, scale=scale)
    except ValueError as exc:
        if count is not None or hours is not None:
            raise SweepError(str(exc), source="--count" if count is not None else "--hours") from None
        what = "count" if sweep.count is not None else "hours" if sweep.hours is not None else "axes"
        raise builder._error(str(exc), (what,)) from None

    axes = sweep.all_axes()
    names = list(axes)
    combos: list[tuple[Level, ...]] = list(itertools.product(*axes.values()))
    keys = ["-".join(lv.label for lv in combo) for combo in combos]
    level_weights = [[lv.weight for lv in levels] for levels in axes.values()]
    splits = list(sweep.split)
    per_split = largest_remainder(total, list(sweep.split.values()), splits, sweep.seed)

    warnings: list[str] = []
    episodes: list[Episode] = []
    for split, n_split in zip(splits, per_split, strict=True):
        if sweep.cover_all and 0 < n_split < len(combos):
            warnings.append(f"split {split}: {n_split} episodes cannot cover all {len(combos)} combinations")
        alloc = balanced_allocation(n_split, level_weights, seed=sweep.seed, cover_all=sweep.cover_all)
        for combo, key, n in zip(combos, keys, alloc, strict=True):
            for r in range(n):
                episode_id = "-".join(p for p in (split, key, f"{r:04d}") if p)
                seed = derive_seed(sweep.seed, episode_id)
                base, base_origin = sweep.default_base, ("base",)
                overrides = list(common)
                overrides.append((f"seed={seed}", ("seed",)))
                params: dict[str, Any] = {}
                for name, level in zip(names, combo, strict=True):
                    origin = ("axes", name)
                    if level.base is not None:
                        base, base_origin = level.base, ("base",) if name == "base" else origin
                    for k, v in level.set.items():
                        overrides.append((_assignment(k, v), origin))
                        params[k] = v
                for k, v in _draw(sweep, seed).items():
                    overrides.append((_assignment(k, v), ("vary", k)))
                    params[k] = v
                overrides.append((_assignment("output.name", episode_id), ("name",)))
                resolved, duration_s, base_dir = builder.build(base, base_origin, overrides, f"episode {episode_id}")
                params["seed"] = resolved["seed"]  # derived, unless an axis sets the seed itself
                episodes.append(Episode(
                    id=episode_id, index=len(episodes), split=split,
                    labels={n: lv.label for n, lv in zip(names, combo, strict=True)},
                    params=params, seed=resolved["seed"], duration_s=duration_s, scenario=resolved,
                    base_dir=base_dir,
                ))
    return Plan(sweep=sweep, episodes=tuple(episodes), combinations=len(combos), warnings=tuple(warnings))


def plan_file(path: str | Path, **kwargs: Any) -> Plan:
    """Load a sweep file and plan it (``kwargs`` as :func:`plan_sweep`)."""
    file = find_sweep(path)
    sweep, doc = load_sweep(file)
    return plan_sweep(sweep, sweep_dir=file.parent, sweep_doc=doc, source=str(file), **kwargs)
