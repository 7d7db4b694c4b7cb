"""``cosim coverage``: ground-truth collaborative coverage, no model involved.

For every ego vehicle and tick, the objects of the scored classes inside its evaluation area are
counted, and for each collaboration setting (the ego alone, + the other vehicles, + RSUs, + drones,
all agents) those that at least one of the setting's agents sees (:class:`VisibilityRule`, from the
``/<agent>/visibility`` annotations). seen / objects is the recall a perfect model could reach with
that setting: an upper bound, broken down by lighting, weather, environment and drone strategy.
Heat maps show, in the ego frame, where the objects no agent sees and those only drones see lie.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.eval.dataset import (
    AREA_HALF_M,
    CONDITIONS,
    DEFAULT_RULE,
    VEHICLE_CLASSES,
    EpisodeRef,
    VisibilityRule,
    iter_truth,
    require_visibility,
)
from cosim.eval.predictions import SETTINGS
from cosim.eval.tables import Table, bar_plot, write_tables

log = logging.getLogger(__name__)

SETTING_LABELS: dict[str, str] = {
    "ego": "ego alone", "vehicles": "+ vehicles", "vehicles+rsus": "+ vehicles + RSUs",
    "vehicles+drones": "+ vehicles + drones", "all": "all agents",
}
HEAT_CELL_M = 4.0


@dataclass
class CoverageCounts:
    """Object instances (one per object, ego and tick) and how many each setting sees."""

    frames: int = 0
    objects: int = 0
    seen: dict[str, int] = field(default_factory=lambda: dict.fromkeys(SETTINGS, 0))

    def recall(self, setting: str) -> float:
        return 100.0 * self.seen[setting] / self.objects if self.objects else float("nan")


@dataclass
class CoverageResult:
    counts: dict[tuple[str, str], CoverageCounts]  # (breakdown, value) -> counts; ("overall", "all") first
    uncovered_xy: np.ndarray  # (K, 2) [m] ego frame: seen by no agent
    drone_only_xy: np.ndarray  # (K, 2) [m] ego frame: seen only by drones
    episodes: int
    rule: VisibilityRule
    classes: tuple[str, ...]


def compute_coverage(refs: Sequence[EpisodeRef], rule: VisibilityRule = DEFAULT_RULE,
                     classes: Sequence[str] = VEHICLE_CLASSES, egos: list[str] | None = None,
                     progress: Callable[[int, int], None] | None = None) -> CoverageResult:
    """Coverage counts over every episode, tick and ego (default: every vehicle agent)."""
    counts: dict[tuple[str, str], CoverageCounts] = {("overall", "all"): CoverageCounts()}
    uncovered: list[np.ndarray] = []
    drone_only: list[np.ndarray] = []
    wanted = set(classes)
    for n, ref in enumerate(refs):
        keys = [("overall", "all")] + [(c, ref.conditions.get(c, "?")) for c in CONDITIONS]
        for k in keys:
            counts.setdefault(k, CoverageCounts())
        for truth in iter_truth(ref, egos=egos, rule=rule):
            seen_by = require_visibility(truth, "coverage")
            mask = truth.in_area & np.array([c in wanted for c in truth.classes], bool)
            seen = {s: int(np.count_nonzero(seen_by[s] & mask)) for s in SETTINGS}
            for k in keys:
                c = counts[k]
                c.frames += 1
                c.objects += int(np.count_nonzero(mask))
                for s in SETTINGS:
                    c.seen[s] += seen[s]
            xy = truth.centers_m[:, :2]
            uncovered.append(xy[mask & ~seen_by["all"]])
            drone_only.append(xy[mask & seen_by["all"] & ~seen_by["vehicles+rsus"]])
        if progress:
            progress(n + 1, len(refs))
    return CoverageResult(counts, _stack(uncovered), _stack(drone_only), len(refs), rule, tuple(classes))


def _stack(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros((0, 2))


def coverage_tables(result: CoverageResult) -> list[Table]:
    """One table per breakdown (overall, lighting, weather, environment, strategy)."""
    columns = ["condition", "ego-ticks", "objects", *SETTING_LABELS.values(), "drones add", "RSUs add"]
    tables = []
    for breakdown in ("overall", *CONDITIONS):
        rows = []
        for (b, value), c in sorted(result.counts.items()):
            if b != breakdown:
                continue
            r = {s: c.recall(s) for s in SETTINGS}
            rows.append([value, c.frames, c.objects, *r.values(), r["all"] - r["vehicles+rsus"],
                         r["all"] - r["vehicles+drones"]])
        title = "Coverage by collaborating agent types" if breakdown == "overall" else f"Coverage by {breakdown}"
        tables.append(Table(f"coverage_{breakdown}", title, columns, rows,
                            note="Share of objects (in %) that at least one agent of the setting sees; "
                                 "`drones add` = all - (vehicles + RSUs), `RSUs add` = all - (vehicles + drones)."))
    return tables


def coverage_adds(result: CoverageResult) -> tuple[dict[tuple[str, str], float], dict[tuple[str, str], float]]:
    """``drones add`` and ``RSUs add`` [points] per (breakdown, value), as in :func:`coverage_tables`."""
    drones, rsus = {}, {}
    for k, c in result.counts.items():
        drones[k] = c.recall("all") - c.recall("vehicles+rsus")
        rsus[k] = c.recall("all") - c.recall("vehicles+drones")
    return drones, rsus


def write_coverage(result: CoverageResult, out_dir: Path) -> list[Path]:
    """coverage.md/.csv/.json, one bar plot per breakdown and the heat maps; returns the paths."""
    tables = coverage_tables(result)
    header = (f"# Collaborative coverage\n\n{result.episodes} episodes; classes {', '.join(result.classes)}; an "
              f"agent sees an object with >= {result.rule.min_points} LiDAR points or >= "
              f"{result.rule.min_pixels} instance pixels; evaluation area x within +-{AREA_HALF_M[0]} m, "
              f"y within +-{AREA_HALF_M[1]} m of the ego.\n")
    extra = {"rule": {"min_points": result.rule.min_points, "min_pixels": result.rule.min_pixels},
             "classes": list(result.classes), "episodes": result.episodes,
             "counts": [{"breakdown": b, "value": v, "ego_ticks": c.frames, "objects": c.objects, "seen": c.seen}
                        for (b, v), c in sorted(result.counts.items())]}
    paths = write_tables(tables, out_dir, "coverage", header, extra)
    for table in tables:
        breakdown = table.name.removeprefix("coverage_")
        groups = [str(r[0]) for r in table.rows]
        series = {label: [r[3 + i] for r in table.rows] for i, label in enumerate(SETTING_LABELS.values())}
        paths.append(bar_plot(out_dir / f"coverage_{breakdown}.png", table.title, groups, series,
                              ylabel="objects seen (%)"))
    paths.append(heat_maps(result, out_dir / "coverage_heatmap.png"))
    return paths


def heat_maps(result: CoverageResult, path: Path) -> Path:
    """Two BEV histograms in the ego frame: objects no agent sees, objects only drones see."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hx, hy = AREA_HALF_M
    xb = np.arange(-hx, hx + 1e-9, HEAT_CELL_M * 2)
    yb = np.arange(-hy, hy + 1e-9, HEAT_CELL_M)
    fig, axes = plt.subplots(2, 1, figsize=(10, 4.6), sharex=True)
    for ax, (title, xy) in zip(axes, (("seen by no agent", result.uncovered_xy),
                                      ("seen only by drones", result.drone_only_xy)), strict=True):
        h, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=(xb, yb))
        im = ax.imshow(h.T, origin="lower", extent=(-hx, hx, -hy, hy), aspect="equal", cmap="magma",
                       vmin=0, vmax=max(1.0, float(h.max())))
        ax.plot([0], [0], marker=">", color="cyan", markersize=8)
        ax.set_title(f"objects {title} ({len(xy)} object-ticks)", fontsize=10)
        ax.set_ylabel("y left (m)")
        fig.colorbar(im, ax=ax, label="count")
    axes[-1].set_xlabel("x forward (m), ego LiDAR frame (ego at the cyan marker)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
