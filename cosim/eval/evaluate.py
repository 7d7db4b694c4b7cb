"""``cosim eval``: score predictions against an episode or a batch, broken down like the paper's tables.

Detection: AP at BEV IoU 0.3, 0.5 and 0.7 (:mod:`cosim.eval.ap`) for the vehicle classes together
(``vehicle``) and per object class, per collaboration setting (the ``agents`` field of the records)
and per condition (overall, lighting, weather, environment, drone strategy). Segmentation: IoU per
BEV layer and their mean, from predicted grids against ``/<ego>/bev``.

Each metric is an accumulator registered by name in :data:`METRICS` (``detection``, ``segmentation``;
:class:`Metric`): it scores one frame, merges frames into the cells of the breakdowns, and gives its
summary (``EvalResult.metrics()[name]``), its tables and plots; ``cosim eval --metric NAME`` picks some.

Default (correct) behaviour and ``compat="airv2x"`` (the AirV2X release's scripts):

=============================  ===================================  =====================================
what                           default                              ``--compat airv2x``
=============================  ===================================  =====================================
ranking of detections          global by score over all frames      per-frame lists concatenated in frame
                                                                    order (AP depends on frame order)
frame without any detection    its ground truth counts (misses)     skipped: its ground truth never counts
no ground truth at all         AP n/a                               AP 0
ground truth in the area       box centre inside x +-140.8, y +-40  all 8 corners inside x +-140.8, y +-40
                                                                    and z in [-3, 1] m (tall boxes drop)
segmentation IoU               intersection / union summed over     per-frame IoU averaged over frames; a
                               all frames per layer                 layer absent from both counts 1.0;
                                                                    a random subset of 1000 frames (seeded)
=============================  ===================================  =====================================
"""

from __future__ import annotations

import logging
import math
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from cosim.errors import InputError
from cosim.eval.ap import THRESHOLDS, DetectionAccumulator
from cosim.eval.boxes import footprints
from cosim.eval.dataset import (
    AREA_HALF_M,
    CONDITIONS,
    DEFAULT_RULE,
    VEHICLE_CLASSES,
    EpisodeRef,
    FrameTruth,
    VisibilityRule,
    agent_kind,
    iter_truth,
    require_visibility,
)
from cosim.eval.predictions import SETTINGS, FramePrediction, PredictionError, iter_bev_layers
from cosim.eval.tables import Table, bar_plot, write_tables
from cosim.io import open_episode
from cosim.registry import Registry

log = logging.getLogger(__name__)

VEHICLE_GROUP = "vehicle"
COMPAT_MODES = ("airv2x",)
RELEASE_SEG_SUBSET = 1000


@dataclass(frozen=True)
class EvalOptions:
    """``visible_only``: drop ground truth no agent of the record's setting sees (the literature's
    "visible" ground truth); ``compat``: None or ``airv2x``; ``seed``: the compat segmentation subset;
    ``metrics``: the names of the metrics to compute (None: all)."""

    thresholds: tuple[float, ...] = THRESHOLDS
    visible_only: bool = False
    rule: VisibilityRule = DEFAULT_RULE
    compat: str | None = None
    seed: int = 0
    metrics: tuple[str, ...] | None = None  # names in METRICS; None: every registered metric

    def __post_init__(self) -> None:
        if self.compat is not None and self.compat not in COMPAT_MODES:
            raise InputError(f"unknown --compat {self.compat!r}; known: {', '.join(COMPAT_MODES)}")
        for name in self.metrics or ():
            METRICS.get(name)

    def active_metrics(self) -> list[tuple[str, type[Metric]]]:
        """(name, class) of the metrics to compute, in registration order."""
        return [(n, m) for n, m in METRICS.items() if self.metrics is None or n in self.metrics]


@dataclass(frozen=True)
class FrameInputs:
    """What a metric scores in one frame: the prediction record, the ground truth, the options, the
    ground-truth BEV grid (None without one) and the set of detection groups seen (to extend)."""

    rec: FramePrediction
    truth: FrameTruth
    options: EvalOptions
    gt_bev: Any
    groups: set[str]


class Metric:
    """An evaluation metric: an accumulator over frames, registered in :data:`METRICS` under its name.

    :meth:`score` gives one frame's accumulator, :meth:`empty` a fresh one, :meth:`merge` adds another
    one into this; :meth:`summary` is ``EvalResult.metrics()[name]``; :meth:`tables` and :meth:`plots` add
    to the report (``eval.md``/``.csv``/``.json`` and PNGs); :meth:`finish` runs once on every cell after
    the last frame."""

    name: ClassVar[str] = ""

    @classmethod
    def empty(cls, options: EvalOptions) -> Metric:
        raise NotImplementedError

    @classmethod
    def score(cls, frame: FrameInputs) -> Metric | None:
        raise NotImplementedError

    def merge(self, other: Any) -> None:
        raise NotImplementedError

    def summary(self, options: EvalOptions) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def tables(cls, result: EvalResult) -> list[Table]:
        return []

    @classmethod
    def plots(cls, result: EvalResult, out_dir: Path) -> list[Path]:
        return []

    @classmethod
    def finish(cls, cells: dict[tuple[str, str, str], Cell], options: EvalOptions) -> None:
        return None


#: Evaluation metrics by name: a duplicate name is an error, an unknown one lists the known ones.
METRICS: Registry[type[Metric]] = Registry("metric")


def register_metric(name: str):
    """Class decorator: add a :class:`Metric` under ``name`` (its key in ``EvalResult.metrics()``)."""

    def add(cls: type[Metric]) -> type[Metric]:
        METRICS.add(name, cls)
        cls.name = name
        return cls

    return add


@dataclass
class SegAccumulator(Metric):
    """BEV segmentation IoU per layer and their mean. Per layer: summed intersection and union (default) and
    per-frame IoUs (release mode)."""

    inter: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    union: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    frame_ious: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    frames: int = 0

    def add(self, layer: str, pred: np.ndarray, gt: np.ndarray) -> None:
        i = int(np.count_nonzero(pred & gt))
        u = int(np.count_nonzero(pred | gt))
        self.inter[layer] += i
        self.union[layer] += u
        self.frame_ious[layer].append(i / u if u else 1.0)

    def merge(self, other: SegAccumulator) -> None:
        for k in other.union:
            self.inter[k] += other.inter[k]
            self.union[k] += other.union[k]
            self.frame_ious[k].extend(other.frame_ious[k])
        self.frames += other.frames

    def ious(self, release: bool) -> dict[str, float]:
        if release:
            return {k: float(np.mean(v)) for k, v in sorted(self.frame_ious.items()) if v}
        return {k: (self.inter[k] / self.union[k] if self.union[k] else float("nan")) for k in sorted(self.union)}

    @classmethod
    def empty(cls, options: EvalOptions) -> SegAccumulator:
        return cls()

    @classmethod
    def score(cls, frame: FrameInputs) -> SegAccumulator:
        rec, gt_bev = frame.rec, frame.gt_bev
        out = cls()
        if rec.bev_path is not None and gt_bev is not None:
            names_layers = gt_bev.cells.dtype.names or ()
            for layer, pred in iter_bev_layers(rec, gt_bev.cells.shape, names_layers):
                out.add(layer, pred, gt_bev.cells[layer].astype(bool))
            out.frames = 1
        return out

    def summary(self, options: EvalOptions) -> dict[str, Any]:
        ious = self.ious(options.compat == "airv2x")
        if not ious:
            return {}
        valid = [v for v in ious.values() if not math.isnan(v)]
        return {"mIoU": 100.0 * float(np.mean(valid)) if valid else float("nan"),
                "iou": {k: 100.0 * v for k, v in ious.items()}, "frames": self.frames}

    @classmethod
    def tables(cls, result: EvalResult) -> list[Table]:
        settings = [s for s in SETTINGS if (s, "overall", "all") in result.cells]
        if not any(result.metrics(s)["segmentation"] for s in settings):
            return []
        layers = sorted({k for s in settings for k in result.metrics(s)["segmentation"].get("iou", {})})
        rows = [[s, *[result.metrics(s)["segmentation"].get("iou", {}).get(k, float("nan")) for k in layers]]
                for s in settings]
        return [Table("segmentation", "BEV segmentation IoU per layer", ["agents", *layers], rows)]

    @classmethod
    def finish(cls, cells: dict[tuple[str, str, str], Cell], options: EvalOptions) -> None:
        if options.compat == "airv2x":
            _release_subset(cells, options.seed)


@dataclass
class Cell:
    """Everything accumulated for one (setting, breakdown, value): frames and each metric's accumulator."""

    frames: int = 0
    results: dict[str, Metric] = field(default_factory=dict)

    def merge(self, frame: Cell, options: EvalOptions) -> None:
        for name, acc in frame.results.items():
            self.results.setdefault(name, METRICS.get(name).empty(options)).merge(acc)

    @property
    def detection(self) -> dict[str, DetectionAccumulator]:
        """The detection accumulators by group (empty when detection is not computed)."""
        acc = self.results.get("detection")
        return acc.groups if isinstance(acc, Detection) else {}

    @property
    def seg(self) -> SegAccumulator:
        acc = self.results.get("segmentation")
        return acc if isinstance(acc, SegAccumulator) else SegAccumulator()


@dataclass
class EvalResult:
    cells: dict[tuple[str, str, str], Cell]  # (setting, breakdown, value)
    options: EvalOptions
    groups: list[str]  # "vehicle" then the object classes seen
    episodes: int
    records: int
    skipped_frames: int
    _memo: dict[tuple[str, str, str], dict[str, Any]] = field(default_factory=dict, repr=False)

    def metrics(self, setting: str, breakdown: str = "overall", value: str = "all") -> dict[str, Any]:
        """AP (in %) per group and threshold, segmentation IoU (in %) per layer and mIoU, frame counts."""
        key = (setting, breakdown, value)
        if key not in self._memo:
            self._memo[key] = self._metrics(*key)
        return self._memo[key]

    def _metrics(self, setting: str, breakdown: str, value: str) -> dict[str, Any]:
        cell = self.cells.get((setting, breakdown, value))
        active = self.options.active_metrics()
        out: dict[str, Any] = {"frames": 0, **{name: {} for name, _ in active}}
        if cell is None:
            return out
        out["frames"] = cell.frames
        for name, _ in active:
            acc = cell.results.get(name)
            out[name] = acc.summary(self.options) if acc is not None else {}
        return out


def _check_record(rec: FramePrediction, ref: EpisodeRef | None, refs: dict[str, EpisodeRef]) -> EpisodeRef:
    if ref is None:
        known = ", ".join(list(refs)[:8]) + (" ..." if len(refs) > 8 else "")
        raise PredictionError(rec.source, rec.line, "episode", f"{rec.episode!r} is not in the dataset ({known})")
    if rec.tick >= ref.n_ticks:
        raise PredictionError(rec.source, rec.line, "tick",
                              f"{rec.tick} out of range: episode {ref.id} has ticks 0..{ref.n_ticks - 1}")
    if rec.ego not in ref.agents:
        raise PredictionError(rec.source, rec.line, "ego",
                              f"{rec.ego!r} is not an agent of {ref.id} ({', '.join(ref.agents)})")
    if agent_kind(rec.ego) != "vehicle":
        vehicles = [a for a in ref.agents if agent_kind(a) == "vehicle"]
        raise PredictionError(rec.source, rec.line, "ego",
                              f"{rec.ego!r} is not a vehicle: the ego of a frame is a connected vehicle "
                              f"({', '.join(vehicles) or f'episode {ref.id} has none'})")
    known_classes = set(ref.object_classes) or set(VEHICLE_CLASSES)
    for i, c in enumerate(rec.classes):
        if c not in known_classes:
            raise PredictionError(rec.source, rec.line, f"boxes[{i}].class",
                                  f"unknown class {c!r}; the episode's object classes are "
                                  f"{', '.join(ref.object_classes)}")
    return ref


def _in_area(centers: np.ndarray) -> np.ndarray:
    hx, hy = AREA_HALF_M
    return (np.abs(centers[:, 0]) <= hx) & (np.abs(centers[:, 1]) <= hy)


def evaluate(refs: Sequence[EpisodeRef], predictions: Sequence[FramePrediction], options: EvalOptions = EvalOptions(),
             progress: Callable[[int, int], None] | None = None) -> EvalResult:
    """Score ``predictions`` against the episodes ``refs`` (see the module doc)."""
    by_id = {r.id: r for r in refs}
    per_episode: dict[str, list[FramePrediction]] = defaultdict(list)
    for rec in predictions:
        _check_record(rec, by_id.get(rec.episode), by_id)
        per_episode[rec.episode].append(rec)
    if not predictions:
        raise InputError("no prediction records: nothing to evaluate")
    release = options.compat == "airv2x"
    cells: dict[tuple[str, str, str], Cell] = {}
    groups: set[str] = set()
    skipped = 0
    evaluated = [r for r in refs if r.id in per_episode]
    for n, ref in enumerate(evaluated):
        recs = sorted(per_episode[ref.id], key=lambda r: (r.tick, r.ego, list(SETTINGS).index(r.agents)))
        egos = sorted({r.ego for r in recs})
        ticks = {r.tick for r in recs}
        need_bev = any(r.bev_path is not None for r in recs)
        truths: dict[tuple[int, str], FrameTruth] = {
            (t.tick, t.ego): t for t in iter_truth(ref, egos=egos, rule=options.rule, ticks=ticks)}
        bev = _read_bev(ref, recs) if need_bev else {}
        keys = [("overall", "all")] + [(c, ref.conditions.get(c, "?")) for c in CONDITIONS]
        for rec in recs:
            truth = truths[(rec.tick, rec.ego)]
            if release and len(rec.classes) == 0:
                skipped += 1
                continue
            frame = _score_frame(rec, truth, options, groups, bev.get((rec.tick, rec.ego)))
            for b, v in keys:
                cell = cells.setdefault((rec.agents, b, v), Cell())
                cell.frames += 1
                cell.merge(frame, options)
        if progress:
            progress(n + 1, len(evaluated))
    for _, metric in options.active_metrics():
        metric.finish(cells, options)
    ordered = [VEHICLE_GROUP, *sorted(groups - {VEHICLE_GROUP})]
    return EvalResult(cells, options, ordered, len(evaluated), len(predictions), skipped)


def _score_frame(rec: FramePrediction, truth: FrameTruth, options: EvalOptions, groups: set[str],
                 gt_bev: Any) -> Cell:
    """One frame as a cell of its own: every active metric's accumulator of the frame."""
    frame = Cell(frames=1)
    inputs = FrameInputs(rec, truth, options, gt_bev, groups)
    for name, metric in options.active_metrics():
        acc = metric.score(inputs)
        if acc is not None:
            frame.results[name] = acc
    return frame


@register_metric("detection")
@dataclass
class Detection(Metric):
    """BEV AP per group (``vehicle``: the vehicle classes together, then each object class) and threshold."""

    groups: dict[str, DetectionAccumulator] = field(default_factory=dict)
    thresholds: tuple[float, ...] = THRESHOLDS

    @classmethod
    def empty(cls, options: EvalOptions) -> Detection:
        return cls(thresholds=options.thresholds)

    def merge(self, other: Detection) -> None:
        for g, acc in other.groups.items():
            self.groups.setdefault(g, DetectionAccumulator(self.thresholds)).merge(acc)

    @classmethod
    def score(cls, frame: FrameInputs) -> Detection:
        rec, truth, options = frame.rec, frame.truth, frame.options
        release = options.compat == "airv2x"
        gt_mask = truth.in_area_release if release else truth.in_area
        if options.visible_only:
            gt_mask = gt_mask & require_visibility(truth, "--visible-only")[rec.agents]
        det_mask = _in_area(rec.centers_m)
        det_fp = footprints(rec.centers_m[:, :2], rec.sizes_m[:, :2], rec.yaws_rad)
        gt_fp = truth.footprints()
        gt_cls = np.array(truth.classes, dtype=object)
        det_cls = np.array(rec.classes, dtype=object)
        out = cls.empty(options)
        names = ({c for c in truth.classes if c} | set(rec.classes))
        for g in [VEHICLE_GROUP, *sorted(names)]:
            if g == VEHICLE_GROUP:
                gm = gt_mask & np.isin(gt_cls, VEHICLE_CLASSES) if len(gt_cls) else gt_mask
                dm = det_mask & np.isin(det_cls, VEHICLE_CLASSES) if len(det_cls) else det_mask
            else:
                gm = gt_mask & (gt_cls == g) if len(gt_cls) else gt_mask
                dm = det_mask & (det_cls == g) if len(det_cls) else det_mask
                if not gm.any() and not dm.any():
                    continue
            frame.groups.add(g)
            acc = DetectionAccumulator(options.thresholds)
            acc.add(det_fp[dm], rec.scores[dm], gt_fp[gm])
            out.groups[g] = acc
        return out

    def summary(self, options: EvalOptions) -> dict[str, Any]:
        release = options.compat == "airv2x"
        out: dict[str, Any] = {}
        for g, acc in self.groups.items():
            d: dict[str, Any] = {}
            for thr in options.thresholds:
                r = acc.result(thr, frame_order=release)
                ap = 0.0 if release and r.n_gt == 0 else r.ap  # the release scores "no ground truth" as 0
                d[f"AP{round(thr * 100)}"] = 100.0 * ap
                d["n_gt"], d["n_det"] = r.n_gt, r.n_det
            out[g] = d
        return out

    @classmethod
    def tables(cls, result: EvalResult) -> list[Table]:
        return _detection_tables(result)

    @classmethod
    def plots(cls, result: EvalResult, out_dir: Path) -> list[Path]:
        return _detection_plots(result, out_dir)


register_metric("segmentation")(SegAccumulator)  # after detection: the registration order is the tables' order


def _read_bev(ref: EpisodeRef, recs: list[FramePrediction]) -> dict[tuple[int, str], Any]:
    wanted = {(r.tick, r.ego) for r in recs if r.bev_path is not None}
    egos = sorted({e for _, e in wanted})
    with open_episode(ref.path) as ep:
        missing = [e for e in egos if f"/{e}/bev" not in ep.topics]
        if missing:
            first = next(r for r in recs if r.bev_path is not None and r.ego in missing)
            raise PredictionError(first.source, first.line, "bev",
                                  f"episode {ref.id} has no /{missing[0]}/bev topic (written without BEV grids), "
                                  "so segmentation cannot be scored on it; drop the 'bev' fields or regenerate "
                                  "the episode with BEV output")
        out = {}
        for tick in ep.ticks(topics=[f"/{e}/bev" for e in egos]):
            for e in egos:
                if (tick.index, e) in wanted:
                    out[(tick.index, e)] = tick.bev(e)
    return out


def _release_subset(cells: dict[tuple[str, str, str], Cell], seed: int) -> None:
    """The release scores segmentation on a random subset of frames: keep the same seeded subset per cell."""
    for cell in cells.values():
        seg = cell.seg
        for layer, ious in seg.frame_ious.items():
            if len(ious) > RELEASE_SEG_SUBSET:
                rng = np.random.default_rng(seed)
                pick = np.sort(rng.choice(len(ious), RELEASE_SEG_SUBSET, replace=False))
                seg.frame_ious[layer] = [ious[i] for i in pick]


# ------------------------------------------------------------------------------------------ tables


def eval_tables(result: EvalResult) -> list[Table]:
    """Every active metric's tables, in registration order: overall, per class, per condition (paper Tables
    3-6 shape: settings as rows) and per BEV layer for the built-in ones."""
    return [t for _, metric in result.options.active_metrics() for t in metric.tables(result)]


def _detection_tables(result: EvalResult) -> list[Table]:
    """Overall, per class and per condition; the segmentation mIoU beside the AP when it is computed."""
    settings = [s for s in SETTINGS if (s, "overall", "all") in result.cells]
    aps = [f"AP{round(t * 100)}" for t in result.options.thresholds]
    tables = []
    rows = []
    has_seg = False
    for s in settings:
        m = result.metrics(s)
        d = m["detection"].get(VEHICLE_GROUP, {})
        seg = m.get("segmentation", {})
        has_seg |= bool(seg)
        rows.append([s, m["frames"], d.get("n_gt", 0), d.get("n_det", 0), *[d.get(a, float("nan")) for a in aps],
                     seg.get("mIoU", float("nan"))])
    tables.append(Table("overall", "Overall (all vehicle classes together)",
                        ["agents", "frames", "GT boxes", "detections", *aps, "mIoU"], rows))
    rows = []
    for s in settings:
        m = result.metrics(s)
        for g in result.groups:
            d = m["detection"].get(g)
            if d is None:
                continue
            rows.append([s, g, d["n_gt"], d["n_det"], *[d[a] for a in aps]])
    tables.append(Table("per_class", "Per class", ["agents", "class", "GT boxes", "detections", *aps], rows))
    for b in CONDITIONS:
        values = sorted({v for (s, bb, v) in result.cells if bb == b})
        cols = ["agents"] + [f"{v} {a}" for v in values for a in aps]
        if has_seg:
            cols += [f"{v} mIoU" for v in values]
        rows = []
        for s in settings:
            row: list[Any] = [s]
            ms = {v: result.metrics(s, b, v) for v in values}
            for v in values:
                d = ms[v]["detection"].get(VEHICLE_GROUP, {})
                row += [d.get(a, float("nan")) for a in aps]
            if has_seg:
                row += [ms[v].get("segmentation", {}).get("mIoU", float("nan")) for v in values]
            rows.append(row)
        tables.append(Table(f"by_{b}", f"By {b} (all vehicle classes)", cols, rows))
    return tables


def write_eval(result: EvalResult, out_dir: Path, title: str = "Evaluation") -> list[Path]:
    """eval.md/.csv/.json (all tables, plus every metric in the JSON) and one plot per breakdown."""
    tables = eval_tables(result)
    o = result.options
    skipped = f", {result.skipped_frames} frames without detections skipped (release behaviour)" if o.compat else ""
    header = (f"# {title}\n\n{result.episodes} episodes, {result.records} prediction records{skipped}"
              f"; AP in %, BEV IoU thresholds {', '.join(str(t) for t in o.thresholds)}; ground truth: "
              f"{'visible to the setting agents only' if o.visible_only else 'every labelled object'} in the area; "
              f"mode: {o.compat or 'default (global ranking)'}.\n")
    metrics = {f"{s}|{b}|{v}": result.metrics(s, b, v) for (s, b, v) in sorted(result.cells)}
    paths = write_tables(tables, out_dir, "eval", header, {"metrics": _json_safe(metrics),
                                                           "compat": o.compat, "visible_only": o.visible_only})
    for _, metric in o.active_metrics():
        paths += metric.plots(result, out_dir)
    return paths


def _detection_plots(result: EvalResult, out_dir: Path) -> list[Path]:
    """AP by each breakdown (bar plots) and the precision-recall curves."""
    o = result.options
    paths = []
    settings = [s for s in SETTINGS if (s, "overall", "all") in result.cells]
    aps = [f"AP{round(t * 100)}" for t in o.thresholds]
    for b in ("overall", *CONDITIONS):
        values = sorted({v for (_, bb, v) in result.cells if bb == b})
        panels = {a: {s: [result.metrics(s, b, v)["detection"].get(VEHICLE_GROUP, {}).get(a, float("nan"))
                          for v in values] for s in settings} for a in aps}
        paths.append(bar_plot(out_dir / f"eval_{b}.png", f"AP by {b} (vehicle classes)", values, {}, panels,
                              ylabel="AP (%)"))
    paths.append(pr_curves(result, out_dir / "eval_pr.png"))
    return paths


def pr_curves(result: EvalResult, path: Path) -> Path:
    """Precision-recall curves of the vehicle group, overall, one panel per threshold, one line per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    thresholds = result.options.thresholds
    fig, axes = plt.subplots(1, len(thresholds), figsize=(4 * len(thresholds), 3.4), squeeze=False)
    for ax, thr in zip(axes[0], thresholds, strict=True):
        for s in SETTINGS:
            cell = result.cells.get((s, "overall", "all"))
            if cell is None or VEHICLE_GROUP not in cell.detection:
                continue
            r = cell.detection[VEHICLE_GROUP].result(thr, frame_order=result.options.compat == "airv2x")
            ax.plot(r.recall, r.precision, label=f"{s} (AP {100 * r.ap:.1f})")
        ax.set_xlim(0, 1.02)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_title(f"IoU {thr}", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _json_safe(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_safe(x) for x in v]
    if isinstance(v, float) and math.isnan(v):
        return None
    return v
