"""``cosim eval`` and ``cosim coverage`` (registered into ``cosim`` by :func:`register`; docs/evaluation.md)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from cosim import cli_args
from cosim.errors import InputError

log = logging.getLogger(__name__)

EXIT_OK = 0
DATASET = cli_args.path("input_path", "episode file or batch folder")


def _rule(args: argparse.Namespace):
    from cosim.eval.dataset import VisibilityRule

    return VisibilityRule(args.min_points, args.min_pixels)


def _log_progress(what: str):
    def update(done: int, total: int) -> None:
        log.info("%s: %d/%d episodes", what, done, total)

    return update


def cmd_eval(args: argparse.Namespace) -> int:
    from cosim.eval.baselines import baseline, write_predictions
    from cosim.eval.dataset import load_dataset
    from cosim.eval.evaluate import EvalOptions, eval_tables, evaluate, write_eval
    from cosim.eval.predictions import read_predictions

    if (args.pred is None) == (args.baseline is None):
        raise InputError("give either --pred PREDICTIONS (your model's output) or --baseline NAME")
    options = EvalOptions(visible_only=args.visible_only, rule=_rule(args), compat=args.compat, seed=args.seed,
                          metrics=tuple(args.metric) if args.metric else None)
    out = Path(args.out)
    if args.pred is not None:
        predictions = read_predictions(Path(args.pred))  # before reading the dataset: fail fast on a bad file
        title = f"Evaluation of {args.pred}"
    refs = load_dataset(Path(args.gt), split=args.split)
    if args.baseline is not None:
        model = baseline(args.baseline, pos_sigma_m=args.pos_sigma_m, size_sigma=args.size_sigma,
                         yaw_sigma_deg=args.yaw_sigma_deg, miss_rate=args.miss_rate, seed=args.seed,
                         bev=not args.no_bev)
        pred_path = write_predictions(model, refs, out / "predictions" / f"{args.baseline}.jsonl", options.rule,
                                      progress=_log_progress("baseline"))
        print(f"predictions {pred_path}")
        title = (f"Evaluation of the {args.baseline} baseline (position sigma {args.pos_sigma_m} m, size sigma "
                 f"{args.size_sigma}, yaw sigma {args.yaw_sigma_deg} deg, miss rate {args.miss_rate})")
        predictions = read_predictions(pred_path)
    result = evaluate(refs, predictions, options, progress=_log_progress("eval"))
    written = write_eval(result, out, title)
    print(eval_tables(result)[0].markdown(), end="")
    for setting, (frames, sent) in bytes_per_setting(predictions).items():
        print(f"sent     {sent / frames:.0f} bytes per ego frame from the collaborators ({setting}, {frames} frames)")
    for p in written:
        print(p)
    return EXIT_OK


def bytes_per_setting(predictions: list) -> dict[str, tuple[int, int]]:
    """Frames and bytes sent per collaboration setting, over the records that say what was sent."""
    out: dict[str, tuple[int, int]] = {}
    for r in predictions:
        if r.bytes_sent is not None:
            frames, sent = out.get(r.agents, (0, 0))
            out[r.agents] = (frames + 1, sent + r.bytes_sent)
    return out


def cmd_coverage(args: argparse.Namespace) -> int:
    from cosim.eval.collaboration import collaboration_tables, compute_collaboration
    from cosim.eval.coverage import compute_coverage, coverage_adds, coverage_tables, write_coverage
    from cosim.eval.dataset import VEHICLE_CLASSES, load_dataset
    from cosim.eval.tables import write_tables

    rule = _rule(args)
    refs = load_dataset(Path(args.dataset), split=args.split)
    known = set(refs[0].object_classes) or set(VEHICLE_CLASSES)
    unknown = [c for c in args.classes or () if c not in known]
    if unknown:
        raise InputError(f"--classes: unknown class {unknown[0]!r}; the episodes' object classes are "
                         f"{', '.join(refs[0].object_classes)}")
    result = compute_coverage(refs, rule, classes=tuple(args.classes or VEHICLE_CLASSES),
                              progress=_log_progress("coverage"))
    written = write_coverage(result, Path(args.out))
    for t in coverage_tables(result):
        print(t.markdown())
    collab = compute_collaboration(refs, rule, classes=tuple(args.classes or VEHICLE_CLASSES))
    tables = collaboration_tables(collab, *coverage_adds(result))
    written += write_tables(tables, Path(args.out), "collaboration")
    for t in tables:
        print(t.markdown())
    for p in written:
        print(p)
    return EXIT_OK


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--split", help="only the episodes of this split of a batch (default: all)")
    p.add_argument("--min-points", type=cli_args.positive_int, default=1, metavar="N",
                   help="an agent sees an object with >= N LiDAR points on it (default 1) ...")
    p.add_argument("--min-pixels", type=cli_args.positive_int, default=1, metavar="M",
                   help="... or >= M instance pixels over its cameras (default 1)")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``eval`` and ``coverage`` to the ``cosim`` command (imports nothing heavy: every cosim start runs it)."""
    p = sub.add_parser("eval", help="score detections / BEV segmentation like the paper's tables (docs/evaluation.md)")
    p.add_argument("--gt", required=True, metavar="DATASET", type=DATASET, help="episode file or batch folder")
    p.add_argument("--pred", metavar="PREDICTIONS", type=cli_args.path("input_path", "prediction file or folder"),
                   help="prediction .jsonl file or folder (docs/evaluation.md)")
    p.add_argument("--baseline", metavar="NAME", help="generate predictions with a reference baseline: oracle-noise")
    p.add_argument("--out", default="eval", type=cli_args.output_folder,
                   help="output folder for tables and plots (default: ./eval)")
    _common(p)
    p.add_argument("--visible-only", action="store_true",
                   help="ground truth only where an agent of the record's setting sees the object")
    p.add_argument("--compat", metavar="MODE", help="airv2x: reproduce the AirV2X release's scoring (see docs)")
    p.add_argument("--seed", type=cli_args.non_negative_int, default=0,
                   help="baseline noise and compat subset seed (default 0)")
    p.add_argument("--metric", action="append", metavar="NAME",
                   help="compute only this metric (repeatable; default: every registered one: detection, "
                        "segmentation and any plug-in, docs/evaluation.md)")
    g = p.add_argument_group("oracle-noise baseline")
    g.add_argument("--pos-sigma-m", type=cli_args.non_negative_float, default=0.0,
                   help="centre noise, std along x and y [m]")
    g.add_argument("--size-sigma", type=cli_args.non_negative_float, default=0.0,
                   help="relative size noise, std (0.1 = 10%%)")
    g.add_argument("--yaw-sigma-deg", type=cli_args.non_negative_float, default=0.0, help="yaw noise, std [deg]")
    g.add_argument("--miss-rate", type=cli_args.fraction, default=0.0, help="probability of dropping a visible object")
    g.add_argument("--no-bev", action="store_true", help="no BEV segmentation predictions")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("coverage", help="ground-truth collaborative coverage per agent types and condition")
    p.add_argument("dataset", metavar="DATASET", type=DATASET,
                   help="episode file or batch folder (episodes with sensors)")
    p.add_argument("--out", default="coverage", type=cli_args.output_folder,
                   help="output folder for tables and plots (default: ./coverage)")
    _common(p)
    p.add_argument("--classes", nargs="+", metavar="CLASS",
                   help="object classes counted (default: car van truck bus motorcycle bicycle)")
    p.set_defaults(func=cmd_coverage)
