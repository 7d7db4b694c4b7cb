"""Sweep files: base scenario(s) times axes, with weights, a size (count or driving hours) and a split.

A sweep is validated like a scenario: frozen pydantic models with ``extra="forbid"``, parsed with the
scenario loader's YAML machinery (line marks, duplicate keys refused), and every problem becomes a
:class:`SweepError` naming the dotted key path and the line it came from.

Example (``sweeps/airv2x_like.yaml`` is the full one)::

    name: small
    base: ../scenarios/base/paper.yaml     # or a list of bases, or a shipped scenario's name
    set: {sensors.enabled: false, duration_s: 2}
    axes:
      weather: {key: environment.weather, values: [clear, foggy]}
      strategy:
        levels:
          - {label: hover, set: {agents.drones: [{strategy: hover}]}}
          - {label: patrol, set: {agents.drones: [{strategy: patrol}]}, weight: 2}
    vary:
      agents.vehicles.count: {choice: [3, 4, 5]}
      traffic.density_veh_per_km: {uniform: [6, 14]}
    count: 6
    split: {train: 2.19, val: 1.02, test: 3.52}
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, Discriminator, Field, Tag, ValidationError, model_validator

from cosim.errors import ScenarioError
from cosim.scenario.loader import (
    YamlDoc,
    clean_error_loc,
    error_message,
    find_yaml,
    located_error,
    parse_yaml,
    unknown_key_message,
)
from cosim.scenario.model import Model as ScenarioModel
from cosim.scenario.model import RuleError

LABEL_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.]*$"  # no '-': it separates the parts of an episode id
Scalar = str | int | float | bool


class SweepError(ScenarioError):
    """A sweep file (or a scenario it produces) is invalid. Exit status 2."""


#: The most episodes one plan may hold (every one is validated while planning; 100 000 episodes of 20 s are
#: 555 hours of driving, far beyond any published V2X data set).
MAX_EPISODES = 100_000


class Model(ScenarioModel):
    """The scenario schema's base: frozen, no unknown keys, strict numbers and booleans."""


class Level(Model):
    """One value of an axis: a label (part of the episode id), overrides, optionally another base."""

    label: str = Field(pattern=LABEL_PATTERN)
    set: dict[str, Any] = Field(default_factory=dict)  # dotted scenario key -> value
    base: str | None = None  # scenario file (relative to the sweep) or shipped name replacing the base
    weight: float = Field(1.0, gt=0)


class Axis(Model):
    """Either ``key`` + ``values`` (+ ``weights``) for one scenario key, or explicit ``levels``."""

    key: str | None = None
    values: list[Scalar] | None = None
    weights: list[float] | None = None
    levels: list[Level] | None = None

    @model_validator(mode="after")
    def _one_form(self) -> Axis:
        if self.levels is not None:
            if self.key is not None or self.values is not None:
                raise RuleError("levels", "an axis has either key + values or levels, not both")
            if self.weights is not None:
                raise RuleError("weights", "with levels, give each level its own weight")
            if not self.levels:
                raise RuleError("levels", "an axis needs at least one level")
            labels = [lv.label for lv in self.levels]
            dupes = sorted({x for x in labels if labels.count(x) > 1})
            if dupes:
                raise RuleError("levels", f"level labels must be unique; repeated: {', '.join(dupes)}")
            return self
        if self.key is None or self.values is None:
            raise RuleError("key", "an axis needs key + values, or levels")
        if not self.values:
            raise RuleError("values", "an axis needs at least one value")
        if self.weights is not None:
            if len(self.weights) != len(self.values):
                raise RuleError("weights", f"{len(self.weights)} weights for {len(self.values)} values")
            if any(w <= 0 for w in self.weights):
                raise RuleError("weights", f"weights must be > 0, got {self.weights}")
        labels = [value_label(v) for v in self.values]
        for i, lab in enumerate(labels):
            if not re.match(LABEL_PATTERN, lab):
                raise RuleError(f"values.{i}", f"value {self.values[i]!r} cannot name an episode; "
                                               "use levels with a label instead")
        if len(set(labels)) != len(labels):
            raise RuleError("values", f"values must be distinct, got {self.values}")
        return self

    def resolved_levels(self) -> tuple[Level, ...]:
        if self.levels is not None:
            return tuple(self.levels)
        weights = self.weights or [1.0] * len(self.values or [])
        return tuple(Level(label=value_label(v), set={self.key: v}, weight=w)
                     for v, w in zip(self.values or [], weights, strict=True))


class Choice(Model):
    """Draw one of ``choice`` per episode (from the episode's own seed)."""

    choice: list[Any] = Field(min_length=1)
    weights: list[float] | None = None

    @model_validator(mode="after")
    def _weights(self) -> Choice:
        if self.weights is not None and (len(self.weights) != len(self.choice) or any(w < 0 for w in self.weights)
                                         or sum(self.weights) <= 0):
            raise RuleError("weights", f"need {len(self.choice)} weights >= 0 with a positive sum, "
                                       f"got {self.weights}")
        return self


class Uniform(Model):
    """Draw a float uniformly in [low, high) per episode, rounded to ``decimals``."""

    uniform: tuple[float, float]
    decimals: int = Field(2, ge=0, le=9)

    @model_validator(mode="after")
    def _range(self) -> Uniform:
        lo, hi = self.uniform
        if not lo <= hi:
            raise RuleError("uniform", f"need low <= high, got {list(self.uniform)}")
        return self


def _vary_kind(value: Any) -> str:
    if isinstance(value, dict):
        return "uniform" if "uniform" in value else "choice"
    return "uniform" if isinstance(value, Uniform) else "choice"


VarySpec = Annotated[Annotated[Choice, Tag("choice")] | Annotated[Uniform, Tag("uniform")],
                     Discriminator(_vary_kind)]


class Sweep(Model):
    name: str = Field(pattern=LABEL_PATTERN)
    description: str = ""
    seed: int = Field(0, ge=0, lt=2**31)  # episode seeds are derived from this and the episode id
    base: str | list[str]
    set: dict[str, Any] = Field(default_factory=dict)  # applied to every episode
    axes: dict[str, Axis] = Field(default_factory=dict)  # the grid, in this order (ids follow it)
    vary: dict[str, VarySpec] = Field(default_factory=dict)  # per-episode random draws
    count: int | None = Field(None, ge=1, le=MAX_EPISODES)  # episodes in total (all splits)
    hours: float | None = Field(None, gt=0)  # or: driving time budget in total
    cover_all: bool = True  # every split gets every combination when it has enough episodes
    split: dict[str, float] = Field(default_factory=lambda: {"all": 1.0})

    @model_validator(mode="after")
    def _rules(self) -> Sweep:
        if self.count is not None and self.hours is not None:
            raise RuleError("hours", "give count or hours, not both")
        for name in self.axes:
            if not re.match(LABEL_PATTERN, name) or name == "base":
                raise RuleError(f"axes.{name}", f"axis name {name!r} must match {LABEL_PATTERN} and not be 'base'")
        if isinstance(self.base, list) and not self.base:
            raise RuleError("base", "base needs at least one scenario")
        if not self.split:
            raise RuleError("split", "split needs at least one part")
        for part, w in self.split.items():
            if not re.match(LABEL_PATTERN, part):
                raise RuleError(f"split.{part}", f"split name {part!r} must match {LABEL_PATTERN}")
            if w <= 0:
                raise RuleError(f"split.{part}", f"split weights must be > 0, got {w}")
        return self

    def all_axes(self) -> dict[str, tuple[Level, ...]]:
        """The grid axes, with a list of bases turned into a leading axis named ``base``."""
        out: dict[str, tuple[Level, ...]] = {}
        if isinstance(self.base, list) and len(self.base) > 1:
            out["base"] = tuple(Level(label=_base_label(b), base=b) for b in self.base)
        for name, axis in self.axes.items():
            out[name] = axis.resolved_levels()
        return out

    @property
    def default_base(self) -> str:
        return self.base[0] if isinstance(self.base, list) else self.base


def value_label(value: Scalar) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _base_label(base: str) -> str:
    stem = Path(base).stem
    return re.sub(r"[^A-Za-z0-9_.]", "_", stem) or "base"


# --------------------------------------------------------------------------------------- loading


def _sweep_model_at(path: list[str | int]) -> type[BaseModel] | None:
    """The model owning the mapping at ``path`` (for 'did you mean' hints)."""
    if not path:
        return Sweep
    if len(path) == 2 and path[0] == "axes":
        return Axis
    if len(path) == 4 and path[0] == "axes" and path[2] == "levels":
        return Level
    if len(path) == 2 and path[0] == "vary":
        return None
    return None


def _sweep_message(err: dict[str, Any], path: list[str | int], data: Any) -> str:
    if err["type"] == "extra_forbidden":
        return unknown_key_message(str(path[-1]), _sweep_model_at(path[:-1]))
    return error_message(err, path, data)


def _clean_loc(loc: Sequence[str | int], data: Any) -> list[str | int]:
    """Sweep locations: drop pydantic's type tags and the ``vary`` union tags, then clean as scenarios do."""
    loc = [p for p in loc if not (isinstance(p, str) and p in ("str", "list[str]"))]
    if len(loc) >= 3 and loc[0] == "vary" and loc[2] in ("choice", "uniform"):
        del loc[2]  # the union tag, not a key
    return clean_error_loc(loc, data)


def _error(exc: ValidationError, doc: YamlDoc, source: str) -> SweepError:
    err = located_error(exc, doc, error_cls=SweepError, clean=_clean_loc, message=_sweep_message)
    if not err.source:
        err = SweepError(err.detail, path=err.path, line=err.line, source=source, problems=err.problems,
                         more=err.more)
    return err


def sweep_dirs() -> list[Path]:
    """Where shipped sweeps live: $COSIM_SWEEP_PATH (os.pathsep-separated), ./sweeps, the checkout's sweeps/."""
    dirs = [Path(p) for p in os.environ.get("COSIM_SWEEP_PATH", "").split(os.pathsep) if p]
    return [*dirs, Path.cwd() / "sweeps", Path(__file__).resolve().parents[2] / "sweeps"]


def find_sweep(name_or_path: str | Path) -> Path:
    """A sweep path as given, or the name of a shipped one (``airv2x_like``)."""
    found = find_yaml(name_or_path, sweep_dirs())
    if found is not None:
        return found
    raise SweepError(f"sweep file not found: {name_or_path}", source=str(name_or_path))


def load_sweep(path: str | Path) -> tuple[Sweep, YamlDoc]:
    """Parse and validate a sweep file; returns the model and the parsed document (for line marks)."""
    file = find_sweep(path)
    try:
        doc = parse_yaml(file)
    except ScenarioError as exc:
        raise SweepError(exc.detail, path=exc.path, line=exc.line, source=exc.source) from None
    try:
        sweep = Sweep.model_validate(json.loads(json.dumps(doc.data)))
    except ValidationError as exc:
        raise _error(exc, doc, str(file)) from None
    return sweep, doc
