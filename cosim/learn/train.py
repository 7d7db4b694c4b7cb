"""Training, checkpoints, validation and prediction of the ``cosim learn`` detector (PyTorch).

A RUN folder holds ``checkpoint.pt`` (weights, optimiser, step, the :class:`~cosim.learn.samples.Setup` and
the training options; written every ``save_every`` steps and at the end), ``best.pt`` (the checkpoint of the
best validation AP50 so far, which ``predict`` uses when present), ``log.jsonl`` (one line per step with the
loss, one per validation with AP30/AP50/AP70 of the vehicle group in percent) and ``summary.json`` (sizes and
wall times). Training is deterministic on CPU: the same data, options and seed give the same weights (the
sample order and the augmentation of step k are drawn from (seed, epoch), (seed, k) and (seed, k, sample, n),
and each step's batch is made from those and the ground-truth database alone, so worker processes and a
resumed run change nothing).

Only numpy, torch and the numpy-only parts of cosim learn are imported at module import (no MCAP reader),
so that benchmarks/learn_device.py trains from a cache on a machine without cosim's dependencies.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cosim.cli_args import check_output_folder
from cosim.errors import InputError
from cosim.eval.predictions import parse_record, record_json
from cosim.learn.augment import (
    GtDatabase,
    drop_points,
    jitter_intensity,
    paste_objects,
    scale,
    transform_poses,
    translate,
)
from cosim.learn.grid import decode, targets, voxelise, warp_index
from cosim.learn.model import PillarDetector, focal_loss, peaks, regression_loss
from cosim.learn.nms import circle_nms
from cosim.learn.samples import (  # noqa: F401 (SCHEDULES: here too)
    BOX_BYTES,
    POINT_BYTES,
    SCHEDULES,
    Perturb,
    Setup,
    agent_grid,
    augment,
    augment_poses,
    pillar_bytes,
)

if TYPE_CHECKING:
    from cosim.eval.dataset import EpisodeRef
    from cosim.learn.data import Samples

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"
BEST = "best.pt"
FORMAT = 2  # checkpoint layout version (2: the yaw as axis and direction, 9 regression channels)


@dataclass(frozen=True)
class TrainOptions:
    epochs: int = 1
    steps: int | None = None  # stop after this many steps in total (None: epochs x samples / batch)
    batch_size: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-2
    every: int = 1  # training ticks: 0, every, 2 every...
    val_every_tick: int = 10
    val_steps: int = 0  # validate every this many steps (0: only at the end); needs a val split
    save_every: int = 100
    keep_every: int = 0  # also keep checkpoint_<step>.pt every this many steps (0: none), for `cosim learn validate`
    seed: int = 0
    width: int = 16  # channels of the pillar features (the backbone has 2x, 3x and 4x)
    threads: int | None = None  # torch CPU threads (None: torch's default)
    schedule: str = "cosine"  # warm-up then cosine decay to 0, or one-cycle (30 % rise from lr/25, then cosine)
    workers: int = 0  # worker processes making the batches (0: in the training process)
    turn_deg: float = 0.0  # turn each sample about z by up to this many degrees either way (0: no turn)
    # the toolbox augmentations (cosim.learn.augment; docs/learnability.md, "Augmentation"); the defaults are off
    scale_min: float = 1.0  # global scaling by a factor drawn uniformly from [scale_min, scale_max]
    scale_max: float = 1.0
    translate_m: float = 0.0  # global translation: N(0, translate_m) [m] per axis x, y, z
    height_m: float = 0.0  # sensor-height jitter: the whole scene moved in z by N(0, height_m) [m]
    point_drop: float = 0.0  # each point dropped with this probability
    intensity_scale: float = 1.0  # intensities times a factor log-uniform in [1 / intensity_scale, intensity_scale]
    intensity_noise: float = 0.0  # plus N(0, intensity_noise) per point, clipped to 0..1
    gt_sample: int = 0  # ground-truth sampling: paste up to this many database objects into each sample
    gt_min_points: int = 5  # objects of the database: at least this many points inside their box

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainOptions:
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    def augments(self) -> bool:
        """Whether any augmentation besides the flips and the turn is on."""
        return (self.scale_min, self.scale_max, self.translate_m, self.height_m, self.point_drop,
                self.intensity_scale, self.intensity_noise, self.gt_sample) != (1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0)


#: Options a resumed run must share with the run it continues: the model's width and the augmentations.
RESUME_FIELDS: tuple[str, ...] = ("width", "turn_deg", "scale_min", "scale_max",
                                  "translate_m", "height_m", "point_drop", "intensity_scale", "intensity_noise",
                                  "gt_sample", "gt_min_points")


def device_of(name: str | None) -> torch.device:
    if name:
        return torch.device(name)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def batch_arrays(clouds: Sequence[np.ndarray], setup: Setup, per_sample: Sequence[int] | None = None,
                 poses: Sequence[np.ndarray] | None = None, encoders: Sequence[np.ndarray] | None = None
                 ) -> dict[str, np.ndarray]:
    """Voxelise clouds into one batch (numpy): ``feats`` (K, 9) the kept points, pillar after pillar,
    ``counts`` (P,) points per pillar, ``coords`` (P, 3) [batch, row, column]. Intermediate fusion (``per_sample``:
    clouds of each sample, in order; ``poses``, ``encoders`` per sample): coords [b x J + j, row, column] in the
    agents' grid, ``poses`` (B, J, 3), ``encoder`` (B, J), ``present`` (B, J) with J the most agents of a
    sample, and the warp's hits ``cell``, ``src``, ``ego`` (:func:`cosim.learn.grid.warp_index`)."""
    inter = per_sample is not None
    grid = agent_grid(setup.grid) if inter else setup.grid
    if inter:
        j_max = max(per_sample)
        slot = [(b, j) for b, n in enumerate(per_sample) for j in range(n)]
    feats, coords, counts = [], [], []
    for n, cloud in enumerate(clouds):
        f, c, k = voxelise(cloud, grid)
        m = slot[n][0] * j_max + slot[n][1] if inter else n
        feats.append(f)
        coords.append(np.concatenate([np.full((len(c), 1), m, np.int64), c], axis=1))
        counts.append(k)
    out = {"feats": np.concatenate(feats), "counts": np.concatenate(counts), "coords": np.concatenate(coords)}
    if inter:
        b = len(per_sample)
        out["poses"] = np.zeros((b, j_max, 3), np.float64)
        out["encoder"] = np.zeros((b, j_max), np.int64)
        out["present"] = np.zeros((b, j_max), bool)
        for i, n in enumerate(per_sample):
            out["poses"][i, :n] = poses[i]
            out["encoder"][i, :n] = encoders[i]
            out["present"][i, :n] = True
        out["cell"], out["src"], out["ego"] = warp_index(out["coords"], out["poses"], out["present"], setup.grid, grid)
    return out


def to_device(arrays: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: (v if isinstance(v, torch.Tensor) else torch.from_numpy(np.asarray(v))).to(device)
            for k, v in arrays.items()}


def run_model(model: PillarDetector, batch: dict[str, torch.Tensor], batch_size: int
              ) -> tuple[torch.Tensor, torch.Tensor]:
    maps = {k: batch[k] for k in ("encoder", "cell", "src", "ego")} if "poses" in batch else None
    return model(batch["feats"], batch["counts"], batch["coords"], batch_size, maps)


def _lr(opts: TrainOptions, step: int, total: int) -> float:
    if opts.schedule == "onecycle":
        rise = max(1, int(0.3 * total))
        if step < rise:
            return opts.lr / 25 + (opts.lr - opts.lr / 25) * 0.5 * (1 - math.cos(math.pi * step / rise))
        return opts.lr * 0.5 * (1 + math.cos(math.pi * (step - rise) / max(1, total - rise)))
    warm = min(50, max(1, total // 10))
    if step < warm:
        return opts.lr * (step + 1) / warm
    return opts.lr * 0.5 * (1 + math.cos(math.pi * (step - warm) / max(1, total - warm)))


def _set_seed(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)


def new_model(setup: Setup, opts: TrainOptions, device: torch.device) -> PillarDetector:
    _set_seed(opts.seed)
    return model_for(setup, opts).to(device)


def model_for(setup: Setup, opts: TrainOptions) -> PillarDetector:
    return PillarDetector(setup.grid, len(setup.classes), width=opts.width, fusion=setup.fusion, fuse=setup.fuse,
                          encoders=setup.encoders, n_sensors=len(setup.sensors))


def check_format(ckpt: Any, path: Path) -> None:
    """InputError unless ``ckpt`` (a loaded checkpoint file) is a cosim learn checkpoint of :data:`FORMAT`."""
    if not isinstance(ckpt, dict) or "format" not in ckpt:
        raise InputError(f"{path}: not a cosim learn checkpoint")
    if ckpt["format"] != FORMAT:
        raise InputError(f"{path}: a cosim learn checkpoint of format {ckpt['format']}; this cosim reads format "
                         f"{FORMAT} (format 2 changed the yaw head, docs/learnability.md): train the model again")


def load_run(run: Path, device: torch.device | None = None) -> tuple[PillarDetector, Setup, dict[str, Any]]:
    """The model of a RUN folder (its ``best.pt``, chosen on validation, else its last checkpoint) or of one
    checkpoint file, its setup and the checkpoint."""
    run = Path(run)
    path = run if run.is_file() else (run / BEST if (run / BEST).is_file() else run / CHECKPOINT)
    if not path.is_file():
        raise InputError(f"{run}: no {CHECKPOINT}: not a training run of cosim learn train")
    device = device or device_of(None)
    try:
        ckpt = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # a truncated or foreign file: say which, once
        raise InputError(f"{path}: cannot read the checkpoint ({exc})") from None
    check_format(ckpt, path)
    setup = Setup.from_dict(ckpt["setup"])
    opts = TrainOptions.from_dict(ckpt["options"])
    model = model_for(setup, opts).to(device)
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as exc:
        raise InputError(f"{path}: the weights do not fit the model its setup describes ({str(exc)[:200]})") from None
    model.eval()
    return model, setup, ckpt


@torch.no_grad()
def predict_sample(model: PillarDetector, item: dict[str, Any], setup: Setup, device: torch.device,
                   score_min: float = 0.05, nms_radius_m: float = 2.0, max_boxes: int = 100
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes (N, 7), scores (N,), class indices (N,) of one sample in the ego LiDAR frame. Late fusion:
    each agent's cloud is detected alone and the boxes of all of them merged by circle NMS."""
    return predict_and_send(model, item, setup, device, score_min, nms_radius_m, max_boxes)[:3]


@torch.no_grad()
def predict_and_send(model: PillarDetector, item: dict[str, Any], setup: Setup, device: torch.device,
                     score_min: float = 0.05, nms_radius_m: float = 2.0, max_boxes: int = 100
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """:func:`predict_sample` and the bytes the collaborators sent for it (docs/learnability.md, "Bytes sent"):
    early fusion their points (:data:`POINT_BYTES` each), intermediate fusion the pillars of their BEV feature
    maps (:func:`pillar_bytes` of the model's width), late fusion their boxes (:data:`BOX_BYTES` each, at most
    ``max_boxes`` an agent); 0 for the ego alone."""
    clouds = item["clouds"]
    if setup.fusion == "intermediate":
        arrays = batch_arrays(clouds, setup, [len(clouds)], [item["poses"]], [item["encoder"]])
        sent = int((arrays["coords"][:, 0] != 0).sum()) * pillar_bytes(model.pfn.out_features)
        batch = to_device(arrays, device)
        n = 1
    else:
        batch = to_device(batch_arrays(clouds, setup), device)
        n = len(clouds)
        sent = POINT_BYTES * int(sum(item.get("sent", ()))) if setup.fusion == "early" else 0
    heat, reg = run_model(model, batch, n)
    heat = peaks(heat).cpu().numpy()
    reg = reg.cpu().numpy()
    parts = [decode(heat[b], reg[b], setup.grid, score_min=score_min) for b in range(n)]
    if setup.fusion == "late":
        sent = BOX_BYTES * sum(min(len(p[0]), max_boxes) for p in parts[1:])
    boxes = np.concatenate([p[0] for p in parts])
    scores = np.concatenate([p[1] for p in parts])
    cls = np.concatenate([p[2] for p in parts])
    keep = circle_nms(boxes[:, :2], scores, nms_radius_m)[:max_boxes]
    return boxes[keep], scores[keep], cls[keep], sent


def record_lines(model: PillarDetector, samples: Any, device: torch.device,
                 progress: Callable[[int, int], None] | None = None) -> list[str]:
    """One prediction record (docs/evaluation.md) per sample, with the bytes its collaborators sent
    (``bytes_sent``, collaborative fusion only)."""
    setup = samples.setup
    was_training = model.training
    model.eval()
    lines = []
    for i in range(len(samples)):
        item = samples.item(i)
        boxes, scores, cls, sent = predict_and_send(model, item, setup, device)
        lines.append(record_json(item["episode"], item["tick"], item["ego"], setup.agents, boxes[:, :3],
                                 boxes[:, 3:6], boxes[:, 6], [setup.classes[k] for k in cls], scores,
                                 bytes_sent=None if setup.fusion == "none" else sent))
        if progress:
            progress(i + 1, len(samples))
    model.train(was_training)
    return lines


def validate(model: PillarDetector, samples: Samples, device: torch.device) -> dict[str, float]:
    """AP30, AP50 and AP70 (%) of the vehicle group on the samples (``cosim eval``'s scoring,
    ``--visible-only`` when the episodes have visibility topics) and the mean bytes the collaborators sent per
    ego frame (``bytes_per_frame``)."""
    from cosim.eval.evaluate import EvalOptions, evaluate

    lines = record_lines(model, samples, device)
    records = [parse_record(json.loads(line), Path("val.jsonl"), n + 1) for n, line in enumerate(lines)]
    result = evaluate(samples.refs, records, EvalOptions(visible_only=True))
    det = result.metrics(samples.setup.agents)["detection"].get("vehicle", {})
    out = {k: round(float(det.get(k, float("nan"))), 2) for k in ("AP30", "AP50", "AP70")}
    out["bytes_per_frame"] = round(sum(r.bytes_sent or 0 for r in records) / max(1, len(records)), 1)
    return out


def step_batch(samples: Any, order: np.ndarray, start: int, opts: TrainOptions, step: int,
               db: GtDatabase | None = None) -> dict[str, Any]:
    """The batch of training step ``step`` (numpy): samples ``order[start:start + batch]`` (wrapping),
    flipped and turned as drawn from (seed, step); late fusion takes one agent's cloud of each sample (also
    drawn). The other augmentations (:func:`augment_item`) draw from streams of their own, (seed, step, j, 1..3)
    for the batch's j-th sample, so that runs without them keep their batches; ``db``: the ground-truth
    database of ``opts.gt_sample``."""
    rng = np.random.default_rng([opts.seed, step])
    setup = samples.setup
    g = setup.grid
    mirrors = np.array([g.x_range[0] == -g.x_range[1], g.y_range[0] == -g.y_range[1]])
    clouds, tgts, per_sample, poses, encoders = [], [], [], [], []
    for j in range(opts.batch_size):
        item = samples.item(int(order[(start + j) % len(order)]))
        k = int(rng.integers(len(item["clouds"])))  # late fusion: one agent's cloud of the sample
        # a mirror stays only where the grid is symmetric about that axis: a front-view grid (x from 0) mirrored
        # in x would see nothing of a camera-view scan (and lose its targets); the draw is kept either way
        flip = (rng.random(2) < 0.5) & mirrors
        # drawn only when turning, so that runs without it keep their batches
        turn = math.radians(opts.turn_deg) * rng.uniform(-1.0, 1.0) if opts.turn_deg else 0.0
        streams = [np.random.default_rng([opts.seed, step, j, n]) for n in (1, 2, 3)] if opts.augments() else None
        if setup.fusion == "intermediate":
            boxes = item["targets"][0][0]
            item_clouds = []
            for cloud in item["clouds"]:
                c, boxes_f = augment(cloud, boxes, bool(flip[0]), bool(flip[1]), turn)
                item_clouds.append(c)
            item_poses = augment_poses(item["poses"], bool(flip[0]), bool(flip[1]), turn)
            labels = item["targets"][0][1]
            if streams is not None:
                item_clouds, boxes_f, labels, item_poses = augment_item(item_clouds, boxes_f, labels, opts, streams,
                                                                        poses=item_poses)
            clouds += item_clouds
            per_sample.append(len(item["clouds"]))
            poses.append(item_poses)
            encoders.append(item["encoder"])
            tgts.append(targets(boxes_f, labels, setup.grid, len(setup.classes)))
            continue
        cloud, boxes = item["clouds"][k], item["targets"][k][0]
        labels = item["targets"][k][1]
        if streams is not None and opts.gt_sample and db is not None:
            cloud, boxes, labels = paste_objects(db, cloud, boxes, labels, opts.gt_sample, streams[2],
                                                 db.source_of(item))
        cloud, boxes = augment(cloud, boxes, bool(flip[0]), bool(flip[1]), turn)
        if streams is not None:
            (cloud,), boxes, labels, _ = augment_item([cloud], boxes, labels, opts, streams)
        clouds.append(cloud)
        tgts.append(targets(boxes, labels, setup.grid, len(setup.classes)))
    if setup.fusion == "intermediate":
        batch = batch_arrays(clouds, setup, per_sample, poses, encoders)
    else:
        batch = batch_arrays(clouds, setup)
    batch.update({f"t_{k}": np.stack([t[k] for t in tgts]) for k in tgts[0]})
    return batch


def augment_item(clouds: list[np.ndarray], boxes: np.ndarray, labels: np.ndarray, opts: TrainOptions,
                 streams: list[np.random.Generator], poses: np.ndarray | None = None
                 ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray | None]:
    """One sample's global scaling, translation and sensor-height jitter (one draw for the whole scene, from
    ``streams[0]``), then each cloud's point drop and intensity jitter (``streams[1]``), as ``opts`` says.

    ``clouds`` (N, 4) float32 in the ego LiDAR frame with ``boxes`` (M, 7) there, or for intermediate fusion
    each in its agent's bird's-eye frame with ``poses`` (J, 3) (yaw, x, y in the ego frame): every agent's cloud,
    the boxes and the poses move as one scene (:func:`cosim.learn.augment.transform_poses`). Returns the
    clouds, boxes, labels and poses (None without)."""
    draw = streams[0]
    factor = float(draw.uniform(opts.scale_min, opts.scale_max))
    offset = draw.normal(0.0, 1.0, 3) * opts.translate_m
    offset[2] += draw.normal(0.0, 1.0) * opts.height_m
    log_i = math.log(opts.intensity_scale)
    gain = math.exp(draw.uniform(-log_i, log_i))
    no_boxes, no_points = np.zeros((0, 7)), np.zeros((0, 4), np.float32)
    out = []
    for cloud in clouds:
        if factor != 1.0:
            cloud, _ = scale(cloud, no_boxes, factor)
        if offset.any():  # the x, y of an agent's frame move with its pose; z moves every cloud
            cloud, _ = translate(cloud, no_boxes, offset if poses is None else np.array([0.0, 0.0, offset[2]]))
        if opts.point_drop:
            cloud = drop_points(cloud, opts.point_drop, streams[1])
        if gain != 1.0 or opts.intensity_noise:
            cloud = jitter_intensity(cloud, gain, opts.intensity_noise, streams[1])
        out.append(cloud)
    if factor != 1.0:
        _, boxes = scale(no_points, boxes, factor)
    if offset.any():
        _, boxes = translate(no_points, boxes, offset)
    if poses is not None:
        poses = transform_poses(poses, factor, offset)
    return out, boxes, labels, poses


class StepBatches:
    """Map-style dataset of training batches by step number, for torch's DataLoader: worker processes
    make the batches (reading, voxelising, targets) while the model trains; batch k depends on k alone."""

    def __init__(self, samples: Any, opts: TrainOptions, per_epoch: int, db: GtDatabase | None = None):
        self.samples, self.opts, self.per_epoch, self.db = samples, opts, per_epoch, db

    def __len__(self) -> int:
        return 1 << 40

    def __getitem__(self, step: int) -> dict[str, Any]:
        epoch, pos = divmod(step, self.per_epoch)
        order = np.random.default_rng([self.opts.seed, 1_000_003 + epoch]).permutation(len(self.samples))
        return step_batch(self.samples, order, pos * self.opts.batch_size, self.opts, step, self.db)


def batches(samples: Any, opts: TrainOptions, per_epoch: int, first: int, total: int, db: GtDatabase | None = None):
    """The batches of steps first..total-1, made in ``opts.workers`` worker processes (0: here)."""
    data = StepBatches(samples, opts, per_epoch, db)
    if opts.workers <= 0:
        for step in range(first, total):
            yield data[step]
        return
    loader = torch.utils.data.DataLoader(data, batch_size=None, sampler=range(first, total),
                                         num_workers=opts.workers, prefetch_factor=2, persistent_workers=False)
    yield from loader


def _append_log(path: Path, rec: dict[str, Any]) -> None:
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(rec) + "\n")


def read_log(run: Path) -> list[dict[str, Any]]:
    path = Path(run) / "log.jsonl"
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


class _NoBar:
    def __init__(self, *args: Any, **kwargs: Any):
        pass

    def update(self, n: int) -> None:
        pass

    def set_postfix(self, **kwargs: Any) -> None:
        pass

    def write(self, text: str) -> None:
        print(text, file=sys.stderr)

    def close(self) -> None:
        pass


def _copy_whole(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` through a temporary file, so that a run stopped mid-copy never leaves a
    truncated checkpoint under ``dst``'s name (a resumed run and ``predict`` read it)."""
    tmp = dst.with_suffix(".tmp")
    shutil.copyfile(src, tmp)
    tmp.replace(dst)


def _cpu_s() -> float:
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def check_run_folder(run: Path, resume: bool) -> None:
    """A run folder ``cosim learn train`` can write (InputError otherwise), checked before any work: not a file,
    with no file above it; a new run's folder holds no run yet, a resumed run's holds its checkpoint."""
    check_output_folder(run)
    if (run / CHECKPOINT).exists() and not resume:
        raise InputError(f"{run} already holds a training run: --resume continues it, or choose another --out")
    if resume and not (run / CHECKPOINT).exists():
        raise InputError(f"{run}: nothing to resume (no {CHECKPOINT})")


def train(train_refs: list[EpisodeRef], val_refs: list[EpisodeRef] | None, setup: Setup, opts: TrainOptions,
          run: Path, resume: bool = False, device: torch.device | None = None, show_progress: bool = True,
          cache: Path | None = None, init: Path | None = None) -> dict[str, Any]:
    """Train (or resume) a detector into ``run`` on the episodes ``train_refs`` (from MCAP, or from the
    ``cosim learn cache`` folder ``cache``), validating on ``val_refs``, starting from the weights of the run
    ``init`` when given; returns the summary (also written to summary.json)."""
    from cosim.learn.data import Samples, check_classes, with_sensors

    run = Path(run)
    check_run_folder(run, resume)
    check_classes(train_refs, setup.classes, "the model")
    t0 = time.perf_counter()
    if not setup.sensors:
        setup = with_sensors(setup, train_refs + list(val_refs or []))
    samples = Samples(train_refs, setup, every=opts.every, cache=cache)
    val = Samples(val_refs, setup, every=opts.val_every_tick, cache=cache) if val_refs else None
    device = device or device_of(None)
    try:
        summary = fit(samples, (lambda model: validate(model, val, device)) if val is not None else None, setup,
                      opts, run, resume=resume, device=device, show_progress=show_progress, init=init)
    finally:
        samples.close()
        if val is not None:
            val.close()
    summary.update({"train_episodes": len(train_refs), "val_episodes": len(val_refs or []),
                    "setup_s": round(summary["setup_s"] + time.perf_counter() - t0 - summary["wall_s"], 1),
                    "cache": str(cache) if cache else None, "init": str(init) if init else None})
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def fit(samples: Any, val_fn: Callable[[PillarDetector], dict[str, float]] | None, setup: Setup,
        opts: TrainOptions, run: Path, resume: bool = False, device: torch.device | None = None,
        show_progress: bool = True, init: Path | None = None) -> dict[str, Any]:
    """The training loop: ``samples`` (``len``, ``item(i)``, ``setup``), ``val_fn`` (model -> AP dict, or
    None). Writes the run folder; ``best.pt`` is the checkpoint of the best validation AP50. ``init``: a run
    whose weights the model starts from (:func:`init_weights`; not on resume)."""
    try:
        from tqdm import tqdm
    except ModuleNotFoundError:  # a bare machine (benchmarks/learn_device.py): no progress bar
        tqdm = _NoBar

    t0 = time.perf_counter()
    run = Path(run)
    ckpt_path = run / CHECKPOINT
    device = device or device_of(None)
    if device.type == "cpu":
        torch.use_deterministic_algorithms(True)
        if opts.threads:
            torch.set_num_threads(opts.threads)
    per_epoch = math.ceil(len(samples) / opts.batch_size)
    total = opts.steps if opts.steps is not None else opts.epochs * per_epoch
    if total < 1:
        raise InputError("nothing to train: give --epochs or --steps >= 1")
    if opts.gt_sample and setup.fusion != "none":
        raise InputError(f"--gt-sample pastes objects cut from single-agent samples: it works with --fusion none "
                         f"only, not {setup.fusion}")
    model = new_model(setup, opts, device)
    if init is not None and not resume:
        init_weights(model, Path(init), setup, device)
    optim = torch.optim.AdamW(model.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
    step = 0
    log_path = run / "log.jsonl"
    prior_s = 0.0
    best = -1.0
    if resume:
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=False)
        check_format(ckpt, ckpt_path)
        old = Setup.from_dict(ckpt["setup"])
        if old != setup:
            raise InputError(f"{run} was trained with fusion {old.fusion}, agents {old.agents}, classes "
                             f"{', '.join(old.classes)}, lidar {old.lidar}, pillars {old.grid.pillar_m:g} m over x "
                             f"{old.grid.x_range[0]:g} to {old.grid.x_range[1]:g}, y {old.grid.y_range[0]:g} to "
                             f"{old.grid.y_range[1]:g}, perturbation {old.perturb.describe()}: resume it with the "
                             "same options")
        old_opts = TrainOptions.from_dict(ckpt["options"])
        differ = [f"{k} {getattr(old_opts, k)} (now {getattr(opts, k)})" for k in RESUME_FIELDS
                  if getattr(old_opts, k) != getattr(opts, k)]
        if differ:
            raise InputError(f"{run} was trained with {', '.join(differ)}: resume it with the same options")
        model.load_state_dict(ckpt["model"])
        optim.load_state_dict(ckpt["optimizer"])
        step = int(ckpt["step"])
        prior_s = float(ckpt.get("train_s", 0.0))
        best = float(ckpt.get("best_ap50", -1.0))
        kept = [r for r in read_log(run) if r["step"] <= step]
        log_path.write_text("".join(json.dumps(r) + "\n" for r in kept))
    else:
        run.mkdir(parents=True, exist_ok=True)
        log_path.write_text("")
    db = None
    if opts.gt_sample:
        db = GtDatabase.build(samples, opts.gt_min_points)
        log.info("ground-truth database: %d objects from %d samples", len(db), len(samples))
    setup_s = time.perf_counter() - t0

    def save(path: Path, step: int, train_s: float) -> None:
        tmp = path.with_suffix(".tmp")
        torch.save({"format": FORMAT, "setup": setup.to_dict(), "options": opts.to_dict(), "step": step,
                    "model": model.state_dict(), "optimizer": optim.state_dict(), "train_s": train_s,
                    "best_ap50": best}, tmp)
        tmp.replace(path)

    val_s = 0.0
    cpu0 = _cpu_s()
    t_train = time.perf_counter()
    model.train()
    bar = tqdm(total=total, initial=step, desc=f"train {setup.fusion}/{setup.agents}", unit="step", file=sys.stderr,
               disable=not show_progress or not sys.stderr.isatty(), dynamic_ncols=True, mininterval=0.5)
    last = None
    for batch in batches(samples, opts, per_epoch, step, total, db):
        epoch = step // per_epoch
        b = to_device(batch, device)
        for group in optim.param_groups:
            group["lr"] = _lr(opts, step, total)
        heat, reg = run_model(model, b, opts.batch_size)
        l_heat = focal_loss(heat, b["t_heatmap"])
        l_reg = regression_loss(reg, b["t_reg"], b["t_index"], b["t_mask"])
        loss = l_heat + 2.0 * l_reg
        optim.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        optim.step()
        step += 1
        last = float(loss.item())
        _append_log(log_path, {"step": step, "epoch": epoch, "loss": round(last, 5),
                               "heat": round(float(l_heat.detach()), 5), "reg": round(float(l_reg.detach()), 5)})
        bar.update(1)
        bar.set_postfix(loss=f"{last:.3f}", epoch=epoch)
        do_val = val_fn is not None and ((opts.val_steps and step % opts.val_steps == 0) or step == total)
        new_best = False
        if do_val:
            tv = time.perf_counter()
            ap = val_fn(model)
            model.train()
            val_s += time.perf_counter() - tv
            _append_log(log_path, {"step": step, "val": ap})
            bar.write(f"step {step}: val AP30 {ap['AP30']:.1f}  AP50 {ap['AP50']:.1f}  AP70 {ap['AP70']:.1f}")
            if ap["AP50"] == ap["AP50"] and ap["AP50"] > best:
                best, new_best = float(ap["AP50"]), True
        kept = bool(opts.keep_every) and step % opts.keep_every == 0
        if kept or new_best or step % opts.save_every == 0 or step == total:
            save(ckpt_path, step, prior_s + time.perf_counter() - t_train)
        if new_best:
            _copy_whole(ckpt_path, run / BEST)
        if kept:
            _copy_whole(ckpt_path, run / f"checkpoint_{step:06d}.pt")
    bar.close()
    wall = time.perf_counter() - t_train
    train_s = prior_s + wall
    summary = {"setup": setup.to_dict(), "options": opts.to_dict(), "train_samples": len(samples), "steps": step,
               "final_loss": last, "best_val_ap50": best if best >= 0 else None, "device": str(device),
               "gt_database_objects": None if db is None else len(db),
               "setup_s": round(setup_s, 1), "train_s": round(train_s, 1), "val_s": round(val_s, 1),
               "wall_s": round(wall, 1), "cpu_s": round(_cpu_s() - cpu0, 1)}
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def init_weights(model: PillarDetector, run: Path, setup: Setup, device: torch.device) -> None:
    """Load the weights of another run's model (``cosim learn train --init``: fine-tuning) into ``model``; one
    InputError when that model has other classes or another shape (fusion, encoders, width)."""
    src, src_setup, ckpt = load_run(run, device)
    mine, theirs = model.state_dict(), src.state_dict()
    bad = sorted(set(mine) ^ set(theirs)) or [k for k in mine if mine[k].shape != theirs[k].shape]
    if bad or src_setup.classes != setup.classes:
        width = TrainOptions.from_dict(ckpt["options"]).width
        raise InputError(f"--init {run}: its model (fusion {src_setup.fusion}, classes {', '.join(src_setup.classes)}, "
                         f"width {width}) is not of this run's shape (fusion {setup.fusion}, classes "
                         f"{', '.join(setup.classes)}{', ' + bad[0] + ' differs' if bad else ''}): train with its "
                         "--fusion, --classes and --width")
    model.load_state_dict(theirs)


def summary_text(out: Path | str, summary: dict[str, Any], data: str) -> str:
    """What ``cosim learn train`` prints at the end: the run folder, ``data`` (where the samples came from),
    steps and final loss, wall time and CPU (``summary.json`` keeps the unrounded values)."""
    loss = "-" if summary["final_loss"] is None else format(summary["final_loss"], ".4g")
    return (f"run      {out}\n"
            f"data     {summary['train_samples']} samples from {data}\n"
            f"steps    {summary['steps']}, final loss {loss} (summary.json: unrounded)\n"
            f"wall     {summary['train_s']:.1f} s training ({summary['val_s']:.1f} s of it validation) on "
            f"{summary['device']}, {summary['cpu_s']:.0f} CPU-s (workers included)")


def run_checkpoints(run: Path) -> list[Path]:
    """A run's kept ``checkpoint_<step>.pt`` files in order, then its last checkpoint; none is an error."""
    files = sorted(run.glob("checkpoint_*.pt"))
    if (run / CHECKPOINT).is_file():
        files.append(run / CHECKPOINT)
    if not files:
        raise InputError(f"{run}: no checkpoints (train with --keep-every N to keep some)")
    return files


def unscored_checkpoints(run: Path, threads: int | None, scored: Callable[[dict], bool], from_step: int = 0):
    """The models of a run's kept checkpoints and its last one (:func:`run_checkpoints`) at steps >=
    ``from_step`` whose step has no line of ``log.jsonl`` for which ``scored(line)`` holds: yields (model,
    setup, step, device), a ``checkpoint_<step>.pt`` that names a skipped step left unloaded."""
    files = run_checkpoints(run)
    if threads:
        torch.set_num_threads(threads)
    device = device_of(None)
    done = {int(r["step"]) for r in read_log(run) if "val" in r and scored(r)}
    for f in files:
        named = f.stem.removeprefix("checkpoint_")
        if named.isdigit() and (int(named) in done or int(named) < from_step):
            continue
        model, setup, ckpt = load_run(f, device)
        step = int(ckpt["step"])
        if step in done or step < from_step:
            continue
        done.add(step)
        yield model, setup, step, device


def validate_checkpoints(run: Path, refs: list[EpisodeRef], every: int, split: str, threads: int | None = None,
                         cache: Path | None = None, from_step: int = 0, perturb: Perturb | None = None):
    """Score ``checkpoint_<step>.pt`` of a run (and its last checkpoint) at steps >= ``from_step`` on
    ``refs`` (ticks 0, every, 2 every...; read from ``cache`` when given) under the test perturbation
    ``perturb`` (none by default, whatever the training's), except steps already scored on ``split`` with the
    same ``every`` and perturbation; each result is appended to the run's ``log.jsonl`` as ``{"step", "val",
    "split", "every"}`` and ``"perturb"`` when there is one (the training's own validations have no ``split``).
    Yields (step, AP dict)."""
    perturb = perturb or Perturb()
    tag = perturb.to_dict() if perturb else None
    run = Path(run)
    samples = None
    for model, setup, step, device in unscored_checkpoints(  # the steps scored before skipped
            run, threads, lambda r: r.get("split") == split and r.get("every") == every and r.get("perturb") == tag,
            from_step):
        if samples is None:
            from cosim.learn.data import Samples, check_classes

            check_classes(refs, setup.classes, f"the model in {run}")
            samples = Samples(refs, replace(setup, perturb=perturb), every=every, cache=cache)
        ap = validate(model, samples, device)
        _append_log(run / "log.jsonl", {"step": step, "val": ap, "split": split, "every": every,
                                        **({"perturb": tag} if tag else {})})
        yield step, ap
    if samples is not None:
        samples.close()
