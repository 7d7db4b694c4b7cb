"""``cosim learn cache|train|predict|validate|curves|recall``: cache a dataset's samples, train the detector,
write predictions for ``cosim eval``, plot learning curves, count what collaboration finds
(docs/learnability.md). Torch is imported only when a command that needs it runs."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from cosim import cli_args
from cosim.errors import InputError

if TYPE_CHECKING:
    from cosim.learn.samples import Perturb

EXIT_OK = 0


_positive = cli_args.positive_int
DATASET = cli_args.path("input_path", "dataset")
RUN = cli_args.path("input_folder", "run folder")
CACHE = cli_args.path("input_folder", "cache folder")


def pose_noise(text: str) -> tuple[float, float]:
    """``POS_M,ROT_DEG``: two numbers >= 0 (the standard deviations of a collaborator's x, y and yaw error)."""
    parts = text.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"must be POS_M,ROT_DEG (two numbers >= 0, e.g. 0.2,0.2), got "
                                         f"{cli_args.shown(text)!r}")
    return tuple(cli_args.non_negative_float(v.strip()) for v in parts)  # type: ignore[return-value]


def latency(text: str) -> int | str:
    """``links`` or a whole number of milliseconds >= 0."""
    return "links" if text == "links" else cli_args.Check("int", low=0, unit="ms")(text)


def loss(text: str) -> float | str:
    """``links`` or a probability from 0 to 1."""
    return "links" if text == "links" else cli_args.fraction(text)


def perturb_of(args: argparse.Namespace) -> Perturb:
    """The :class:`~cosim.learn.samples.Perturb` of a command's ``--pose-noise``, ``--latency``, ``--loss``
    (``--delivery``: ``--loss links``) and ``--perturb-seed``."""
    from cosim.learn.samples import Perturb

    pos_m, rot_deg = args.pose_noise or (0.0, 0.0)
    lat = args.latency or 0
    drop = "links" if getattr(args, "delivery", False) else (args.loss or 0.0)
    return Perturb(pose_m=pos_m, pose_deg=rot_deg, latency_ms=0 if lat == "links" else lat,
                   latency_links=lat == "links", loss=0.0 if drop == "links" else drop, loss_links=drop == "links",
                   seed=args.perturb_seed)


def add_perturb_options(p: argparse.ArgumentParser, when: str) -> None:
    """The perturbation flags (docs/learnability.md, "Collaboration as deployed"), applied ``when``."""
    g = p.add_argument_group(f"collaboration as deployed, {when} (docs/learnability.md; each off by default)")
    g.add_argument("--pose-noise", type=pose_noise, metavar="POS_M,ROT_DEG",
                   help="Gaussian error on each collaborator's pose: POS_M metres on x and y, ROT_DEG degrees on "
                        "yaw (standard deviations; e.g. 0.2,0.2)")
    g.add_argument("--latency", type=latency, metavar="MS|links",
                   help="each collaborator's data from MS milliseconds before the ego's tick (a whole number of "
                        "ticks), placed with its pose of then; 'links': its /comm/links delay rounded up to ticks")
    g.add_argument("--loss", type=loss, metavar="P|links",
                   help="each collaborator's message lost with probability P; 'links': with one minus its "
                        "/comm/links delivery probability")
    g.add_argument("--delivery", action="store_true", help="the same as --loss links (deprecated)")
    g.add_argument("--perturb-seed", type=cli_args.non_negative_int, default=0, metavar="S",
                   help="the perturbations' seed: the same seed, the same draws (default 0)")


def cmd_train(args: argparse.Namespace) -> int:
    from cosim.learn import require_torch

    require_torch()
    from cosim.eval.dataset import VEHICLE_CLASSES, load_dataset
    from cosim.learn.data import Setup, split_episodes
    from cosim.learn.grid import make_grid
    from cosim.learn.kitti import episodes_lidar_height_m
    from cosim.learn.train import TrainOptions, check_run_folder, device_of, summary_text, train

    check_run_folder(Path(args.out), args.resume)  # before the dataset is read
    augment = _augment_options(args)
    grid = make_grid(args.pillar_m, *((args.range_m[:2], args.range_m[2:]) if args.range_m else (None, None)))

    setup = Setup(fusion=args.fusion, agents=args.agents or ("ego" if args.fusion == "none" else "all"),
                  classes=tuple(args.classes or VEHICLE_CLASSES), perturb=perturb_of(args), lidar=args.lidar,
                  fuse=args.fuse, encoders=args.encoders, grid=grid)
    opts = TrainOptions(epochs=args.epochs, steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                        every=args.every, val_every_tick=args.val_every_tick, val_steps=args.val_steps,
                        save_every=args.save_every, keep_every=args.keep_every, seed=args.seed, width=args.width,
                        threads=args.threads, schedule=args.schedule, workers=args.workers, turn_deg=args.turn,
                        **augment)
    if args.kitti or args.kitti_val or args.init:
        from cosim.learn.kitti_cli import cmd_train as kitti_train

        return kitti_train(args, setup, opts)
    if not args.dataset:
        raise InputError("cosim learn train: give a dataset or --kitti DIR")
    refs = load_dataset(Path(args.dataset))
    train_refs = split_episodes(refs, args.split, "train", args.dataset)
    setup = dataclasses.replace(setup, lidar_height_m=episodes_lidar_height_m(train_refs))
    val_refs = None
    if not args.no_val and (args.val_split is not None or any(r.split == "val" for r in refs)):
        val_refs = split_episodes(refs, args.val_split or "val", "val", args.dataset)
    summary = train(train_refs, val_refs, setup, opts, Path(args.out), resume=args.resume,
                    device=device_of(args.device), show_progress=not args.quiet,
                    cache=Path(args.cache) if args.cache else None)
    print(summary_text(args.out, summary, f"{summary['train_episodes']} episodes "
                                          f"(val: {summary['val_episodes']} episodes)"))
    return EXIT_OK


def _augment_options(args: argparse.Namespace) -> dict:
    """The augmentation fields of TrainOptions from ``cosim learn train``'s flags, each checked (InputError)."""
    lo, hi = args.scale
    if not (0.5 <= lo <= hi <= 2.0):
        raise InputError(f"--scale {lo:g} {hi:g}: give LOW <= HIGH, both within 0.5 to 2")
    for flag, v, top in (("--translate-m", args.translate_m, 5.0), ("--height-jitter-m", args.height_jitter_m, 2.0),
                         ("--intensity-noise", args.intensity_noise, 1.0)):
        if not 0.0 <= v <= top:
            raise InputError(f"{flag} {v:g}: a standard deviation of 0 to {top:g}")
    if not 0.0 <= args.point_drop < 1.0:
        raise InputError(f"--point-drop {args.point_drop:g}: the share of points dropped must be 0 to below 1")
    if not 1.0 <= args.intensity_scale <= 10.0:
        raise InputError(f"--intensity-scale {args.intensity_scale:g}: a factor of 1 (off) to 10")
    if args.gt_sample < 0:
        raise InputError(f"--gt-sample {args.gt_sample}: objects pasted per sample must be 0 (off) or more")
    if args.gt_sample and args.fusion != "none":
        raise InputError(f"--gt-sample pastes objects cut from single-agent samples: it works with --fusion none "
                         f"only, not {args.fusion}")
    return {"scale_min": lo, "scale_max": hi, "translate_m": args.translate_m, "height_m": args.height_jitter_m,
            "point_drop": args.point_drop, "intensity_scale": args.intensity_scale,
            "intensity_noise": args.intensity_noise, "gt_sample": args.gt_sample, "gt_min_points": args.gt_min_points}


def cmd_predict(args: argparse.Namespace) -> int:
    from cosim.learn import require_torch

    require_torch()
    from tqdm import tqdm

    from cosim.eval.dataset import load_dataset
    from cosim.eval.predictions import write_prediction_lines
    from cosim.learn.data import Samples, check_classes, split_episodes
    from cosim.learn.train import device_of, load_run, record_lines

    if args.kitti:
        from cosim.learn.kitti_cli import cmd_predict as kitti_predict

        return kitti_predict(args)
    if not args.dataset:
        raise InputError("cosim learn predict: give a dataset or --kitti DIR")
    if not args.out.endswith(".jsonl"):
        raise InputError(f"--out {args.out}: predictions are a .jsonl file")
    device = device_of(args.device)
    if args.threads:
        require_torch().set_num_threads(args.threads)
    model, setup, _ = load_run(Path(args.run), device)
    if args.fusion or args.agents:
        if (args.fusion == "intermediate") != (setup.fusion == "intermediate"):
            raise InputError(f"the model in {args.run} was trained for fusion {setup.fusion}: intermediate fusion "
                             "needs a model trained for it (and such a model predicts with intermediate only)")
        setup = setup.with_agents(args.fusion, args.agents)
    setup = dataclasses.replace(setup, perturb=perturb_of(args))  # the test's perturbation, never the training's
    if args.lidar:
        setup = dataclasses.replace(setup, lidar=args.lidar)
    refs = split_episodes(load_dataset(Path(args.dataset)), args.split, "test", args.dataset)
    check_classes(refs, setup.classes, f"the model in {args.run}")
    samples = Samples(refs, setup, every=args.every, cache=Path(args.cache) if args.cache else None)
    t0 = time.perf_counter()
    bar = tqdm(total=len(samples), desc="predict", unit="sample", file=sys.stderr,
               disable=args.quiet or not sys.stderr.isatty(), dynamic_ncols=True)
    try:
        lines = record_lines(model, samples, device, progress=lambda done, total: bar.update(done - bar.n))
    finally:
        bar.close()
        samples.close()
    out = write_prediction_lines(Path(args.out), lines)
    sent = [json.loads(line).get("bytes_sent", 0) for line in lines]
    print(f"predictions {out}: {len(lines)} records from {len(refs)} episodes, fusion {setup.fusion}, agents "
          f"{setup.agents}, lidar {setup.lidar} ({time.perf_counter() - t0:.1f} s)\n"
          f"sent     {sum(sent) / max(1, len(sent)):.0f} bytes per ego frame from the collaborators; perturbation "
          f"{setup.perturb.describe()}")
    return EXIT_OK


def cmd_validate(args: argparse.Namespace) -> int:
    from cosim.learn import require_torch

    require_torch()
    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import split_episodes
    from cosim.learn.train import validate_checkpoints

    if args.kitti:
        from cosim.learn.kitti_cli import cmd_validate as kitti_validate

        return kitti_validate(args)
    if not args.dataset:
        raise InputError("cosim learn validate: give a dataset or --kitti DIR")
    run = Path(args.run)
    refs = split_episodes(load_dataset(Path(args.dataset)), args.split, args.split, args.dataset)
    t0 = time.perf_counter()
    for step, ap in validate_checkpoints(run, refs, args.every, args.split, threads=args.threads,
                                         cache=Path(args.cache) if args.cache else None, from_step=args.from_step,
                                         perturb=perturb_of(args)):
        print(f"step {step}: {args.split} AP30 {ap['AP30']:.1f}  AP50 {ap['AP50']:.1f}  AP70 {ap['AP70']:.1f}  "
              f"sent {ap['bytes_per_frame']:.0f} bytes per ego frame")
    print(f"wall     {time.perf_counter() - t0:.1f} s")
    return EXIT_OK


def cmd_cache(args: argparse.Namespace) -> int:
    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import split_episodes, write_cache

    refs = load_dataset(Path(args.dataset))
    if args.split:
        refs = split_episodes(refs, args.split, args.split, args.dataset)
    out = write_cache(refs, Path(args.out), args.lidar, args.every,
                      progress=None if args.quiet else lambda n, total, eid: print(f"cached {n}/{total} {eid}",
                                                                                   file=sys.stderr))
    print(f"cache    {args.out}: {out['episodes']} episodes, every {args.every} ticks, lidar {args.lidar}, "
          f"{out['bytes'] / 1e6:.0f} MB ({out['s']:.0f} s)")
    return EXIT_OK


def cmd_recall(args: argparse.Namespace) -> int:
    from cosim.eval.dataset import load_dataset
    from cosim.learn.data import split_episodes
    from cosim.learn.recall import recall_rows, write_recall

    if args.kitti:  # a KITTI folder: recall by range band (cosim learn score); the first positional is a file
        from cosim.learn.kitti_cli import cmd_score

        args.pred, args.dataset = ([args.dataset] if args.dataset else []) + list(args.pred), None
        return cmd_score(args)
    if not args.dataset:
        raise InputError("cosim learn recall: give a dataset or --kitti DIR")
    refs = split_episodes(load_dataset(Path(args.dataset)), args.split, "test", args.dataset)
    files = [Path(f) for f in args.pred]
    for f in files:
        if not f.is_file():
            raise InputError(f"{f}: no such prediction file")
    rows = recall_rows(refs, files, iou=args.iou, min_score=args.min_score, by=args.by)
    md, _js = write_recall(rows, Path(args.out), args.iou, args.min_score, args.by)
    print(md.read_text(), end="")
    return EXIT_OK


def cmd_curves(args: argparse.Namespace) -> int:
    from cosim.learn.curves import plot_curves

    path = plot_curves([Path(r) for r in args.runs], Path(args.out), args.title)
    print(path)
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    from cosim.eval.predictions import SETTINGS
    from cosim.learn.kitti_cli import add_kitti_options
    from cosim.learn.kitti_cli import register as register_kitti
    from cosim.learn.samples import ENCODERS, FUSES, FUSIONS, LIDAR_MODES, SCHEDULES

    lidar_help = ("LiDAR motion compensation: tick (every sweep moved to the sensor pose at the tick, as the "
                  "exports; default), objects (also moving objects' points to the tick), raw (as fired)")

    lp = sub.add_parser("learn", help="train the LiDAR detector on a dataset and predict (needs the 'learn' extra)")
    lsub = lp.add_subparsers(dest="learn_command", metavar="ACTION", parser_class=type(lp))
    lsub.required = True

    tr = lsub.add_parser("train", help="train a detector: cosim learn train DATASET --out RUN")
    tr.add_argument("dataset", type=DATASET, nargs="?",
                    help="batch folder (its train split, or every episode when it has no splits), a "
                         "folder of episodes or one episode (or --kitti DIR)")
    tr.add_argument("--out", required=True, type=cli_args.output_folder,
                    help="run folder: checkpoint.pt, log.jsonl, summary.json")
    tr.add_argument("--fusion", choices=FUSIONS, default="none",
                    help="none (ego only), late (boxes merged), early (points merged), intermediate (BEV features "
                         "warped into the ego frame and fused); default none")
    tr.add_argument("--fuse", choices=FUSES, default="max", help="intermediate fusion per cell: max (F-Cooper) or "
                                                                 "attention (AttFuse); default max")
    tr.add_argument("--encoders", choices=ENCODERS, default="shared",
                    help="intermediate fusion: one pillar encoder for all agents (shared), one per agent kind "
                         "(kind), or one per LiDAR of the training data (sensor: its preset, or its kind's LiDAR; "
                         "a LiDAR unknown at prediction takes its kind's encoder)")
    tr.add_argument("--lidar", choices=LIDAR_MODES, default="tick", help=lidar_help)
    tr.add_argument("--cache", type=CACHE,
                    help="a folder of cosim learn cache: read the samples from it, not from MCAP")
    tr.add_argument("--workers", type=cli_args.non_negative_int, default=0,
                    help="processes that make the batches (default 0: none)")
    tr.add_argument("--turn", type=cli_args.float_in(0, 180, "degrees"), default=0.0, metavar="DEG",
                    help="turn each training sample about z by a random angle of up to DEG degrees either way "
                         "(default 0: mirror only)")
    ag = tr.add_argument_group("augmentation (docs/learnability.md, \"Augmentation\"; each off by default)")
    ag.add_argument("--scale", type=cli_args.finite_float, nargs=2, default=(1.0, 1.0), metavar=("LOW", "HIGH"),
                    help="global scaling of each sample by a factor drawn from LOW to HIGH (e.g. 0.95 1.05)")
    ag.add_argument("--translate-m", type=cli_args.finite_float, default=0.0, metavar="SIGMA",
                    help="global translation: each sample moved by N(0, SIGMA) m along x, y and z (e.g. 0.2)")
    ag.add_argument("--height-jitter-m", type=cli_args.finite_float, default=0.0, metavar="SIGMA",
                    help="sensor-height jitter: each sample moved in z by N(0, SIGMA) m (e.g. 0.2)")
    ag.add_argument("--point-drop", type=cli_args.finite_float, default=0.0, metavar="SHARE",
                    help="drop each point with this probability (e.g. 0.1)")
    ag.add_argument("--intensity-scale", type=cli_args.finite_float, default=1.0, metavar="F",
                    help="intensities times a factor drawn log-uniformly from 1/F to F (e.g. 2; 1: off)")
    ag.add_argument("--intensity-noise", type=cli_args.finite_float, default=0.0, metavar="SIGMA",
                    help="plus N(0, SIGMA) per point, clipped to 0..1 (e.g. 0.05)")
    ag.add_argument("--gt-sample", type=cli_args.whole_number, default=0, metavar="N",
                    help="ground-truth sampling (fusion none): paste up to N labelled objects cut from other "
                         "training samples into each sample, at free places on its ground, hiding what they "
                         "occlude (e.g. 10)")
    ag.add_argument("--gt-min-points", type=_positive, default=5, metavar="N",
                    help="objects of the ground-truth database have at least N points (default 5)")
    tr.add_argument("--pillar-m", type=cli_args.finite_float, default=0.8, metavar="M",
                    help="pillar size (default 0.8; e.g. 0.4, 0.32, 0.2: finer costs CPU, docs/learnability.md)")
    tr.add_argument("--range-m", type=cli_args.finite_float, nargs=4, metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                    help="the detection range in the ego LiDAR frame (default -140.8 140.8 -40 40, cosim eval's "
                         "area; KITTI-like front view: 0 70.4 -40 40)")
    tr.add_argument("--schedule", choices=SCHEDULES, default="cosine",
                    help="learning rate: cosine (warm-up, cosine to 0; default) or onecycle")
    tr.add_argument("--agents", choices=list(SETTINGS), help="collaborating agent kinds (default: ego for "
                                                                    "fusion none, all otherwise)")
    tr.add_argument("--classes", nargs="+", metavar="CLASS", help="object classes to detect (default: the six "
                                                                  "vehicle classes)")
    add_perturb_options(tr, "at training (and its own validation)")
    tr.add_argument("--epochs", type=_positive, default=1, help="passes over the training samples (default 1)")
    tr.add_argument("--steps", type=_positive, help="optimiser steps in total (overrides --epochs)")
    tr.add_argument("--batch-size", type=_positive, default=8)
    tr.add_argument("--lr", type=cli_args.positive_float, default=2e-3)
    tr.add_argument("--every", type=_positive, default=1, help="train on ticks 0, every, 2 every... (default 1)")
    tr.add_argument("--split", help="training split (default: train, or all episodes of a dataset without splits)")
    tr.add_argument("--val-split", help="validation split (default: val when the dataset has one)")
    tr.add_argument("--no-val", action="store_true", help="no validation")
    tr.add_argument("--val-every-tick", type=_positive, default=10, help="validate on ticks 0, k, 2k... (default 10)")
    tr.add_argument("--val-steps", type=cli_args.non_negative_int, default=0,
                    help="validate every this many steps (default: at the end)")
    tr.add_argument("--save-every", type=_positive, default=100, help="checkpoint every this many steps")
    tr.add_argument("--keep-every", type=cli_args.non_negative_int, default=0,
                    help="also keep checkpoint_<step>.pt every this many "
                                                              "steps (for cosim learn validate)")
    tr.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    tr.add_argument("--seed", type=cli_args.non_negative_int, default=0)
    tr.add_argument("--width", type=_positive, default=16, help="pillar feature channels (default 16)")
    tr.add_argument("--threads", type=_positive, help="torch CPU threads (default: torch's; 1 is fastest on a "
                                                      "busy machine)")
    tr.add_argument("--device", help="torch device (default: cuda when present, else cpu)")
    tr.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_kitti_options(tr, "train")
    tr.set_defaults(func=cmd_train)

    pr = lsub.add_parser("predict", help="write predictions for cosim eval: cosim learn predict RUN DATASET --out F")
    pr.add_argument("run", type=RUN, help="a run folder of cosim learn train")
    pr.add_argument("dataset", type=DATASET, nargs="?",
                    help="batch folder (its test split by default), a folder of episodes or one episode (or "
                         "--kitti DIR)")
    pr.add_argument("--out", required=True, type=cli_args.output_file, help="predictions file (.jsonl)")
    pr.add_argument("--split", help="split to predict (default: test, or all episodes of a dataset without splits)")
    pr.add_argument("--every", type=_positive, default=1, help="predict ticks 0, every, 2 every... (default 1)")
    pr.add_argument("--fusion", choices=FUSIONS, help="fuse otherwise than the model was trained (e.g. late with an "
                                                      "ego-only model: each agent's cloud detected alone)")
    pr.add_argument("--agents", choices=list(SETTINGS), help="collaborating agent kinds at prediction time "
                                                             "(default: the model's)")
    add_perturb_options(pr, "at test (never the model's training perturbation)")
    pr.add_argument("--lidar", choices=LIDAR_MODES, help="LiDAR compensation (default: the model's)")
    pr.add_argument("--cache", type=CACHE, help="a folder of cosim learn cache to read the samples from")
    pr.add_argument("--device", help="torch device (default: cuda when present, else cpu)")
    pr.add_argument("--threads", type=_positive, help="torch CPU threads (default: torch's)")
    pr.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_kitti_options(pr, "predict")
    pr.set_defaults(func=cmd_predict)

    va = lsub.add_parser("validate", help="score every kept checkpoint of a run on a split (the learning curve "
                                          "in log.jsonl)")
    va.add_argument("run", type=RUN,
                    help="a run folder of cosim learn train (with checkpoint_<step>.pt from --keep-every)")
    va.add_argument("dataset", type=DATASET, nargs="?", help="batch folder (or --kitti DIR)")
    va.add_argument("--split", default="val", help="split to score (default val)")
    va.add_argument("--every", type=_positive, default=10, help="ticks 0, every, 2 every... (default 10)")
    va.add_argument("--from-step", type=cli_args.non_negative_int, default=0, metavar="STEP",
                    help="only the checkpoints at this step or later (e.g. the last 20 %% of the steps)")
    va.add_argument("--cache", type=CACHE, help="a folder of cosim learn cache to read the samples from")
    va.add_argument("--threads", type=_positive, help="torch CPU threads (default: torch's)")
    add_perturb_options(va, "at test")
    add_kitti_options(va, "validate")
    va.set_defaults(func=cmd_validate)

    ca = lsub.add_parser("cache", help="cache a dataset's samples (one .npz per episode): cosim learn cache "
                                       "DATASET --out DIR")
    ca.add_argument("dataset", type=DATASET, help="batch folder, a folder of episodes or one episode")
    ca.add_argument("--out", required=True, type=cli_args.output_folder,
                    help="cache folder (cache.json and <split>/<episode>.npz)")
    ca.add_argument("--lidar", choices=LIDAR_MODES, default="tick", help=lidar_help)
    ca.add_argument("--every", type=_positive, default=1, help="cache ticks 0, every, 2 every... (default 1)")
    ca.add_argument("--split", help="cache only this split (default: every episode)")
    ca.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    ca.set_defaults(func=cmd_cache)

    rc = lsub.add_parser("recall", help="objects the ego has no return on, found by each model (one prediction "
                                        "file per setting)")
    rc.add_argument("dataset", type=DATASET, nargs="?", help="batch folder (or --kitti DIR)")
    rc.add_argument("pred", nargs="+", type=cli_args.path("input_file", "prediction file"),
                    help="prediction files of cosim learn predict (.jsonl)")
    rc.add_argument("--out", required=True, type=cli_args.output_folder, help="folder for recall.md and recall.json")
    rc.add_argument("--split", help="split of the predictions (default test)")
    rc.add_argument("--iou", type=cli_args.fraction, default=0.3, help="BEV IoU of a match (default 0.3)")
    rc.add_argument("--min-score", type=cli_args.fraction, default=0.3,
                    help="predictions of at least this score (default 0.3)")
    rc.add_argument("--by", help="one row per file and value of this episode condition (lighting, weather, "
                                 "environment or strategy)")
    add_kitti_options(rc, "recall")
    rc.set_defaults(func=cmd_recall)

    cu = lsub.add_parser("curves", help="plot validation AP against steps of one or more runs (PNG)")
    cu.add_argument("runs", nargs="+", type=RUN, help="run folders")
    cu.add_argument("--out", required=True, type=cli_args.output_file, help="PNG file")
    cu.add_argument("--title", default="validation AP (vehicle) against training steps")
    cu.set_defaults(func=cmd_curves)
    register_kitti(lsub)

