"""Training, checkpoints, validation and prediction of the ``cosim learn`` detector (PyTorch).

A RUN folder holds ``checkpoint.pt`` (weights, optimiser, step, the :class:`~cosim.learn.data.Setup` and the
training options; written every ``save_every`` steps and at the end), ``log.jsonl`` (one line per step with
the loss, one per validation with AP30/AP50/AP70 of the vehicle group in percent) and ``summary.json``
(sizes and wall times). Training is deterministic on CPU: the same data, options and seed give the same
weights (the sample order and the augmentation of step k are drawn from (seed, epoch) and (seed, k), so a
resumed run continues exactly as an uninterrupted one would).
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cosim.errors import InputError
from cosim.eval.dataset import EpisodeRef
from cosim.eval.predictions import parse_record, record_json
from cosim.learn.data import Samples, Setup, augment, check_classes
from cosim.learn.grid import decode, targets, voxelise
from cosim.learn.model import PillarDetector, focal_loss, peaks, regression_loss
from cosim.learn.nms import circle_nms

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"
FORMAT = 1  # checkpoint layout version


@dataclass(frozen=True)
class TrainOptions:
    epochs: int = 1
    steps: int | None = None  # stop after this many steps in total (None: epochs x samples / batch)
    batch_size: int = 2
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

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def device_of(name: str | None) -> torch.device:
    if name:
        return torch.device(name)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def batch_tensors(clouds: Sequence[np.ndarray], setup: Setup, device: torch.device
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Voxelise clouds into one batch: features (P, M, 9), mask (P, M), coords (P, 3) [batch, row, col]."""
    feats, coords, masks = [], [], []
    for b, cloud in enumerate(clouds):
        f, c, n = voxelise(cloud, setup.grid)
        feats.append(f)
        coords.append(np.concatenate([np.full((len(c), 1), b, np.int64), c], axis=1))
        masks.append(np.arange(setup.grid.max_points)[None, :] < n[:, None])
    return (torch.from_numpy(np.concatenate(feats)).to(device), torch.from_numpy(np.concatenate(masks)).to(device),
            torch.from_numpy(np.concatenate(coords)).to(device))


def _lr(opts: TrainOptions, step: int, total: int) -> float:
    warm = min(50, max(1, total // 10))
    if step < warm:
        return opts.lr * (step + 1) / warm
    return opts.lr * 0.5 * (1 + math.cos(math.pi * (step - warm) / max(1, total - warm)))


def _set_seed(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)


def new_model(setup: Setup, opts: TrainOptions, device: torch.device) -> PillarDetector:
    _set_seed(opts.seed)
    return PillarDetector(setup.grid, len(setup.classes), width=opts.width).to(device)


def load_run(run: Path, device: torch.device | None = None) -> tuple[PillarDetector, Setup, dict[str, Any]]:
    """The model of a RUN folder (its last checkpoint) or of one checkpoint file, its setup and the checkpoint."""
    run = Path(run)
    path = run if run.is_file() else run / CHECKPOINT
    if not path.is_file():
        raise InputError(f"{run}: no {CHECKPOINT}: not a training run of cosim learn train")
    device = device or device_of(None)
    try:
        ckpt = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # a truncated or foreign file: say which, once
        raise InputError(f"{path}: cannot read the checkpoint ({exc})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise InputError(f"{path}: not a cosim learn checkpoint of format {FORMAT}")
    setup = Setup.from_dict(ckpt["setup"])
    opts = TrainOptions(**ckpt["options"])
    model = PillarDetector(setup.grid, len(setup.classes), width=opts.width).to(device)
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
    clouds = item["clouds"]
    feats, mask, coords = batch_tensors(clouds, setup, device)
    heat, reg = model(feats, mask, coords, len(clouds))
    heat = peaks(heat).cpu().numpy()
    reg = reg.cpu().numpy()
    parts = [decode(heat[b], reg[b], setup.grid, score_min=score_min) for b in range(len(clouds))]
    boxes = np.concatenate([p[0] for p in parts])
    scores = np.concatenate([p[1] for p in parts])
    cls = np.concatenate([p[2] for p in parts])
    keep = circle_nms(boxes[:, :2], scores, nms_radius_m)[:max_boxes]
    return boxes[keep], scores[keep], cls[keep]


def record_lines(model: PillarDetector, samples: Samples, device: torch.device,
                 progress: Callable[[int, int], None] | None = None) -> list[str]:
    """One prediction record (docs/evaluation.md) per sample."""
    setup = samples.setup
    was_training = model.training
    model.eval()
    lines = []
    for i in range(len(samples)):
        item = samples.item(i)
        boxes, scores, cls = predict_sample(model, item, setup, device)
        lines.append(record_json(item["episode"], item["tick"], item["ego"], setup.agents, boxes[:, :3],
                                 boxes[:, 3:6], boxes[:, 6], [setup.classes[k] for k in cls], scores))
        if progress:
            progress(i + 1, len(samples))
    model.train(was_training)
    return lines


def validate(model: PillarDetector, samples: Samples, device: torch.device) -> dict[str, float]:
    """AP30, AP50 and AP70 (%) of the vehicle group on the samples (``cosim eval``'s scoring,
    ``--visible-only`` when the episodes have visibility topics)."""
    from cosim.eval.evaluate import EvalOptions, evaluate

    lines = record_lines(model, samples, device)
    records = [parse_record(json.loads(line), Path("val.jsonl"), n + 1) for n, line in enumerate(lines)]
    result = evaluate(samples.refs, records, EvalOptions(visible_only=True))
    det = result.metrics(samples.setup.agents)["detection"].get("vehicle", {})
    return {k: round(float(det.get(k, float("nan"))), 2) for k in ("AP30", "AP50", "AP70")}


def _step_batch(samples: Samples, order: np.ndarray, start: int, opts: TrainOptions, step: int
                ) -> tuple[list[np.ndarray], list[dict[str, np.ndarray]]]:
    rng = np.random.default_rng([opts.seed, step])
    clouds, tgts = [], []
    setup = samples.setup
    for j in range(opts.batch_size):
        item = samples.item(int(order[(start + j) % len(order)]))
        k = int(rng.integers(len(item["clouds"])))  # late fusion: one agent's cloud of the sample
        flip = rng.random(2) < 0.5
        cloud, boxes = augment(item["clouds"][k], item["targets"][k][0], bool(flip[0]), bool(flip[1]))
        clouds.append(cloud)
        tgts.append(targets(boxes, item["targets"][k][1], setup.grid, len(setup.classes)))
    return clouds, tgts


def _stack(tgts: list[dict[str, np.ndarray]], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.stack([t[k] for t in tgts])).to(device) for k in tgts[0]}


def _append_log(path: Path, rec: dict[str, Any]) -> None:
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(rec) + "\n")


def read_log(run: Path) -> list[dict[str, Any]]:
    path = Path(run) / "log.jsonl"
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def train(train_refs: list[EpisodeRef], val_refs: list[EpisodeRef] | None, setup: Setup, opts: TrainOptions,
          run: Path, resume: bool = False, device: torch.device | None = None, show_progress: bool = True
          ) -> dict[str, Any]:
    """Train (or resume) a detector into ``run``; returns the summary (also written to summary.json)."""
    from tqdm import tqdm

    run = Path(run)
    ckpt_path = run / CHECKPOINT
    device = device or device_of(None)
    if device.type == "cpu":
        torch.use_deterministic_algorithms(True)
        if opts.threads:
            torch.set_num_threads(opts.threads)
    if ckpt_path.exists() and not resume:
        raise InputError(f"{run} already holds a training run: --resume continues it, or choose another --out")
    if resume and not ckpt_path.exists():
        raise InputError(f"{run}: nothing to resume (no {CHECKPOINT})")
    check_classes(train_refs, setup.classes, "the model")
    t0 = time.perf_counter()
    samples = Samples(train_refs, setup, every=opts.every)
    val = Samples(val_refs, setup, every=opts.val_every_tick) if val_refs else None
    per_epoch = math.ceil(len(samples) / opts.batch_size)
    total = opts.steps if opts.steps is not None else opts.epochs * per_epoch
    if total < 1:
        raise InputError("nothing to train: give --epochs or --steps >= 1")
    model = new_model(setup, opts, device)
    optim = torch.optim.AdamW(model.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
    step = 0
    log_path = run / "log.jsonl"
    prior_s = 0.0
    if resume:
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=False)
        old = Setup.from_dict(ckpt["setup"])
        if old != setup:
            raise InputError(f"{run} was trained with fusion {old.fusion}, agents {old.agents}, classes "
                             f"{', '.join(old.classes)}: resume it with the same options")
        model.load_state_dict(ckpt["model"])
        optim.load_state_dict(ckpt["optimizer"])
        step = int(ckpt["step"])
        prior_s = float(ckpt.get("train_s", 0.0))
        kept = [r for r in read_log(run) if r["step"] <= step]
        log_path.write_text("".join(json.dumps(r) + "\n" for r in kept))
    else:
        run.mkdir(parents=True, exist_ok=True)
        log_path.write_text("")
    setup_s = time.perf_counter() - t0

    def save(step: int, train_s: float) -> None:
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save({"format": FORMAT, "setup": setup.to_dict(), "options": opts.to_dict(), "step": step,
                    "model": model.state_dict(), "optimizer": optim.state_dict(), "train_s": train_s}, tmp)
        tmp.replace(ckpt_path)

    val_s = 0.0
    t_train = time.perf_counter()
    model.train()
    bar = tqdm(total=total, initial=step, desc=f"train {setup.fusion}/{setup.agents}", unit="step", file=sys.stderr,
               disable=not show_progress or not sys.stderr.isatty(), dynamic_ncols=True, mininterval=0.5)
    last = None
    while step < total:
        epoch, pos = divmod(step, per_epoch)
        order = np.random.default_rng([opts.seed, 1_000_003 + epoch]).permutation(len(samples))
        clouds, tgts = _step_batch(samples, order, pos * opts.batch_size, opts, step)
        feats, mask, coords = batch_tensors(clouds, setup, device)
        tg = _stack(tgts, device)
        for group in optim.param_groups:
            group["lr"] = _lr(opts, step, total)
        heat, reg = model(feats, mask, coords, len(clouds))
        l_heat = focal_loss(heat, tg["heatmap"])
        l_reg = regression_loss(reg, tg["reg"], tg["index"], tg["mask"])
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
        do_val = val is not None and ((opts.val_steps and step % opts.val_steps == 0) or step == total)
        if do_val:
            tv = time.perf_counter()
            ap = validate(model, val, device)
            val_s += time.perf_counter() - tv
            _append_log(log_path, {"step": step, "val": ap})
            bar.write(f"step {step}: val AP30 {ap['AP30']:.1f}  AP50 {ap['AP50']:.1f}  AP70 {ap['AP70']:.1f}")
        kept = bool(opts.keep_every) and step % opts.keep_every == 0
        if kept or step % opts.save_every == 0 or step == total:
            save(step, prior_s + time.perf_counter() - t_train)
        if kept:
            shutil.copyfile(ckpt_path, run / f"checkpoint_{step:06d}.pt")
    bar.close()
    train_s = prior_s + time.perf_counter() - t_train
    samples.close()
    if val is not None:
        val.close()
    summary = {"setup": setup.to_dict(), "options": opts.to_dict(), "train_samples": len(samples),
               "train_episodes": len(train_refs), "val_episodes": len(val_refs or []), "steps": step,
               "final_loss": last, "device": str(device), "setup_s": round(setup_s, 1),
               "train_s": round(train_s, 1), "val_s": round(val_s, 1)}
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def validate_checkpoints(run: Path, refs: list[EpisodeRef], every: int, split: str, threads: int | None = None):
    """Score ``checkpoint_<step>.pt`` of a run (and its last checkpoint) on ``refs``, except steps already
    scored on ``split``; each result is appended to the run's ``log.jsonl`` as ``{"step", "val", "split"}``.
    Yields (step, AP dict)."""
    run = Path(run)
    files = sorted(run.glob("checkpoint_*.pt"))
    if (run / CHECKPOINT).is_file():
        files.append(run / CHECKPOINT)
    if not files:
        raise InputError(f"{run}: no checkpoints (train with --keep-every N to keep some)")
    if threads:
        torch.set_num_threads(threads)
    device = device_of(None)
    done = {int(r["step"]) for r in read_log(run) if "val" in r and r.get("split") == split}  # scored before
    samples = None
    for f in files:
        model, setup, ckpt = load_run(f, device)
        step = int(ckpt["step"])
        if step in done:
            continue
        done.add(step)
        if samples is None:
            check_classes(refs, setup.classes, f"the model in {run}")
            samples = Samples(refs, setup, every=every)
        ap = validate(model, samples, device)
        _append_log(run / "log.jsonl", {"step": step, "val": ap, "split": split})
        yield step, ap
    if samples is not None:
        samples.close()
