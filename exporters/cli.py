"""``cosim export``: registered into the ``cosim`` command by :func:`register` (cosim/cli.py calls it)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cosim import cli_args

EXIT_OK = 0


def cmd_export(args: argparse.Namespace) -> int:
    from cosim.exporters.export import ExportOptions, get_format, run_export

    from cosim.progress import progress_display

    get_format(args.format)  # an unknown format fails before any work
    # a bar on a terminal, else a plain line every 10 s (cosim.progress)
    progress, close = progress_display(f"export {args.format}", enabled=not args.quiet, unit="agent-frame")
    try:
        result = run_export(Path(args.source), args.format, Path(args.out),
                            ExportOptions(every=args.every, masks=args.masks, raw_lidar=args.raw_lidar,
                                          objects_at_tick=args.objects_at_tick, png_images=args.png_images),
                            split=args.split, workers=args.workers, progress=progress,
                            agents=args.agents)
    finally:
        close()
    for p in result.written:
        print(f"exported {p}")
    for p in result.skipped:
        print(f"skipped  {p} (already complete)")
    print(f"{len(result.written)} sequence(s) written, {len(result.skipped)} skipped, "
          f"{result.agent_frames} agent-frames")
    for line in result.warnings:
        print(f"warning: {line}")
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``export`` to the ``cosim`` command."""
    p = sub.add_parser("export", help="episodes into the AirV2X-Perception, OPV2V/V2XSet or KITTI object layout "
                                      "(docs/exports.md)")
    p.add_argument("source", type=cli_args.path("input_path", "episode file or batch folder"),
                   help="episode file (.mcap) or batch folder (its manifest gives the splits)")
    p.add_argument("--format", required=True, metavar="FORMAT", help="airv2x, opv2v or kitti")
    p.add_argument("--out", required=True, type=cli_args.output_folder,
                   help="export root (no date-like YYYY_MM_DD_HH_MM_SS in its path)")
    p.add_argument("--split", help="split folder for every episode (default: the manifest's split, or train)")
    p.add_argument("--every", type=cli_args.positive_int, default=1, metavar="K",
                   help="keep every K-th tick (default 1)")
    p.add_argument("--workers", type=cli_args.positive_int, default=1, metavar="N",
                   help="processes writing ticks (default 1)")
    p.add_argument("--masks", action="store_true", help="also semantic and instance images (AirV2X)")
    p.add_argument("--png-images", action="store_true",
                   help="camera files as lossless PNG where the episode stored JPEG (the default keeps its JPEG "
                        "bytes under the layouts' .png names: the same pixels, an eighth of the bytes)")
    p.add_argument("--raw-lidar", action="store_true",
                   help="LiDAR points as fired (each in its firing's sensor frame), not compensated to the tick pose")
    motion = p.add_mutually_exclusive_group()
    motion.add_argument("--objects-at-tick", dest="objects_at_tick", action="store_true", default=None,
                        help="move each moving object's points to where it is at the tick, with its recorded "
                             "velocity, as the datasets were recorded (the default, except with --raw-lidar)")
    motion.add_argument("--object-motion", dest="objects_at_tick", action="store_false",
                        help="keep each object's own motion over the sweep (nuScenes-style): a moving object's "
                             "points trail its box by up to speed x 50 ms")
    p.add_argument("--agents", metavar="WHO",
                   help="kitti: the egos, one frame per ego and tick: vehicles (default), rsus, drones, all, or "
                        "agent ids such as vehicle_0, comma-separated")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_export)
