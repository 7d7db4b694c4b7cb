"""``cosim batch`` and ``cosim report``: registered into the main CLI by :func:`register`."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import tempfile
from pathlib import Path
from typing import Any

from cosim import cli_args

EXIT_OK, EXIT_FAILURE, EXIT_INTERRUPTED = 0, 1, 130


def _shard(text: str) -> tuple[int, int]:
    i, sep, k = text.partition("/")
    if not sep or not i.strip().isdigit() or not k.strip().isdigit():
        raise argparse.ArgumentTypeError(f"expected i/k (0 <= i < k), got {text!r}")
    index, count = int(i), int(k)
    if count < 1 or not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"expected i/k with 0 <= i < k, got {text!r}")
    return index, count


def _human_size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} TiB"


def _human_time(s: float) -> str:
    s = round(s)
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}h{m:02d}m{sec:02d}s" if h else f"{m}m{sec:02d}s"


def _plan(args: argparse.Namespace) -> Any:
    from cosim.batch.plan import plan_file

    plan = plan_file(args.sweep, count=args.count, hours=args.hours, scale=args.scale, cli_set=args.set or [])
    if args.split:
        plan = plan.only_splits(args.split)
    if args.shard:
        plan = plan.sharded(*args.shard)
    return plan


def _print_plan(plan: Any, out: Path) -> None:
    from collections import Counter

    from cosim.batch.runner import is_finished
    from cosim.io.manifest import latest_records

    existing = latest_records(out) if out.is_dir() else {}
    finished = sum(is_finished(out, ep, existing.get(ep.id)) for ep in plan.episodes)
    shard = f" (shard {plan.shard[0]}/{plan.shard[1]})" if plan.shard[1] > 1 else ""
    print(f"sweep    {plan.sweep.name}{shard}: {len(plan.episodes)} episodes, {plan.sim_seconds / 3600:.3f} h "
          f"of driving, {plan.combinations} combinations; {finished} already finished in {out}")
    by_split: Counter[str] = Counter()
    secs: Counter[str] = Counter()
    for ep in plan.episodes:
        by_split[ep.split] += 1
        secs[ep.split] += ep.duration_s
    for split in plan.sweep.split:
        print(f"split    {split:<8} {by_split[split]:>6} episodes  {secs[split] / 3600:8.3f} h")
    for axis, levels in plan.sweep.all_axes().items():
        counts = Counter(ep.labels[axis] for ep in plan.episodes)
        print(f"axis     {axis:<12} " + ", ".join(f"{lv.label} {counts[lv.label]}" for lv in levels))
    for w in plan.warnings:
        print(f"warning  {w}")
    for ep in plan.episodes[:10]:
        print(f"episode  {ep.describe(list(plan.sweep.vary))}")
    if len(plan.episodes) > 10:
        print(f"episode  ... and {len(plan.episodes) - 10} more")


def _calibrate(plan: Any, seconds: float, workers: int) -> None:
    """Run the first episode shortened to ``seconds`` and extrapolate wall time and disk size."""
    from cosim.batch.estimate import CARLA_ANCHORS, PAPER_FRAMES, calibrate

    if not plan.episodes:
        return
    with tempfile.TemporaryDirectory(prefix="cosim-calibrate-") as tmp:
        est = calibrate(plan, Path(tmp), seconds=seconds, workers=workers)
    print(f"estimate from a {est.calibration_s:g} s calibration run of {est.episode}: "
          f"startup {est.startup_s:.1f} s + {est.per_tick_s * 1000:.0f} ms per tick; size "
          f"{_human_size(est.fixed_bytes)} + {_human_size(est.bytes_per_tick)} per tick")
    print(f"estimate wall time {_human_time(est.wall_s)} with {workers} worker(s) "
          f"({_human_time(est.cpu_s)} of episode time), disk {_human_size(est.bytes)}")
    cpu_h, size = est.dataset_cost()
    if est.cpu_per_tick_s:
        print(f"dataset cost of this rig: {est.cpu_per_tick_s:.2f} CPU-s per frame ({3600 / est.cpu_per_tick_s:,.0f} "
              f"frames per CPU-hour, all processes of an episode), {est.bytes_per_tick / 1e6:.1f} MB per frame; "
              f"the paper's {PAPER_FRAMES:,} frames: {cpu_h:,.0f} CPU-hours, {size / 1e12:.2f} TB")
        print(f"  CARLA for comparison: {'; '.join(CARLA_ANCHORS)}")


def _sigterm_as_interrupt(*_: Any) -> None:
    raise KeyboardInterrupt


def cmd_batch(args: argparse.Namespace) -> int:
    from cosim.batch.executors import make_executor
    from cosim.batch.runner import run_batch
    from cosim.preflight import check_plan_inputs, check_ray_installed
    from cosim.runner import check_output_dir

    out = Path(args.out)
    plan = _plan(args)
    check_plan_inputs(plan.episodes)  # before the output folder is made
    check_output_dir(out, create=not args.dry_run)  # one message (exit 2) for a folder that cannot take episodes
    if args.backend == "ray":
        check_ray_installed()
    if args.dry_run:
        _print_plan(plan, out)
        if args.calibrate_s > 0:
            _calibrate(plan, args.calibrate_s, args.workers)
        return EXIT_OK
    for w in plan.warnings:
        logging.getLogger("cosim.batch").warning(w)
    executor = make_executor(args.backend, workers=args.workers, address=args.address,
                             max_in_flight=args.max_in_flight, log_level=logging.getLogger().level)
    previous = signal.signal(signal.SIGTERM, _sigterm_as_interrupt)  # docker stop, SLURM preemption
    try:
        summary = run_batch(plan, out, executor, retries=args.retries, show_progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"cosim: batch interrupted; running episodes stopped, finished ones are kept in {out}; "
              "run the same command again to resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, previous)
    print(f"batch    {summary.planned} planned, {summary.skipped} already finished, {summary.done} generated, "
          f"{len(summary.failed)} failed, {summary.retried} retried attempts, {_human_time(summary.wall_time_s)}")
    print(f"manifest {summary.manifest}")
    for episode, error in summary.failed.items():
        print(f"FAILED   {episode}: {error}")
    return EXIT_OK if summary.ok else EXIT_FAILURE


def cmd_report(args: argparse.Namespace) -> int:
    from cosim.batch.report import build_report

    report = build_report(Path(args.dir), md_path=Path(args.md) if args.md else None,
                          img_dir=Path(args.img_dir) if args.img_dir else None, img_prefix=args.prefix)
    print(f"report   {report.md_path} ({report.episodes} episodes, {report.hours:.3f} h)")
    for node, t in report.stats["nodes"].items():
        print(f"node     {node}: {t['episodes']} episodes, {t['sim_s']:.1f} sim s in {t['span_s']:.1f} s "
              f"({t['sim_per_wall']:.3f} sim s per wall s)")
    for p in report.images:
        print(f"plot     {p}")
    print(report.collaboration)
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser("batch", help="generate a sweep of episodes (local processes, Ray, shards; resumable)")
    b.add_argument("sweep", help="sweep YAML file, or the name of a shipped one (sweeps/)")
    b.add_argument("--out", required=True, help="output folder: <split>/<episode>.mcap and manifest*.jsonl")
    b.add_argument("--workers", type=cli_args.positive_int, default=1,
                   help="episodes at a time (local); CPUs of a local Ray")
    b.add_argument("--backend", default="local", choices=["local", "ray"], help="where episodes run")
    b.add_argument("--address", help="Ray cluster: auto, HOST:PORT or ray://HOST:PORT (default: a local Ray)")
    b.add_argument("--max-in-flight", type=cli_args.positive_int,
                   help="Ray: tasks submitted at once (default 2 x cluster CPUs)")
    b.add_argument("--shard", type=_shard, metavar="I/K", help="run only episodes i, i+k, ... (0 <= i < k)")
    b.add_argument("--split", action="append", metavar="NAME",
                   help="run only this split's episodes (repeatable), e.g. --split test --set tick_hz=10")
    b.add_argument("--retries", type=cli_args.non_negative_int, default=2,
                   help="extra attempts per failed episode (default 2)")
    size = b.add_mutually_exclusive_group()
    size.add_argument("--count", type=cli_args.positive_int,
                      help="episodes in total (overrides the sweep's count/hours)")
    size.add_argument("--hours", type=cli_args.positive_float,
                      help="driving time in total (overrides the sweep's count/hours)")
    b.add_argument("--scale", type=cli_args.at_least(0, noun="scale", above=True), default=1.0,
                   help="multiply the sweep's size (e.g. 0.01 for a smoke run)")
    b.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a scenario field in every episode, e.g. --set sensors.enabled=false")
    b.add_argument("--dry-run", action="store_true", help="print the plan and an estimate; generate nothing")
    b.add_argument("--calibrate-s", type=cli_args.at_least(0, "seconds"), default=2.0,
                   help="--dry-run: simulated seconds of the calibration episode (0: no calibration)")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    b.set_defaults(func=cmd_batch)

    r = sub.add_parser("report", help="dataset statistics of a batch folder: Markdown + PNG plots")
    r.add_argument("dir", type=cli_args.path("input_folder", "batch folder"),
                   help="batch output folder (with manifest*.jsonl)")
    r.add_argument("--md", type=cli_args.output_file, help="Markdown file to write (default DIR/report.md)")
    r.add_argument("--img-dir", type=cli_args.output_folder,
                   help="folder for the PNG plots (default: beside the Markdown)")
    r.add_argument("--prefix", default="report_", help="file name prefix of the plots (default report_)")
    r.set_defaults(func=cmd_report)


__all__ = ["register"]
