"""The KITTI options of ``cosim learn train|predict|validate|recall`` and the subcommands ``cosim learn score`` and
``cosim learn transfer``: real scans (or cosim's KITTI export) as a dataset (:mod:`cosim.learn.kitti`,
docs/realism.md, "Scoring a model on real scans"). Torch is imported only when a command needs it."""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

from cosim import cli_args
from cosim.errors import InputError

EXIT_OK = 0
KITTI_DIR = cli_args.path("input_folder", "KITTI folder")
RUN = cli_args.path("input_path", "run folder")
HEIGHT = cli_args.float_in(0.2, 10.0, "m")
SCALE = cli_args.at_least(0.0, above=True)
KITTI_TYPE_NAMES = ("Car", "Van", "Truck", "Tram", "Cyclist")


# -------------------------------------------------------------------------------------------- options


def add_source_options(p: argparse.ArgumentParser, training: bool = False) -> None:
    """How a KITTI folder is read: its sensor height, the reflectance factor, its ImageSets split, the types
    that are targets."""
    p.add_argument("--lidar-height-m", type=HEIGHT, metavar="M",
                   help="the KITTI folders' LiDAR height above the road (default: estimated from each folder's "
                        "ground, and printed); scans move in z to the model's own height")
    p.add_argument("--kitti-intensity-scale", type=SCALE, default=1.0, metavar="F",
                   help="the KITTI reflectance times F (then clipped to 0..1, in steps of 1/255 as cosim stores "
                        "intensity; default 1: KITTI's 0..1 as it is)")
    p.add_argument("--kitti-split", metavar="SPLIT",
                   help="only the scans of the folders' ImageSets/SPLIT.txt (default: every scan)")
    p.add_argument("--kitti-types", nargs="+", choices=KITTI_TYPE_NAMES, default=["Car", "Van"], metavar="TYPE",
                   help="KITTI types that are the vehicles to find (default Car Van; add Truck Tram Cyclist)")
    if training:
        p.add_argument("--kitti-val-split", metavar="SPLIT",
                       help="only the scans of the --kitti-val folders' ImageSets/SPLIT.txt")


def add_score_options(p: argparse.ArgumentParser, own_match: bool = True) -> None:
    """What counts on a KITTI folder (:class:`cosim.learn.kitti.ScoreOptions`); ``own_match`` False: the command
    has its own ``--min-score`` and ``--iou``."""
    from cosim.learn.kitti import DET_CLASSES, FOVS

    p.add_argument("--fov", choices=FOVS, default="camera",
                   help="score boxes in the front camera's view (default: KITTI labels nothing else), the front 90 "
                        "deg, or all (cosim's own KITTI export as cosim eval scores: its area, nothing left out)")
    p.add_argument("--max-range-m", type=cli_args.positive_float, default=40.0, metavar="M",
                   help="AP and false positives within M of the sensor (default 40)")
    p.add_argument("--min-points", type=cli_args.non_negative_int, default=5, metavar="N",
                   help="labelled vehicles with fewer LiDAR points are neither scored nor false positives (default 5)")
    if own_match:
        p.add_argument("--min-score", type=cli_args.fraction, default=0.3, metavar="S",
                       help="recall and false positives at score >= S (default 0.3)")
        p.add_argument("--iou", type=cli_args.fraction, default=0.3,
                       help="BEV IoU of a found vehicle (default 0.3)")
    p.add_argument("--det-classes", choices=DET_CLASSES, default=DET_CLASSES[0],
                   help="detections scored: those of the classes the KITTI types map to (default; KITTI scores each "
                        "class on its own detections, so a bicycle detection is no false car), or every vehicle "
                        "class's (--fov all always takes every class, as cosim eval)")


def add_kitti_options(p: argparse.ArgumentParser, command: str) -> None:
    """The KITTI options of ``cosim learn COMMAND`` (train, predict, validate, recall)."""
    g = p.add_argument_group("KITTI-layout folders (docs/realism.md, \"Scoring a model on real scans\")")
    if command == "train":
        g.add_argument("--kitti", action="append", type=KITTI_DIR, metavar="DIR",
                       help="train on the scans of this KITTI folder (velodyne/, label_2/, calib/) instead of a "
                            "dataset (repeatable)")
        g.add_argument("--kitti-val", action="append", type=KITTI_DIR, metavar="DIR",
                       help="validate on this KITTI folder (repeatable; with a dataset or --kitti)")
        g.add_argument("--init", type=RUN, metavar="RUN",
                       help="start from the weights of this run (fine-tuning; same fusion, classes and width)")
        add_source_options(g, training=True)
        add_score_options(g)
        return
    g.add_argument("--kitti", action="append" if command in ("validate", "recall") else None, type=KITTI_DIR,
                   metavar="DIR", help="a KITTI folder instead of a dataset" +
                                       (" (repeatable)" if command in ("validate", "recall") else ""))
    add_source_options(g)
    if command in ("validate", "recall"):
        add_score_options(g, own_match=command != "recall")


def sources(dirs: list[str], args: argparse.Namespace, labels: bool = True, split: str | None = None,
            quiet: bool = False) -> list[Any]:
    """The :class:`cosim.learn.kitti.KittiSource` of each folder, its height printed."""
    from cosim.learn.kitti import KittiSource

    out = []
    for d in dirs:
        s = KittiSource(d, height_m=args.lidar_height_m, intensity_scale=args.kitti_intensity_scale,
                        types=tuple(args.kitti_types), labels=labels, split=split)
        if not quiet:
            print(f"kitti    {s.id}: {len(s)} scans, LiDAR {s.height_m:.3f} m above the road "
                  f"({'given' if s.height_given else 'estimated from the ground'})")
        out.append(s)
    return out


def score_options(args: argparse.Namespace) -> Any:
    from cosim.learn.kitti import ScoreOptions

    return ScoreOptions(fov=args.fov, max_range_m=args.max_range_m, min_points=args.min_points,
                        min_score=args.min_score, iou=args.iou, det_classes=args.det_classes)


def _no_dataset(args: argparse.Namespace, command: str) -> None:
    if getattr(args, "dataset", None) and args.kitti:
        raise InputError(f"cosim learn {command}: give a dataset or --kitti, not both")


# ------------------------------------------------------------------------------------------ commands


def cmd_train(args: argparse.Namespace, setup: Any, opts: Any) -> int:
    """``cosim learn train --kitti DIR`` (or a dataset validated on ``--kitti-val``), with ``--init``."""
    from cosim.learn.kitti import episodes_lidar_height_m, kitti_samples, run_training, val_fn
    from cosim.learn.train import device_of, load_run, summary_text

    if args.dataset and args.kitti:
        raise InputError("cosim learn train: give a dataset or --kitti, not both")
    if args.fusion != "none" and (args.kitti or args.kitti_val):
        raise InputError(f"a KITTI folder has one agent: train on it with --fusion none, not {args.fusion}")
    device = device_of(args.device)
    height = None
    if args.init:
        init_setup = load_run(Path(args.init), device)[1]
        height = init_setup.lidar_height_m
    train_src = sources(args.kitti or [], args, split=args.kitti_split)
    val_src = sources(args.kitti_val or [], args, split=args.kitti_val_split)
    refs = None
    if args.dataset:
        from cosim.eval.dataset import load_dataset
        from cosim.learn.data import Samples, check_classes, split_episodes

        all_refs = load_dataset(Path(args.dataset))
        refs = split_episodes(all_refs, args.split, "train", args.dataset)
        check_classes(refs, setup.classes, "the model")
        if height is None:
            height = episodes_lidar_height_m(refs)
    elif height is None:
        height = train_src[0].height_m
    setup = dataclasses.replace(setup, lidar_height_m=height)
    if refs is not None:
        samples = Samples(refs, setup, every=opts.every, cache=Path(args.cache) if args.cache else None)
    else:
        samples = kitti_samples(train_src, setup, crop_fov="camera")
    validate = val_fn(val_src, setup, device, score_options(args)) if val_src and not args.no_val else None
    val = None
    if refs is not None and validate is None and not args.no_val and (
            args.val_split is not None or any(r.split == "val" for r in all_refs)):
        from cosim.learn.train import validate as validate_episodes

        val = Samples(split_episodes(all_refs, args.val_split or "val", "val", args.dataset), setup,
                      every=opts.val_every_tick, cache=Path(args.cache) if args.cache else None)

        def validate(model: Any) -> dict[str, float]:
            return validate_episodes(model, val, device)
    print(f"model    LiDAR at {'-' if height is None else format(height, '.3f')} m above the road"
          + (f" (from {args.init})" if args.init else ""))
    about = {"train_episodes": len(refs) if refs is not None else 0, "train_kitti": [s.id for s in train_src],
             "val_kitti": [s.id for s in val_src], "val_episodes": len(val.refs) if val is not None else 0,
             "init": str(args.init) if args.init else None,
             "kitti_heights_m": {s.id: s.height_m for s in train_src + val_src}}
    try:
        summary = run_training(samples, validate, setup, opts, Path(args.out), args.resume, device, not args.quiet,
                               Path(args.init) if args.init else None, about)
    finally:
        if val is not None:
            val.close()
    what = f"{len(refs)} episodes" if refs is not None else ", ".join(s.id for s in train_src)
    val_what = ", ".join(s.id for s in val_src) or (f"{len(val.refs)} episodes" if val is not None else "none")
    print(summary_text(args.out, summary, f"{what} (val: {val_what})"))
    return EXIT_OK


def cmd_predict(args: argparse.Namespace) -> int:
    """``cosim learn predict RUN --kitti DIR --out F.jsonl``."""
    from cosim.learn import require_torch

    torch = require_torch()
    from cosim.eval.predictions import write_prediction_lines
    from cosim.learn.kitti import predict_source, prediction_lines
    from cosim.learn.train import device_of, load_run

    _no_dataset(args, "predict")
    if not args.out.endswith(".jsonl"):
        raise InputError(f"--out {args.out}: predictions are a .jsonl file")
    device = device_of(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    model, setup, _ = load_run(Path(args.run), device)
    if setup.fusion != "none":
        raise InputError(f"the model in {args.run} was trained for fusion {setup.fusion}: a KITTI folder has one "
                         "agent (predict with a model of fusion none)")
    src = sources([args.kitti], args, labels=False, split=args.kitti_split)[0]
    t0 = time.perf_counter()
    lines = prediction_lines(src, setup, predict_source(model, setup, src, device))
    out = write_prediction_lines(Path(args.out), lines)
    shift = "no height recorded: not moved" if setup.lidar_height_m is None else \
        f"moved {src.height_m - setup.lidar_height_m:+.3f} m to the model's {setup.lidar_height_m:.3f} m"
    print(f"predictions {out}: {len(lines)} scans of {src.id} (points {shift}; {time.perf_counter() - t0:.1f} s)")
    return EXIT_OK


def cmd_validate(args: argparse.Namespace) -> int:
    """``cosim learn validate RUN --kitti DIR``: every kept checkpoint scored on KITTI folders."""
    from cosim.learn import require_torch

    require_torch()
    from cosim.learn.kitti import validate_checkpoints

    _no_dataset(args, "validate")
    src = sources(args.kitti, args, split=args.kitti_split)
    t0 = time.perf_counter()
    for step, ap in validate_checkpoints(Path(args.run), src, score_options(args), threads=args.threads,
                                         from_step=args.from_step):
        print(f"step {step}: {', '.join(s.id for s in src)} AP30 {ap['AP30']:.1f}  AP50 {ap['AP50']:.1f}  "
              f"AP70 {ap['AP70']:.1f}")
    print(f"wall     {time.perf_counter() - t0:.1f} s")
    return EXIT_OK


def cmd_score(args: argparse.Namespace) -> int:
    """``cosim learn score PRED... --kitti DIR... --out DIR`` (and ``cosim learn recall --kitti``): one row per
    prediction file and KITTI folder."""
    from cosim.eval.predictions import read_predictions
    from cosim.learn.kitti import predictions_from_file, score_source, score_title, write_score

    _no_dataset(args, "recall")
    o = score_options(args)
    src = sources(args.kitti, args, split=args.kitti_split)
    rows = []
    for f in args.pred:
        episodes = {r.episode for r in read_predictions(Path(f))}
        matched = [s for s in src if s.id in episodes]
        unknown = sorted(episodes - {s.id for s in src})
        if unknown:
            raise InputError(f"{f}: records of {unknown[0]!r}, which is none of the --kitti folders "
                             f"({', '.join(s.id for s in src)})")
        for s in matched:
            preds = predictions_from_file(Path(f), s)
            rows.append({"predictions": Path(f).name, "folder": s.id, **score_source(s, preds, o).summary()})
    md, _js = write_score(rows, Path(args.out), o, score_title(o))
    print(md.read_text(), end="")
    return EXIT_OK


def register(lsub: argparse._SubParsersAction) -> None:
    """``cosim learn score`` and ``cosim learn transfer``."""
    sc = lsub.add_parser("score", help="score predictions on KITTI folders: recall by range, false positives per "
                                       "frame, BEV AP (cosim learn score PRED --kitti DIR --out DIR)")
    sc.add_argument("pred", nargs="+", type=cli_args.path("input_file", "prediction file"),
                    help="prediction files of cosim learn predict --kitti (.jsonl)")
    sc.add_argument("--kitti", action="append", required=True, type=KITTI_DIR, metavar="DIR",
                    help="the KITTI folder the predictions are of (repeatable)")
    sc.add_argument("--out", required=True, type=cli_args.output_folder, help="folder for score.md and score.json")
    add_source_options(sc)
    add_score_options(sc)
    sc.set_defaults(func=cmd_score)
    register_transfer(lsub)


def cmd_transfer(args: argparse.Namespace) -> int:
    from cosim.learn import require_torch

    torch = require_torch()
    from cosim.learn.kitti import finite
    from cosim.learn.train import device_of
    from cosim.learn.transfer import markdown, parse_runs, transfer

    runs = parse_runs(args.run)
    o = score_options(args)
    if args.picture and not args.picture.endswith(".png"):
        raise InputError(f"--picture {args.picture}: a .png file")
    if args.threads:
        torch.set_num_threads(args.threads)
    src = sources(args.kitti, args, split=args.kitti_split)
    report = transfer(runs, src, o, device_of(args.device), Path(args.picture) if args.picture else None,
                      args.picture_scans)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    md = markdown(report)
    (out / "transfer.md").write_text(md)
    (out / "transfer.json").write_text(json.dumps(finite(report), indent=1) + "\n")
    print(md, end="")
    print(f"report   {out / 'transfer.md'}, {out / 'transfer.json'}")
    return EXIT_OK


def register_transfer(lsub: argparse._SubParsersAction) -> None:
    tf = lsub.add_parser("transfer", help="the transfer report: runs (by name, several seeds) scored on KITTI "
                                          "folders (docs/realism.md)")
    tf.add_argument("--run", action="append", required=True, metavar="NAME=RUN",
                    help="a run folder and the name of its row (repeat the name for each seed; e.g. cosim=runs/c0)")
    tf.add_argument("--kitti", action="append", required=True, type=KITTI_DIR, metavar="DIR",
                    help="a KITTI folder of real scans (repeatable: one table each)")
    tf.add_argument("--out", required=True, type=cli_args.output_folder, help="folder for transfer.md and "
                                                                              "transfer.json")
    tf.add_argument("--picture", type=cli_args.output_file, metavar="PNG",
                    help="real scans of the first folder in bird's eye view with each name's boxes and the labels")
    tf.add_argument("--picture-scans", type=cli_args.positive_int, default=4, metavar="N",
                    help="scans in the picture (those with the most vehicles; default 4)")
    tf.add_argument("--device", help="torch device (default: cuda when present, else cpu)")
    tf.add_argument("--threads", type=cli_args.positive_int, help="torch CPU threads (default: torch's)")
    add_source_options(tf)
    add_score_options(tf)
    tf.set_defaults(func=cmd_transfer)
