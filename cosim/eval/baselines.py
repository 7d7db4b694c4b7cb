"""Reference baselines that need no training: prediction generators writing the documented format.

``oracle-noise``: for every (episode, tick, ego vehicle) and collaboration setting, the ground-truth
boxes that the setting's agents see (the visible ground truth), each dropped with probability
``miss_rate`` and otherwise perturbed: centre by N(0, ``pos_sigma_m``) along x and y, length/width/
height by a factor 1 + N(0, ``size_sigma``), yaw by N(0, ``yaw_sigma_deg``). Its score falls with the
perturbation, exp(-(|d_xy| + |d_size| + 2 |d_yaw|)), so better boxes rank first, as a calibrated
detector's would. With the episode's BEV grids it also writes BEV predictions: static layers copied
from the ground truth (a perfect map) and the object layers rasterised from its own boxes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.errors import InputError
from cosim.eval.dataset import DEFAULT_RULE, EpisodeRef, FrameTruth, VisibilityRule, iter_truth, require_visibility
from cosim.eval.predictions import SETTINGS, record_json
from cosim.io import Grid, open_episode
from cosim.snapshot import Actor, AgentState


@dataclass(frozen=True)
class OracleNoise:
    """Parameters of the ``oracle-noise`` baseline (see the module doc); ``seed`` fixes every draw."""

    pos_sigma_m: float = 0.0
    size_sigma: float = 0.0
    yaw_sigma_deg: float = 0.0
    miss_rate: float = 0.0
    seed: int = 0
    settings: tuple[str, ...] = tuple(SETTINGS)
    bev: bool = True

    def __post_init__(self) -> None:
        for name in ("pos_sigma_m", "size_sigma", "yaw_sigma_deg"):
            if not getattr(self, name) >= 0:
                raise InputError(f"oracle-noise: {name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.miss_rate <= 1:
            raise InputError(f"oracle-noise: miss_rate must be in [0, 1], got {self.miss_rate}")
        unknown = [s for s in self.settings if s not in SETTINGS]
        if unknown:
            raise InputError(f"oracle-noise: unknown setting {unknown[0]!r}; known: {', '.join(SETTINGS)}")

    def boxes(self, truth: FrameTruth, setting: str, rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...], np.ndarray]:
        """Noisy boxes (centres, sizes, yaws, classes, scores) of the objects ``setting`` sees."""
        idx = np.nonzero(require_visibility(truth, "the oracle-noise baseline")[setting])[0]
        n = len(idx)
        keep = rng.random(n) >= self.miss_rate
        d_xy = rng.normal(0.0, 1.0, (n, 2)) * self.pos_sigma_m
        d_size = rng.normal(0.0, 1.0, (n, 3)) * self.size_sigma
        d_yaw = rng.normal(0.0, 1.0, n) * math.radians(self.yaw_sigma_deg)
        centers = truth.centers_m[idx].copy()
        centers[:, :2] += d_xy
        sizes = np.maximum(truth.sizes_m[idx] * (1.0 + d_size), 0.05)
        yaws = truth.yaws_rad[idx] + d_yaw
        err = (np.linalg.norm(d_xy, axis=1) + np.linalg.norm(sizes - truth.sizes_m[idx], axis=1)
               + 2.0 * np.abs(d_yaw))
        scores = np.exp(-err)
        classes = tuple(truth.classes[i] for i in idx[keep])
        return centers[keep], sizes[keep], yaws[keep], classes, scores[keep]


BASELINES: dict[str, type[OracleNoise]] = {"oracle-noise": OracleNoise}


def baseline(name: str, **params: object) -> OracleNoise:
    """A registered baseline by name; unknown names list the known ones."""
    try:
        cls = BASELINES[name]
    except KeyError:
        raise InputError(f"unknown baseline {name!r}; known: {', '.join(BASELINES)}") from None
    return cls(**params)  # type: ignore[arg-type]


def write_predictions(model: OracleNoise, refs: Sequence[EpisodeRef], out_file: Path,
                      rule: VisibilityRule = DEFAULT_RULE,
                      progress: Callable[[int, int], None] | None = None) -> Path:
    """Run the baseline over every episode, tick, ego vehicle and setting; write one ``.jsonl`` file
    (and ``<stem>_bev/*.npz`` beside it when BEV is on and the episodes have BEV grids)."""
    out_file.parent.mkdir(parents=True, exist_ok=True)
    bev_dir = out_file.parent / f"{out_file.stem}_bev"
    tmp = out_file.with_name(f".{out_file.name}.partial")
    settings = [s for s in SETTINGS if s in model.settings]
    with open(tmp, "w", encoding="utf-8") as f:
        for n, ref in enumerate(refs):
            bevs = _bev_grids(ref) if model.bev else {}
            for truth in iter_truth(ref, rule=rule):
                grid = bevs.get((truth.tick, truth.ego))
                for si, setting in enumerate(settings):
                    rng = np.random.default_rng([model.seed, n, truth.tick, ref.agents.index(truth.ego), si])
                    c, s, y, k, p = model.boxes(truth, setting, rng)
                    bev_name = None
                    if grid is not None:
                        bev_name = f"{bev_dir.name}/{ref.id}_{truth.tick}_{truth.ego}_{setting}.npz"
                        _write_bev(out_file.parent / bev_name, grid, truth, c, s, y, k, ref.object_classes)
                    f.write(record_json(ref.id, truth.tick, truth.ego, setting, c, s, y, k, p, bev_name) + "\n")
            if progress:
                progress(n + 1, len(refs))
    tmp.replace(out_file)
    return out_file


def _bev_grids(ref: EpisodeRef) -> dict[tuple[int, str], Grid]:
    egos = [a for a in ref.agents if a.startswith("vehicle_")]
    with open_episode(ref.path) as ep:
        if not all(f"/{e}/bev" in ep.topics for e in egos):
            return {}
        return {(t.index, e): t.bev(e) for t in ep.ticks(topics=[f"/{e}/bev" for e in egos]) for e in egos}


def rasterise_boxes(grid: Grid, map_centers: np.ndarray, map_yaws: np.ndarray, sizes: np.ndarray,
                    classes: tuple[str, ...]) -> np.ndarray:
    """Object layers of the episode's BEV grid drawn from boxes in ``map`` (centres (N, 3), yaws (N,), sizes
    (N, 3)) by the BEV renderer itself (sensors/bev.py), so a perfect box fills exactly the true cells.

    Returns (rows, columns, len(BEV_LAYERS)) uint8; the static layers are empty.
    """
    from cosim.sensors.bev import StaticRaster, render_bev  # the sensor package loads Open3D: only when needed
    rows, cols = grid.cells.shape
    cell = float(grid.cell_size_m[0])
    q = grid.origin_rotation
    gyaw = math.atan2(2 * (q[3] * q[2] + q[0] * q[1]), 1 - 2 * (q[1] ** 2 + q[2] ** 2))
    hx, hy = cols * cell / 2, rows * cell / 2
    centre = (float(grid.origin_m[0] + math.cos(gyaw) * hx - math.sin(gyaw) * hy),
              float(grid.origin_m[1] + math.sin(gyaw) * hx + math.cos(gyaw) * hy), 0.0)

    def quat(yaw: float) -> tuple[float, float, float, float]:
        return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))

    viewer = AgentState("eval", "vehicle", centre, quat(gyaw))
    actors = tuple(Actor(i + 1, k, tuple(float(v) for v in c), tuple(float(v) for v in s), quat(float(y)),
                         (0.0, 0.0, 0.0), None)  # type: ignore[arg-type]
                   for i, (c, y, s, k) in enumerate(zip(map_centers, map_yaws, sizes, classes, strict=True)))
    empty = StaticRaster(np.zeros((1, 1), np.uint16), 0.0, 0.0, cell)
    return render_bev(viewer, empty, actors, cell, (hx, hy)).grid


def _write_bev(path: Path, grid: Grid, truth: FrameTruth, centers: np.ndarray, sizes: np.ndarray,
               yaws: np.ndarray, classes: tuple[str, ...], object_classes: tuple[str, ...]) -> None:
    names = grid.cells.dtype.names or ()
    if truth.ego_box is not None:  # the ego knows where it is: its own footprint is in its BEV
        c, s, y, k = truth.ego_box
        centers, sizes = np.vstack([centers, c]), np.vstack([sizes, s])
        yaws, classes = np.append(yaws, y), (*classes, k)
    map_from_ego = np.linalg.inv(truth.ego_from_map)
    map_centers = centers @ map_from_ego[:3, :3].T + map_from_ego[:3, 3]
    map_yaws = yaws + math.atan2(map_from_ego[1, 0], map_from_ego[0, 0])
    from cosim.sensors.bev import BEV_LAYERS

    drawn = rasterise_boxes(grid, map_centers, map_yaws, sizes, classes)
    layers: dict[str, np.ndarray] = {}
    for name in names:
        if name in object_classes and name in BEV_LAYERS:
            layers[name] = drawn[..., BEV_LAYERS.index(name)].astype(bool)
        else:  # the map layers: a perfect map prior
            layers[name] = grid.cells[name].astype(bool)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **layers)
